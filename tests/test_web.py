"""The web pages and the HTTP API through an in-process client, on a store built by processing
the depot samples: what an operator sees, what a robot fetches, and who may change what."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import socket
from pathlib import Path

import pytest
import yaml
from fastapi.testclient import TestClient
from prometheus_client.metrics_core import Metric
from prometheus_client.parser import text_string_to_metric_families

from mapserver.config import Config
from mapserver.errors import ConfigError
from mapserver.web.app import create_app
from mapserver.web.server import make_server
from tests.web_support import DEPOT, TOKEN, build_site, copy_results

pytestmark = pytest.mark.skipif(len(DEPOT) < 3, reason="the depot samples are not shipped")
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Config:
    return build_site(tmp_path_factory.mktemp("site"))


@pytest.fixture
def fresh(tmp_path: Path) -> Config:
    """A site of its own, for the tests that change it."""
    return build_site(tmp_path / "site")


def client(config: Config) -> TestClient:
    return TestClient(create_app(config))


def confirmed(c: TestClient) -> list[int]:
    page = c.get("/api/maps/depot/changes", params={"state": "confirmed"}).json()
    return [item["id"] for item in page["items"]]


def test_the_dashboard_shows_queue_robots_maps_and_failures(site: Config) -> None:
    page = client(site).get("/")
    assert page.status_code == 200
    html = page.text
    assert "The daemon is not running" in html  # no mapserver run in this test
    for robot in ("demo-01", "demo-03"):
        assert robot in html
    assert 'href="/maps/depot"' in html and "depot-demo-04" in html
    assert "broken-upload" in html and "missing key" in html


def test_a_bundle_page_shows_its_overlay_differences_and_change_ids(site: Config) -> None:
    c = client(site)
    page = c.get("/bundles/depot-demo-01")
    assert page.status_code == 200
    result = yaml.safe_load((site.outbox / "depot-demo-01" / "result.yaml").read_text())
    for d in result["differences"]:
        assert f'href="/changes/{d["change"]}"' in page.text
    # The result's versions are the bundle's, not live ones (session 58's review: a page said
    # "current 2" after a rollback had made version 3 current).
    m = result["map"]
    assert (
        f"navigated on version {m['version']} (version {m['current_version']} was current "
        "when this bundle was processed)" in page.text
    )
    image = c.get("/bundles/depot-demo-01/overlay.png")
    assert image.content == (site.outbox / "depot-demo-01" / "overlay.png").read_bytes()
    failed = c.get("/bundles/broken-upload")
    assert failed.status_code == 200 and "missing key" in failed.text


def test_the_map_page_lists_changes_by_state_and_the_versions(site: Config) -> None:
    c = client(site)
    page = c.get("/maps/depot")
    assert page.status_code == 200 and "Map depot" in page.text
    ids = confirmed(c)
    assert ids and all(f'href="/changes/{i}"' in page.text for i in ids)
    only = c.get("/maps/depot", params={"state": "expired"}).text
    assert all(f'href="/changes/{i}"' not in only for i in ids)
    picture = c.get("/maps/depot/picture.png")
    assert picture.status_code == 200 and picture.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_lists_are_paginated_by_key_without_repeats_or_gaps(tmp_path: Path) -> None:
    config = build_site(tmp_path / "site", page_size=5)
    extra = copy_results(config, 12)
    c = client(config)
    seen: list[str] = []
    cursor = None
    while True:
        page = c.get(
            "/api/bundles", params={"limit": 5, **({"before": cursor} if cursor else {})}
        ).json()
        seen += [item["bundle"] for item in page["items"]]
        cursor = page["next"]
        if cursor is None:
            break
    assert len(seen) == len(set(seen)) == 12 + len(DEPOT)
    assert set(extra) <= set(seen)
    times = [c.get(f"/api/bundles/{b}").json()["processed_at"] for b in seen]
    assert times == sorted(times, reverse=True)
    html = c.get("/bundles").text
    assert "Older" in html
    # A mistyped cursor is refused, not read as the first page (session 58's review).
    for path in ("/api/bundles", "/api/failures"):
        bad = c.get(path, params={"before": "garbage"})
        assert bad.status_code == 422 and "not a page cursor" in bad.text
    assert c.get("/bundles", params={"before": "garbage"}).status_code == 200


def test_robots_fetch_current_yaml_and_images_byte_for_byte_with_etags(site: Config) -> None:
    c = client(site)
    assert site.maps is not None
    got = c.get("/maps/depot/current.yaml")
    assert got.status_code == 200
    assert got.content == (site.maps / "depot" / "current.yaml").read_bytes()
    tag = got.headers["etag"]
    again = c.get("/maps/depot/current.yaml", headers={"If-None-Match": tag})
    assert again.status_code == 304 and again.content == b""
    image_name = yaml.safe_load(got.content)["image"]
    image = c.get(f"/maps/depot/files/{image_name}")
    assert (
        hashlib.sha256(image.content).hexdigest()
        == hashlib.sha256((site.maps / "depot" / image_name).read_bytes()).hexdigest()
    )


def test_a_browser_gets_its_errors_as_pages_and_a_program_as_json(site: Config) -> None:
    """Session 58's review: /maps/nosuch and /changes/abc answered a browser with JSON."""
    c = client(site)
    html = {"Accept": "text/html,application/xhtml+xml"}
    missing = c.get("/maps/nosuch", headers=html)
    assert missing.status_code == 404 and missing.headers["content-type"].startswith("text/html")
    assert "404: Not Found" in missing.text and 'href="/"' in missing.text
    bad = c.get("/changes/abc", headers=html)
    assert bad.status_code == 422 and bad.headers["content-type"].startswith("text/html")
    assert "change_id" in bad.text
    # The API, an image, the metrics: JSON or the status alone, whatever the browser accepts.
    api = c.get("/api/maps/nosuch", headers=html)
    assert api.status_code == 404 and api.headers["content-type"] == "application/json"
    assert c.get("/maps/nosuch").headers["content-type"] == "application/json"  # no Accept
    image = c.get("/bundles/nosuch/overlay.png", headers=html)
    assert image.status_code == 404 and "html" not in image.headers["content-type"]
    # The page keeps what the error says in its headers (session 58's review: a 405 lost Allow).
    wrong = c.get("/changes/1/approve", headers=html)
    assert wrong.status_code == 405 and wrong.headers["allow"] == "POST"


