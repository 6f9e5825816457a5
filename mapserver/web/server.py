"""Serving the web application with uvicorn: alone (``mapserver web``) or in a thread of the
daemon (``mapserver run`` with ``web:`` set)."""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass

import uvicorn

from mapserver.config import Config, WebConfig
from mapserver.errors import ConfigError
from mapserver.web import security
from mapserver.web.app import create_app
from mapserver.web.index import BundleIndex

log = logging.getLogger(__name__)


@dataclass
class WebServer:
    """A uvicorn server for ``config``, not yet started."""

    config: Config
    server: uvicorn.Server
    index: BundleIndex
    url: str
    sock: socket.socket
    """Bound when the server was made: a port another program holds stops the command there,
    before anything says it serves (session 58's review: the daemon logged "serving", uvicorn's
    thread then failed on the busy port, and the daemon ran on without pages or metrics)."""

    def run(self) -> None:
        """Serve until :meth:`stop` (or SIGTERM/SIGINT when run in the main thread)."""
        self.index.start()
        try:
            self.server.run(sockets=[self.sock])
        finally:
            self.index.stop()
            self.sock.close()

    def start_thread(self) -> threading.Thread:
        thread = threading.Thread(target=self.run, name="mapserver-web", daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        self.server.should_exit = True


def make_server(config: Config) -> WebServer:
    """Check the web settings (a non-loopback address needs a token) and build the server."""
    web = config.web or WebConfig()
    config = config.model_copy(update={"web": web})
    host, port = security.host_port(web.listen)
    security.check_settings(web)
    index = BundleIndex(config.outbox, config.failed)
    app = create_app(config, index=index)
    settings = uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="warning",
        access_log=False,
        server_header=False,
        lifespan="off",
    )
    # uvicorn takes SIGTERM/SIGINT only when it runs in the main thread: in the daemon's
    # thread the daemon keeps them, and stops the server itself.
    server = uvicorn.Server(settings)
    shown = f"[{host}]" if ":" in host else host
    return WebServer(config, server, index, f"http://{shown}:{port}/", _bound(host, port))


def _bound(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host``:``port`` (as uvicorn binds one: SO_REUSEADDR, so a port
    in TIME_WAIT after a restart is free), or a :class:`ConfigError` saying why not."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as error:
        raise ConfigError(f"web.listen: cannot resolve {host}: {error.strerror}") from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as error:
        sock.close()
        raise ConfigError(
            f"web.listen {host}:{port}: {error.strerror} (another program serves there; "
            "choose another port in web.listen, or stop that program)"
        ) from None
    return sock
