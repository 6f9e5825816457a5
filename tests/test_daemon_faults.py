"""Faults of the server's own folders are not the bundle's: a real full disk (a tmpfs filled to
the last byte), a filesystem gone read-only, a map store another writer holds locked, a folder
the daemon may not write. The bundles wait (inbox, or taken), nothing partial is visible, the
daemon says it is degraded once (not once per bundle), and when the cause goes every bundle is
done exactly once, its result written once."""

from __future__ import annotations

import errno
import logging
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import pytest
import yaml
from daemon_support import (
    Daemon,
    assert_settled,
    fill_disk,
    layout,
    make_bundle,
    remount,
    small_disk,
    upload,
    visible,
    wait_until,
    write_config,
)
from test_service import config_for, running

from mapserver.config import load_config
from mapserver.faults import Fault, Health, fault_of, is_transient
from mapserver.outbox import Store
from mapserver.status import STATUS_NAME, read_status, report


def on_disk(disk: Path, tmp_path: Path, **overrides: Any) -> Path:
    """A daemon configuration (in ``tmp_path``) whose four folders are on ``disk``."""
    folders = {name: str(disk / name) for name in ("inbox", "outbox", "archive", "failed")}
    return write_config(tmp_path, **folders, **overrides)


def done(root: Path, ids: list[str]) -> bool:
    dirs = layout(root)
    return all(
        (dirs["archive"] / i).is_dir() and (dirs["outbox"] / i / "result.yaml").is_file()
        for i in ids
    )


def taken(root: Path) -> list[str]:
    return visible(root / "inbox" / ".taken")


def status_and_log(disk: Path, daemon: Daemon) -> str:
    """What tells why a wait failed: the status file as it is, the disk's space, the log."""
    try:
        status = (disk / "inbox" / STATUS_NAME).read_text(errors="replace")
    except OSError as error:
        status = f"unreadable: {error}"
    usage = shutil.disk_usage(disk)
    return (
        f"status file:\n{status}\nfree {usage.free} of {usage.total} bytes\n"
        f"daemon log:\n{daemon.log()}"
    )


def degraded_warnings(log: str) -> list[str]:
    return [
        line
        for line in log.splitlines()
        if line.startswith("WARNING mapserver.faults: ") and "degraded" in line
    ]


def test_a_full_disk_keeps_two_good_bundles_waiting_and_does_each_once_when_space_returns(
    tmp_path: Path,
) -> None:
    disk = tmp_path / "disk"
    with small_disk(disk):
        sources = {n: make_bundle(tmp_path / "src" / n, seed=i) for i, n in enumerate(["a", "b"])}
        # Settling takes 1 s: time to fill the disk while both bundles are in the inbox.
        config = on_disk(disk, tmp_path, settle_seconds=1.0)
        with Daemon(config) as daemon:
            daemon.wait_ready()
            for source in sources.values():
                upload(source, disk / "inbox")
            filler = fill_disk(disk)
            wait_until(
                lambda: daemon.log().count(": waits: outbox ") == 2,
                timeout=30,
                what="both bundles processed and waiting for space",
            )
            # Nothing failed, nothing partial: both are taken, the outbox holds no trace.
            assert sorted(taken(disk)) == ["a", "b"]
            assert visible(disk / "failed") == []
            assert list((disk / "outbox").iterdir()) == []
            wait_until(
                lambda: (read_status(disk / "inbox") or {}).get("degraded"),
                timeout=30,
                what="the status file to say degraded (written in place on the full disk)",
                context=lambda: status_and_log(disk, daemon),
            )
            found = report(load_config(config))
            assert found.degraded is not None and found.degraded["waiting"] == 2
            lines = found.lines(load_config(config))
            assert (
                lines[1].startswith("health:    DEGRADED since 20") and "2 bundles wait" in lines[1]
            )
            assert lines[2].startswith(f"  outbox {disk / 'outbox'}: No space left on device (")
            (fault,) = found.degraded["faults"]
            assert fault["folder"] == "outbox" and fault["reason"] == "No space left on device"
            assert fault["free_bytes"] < 64 * 1024  # a few blocks at most: the disk is full
            filler.unlink()
            wait_until(lambda: done(disk, ["a", "b"]), timeout=60, what="both results")
            wait_until(
                lambda: (read_status(disk / "inbox") or {"degraded": 1}).get("degraded") is None,
                timeout=30,
                what="the status file to say healthy again",
                context=lambda: status_and_log(disk, daemon),
            )
            assert daemon.stop() == 0, daemon.log()
        log = daemon.log()
        assert_settled(disk, sources)
        assert (disk / "inbox" / STATUS_NAME).is_file()
        warnings = degraded_warnings(log)
        assert len(warnings) == 1, log  # one, not one per bundle (and less than a minute)
        assert "outbox " + str(disk / "outbox") in warnings[0] and " free of " in warnings[0]
        assert "recovered after" in log
        for bundle_id in sources:  # processed once: the outcome waited, it was not redone
            assert log.count(f"{bundle_id}: queue ") == 1, log
            assert log.count(f"{bundle_id}: done: ok") == 1, log
        assert "failed at stage" not in log