def test_paths_from_requests_never_leave_the_folders(site: Config, tmp_path: Path) -> None:
    c = client(site)
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"\x89PNG secret")
    os.symlink(tmp_path, site.outbox / "sneaky")
    for url in (
        "/bundles/..%2F..%2Fetc/overlay.png",
        "/bundles/sneaky/overlay.png",
        "/maps/depot/files/..%2Fstore.db",
        "/maps/depot/files/.mapserver.lock",
        "/api/bundles/..",
        "/maps/..%2F..%2Fetc/current.yaml",
    ):
        r = c.get(url)
        assert r.status_code in (404, 422), url
        assert b"secret" not in r.content


def test_review_actions_need_the_token(fresh: Config) -> None:
    c = client(fresh)
    (cid, *_) = confirmed(c)
    assert c.post(f"/api/changes/{cid}/approve").status_code == 401
    bad = c.post(f"/api/changes/{cid}/approve", headers={"Authorization": "Bearer " + "y" * 26})
    assert bad.status_code == 401
    assert c.get("/api/maps/depot").json()["current_version"] == 1
    ok = c.post(f"/api/changes/{cid}/approve", headers=AUTH)
    assert ok.status_code == 200 and ok.json()["version"] == 2
    change = c.get(f"/api/changes/{cid}").json()
    assert change["state"] == "published" and change["history"][0]["actor"] == "api (token)"
    again = c.post(f"/api/changes/{cid}/approve", headers=AUTH)
    assert again.status_code == 409 and "not confirmed" in again.text
    assert c.post("/api/changes/9999/reject", headers=AUTH).status_code == 404
    rollback = c.post("/api/maps/depot/rollback", json={"version": 1}, headers=AUTH)
    assert rollback.status_code == 200 and rollback.json()["version"] == 3


