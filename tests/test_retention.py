"""Retention: what is older than ``retention:`` says is deleted, a few entries a turn, each
deletion logged; dot-names and the files of bundles a change under review was seen in stay."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import pytest
from daemon_support import Daemon, layout, make_bundle, upload, visible, wait_until
from daemon_support import write_config as write_daemon_config

from mapserver.config import RetentionConfig
from mapserver.retention import DAY_S, Retention
from tests.fleet_support import WALL, Robot, write_building

NOW = time.time()


def aged(path: Path, days: float, *, file: bool = False) -> Path:
    """``path`` made (a folder, or a file) and dated ``days`` before NOW. Its ctime is now:
    the retention clock is moved ahead instead (see ``sweep``)."""
    if file:
        path.write_text("x")
    else:
        path.mkdir(parents=True)
        (path / "bundle.yaml").write_text("format: 1\n")
    stamp = NOW - days * DAY_S
    os.utime(path, (stamp, stamp))
    return path


def sweep(root: Path, settings: RetentionConfig, *, ahead_days: float, **kw: object) -> Retention:
    """A retention of ``root``'s folders whose clock is ``ahead_days`` in the future: every
    entry made now is that old, except those dated after NOW (their mtime wins)."""
    dirs = layout(root)
    return Retention(settings, dirs, clock=lambda: NOW + ahead_days * DAY_S, **kw)  # type: ignore[arg-type]


def test_entries_past_their_folders_limit_are_deleted_a_few_per_turn_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    dirs = layout(tmp_path)
    for name in ("archive", "failed", "outbox"):
        dirs[name].mkdir()
    # The clock runs 40 days ahead: everything is 40 days old, except what is dated later.
    for i in range(5):
        aged(dirs["archive"] / f"old-{i}", 0)
    aged(dirs["archive"] / "young", -35)  # 5 days old then
    aged(dirs["archive"] / ".taken-like", 0)  # a dot-name: the daemon's own
    aged(dirs["failed"] / "bad", 0)
    aged(dirs["outbox"] / "old-0", 0)
    aged(dirs["outbox"] / ".tmp-old-1-abcd", 0)
    aged(dirs["outbox"] / "stray.txt", 0, file=True)
    settings = RetentionConfig(archive_days=30, outbox_days=60)  # failed/: kept for ever
    retention = sweep(tmp_path, settings, ahead_days=40, per_turn=2)
    caplog.set_level(logging.INFO, logger="mapserver.retention")
    looked = []
    while True:
        n = retention.step()
        if n == 0:
            break
        looked.append(n)
    assert looked == [2, 2, 2, 2]  # 6 in archive/, 2 in the outbox, 2 at a time
    assert visible(dirs["archive"]) == ["young"]
    assert (dirs["archive"] / ".taken-like").is_dir()
    assert visible(dirs["failed"]) == ["bad"]
    assert visible(dirs["outbox"]) == ["old-0", "stray.txt"]  # 40 days: not past 60
    messages = [r.getMessage() for r in caplog.records]
    assert messages == [
        f"retention: deleted archive/old-{i}, 40.0 days old (archive_days: 30)" for i in range(5)
    ]
    assert retention.deleted == 5
    assert retention.step() == 0  # the next sweep is an hour away


def test_the_files_of_bundles_a_change_under_review_was_seen_in_are_kept(tmp_path: Path) -> None:
    from mapserver.config import UpdateConfig
    from mapserver.fleet.store import FleetStore

    hall = write_building(tmp_path / "src")
    robot = Robot("r1")
    with FleetStore(tmp_path / "maps", UpdateConfig(mode="review")) as store:
        store.add_map("hall", hall)
        seen = robot.observe(0, added=(WALL,), found=(("added", WALL),))  # a pending change
        store.apply(seen)
        store.apply(robot.observe(1, view=(slice(0, 240), slice(0, 100))))  # not the wall
        under_review = store.bundles_under_review()
        assert under_review == {seen.bundle_id}
        dirs = layout(tmp_path)
        for name in ("archive", "outbox"):
            for bundle_id in ("r1-001", "r1-002"):
                aged(dirs[name] / bundle_id, 0)
        settings = RetentionConfig(archive_days=1, outbox_days=1)
        retention = sweep(tmp_path, settings, ahead_days=10, keep=store.bundles_under_review)
        while retention.step():
            pass
    assert visible(dirs["archive"]) == visible(dirs["outbox"]) == [seen.bundle_id]


def test_the_daemon_prunes_by_itself_and_keeps_serving(tmp_path: Path) -> None:
    good = make_bundle(tmp_path / "src" / "good")
    bad = make_bundle(tmp_path / "src" / "bad", seed=1)
    (bad / "slam_map.pgm").write_text("not an image")
    minute = 1 / (24 * 60)  # retention in days: a minute is the smallest the test waits for
    retention = {
        "archive_days": minute / 30,  # two seconds
        "failed_days": minute / 30,
        "outbox_days": minute / 30,
        "every_hours": 1 / 3600,  # every second
    }
    config = write_daemon_config(tmp_path, retention=retention)
    dirs = layout(tmp_path)
    with Daemon(config) as daemon:
        daemon.wait_ready()
        upload(good, dirs["inbox"])
        upload(bad, dirs["inbox"])
        wait_until(
            lambda: daemon.log().count("retention: deleted ") == 3,
            timeout=30,
            what="the result, the archived and the failed bundle deleted",
        )
        assert visible(dirs["archive"]) == visible(dirs["failed"]) == visible(dirs["outbox"]) == []
        upload(good, dirs["inbox"], name="good-again")  # still serving
        wait_until(
            lambda: (dirs["outbox"] / "good-again" / "result.yaml").is_file(),
            timeout=30,
            what="another result",
        )
        assert daemon.stop() == 0, daemon.log()
    log = daemon.log()
    for line in ("archive/good", "outbox/good", "failed/bad"):
        assert f"INFO mapserver.retention: retention: deleted {line}, " in log, log