def test_the_status_file_is_there_when_the_daemon_says_it_is_ready(tmp_path: Path) -> None:
    """The first status file is written before the "ready" line (and READY=1): a disk that
    fills at once after still has that file's block to rewrite in place. Written after it, a
    test (or an operator) that filled the disk on "ready" left the daemon without any status
    file to say it was degraded (the CI failure of the full-disk test above)."""
    disk = tmp_path / "disk"
    with small_disk(disk), Daemon(on_disk(disk, tmp_path, settle_seconds=1.0)) as daemon:
        daemon.wait_ready()
        status = read_status(disk / "inbox")  # no waiting: it must be there already
        assert status is not None and status["pid"] == daemon.process.pid
        assert status["degraded"] is None
        assert daemon.stop() == 0, daemon.log()


def test_a_filesystem_gone_read_only_leaves_the_upload_in_the_inbox_until_it_is_writable(
    tmp_path: Path,
) -> None:
    disk = tmp_path / "disk"
    with small_disk(disk):
        source = make_bundle(tmp_path / "src" / "run-1")
        config = on_disk(disk, tmp_path, settle_seconds=1.0)
        with Daemon(config) as daemon:
            daemon.wait_ready()
            upload(source, disk / "inbox")
            remount(disk, "ro")
            try:
                wait_until(
                    lambda: "run-1: cannot take it now" in daemon.log(),
                    timeout=30,
                    what="a take refused by the read-only filesystem",
                )
                wait_until(lambda: degraded_warnings(daemon.log()), timeout=10, what="degraded")
                assert visible(disk / "inbox") == ["run-1"] and taken(disk) == []
            finally:
                remount(disk, "rw")
            wait_until(lambda: done(disk, ["run-1"]), timeout=60, what="the result")
            assert daemon.stop() == 0, daemon.log()
        log = daemon.log()
        assert_settled(disk, {"run-1": source})
        assert "Read-only file system" in degraded_warnings(log)[0]
        assert len(degraded_warnings(log)) == 1 and "recovered after" in log, log


def _wait_held_for_the_store(daemon: Daemon, root: Path, name: str) -> None:
    """Until the daemon holds bundle ``name`` for the map store, and its status file says it is
    degraded."""
    wait_until(
        lambda: f"{name}: waits: maps " in daemon.log(),
        timeout=60,
        what="the bundle waiting for the map store",
    )
    wait_until(
        lambda: (read_status(root / "inbox") or {}).get("degraded"),
        timeout=10,
        what="the status file to say degraded",
    )


def test_a_locked_map_store_keeps_the_bundle_waiting_and_applies_it_once_when_released(
    tmp_path: Path,
) -> None:
    from test_fleet_daemon import applied, setup

    config, sources = setup(tmp_path, 1)
    (name,) = sources
    holder = sqlite3.connect(tmp_path / "maps" / "store.db", isolation_level=None)
    try:
        with Daemon(config) as daemon:
            daemon.wait_ready()
            holder.execute("BEGIN IMMEDIATE")  # another writer (an operator's sqlite3 shell)
            upload(sources[name], layout(tmp_path)["inbox"])
            _wait_held_for_the_store(daemon, tmp_path, name)
            assert "database is locked" in daemon.log()
            assert taken(tmp_path) == [name]
            assert list((tmp_path / "outbox").iterdir()) == []
            assert visible(tmp_path / "failed") == []
            holder.execute("COMMIT")
            wait_until(lambda: done(tmp_path, [name]), timeout=60, what="the result")
            assert daemon.stop() == 0, daemon.log()
    finally:
        holder.close()
    assert_settled(tmp_path, sources)
    assert applied(tmp_path) == [name]
    assert "failed at stage" not in daemon.log()