def test_the_map_page_shows_the_newest_versions_and_links_to_all(tmp_path: Path) -> None:
    """A map publishing every day has hundreds of versions after a year: its page lists the
    newest page of them (web.page_size) and links to all."""
    c = client(build_site(tmp_path / "site", page_size=5))
    (cid, *_) = confirmed(c)
    assert c.post(f"/api/changes/{cid}/approve", headers=AUTH).json()["version"] == 2
    for version in (1, 2, 1, 2, 1):  # versions 3 to 7
        c.post("/api/maps/depot/rollback", json={"version": version}, headers=AUTH)
    rows = re.compile(r'href="/maps/depot/versions/(\d+)"')
    page = c.get("/maps/depot").text
    assert rows.findall(page) == ["7", "6", "5", "4", "3"]
    assert "The newest 5 of 7 versions" in page and 'href="/maps/depot?versions=all"' in page
    every = c.get("/maps/depot", params={"versions": "all"}).text
    assert rows.findall(every) == ["7", "6", "5", "4", "3", "2"]  # version 1 has no page
    assert "The newest" not in every


def test_forms_need_a_signed_session_and_a_csrf_token(fresh: Config) -> None:
    c = client(fresh)
    (cid, *_) = confirmed(c)
    assert c.post(f"/changes/{cid}/approve", data={"csrf": "x"}).status_code == 401
    wrong = c.post("/login", data={"token": "nope" * 5, "name": "alice"}, follow_redirects=False)
    assert wrong.status_code == 303 and "error=token" in wrong.headers["location"]
    signed = c.post("/login", data={"token": TOKEN, "name": "alice"}, follow_redirects=False)
    assert signed.status_code == 303 and "mapserver_session" in signed.headers["set-cookie"]
    assert "samesite=strict" in signed.headers["set-cookie"].lower()
    assert c.post(f"/changes/{cid}/approve", data={"csrf": "forged"}).status_code == 403
    page = c.get("/maps/depot").text
    csrf = page.split('name="csrf" value="', 1)[1].split('"', 1)[0]
    done = c.post(f"/changes/{cid}/approve", data={"csrf": csrf}, follow_redirects=False)
    assert done.status_code == 303
    history = c.get(f"/api/changes/{cid}").json()["history"]
    assert history[-1]["actor"] == "alice (web)" and history[-1]["action"] == "approved"
    assert "version 2" in c.get("/maps/depot").text
    # Signing out is a form like the others (session 54's review: a forged one was accepted).
    assert c.post("/logout", follow_redirects=False).status_code == 403
    assert "signed in as alice" in c.get("/").text
    # From another site the browser sends no session cookie (SameSite=Strict): the answer must
    # not delete it either (a browser applies a Set-Cookie on the forged page's word).
    other = client(fresh)
    forged = other.post("/logout", follow_redirects=False)
    assert forged.status_code == 303 and "set-cookie" not in forged.headers
    out = c.post("/logout", data={"csrf": csrf}, follow_redirects=False)
    assert out.status_code == 303 and "signed in as" not in c.get("/").text


def test_a_non_loopback_address_without_a_token_is_refused(site: Config) -> None:
    from mapserver.config import WebConfig

    open_web = site.model_copy(update={"web": WebConfig(listen="0.0.0.0:8350")})
    with pytest.raises(ConfigError, match=r"without web\.token_file"):
        make_server(open_web)
    port = _free_port()
    local = site.model_copy(update={"web": WebConfig(listen=f"127.0.0.1:{port}")})
    web = make_server(local)
    assert web.url == f"http://127.0.0.1:{port}/"
    web.sock.close()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_a_port_another_program_holds_is_refused_before_serving(site: Config) -> None:
    """Session 58's review: the daemon logged "serving", then uvicorn's thread failed on the
    busy port and the daemon ran on without pages, API or metrics."""
    from mapserver.config import WebConfig

    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        busy = site.model_copy(update={"web": WebConfig(listen=f"127.0.0.1:{port}")})
        with pytest.raises(ConfigError, match=f"web.listen 127.0.0.1:{port}: Address already"):
            make_server(busy)


