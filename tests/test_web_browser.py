"""A real browser on a real ``mapserver web``: headless Chromium (Debian's package, driven by
Playwright) loads the dashboard, a bundle and a map, signs in with the token, approves a change,
and sees the new version. Screenshots go to ``test-artifacts/`` (or $MAPSERVER_TEST_ARTIFACTS).

Skips, saying why, where no Chromium or no Playwright is installed (``.ci/run`` installs both).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.daemon_support import wait_until
from tests.web_support import DEPOT, TOKEN, build_site

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARTIFACTS = Path(
    os.environ.get(
        "MAPSERVER_TEST_ARTIFACTS", Path(__file__).resolve().parents[1] / "test-artifacts"
    )
)

try:
    from playwright.sync_api import Page, sync_playwright
except ImportError:  # pragma: no cover - the dev extras install it
    sync_playwright = None  # type: ignore[assignment]

pytestmark = [
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="no Chromium here (apt-get install chromium): browser tests skipped",
    ),
    pytest.mark.skipif(
        sync_playwright is None, reason="Playwright is not installed (pip install playwright)"
    ),
    pytest.mark.skipif(len(DEPOT) < 3, reason="the depot samples are not shipped"),
]

# Chromium as root in a sandbox with no network (the env notes): no sandbox, no background traffic.
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def server(tmp_path: Path) -> Iterator[str]:
    config = build_site(tmp_path / "site", mode="review")
    port = free_port()
    log = (tmp_path / "web.log").open("wb")
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mapserver.cli",
            "web",
            "--config",
            str(tmp_path / "site" / "mapserver.yaml"),
            "--listen",
            f"127.0.0.1:{port}",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"

    def up() -> bool:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return True
        except OSError:
            return process.poll() is not None

    try:
        wait_until(up, timeout=30, what="mapserver web to listen")
        assert process.poll() is None, (tmp_path / "web.log").read_text()
        assert config.maps is not None
        yield url
    finally:
        process.terminate()
        process.wait(timeout=10)
        log.close()


def shot(page: Page, name: str) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def test_an_operator_reviews_a_change_in_a_real_browser(server: str, tmp_path: Path) -> None:
    assert sync_playwright is not None
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": 1300, "height": 900})
            page.goto(server + "/")
            assert page.locator("h1").inner_text() == "Dashboard"
            assert page.get_by_role("link", name="depot-demo-04").count() >= 1
            shot(page, "dashboard")

            page.get_by_role("link", name="depot-demo-01").first.click()
            page.wait_for_load_state()
            assert page.locator("h1").inner_text() == "depot-demo-01"
            overlay = page.locator("img.pic")
            assert overlay.evaluate("img => img.complete && img.naturalWidth > 100")
            assert page.locator("table tr").count() >= 5  # the differences
            shot(page, "bundle")

            page.goto(server + "/maps/depot")
            assert "version 1" in page.locator("h1").inner_text()
            assert page.locator("img.pic").evaluate("img => img.complete && img.naturalWidth > 100")
            assert page.get_by_role("button", name="Approve").count() == 0  # not signed in
            shot(page, "map-before")

            page.goto(server + "/login")
            page.fill("input[name=name]", "alice")
            page.fill("input[name=token]", TOKEN)
            page.get_by_role("button", name="Sign in").click()
            page.wait_for_load_state()
            assert "signed in as alice" in page.locator("header").inner_text()

            page.goto(server + "/maps/depot")
            approve = page.get_by_role("button", name="Approve")
            assert approve.count() >= 3  # the confirmed changes
            approve.first.click()
            page.wait_for_load_state()
            assert "version 2" in page.locator("h1").inner_text()
            assert page.get_by_role("link", name="2", exact=True).count() >= 1  # in the versions
            shot(page, "map-after-approve")

            page.goto(server + "/maps/depot/versions/2")
            assert page.locator("img.pic").evaluate("img => img.complete && img.naturalWidth > 50")
            shot(page, "version-2")
        finally:
            browser.close()
