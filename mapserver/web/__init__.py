"""The operator's window: web pages, a JSON API and Prometheus metrics over the folders and the
map store (``mapserver web``, or inside ``mapserver run`` when the configuration's ``web:`` is
set). See :func:`mapserver.web.app.create_app` and :func:`mapserver.web.server.serve`."""
