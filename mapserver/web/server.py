"""Serving the web application with uvicorn: alone (``mapserver web``) or in a thread of the
daemon (``mapserver run`` with ``web:`` set)."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import uvicorn

from mapserver.config import Config, WebConfig
from mapserver.errors import ConfigError
from mapserver.web import security
from mapserver.web.app import create_app
from mapserver.web.index import BundleIndex

log = logging.getLogger(__name__)


def host_port(listen: str) -> tuple[str, int]:
    host, _, port = listen.rpartition(":")
    number = int(port)
    if not 0 < number < 65536:
        raise ConfigError(f"web.listen: port {number} is not between 1 and 65535")
    return host.strip("[]"), number


@dataclass
class WebServer:
    """A uvicorn server for ``config``, not yet started."""

    config: Config
    server: uvicorn.Server
    index: BundleIndex
    url: str

    def run(self) -> None:
        """Serve until :meth:`stop` (or SIGTERM/SIGINT when run in the main thread)."""
        self.index.start()
        try:
            self.server.run()
        finally:
            self.index.stop()

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
    host, port = host_port(web.listen)
    token = security.read_token(web.token_file)
    security.check_listen(host, token)
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
    return WebServer(config, server, index, f"http://{shown}:{port}/")