def metric_families(c: TestClient) -> dict[str, Metric]:
    return {f.name: f for f in text_string_to_metric_families(c.get("/metrics").text)}


def test_metrics_count_bundles_changes_and_versions(site: Config) -> None:
    families = metric_families(client(site))
    assert families["mapserver_results"].samples[0].value == len(DEPOT)
    failed = {s.labels["stage"]: s.value for s in families["mapserver_failed_bundles"].samples}
    assert failed == {"bundle": 1}
    states = {
        s.labels["state"]: s.value
        for s in families["mapserver_changes"].samples
        if s.labels["map"] == "depot"
    }
    assert states["confirmed"] >= 3 and states["published"] == 0
    align = {
        s.labels["le"]: s.value
        for s in families["mapserver_results_by_stage_seconds"].samples
        if s.labels["stage"] == "align"
    }
    assert align["+Inf"] == len(DEPOT) and align["0.01"] <= align["30.0"] <= len(DEPOT)
    stages = {s.labels["stage"] for s in families["mapserver_results_by_stage_seconds"].samples}
    assert {"align", "diff", "update"} <= stages
    scores = families["mapserver_results_by_alignment_score"].samples
    assert [s.value for s in scores if s.labels["le"] == "+Inf"] == [len(DEPOT)]
    assert families["mapserver_daemon_up"].samples[0].value == 0
    health = client(site).get("/healthz").json()
    assert health["results_indexed"] == len(DEPOT)
    # No daemon serves the site: the status says so first (session 58's review: "ok").
    assert (health["status"], health["daemon_running"]) == ("daemon not running", False)


def test_what_the_folders_hold_is_a_gauge_and_only_the_daemons_counts_are_counters(
    tmp_path: Path,
) -> None:
    # Requeue and retention empty failed/ and the outbox: exposed as counters, the fall would
    # read as a reset, and increase() would count the failures again.
    from mapserver.lock import daemon_lock
    from mapserver.requeue import requeue
    from mapserver.status import write_status

    config = build_site(tmp_path / "site")
    families = metric_families(client(config))
    for name in (
        "mapserver_results",
        "mapserver_failed_bundles",
        "mapserver_results_by_stage_seconds",
        "mapserver_results_by_alignment_score",
    ):
        assert families[name].type == "gauge", name
    rising = {f.name for f in families.values() if f.type in ("counter", "histogram")}
    assert rising == {"mapserver_map_versions_published"}  # no daemon runs: none of its counts
    config.inbox.mkdir(exist_ok=True)
    requeue(config, ["broken-upload"])
    assert metric_families(client(config))["mapserver_failed_bundles"].samples == []
    with daemon_lock(config):  # as a running daemon holds it, with its counts since it started
        write_status(
            config.inbox,
            {
                "pid": os.getpid(),
                "uploading": 0,
                "queued": 0,
                "processing": 0,
                "results": 7,
                "failed": 2,
                "degraded": None,
            },
        )
        families = metric_families(client(config))
    assert families["mapserver_bundles_processed"].type == "counter"
    assert families["mapserver_bundles_processed"].samples[0].value == 7
    assert families["mapserver_bundles_failed"].type == "counter"
    assert families["mapserver_bundles_failed"].samples[0].value == 2


def test_the_openapi_schema_documents_the_api(site: Config) -> None:
    schema = client(site).get("/openapi.json").json()
    for path in (
        "/api/bundles",
        "/api/maps/{name}/changes",
        "/api/changes/{change_id}/approve",
        "/maps/{name}/current.yaml",
    ):
        assert path in schema["paths"], path


def test_a_session_cookie_expires_and_cannot_be_reused_with_another_name() -> None:
    from mapserver.web import security

    cookie = security.new_session_cookie(TOKEN, "alice", now=1_000_000)
    assert security.read_session(TOKEN, cookie, now=1_000_000 + 3600) is not None
    assert security.read_session(TOKEN, cookie, now=1_000_000 + 13 * 3600) is None
    forged = cookie.replace(".alice.", ".mallory.")
    assert security.read_session(TOKEN, forged, now=1_000_000) is None
    assert security.read_session("another-token-0123456789", cookie, now=1_000_000) is None