def test_a_map_store_a_worker_cannot_read_keeps_the_bundle_and_processes_it_again_after(
    tmp_path: Path,
) -> None:
    """The store's file replaced under the daemon (a restore gone wrong, a damaged disk): the
    worker cannot link the bundle to its map. That is the server's fault, not the bundle's: it
    waits (it went to failed/ before), the daemon says it is degraded,
    and once the file is back the bundle is processed again and applied once."""
    from test_fleet_daemon import applied, setup

    config, sources = setup(tmp_path, 1)
    (name,) = sources
    db = tmp_path / "maps" / "store.db"
    with Daemon(config) as daemon:
        daemon.wait_ready()
        # The daemon's own connection keeps the real file; a worker opens the name.
        db.rename(db.with_name("store.db.moved"))
        db.write_bytes(b"not a database, " * 512)
        upload(sources[name], layout(tmp_path)["inbox"])
        _wait_held_for_the_store(daemon, tmp_path, name)
        assert "cannot read the map store" in daemon.log()
        assert taken(tmp_path) == [name]
        assert visible(tmp_path / "failed") == [] and visible(tmp_path / "outbox") == []
        db.unlink()
        db.with_name("store.db.moved").rename(db)
        wait_until(lambda: done(tmp_path, [name]), timeout=60, what="the result")
        wait_until(
            lambda: not (read_status(tmp_path / "inbox") or {}).get("degraded", True),
            timeout=30,
            what="the status file to say healthy again",
        )
        assert daemon.stop() == 0, daemon.log()
    assert (
        f"{name}: processed again after: cannot read the map store: file is not a" in daemon.log()
    )
    assert_settled(tmp_path, sources)
    assert applied(tmp_path) == [name]
    assert "failed at stage" not in daemon.log()


def test_a_result_that_cannot_be_written_after_the_store_applied_the_bundle_counts_it_once(
    tmp_path: Path,
) -> None:
    """Apply commits (the store is not on the full disk), then the result cannot be written:
    the retry applies the bundle again as a no-op ("already applied") and writes its result."""
    from test_fleet_daemon import applied, setup

    disk = tmp_path / "disk"
    with small_disk(disk):
        _, sources = setup(tmp_path, 1)
        (name,) = sources
        config = on_disk(disk, tmp_path, workers=1, settle_seconds=1.0, maps=str(tmp_path / "maps"))
        with Daemon(config) as daemon:
            daemon.wait_ready()
            upload(sources[name], disk / "inbox")
            filler = fill_disk(disk)
            wait_until(
                lambda: f"{name}: waits: outbox " in daemon.log(), timeout=30, what="waiting"
            )
            assert applied(tmp_path) == [name]
            filler.unlink()
            wait_until(lambda: done(disk, [name]), timeout=60, what="the result")
            assert daemon.stop() == 0, daemon.log()
        log = daemon.log()
        assert_settled(disk, sources)
        assert applied(tmp_path) == [name]
        assert f"{name}: update" in log and "already applied" in log, log
        result = yaml.safe_load((disk / "outbox" / name / "result.yaml").read_text())
        assert result["map"]["name"] == "site"
        assert [d["change"] for d in result["differences"]] == [1]


# -- in process: faults the tests cannot make for real as root ---------------------------------


