"""``mapserver run`` with ``web:`` set serves the pages from a thread of the daemon: they see the
daemon running and its results as they come, and a stop ends both."""

from __future__ import annotations

import json
import socket
import urllib.request
from pathlib import Path

from tests.daemon_support import Daemon, layout, make_bundle, upload, wait_until, write_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as response:
        return response.read().decode()


def test_the_daemon_serves_its_pages_when_web_is_set(tmp_path: Path) -> None:
    port = free_port()
    config = write_config(tmp_path, workers=1, web={"listen": f"127.0.0.1:{port}"})
    base = f"http://127.0.0.1:{port}"
    source = make_bundle(tmp_path / "src" / "run-1")
    with Daemon(config) as daemon:
        daemon.wait_ready()
        health = json.loads(get(base + "/healthz"))
        assert health["daemon_running"] is True and health["results_indexed"] == 0
        assert health["status"] == "ok"
        upload(source, layout(tmp_path)["inbox"])
        wait_until(
            lambda: (tmp_path / "outbox/run-1/result.yaml").exists(), timeout=30, what="run-1"
        )
        wait_until(lambda: "run-1" in get(base + "/"), timeout=10, what="run-1 on the dashboard")
        assert "The daemon is running" in get(base + "/")
        assert daemon.stop() == 0, daemon.log()
    try:
        get(base + "/healthz")
    except OSError:
        pass
    else:
        raise AssertionError("the pages outlived the daemon")


def test_run_no_web_serves_nothing(tmp_path: Path) -> None:
    port = free_port()
    config = write_config(tmp_path, workers=1, web={"listen": f"127.0.0.1:{port}"})
    import subprocess
    import sys

    log = (tmp_path / "d.log").open("wb")
    process = subprocess.Popen(
        [sys.executable, "-m", "mapserver.cli", "run", "--no-web", "--config", str(config)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        wait_until(lambda: "ready:" in (tmp_path / "d.log").read_text(), timeout=30, what="ready")
        with socket.socket() as probe:
            assert probe.connect_ex(("127.0.0.1", port)) != 0
    finally:
        process.terminate()
        process.wait(timeout=30)
        log.close()