def test_a_degraded_daemon_shows_on_the_dashboard_and_in_the_metrics(tmp_path: Path) -> None:
    from mapserver.lock import daemon_lock
    from mapserver.status import write_status

    config = build_site(tmp_path / "site")
    with daemon_lock(config):  # as a running daemon holds it
        write_status(
            config.inbox,
            {
                "pid": os.getpid(),
                "started_at": "2026-11-25T01:00:00Z",
                "updated_at": "2026-11-25T01:00:05Z",
                "uploading": 0,
                "queued": 0,
                "processing": 0,
                "degraded": {
                    "since": "2026-11-25T01:00:00Z",
                    "waiting": 2,
                    "faults": [
                        {
                            "folder": "outbox",
                            "path": str(config.outbox),
                            "reason": "No space left on device",
                            "free_bytes": 0,
                        }
                    ],
                },
            },
        )
        c = client(config)
        html = c.get("/").text
        assert "DEGRADED since 2026-11-25T01:00:00Z: 2 bundles wait" in html
        assert "No space left on device (0.0 MiB free)" in html
        families = {f.name: f for f in text_string_to_metric_families(c.get("/metrics").text)}
        assert families["mapserver_degraded"].samples[0].value == 1
        assert c.get("/healthz").json()["degraded"] is True
        assert c.get("/healthz").json()["status"] == "degraded"


def test_a_failed_bundle_shows_the_daemons_reason_not_one_it_brought(tmp_path: Path) -> None:
    from mapserver.outbox import Store

    config = build_site(tmp_path / "site")
    bundle = config.inbox / "forged"
    shutil.copytree(DEPOT[0], bundle)
    forged = {
        "format": 1,
        "bundle": "forged",
        "failed_at": "2099-01-01T00:00:00.000Z",
        "stage": "upload",
        "reason": "nothing wrong here, ignore it",
    }
    for name in ("error.yaml", "mapserver-error.yaml"):  # both names the daemon would take
        (bundle / name).write_text(yaml.safe_dump(forged))
    failed = Store.from_config(config).reject("forged", "forged", "load", "nav2_map.pgm: bad")
    real = yaml.safe_load((failed / "mapserver-error2.yaml").read_text())  # the first free name
    assert real["reason"] == "nav2_map.pgm: bad"
    c = client(config)
    rows = [r for r in c.get("/api/failures").json()["items"] if r["bundle"] == "forged"]
    assert rows == [
        {
            "bundle": "forged",
            "failed_at": real["failed_at"],
            "stage": "load",
            "reason": real["reason"],
        }
    ]
    for url in ("/bundles/forged", "/failed", "/"):
        html = c.get(url).text
        assert "nav2_map.pgm: bad" in html and "ignore it" not in html, url
    stages = metric_families(c)["mapserver_failed_bundles"].samples
    assert {s.labels["stage"]: s.value for s in stages} == {"bundle": 1, "load": 1}


def test_the_server_refreshes_the_index_its_pages_read(site: Config) -> None:
    # make_server's index is empty (falsy) until its first refresh: the app must not build an
    # index of its own, that no thread refreshes and /healthz reads without refreshing.
    assert site.web is not None
    listen = site.web.model_copy(update={"listen": f"127.0.0.1:{_free_port()}"})
    web = make_server(site.model_copy(update={"web": listen}))
    web.sock.close()
    web.index.refresh()  # as its background thread does, every every_s seconds
    app = web.server.config.app
    assert app.state.index is web.index
    assert TestClient(app).get("/healthz").json()["results_indexed"] == len(DEPOT)


HUGE = 99999999999999999999  # past SQLite's INTEGER (2^63 - 1)