def test_a_folder_the_daemon_may_not_write_keeps_the_bundle_and_its_result_is_written_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """EACCES on archive/ (a chmod a root test cannot feel): the result is published once, the
    bundle stays taken, and is archived once the folder can be written."""
    refuse = {"on": True}
    archive = Store.archive

    def archive_or_refuse(self: Store, bundle_id: str) -> Path:
        if refuse["on"]:
            target = self.archive_dir / bundle_id
            raise PermissionError(errno.EACCES, "Permission denied", str(target))
        return archive(self, bundle_id)

    monkeypatch.setattr(Store, "archive", archive_or_refuse)
    source = make_bundle(tmp_path / "src" / "run-1")
    dirs = layout(tmp_path)
    with running(config_for(tmp_path)) as (service, _):
        upload(source, dirs["inbox"])
        wait_until(lambda: service.health.degraded, timeout=30, what="degraded")
        (fault,) = service.health.faults
        assert (fault.folder, fault.reason) == ("archive", "Permission denied")
        assert service.health.waiting == 1
        result = dirs["outbox"] / "run-1" / "result.yaml"
        assert result.is_file() and taken(tmp_path) == ["run-1"]
        written = (result.read_bytes(), result.stat().st_mtime_ns)
        refuse["on"] = False
        wait_until(lambda: done(tmp_path, ["run-1"]), timeout=60, what="archived")
        wait_until(lambda: not service.health.degraded, timeout=10, what="healthy")
    assert_settled(tmp_path, {"run-1": source})
    assert (result.read_bytes(), result.stat().st_mtime_ns) == written  # not written again


