"""The fleet map fed by a real ``mapserver run``: kill -9 while a bundle's evidence is applied,
after its commit, and while a version is written; then restart. Every bundle counts once, the
change is published once, and every bundle ends archived with its result."""

from __future__ import annotations

import shutil
import signal
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml

from mapserver.bundle import sha256_file
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, load_map, save_map
from mapserver.service import CRASH_ENV
from tests.daemon_support import (
    Daemon,
    assert_settled,
    layout,
    upload,
    visible,
    wait_until,
    write_config,
)

SIZE = 120
BOX = (slice(60, 68), slice(70, 78))  # the new obstacle, in map rows/cols
STAMPS = [f"2026-11-2{d}T{h:02d}:00:00Z" for d, h in ((1, 8), (1, 15), (2, 2), (2, 9), (2, 20))]


def room() -> np.ndarray:
    state = np.full((SIZE, SIZE), FREE, np.uint8)
    state[:3, :] = state[-3:, :] = state[:, :3] = state[:, -3:] = OCCUPIED
    state[20:50, 30:33] = OCCUPIED
    state[85:88, 40:90] = OCCUPIED
    return state


def building_map(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return save_map(folder / "site.yaml", room(), 0.05, (-1.0, -2.0, 0.0))


def fleet_bundle(path: Path, site: Path, stamp: str, robot: str) -> Path:
    """A session that sees the room with the box in it, on the stored building map."""
    path.mkdir(parents=True)
    shutil.copyfile(site, path / "nav2_map.yaml")
    shutil.copyfile(site.with_suffix(".pgm"), path / "site.pgm")
    local = room()
    local[BOX] = OCCUPIED
    local[:, :15] = UNKNOWN
    save_map(path / "slam_map.yaml", local, 0.05, (-1.0, -2.0, 0.0))
    names = ("nav2_map.yaml", "site.pgm", "slam_map.yaml", "slam_map.pgm")
    doc = {
        "format": 1,
        "robot": robot,
        "stamp": stamp,
        "slam_map": "slam_map.yaml",
        "nav2_map": "nav2_map.yaml",
        "pose": {
            "nav2": {"x": 1.0, "y": 1.0, "yaw": 0.0},
            "slam": {"x": 1.0, "y": 1.0, "yaw": 0.0},
        },
        "checksums": {n: sha256_file(path / n) for n in names},
    }
    (path / "bundle.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def setup(tmp_path: Path, n: int) -> tuple[Path, dict[str, Path]]:
    from mapserver.config import UpdateConfig
    from mapserver.fleet.store import FleetStore

    site = building_map(tmp_path / "building")
    with FleetStore(tmp_path / "maps", UpdateConfig(mode="auto")) as store:
        store.add_map("site", site)
    sources = {
        f"run-{i}": fleet_bundle(tmp_path / "src" / f"run-{i}", site, STAMPS[i], f"r{i % 2 + 1}")
        for i in range(n)
    }
    config = write_config(
        tmp_path, workers=1, maps="maps", update={"mode": "auto", "confirm_sessions": 3}
    )
    return config, sources


def results(root: Path) -> int:
    return len(list((root / "outbox").glob("*/result.yaml")))


def applied(root: Path) -> list[str]:
    conn = sqlite3.connect(root / "maps" / "store.db")
    try:
        return sorted(r[0] for r in conn.execute("SELECT bundle_id FROM bundles"))
    finally:
        conn.close()


def assert_fleet_settled(root: Path, sources: dict[str, Path], version: int = 2) -> None:
    assert_settled(root, sources)
    assert applied(root) == sorted(sources)  # each bundle once
    doc = yaml.safe_load((root / "maps/site/changes.yaml").read_text())
    (change,) = doc["changes"]
    # Confirmed by the third session applied (bundles uploaded together may be applied in
    # either order); later ones are judged against the version that has it.
    assert change["sessions"] == 3 and len(set(change["bundles"])) == 3
    assert set(change["bundles"]) <= set(sources)
    assert (change["state"], change["version"], doc["current_version"]) == (
        "published",
        version,
        version,
    )
    assert sorted(p.name for p in (root / "maps/site").glob("v*.yaml")) == [
        "v0001.yaml",
        f"v{version:04d}.yaml",
    ]
    # A version written and killed before its commit is set aside when the daemon starts
    # again, and its number is not given to the version published instead (session 59).
    aside = sorted(p.name for p in (root / "maps/site/.unpublished").glob("v*"))
    assert aside == ([] if version == 2 else ["v0002.pgm", "v0002.yaml"])
    current = load_map(root / "maps/site/current.yaml").state
    expected = room()
    expected[BOX] = OCCUPIED
    assert np.array_equal(current, expected)
    for bundle_id in sources:
        result = yaml.safe_load((root / "outbox" / bundle_id / "result.yaml").read_text())
        assert result["map"]["name"] == "site" and result["map"]["version"] == 1
        changes = [d.get("change") for d in result["differences"] if d["kind"] == "added"]
        assert changes == [change["id"]], (bundle_id, result["differences"])


@pytest.mark.parametrize("point", ["evidence-applied", "bundle-applied", "version-written"])
def test_kill_9_while_the_fleet_map_is_updated_counts_every_bundle_once(
    tmp_path: Path, point: str
) -> None:
    config, sources = setup(tmp_path, 3)
    inbox = layout(tmp_path)["inbox"]
    names = list(sources)
    # The crash comes at the first bundle (evidence) or at the third (the one that confirms).
    crash_at = 2 if point == "version-written" else 0
    with Daemon(config, env={CRASH_ENV: point}) as first:
        first.wait_ready()
        for name in names[: crash_at + 1]:
            upload(sources[name], inbox)
            if name != names[crash_at]:
                wait_until(
                    lambda n=name: (tmp_path / "outbox" / n / "result.yaml").exists(),
                    timeout=30,
                    what=name,
                )
        assert first.wait_exit() == -signal.SIGKILL, first.log()
        wait_until(first.group_gone, timeout=10, what="the workers to exit")
    with Daemon(config) as second:
        second.wait_ready()
        for name in names[crash_at + 1 :]:
            upload(sources[name], inbox)
        wait_until(lambda: results(tmp_path) == len(names), timeout=60, what="all results")
        wait_until(
            lambda: visible(inbox) == [],  # the daemon's own files are dot-names
            timeout=10,
            what="empty inbox",
        )
        assert second.stop() == 0, second.log()
    assert_fleet_settled(tmp_path, sources, 3 if point == "version-written" else 2)


def test_two_kill_9s_of_a_busy_daemon_lose_and_repeat_no_evidence(tmp_path: Path) -> None:
    config, sources = setup(tmp_path, 5)
    inbox = layout(tmp_path)["inbox"]
    names = list(sources)
    done = 0
    for kill_after in (2, 4):
        with Daemon(config) as daemon:
            daemon.wait_ready()
            for name in names[done:kill_after]:
                upload(sources[name], inbox)
            wait_until(
                lambda k=kill_after: results(tmp_path) >= k,
                timeout=60,
                what=f"{kill_after} results",
            )
            daemon.kill_group()
        done = kill_after
    with Daemon(config) as last:
        last.wait_ready()
        for name in names[done:]:
            upload(sources[name], inbox)
        wait_until(lambda: results(tmp_path) == len(names), timeout=60, what="all results")
        assert last.stop() == 0, last.log()
    assert_fleet_settled(tmp_path, sources)


def test_a_daemon_refuses_to_start_on_a_damaged_store_and_says_how_to_recover(
    tmp_path: Path,
) -> None:
    config, _ = setup(tmp_path, 1)
    for name in ("store.db-wal", "store.db-shm"):
        (tmp_path / "maps" / name).unlink(missing_ok=True)
    (tmp_path / "maps" / "store.db").write_bytes(b"\0garbage" * 512)
    with Daemon(config) as daemon:
        assert daemon.wait_exit() == 1
        log = daemon.log()
    assert "store.db" in log and "restore" in log and "mapserver maps add" in log, log
    assert (tmp_path / "maps" / "site" / "v0001.pgm").is_file()  # the versions are untouched


def test_process_is_refused_while_a_daemon_feeds_the_store_and_review_commands_are_not(
    tmp_path: Path,
) -> None:
    import subprocess
    import sys

    config, sources = setup(tmp_path, 1)
    other = tmp_path / "other.yaml"  # another inbox, the same store
    other.write_text(yaml.safe_dump({"maps": "maps", "outbox": "out2", "inbox": "inbox2"}))
    with Daemon(config) as daemon:
        daemon.wait_ready()
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "mapserver.cli",
                "process",
                "--config",
                str(other),
                str(sources["run-0"]),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 1
        assert f"(pid {daemon.process.pid}) feeds the map store" in done.stderr, done.stderr
        listed = subprocess.run(
            [sys.executable, "-m", "mapserver.cli", "changes", "list", "--config", str(other)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert listed.returncode == 0, listed.stderr
        assert daemon.stop() == 0
    assert not (tmp_path / "out2").exists()