def test_ids_and_versions_past_sqlite_integers_are_refused_not_a_server_error(
    site: Config,
) -> None:
    c = client(site)
    for url in (
        f"/api/changes/{HUGE}",
        f"/changes/{HUGE}",
        f"/maps/depot?before={HUGE}",
        f"/api/maps/depot/changes?before={HUGE}",
    ):
        assert c.get(url).status_code == 422, url
    assert c.post(f"/api/changes/{HUGE}/approve", headers=AUTH).status_code == 422
    assert c.post(f"/api/changes/{HUGE}/reject", headers=AUTH).status_code == 422
    rollback = c.post("/api/maps/depot/rollback", json={"version": HUGE}, headers=AUTH)
    assert rollback.status_code == 422
    c.post("/login", data={"token": TOKEN, "name": "alice"})
    csrf = c.get("/maps/depot").text.split('name="csrf" value="', 1)[1].split('"', 1)[0]
    assert c.post(f"/changes/{HUGE}/approve", data={"csrf": csrf}).status_code == 422
    form = c.post("/maps/depot/rollback", data={"csrf": csrf, "version": str(HUGE)})
    assert form.status_code == 422
    # The largest id SQLite holds is just an id no change has.
    assert c.get(f"/api/changes/{2**63 - 1}").status_code == 404
    assert c.get("/api/maps/depot").json()["current_version"] == 1


def test_robots_may_ask_for_the_headers_alone(site: Config) -> None:
    assert site.maps is not None
    c = client(site)
    image = yaml.safe_load((site.maps / "depot" / "current.yaml").read_text())["image"]
    for url, path in (
        ("/maps/depot/current.yaml", site.maps / "depot" / "current.yaml"),
        (f"/maps/depot/files/{image}", site.maps / "depot" / image),
    ):
        got = c.get(url)
        head = c.head(url)
        assert head.status_code == 200 and head.content == b"", url
        assert head.headers["etag"] == got.headers["etag"]
        assert head.headers["content-type"] == got.headers["content-type"]
        assert int(head.headers["content-length"]) == path.stat().st_size == len(got.content)
        again = c.head(url, headers={"If-None-Match": got.headers["etag"]})
        assert again.status_code == 304


@pytest.mark.parametrize(
    ("header", "code"),
    [
        ("{tag}", 304),
        ("W/{tag}", 304),  # a cache may weaken the tag: If-None-Match compares weakly
        ("*", 304),
        ('"0123", W/{tag}', 304),
        ('W/"0123" , {tag}', 304),
        ('"0123"', 200),
        ('W/"0123"', 200),
    ],
)
def test_if_none_match_is_the_weak_comparison_of_rfc_9110(
    site: Config, header: str, code: int
) -> None:
    c = client(site)
    tag = c.get("/maps/depot/current.yaml").headers["etag"]
    got = c.get("/maps/depot/current.yaml", headers={"If-None-Match": header.format(tag=tag)})
    assert got.status_code == code
    assert got.headers["etag"] == tag


def test_version_1_is_shown_as_the_first_version_without_a_before(fresh: Config) -> None:
    c = client(fresh)
    (cid, *_) = confirmed(c)
    assert c.post(f"/api/changes/{cid}/approve", headers=AUTH).json()["version"] == 2
    first = c.get("/maps/depot/versions/1")
    assert first.status_code == 200
    assert "The first version" in first.text
    assert "version 0" not in first.text and "change.png" not in first.text
    second = c.get("/maps/depot/versions/2").text
    assert "Before (version 1)" in second
    picture = c.get("/maps/depot/versions/2/change.png")
    assert 'src="/maps/depot/versions/2/change.png"' in second
    assert picture.status_code == 200 and picture.content[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("name", ["Mallory\n", "Mallory\nAdmin", "x" * 41])
def test_a_sign_in_name_is_refused_unless_all_of_it_is_allowed(site: Config, name: str) -> None:
    from mapserver.web import security

    assert not security.valid_name(name)
    c = client(site)
    refused = c.post("/login", data={"token": TOKEN, "name": name}, follow_redirects=False)
    assert refused.status_code == 303 and refused.headers["location"] == "/login?error=name"
    assert "set-cookie" not in refused.headers
    assert security.valid_name("Mallory O.")