def test_a_bundle_folder_the_daemon_may_not_write_is_said_once_and_taken_when_it_may(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A bundle folder copied from a read-only one (mode 0555) cannot be moved: a directory
    moves only with write permission on itself. That is the bundle's fault, not the inbox's
    (session 53's review: the inbox was reported degraded, "Permission denied", for ever). As
    root the test may write anything: the refusal and the permission are simulated."""
    from mapserver import service as service_module

    locked, tries = {"on": True}, {"n": 0}
    claim, may_write = Store.claim, service_module.may_write

    def claim_or_refuse(self: Store, name: str, bundle_id: str) -> Path:
        tries["n"] += 1
        if locked["on"]:
            raise PermissionError(errno.EACCES, "Permission denied", str(self.inbox / name))
        return claim(self, name, bundle_id)

    monkeypatch.setattr(Store, "claim", claim_or_refuse)
    monkeypatch.setattr(
        service_module,
        "may_write",
        lambda path: may_write(path) and not (locked["on"] and path.name == "ro-1"),
    )
    caplog.set_level(logging.INFO, logger="mapserver")
    source = make_bundle(tmp_path / "src" / "ro-1")
    dirs = layout(tmp_path)
    config = config_for(tmp_path, rescan_seconds=1.0)
    with running(config) as (service, _):
        upload(source, dirs["inbox"])
        said = "ro-1: cannot take it: the server may not write its folder"
        wait_until(lambda: said in caplog.text, timeout=30, what="the bundle's folder named")
        wait_until(lambda: tries["n"] >= 2, timeout=30, what="a second try (the rescan)")
        assert not service.health.degraded and service.health.faults == ()
        assert caplog.text.count(said) == 1  # once, not once per try
        assert visible(dirs["inbox"]) == ["ro-1"]
        locked["on"] = False
        wait_until(lambda: done(tmp_path, ["ro-1"]), timeout=60, what="processed")
    assert "ro-1: its folder may be written now: taken" in caplog.text
    assert_settled(tmp_path, {"ro-1": source})


def test_a_map_version_that_cannot_be_published_makes_the_daemon_degraded_until_it_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk under maps/ while a confirmed change is published (auto mode): the bundle
    is done (its evidence counted), the daemon is degraded, and the version is published when
    space returns, without another bundle."""
    from test_fleet_daemon import setup

    from mapserver.fleet import publish

    _, sources = setup(tmp_path, 1)
    (name,) = sources
    full = {"on": True}
    write_version = publish.write_version

    def write_or_fail(folder: Path, *args: Any) -> Any:
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device", str(folder / "v0002.pgm"))
        return write_version(folder, *args)

    monkeypatch.setattr(publish, "write_version", write_or_fail)
    update = {"mode": "auto", "confirm_sessions": 1, "confirm_span_hours": 0}
    config = config_for(tmp_path, maps="maps", update=update)
    with running(config) as (service, _):
        upload(sources[name], layout(tmp_path)["inbox"])
        wait_until(lambda: done(tmp_path, [name]), timeout=30, what="the bundle done")
        wait_until(lambda: service.health.degraded, timeout=10, what="degraded")
        (fault,) = service.health.faults
        assert fault.folder == "maps" and fault.reason == "No space left on device"
        assert not (tmp_path / "maps" / "site" / "v0002.yaml").exists()
        full["on"] = False
        wait_until(lambda: not service.health.degraded, timeout=30, what="published")
    current = yaml.safe_load((tmp_path / "maps" / "site" / "current.yaml").read_text())
    assert current["image"] == "v0002.pgm"
    assert_settled(tmp_path, sources)


# -- the pieces ---------------------------------------------------------------------------------


def test_transient_errors_are_the_servers_and_the_rest_the_bundles(tmp_path: Path) -> None:
    for code in (errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EACCES, errno.EROFS):
        assert is_transient(OSError(code, "x")), code
    for code in (errno.ENOENT, errno.EEXIST, errno.EXDEV, errno.ENOTDIR):
        assert not is_transient(OSError(code, "x")), code
    assert not is_transient(ValueError("a result YAML cannot hold this"))
    db = tmp_path / "db.sqlite"
    first = sqlite3.connect(db, isolation_level=None)
    first.execute("CREATE TABLE t (x INTEGER PRIMARY KEY)")
    second = sqlite3.connect(db, isolation_level=None, timeout=0.05)
    try:
        first.execute("BEGIN IMMEDIATE")
        with pytest.raises(sqlite3.OperationalError) as locked:
            second.execute("BEGIN IMMEDIATE")
        assert is_transient(locked.value)
        first.execute("INSERT INTO t VALUES (1)")
        with pytest.raises(sqlite3.IntegrityError) as duplicate:
            first.execute("INSERT INTO t VALUES (1)")
        assert not is_transient(duplicate.value)  # a bug, not the disk
    finally:
        first.close()
        second.close()


def test_a_fault_names_the_folder_of_the_step_that_failed(tmp_path: Path) -> None:
    folders = {n: tmp_path / n for n in ("inbox", "outbox", "archive", "failed", "maps")}
    for path in folders.values():
        path.mkdir()
    rename = PermissionError(
        errno.EACCES, "Permission denied", str(folders["inbox"] / ".taken/a"), None
    )
    rename.filename2 = str(folders["archive"] / "a")
    assert fault_of(rename, folders, "archive").folder == "archive"
    staged = OSError(errno.ENOSPC, "No space left", str(folders["inbox"] / ".taken/.a.tmp"))
    assert fault_of(staged, folders, "failed").folder == "inbox"
    locked = fault_of(sqlite3.OperationalError("database is locked"), folders, "maps")
    assert (locked.folder, locked.path, locked.reason) == (
        "maps",
        folders["maps"],
        "database is locked",
    )
    assert locked.free_bytes is not None and locked.free_bytes > 0


def test_health_warns_once_a_minute_and_backs_off(caplog: pytest.LogCaptureFixture) -> None:
    now = [1000.0]
    health = Health(clock=lambda: now[0])
    full = Fault("outbox", Path("/srv/outbox"), "No space left on device", 0, 2**30)
    caplog.set_level(logging.INFO, logger="mapserver.faults")
    retries = []
    for _ in range(150):  # 150 s of one-second turns, a bundle more waiting every turn
        health.update([full] * (health.waiting + 1), health.waiting + 1)
        if health.due():
            retries.append(now[0] - 1000.0)
            health.retried()
        now[0] += 1.0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3, warnings  # at 0, 60 and 120 s
    assert warnings[0].startswith("degraded: outbox /srv/outbox: No space left on device (0 B free")
    assert warnings[1].startswith("still degraded after 60 s: ")
    assert retries[:7] == [1.0, 3.0, 7.0, 15.0, 31.0, 51.0, 71.0]  # 1, 2, 4, 8, 16, 20, 20 s
    assert health.document() == {
        "since": health.since,
        "waiting": 150,
        "faults": [
            {"folder": "outbox", "path": "/srv/outbox", "reason": full.reason, "free_bytes": 0}
        ],
    }
    health.update([], 0)
    assert not health.degraded and health.document() is None and health.summary() == ""
    assert caplog.records[-1].getMessage().startswith("recovered after 150 s")
