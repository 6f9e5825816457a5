"""Helpers for the daemon tests: small bundles, rsync-like uploads, a real ``mapserver run``
subprocess, waiting on conditions with a deadline, and the invariants every run must keep."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from mapserver.bundle import sha256_file
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, save_map

MAP_FILES = ("nav2_map.yaml", "nav2_map.pgm", "slam_map.yaml", "slam_map.pgm")


def make_bundle(
    path: Path,
    *,
    seed: int = 0,
    size: int = 100,
    robot: str = "r1",
    checksums: bool = True,
    manifest: dict[str, Any] | None = None,
) -> Path:
    """A small valid bundle: a walled room (``size`` px at 0.05 m) and a local map of it with one
    added box, both in the same frame. ``manifest`` entries override the defaults."""
    rng = np.random.default_rng(seed)
    path.mkdir(parents=True)
    room = np.full((size, size), FREE, np.uint8)
    room[:3, :] = room[-3:, :] = room[:, :3] = room[:, -3:] = OCCUPIED
    for _ in range(4):
        r, c = (int(v) for v in rng.integers(10, size - 20, 2))
        room[r : r + int(rng.integers(4, 12)), c : c + 3] = OCCUPIED
    save_map(path / "nav2_map.yaml", room, 0.05, (-1.0, -2.0, 0.0))
    local = room.copy()
    # The box 0.5 m clear of every wall (closer, it could be that wall seen displaced).
    walls = cv2.dilate((room == OCCUPIED).view(np.uint8), np.ones((21, 21), np.uint8)) > 0
    while True:
        r, c = (int(v) for v in rng.integers(15, size - 25, 2))
        if not walls[r : r + 6, c : c + 6].any():
            break
    local[r : r + 6, c : c + 6] = OCCUPIED
    local[:, : size // 6] = UNKNOWN
    save_map(path / "slam_map.yaml", local, 0.05, (-1.0, -2.0, 0.0))
    doc: dict[str, Any] = {
        "format": 1,
        "robot": robot,
        "stamp": "2026-11-21T10:15:00Z",
        "slam_map": "slam_map.yaml",
        "nav2_map": "nav2_map.yaml",
        "pose": {
            "nav2": {"x": 1.0, "y": 1.0, "yaw": 0.0},
            "slam": {"x": 1.0, "y": 1.0, "yaw": 0.0},
        },
    }
    if checksums:
        doc["checksums"] = {name: sha256_file(path / name) for name in MAP_FILES}
    doc.update(manifest or {})
    (path / "bundle.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def upload(
    source: Path,
    inbox: Path,
    *,
    name: str | None = None,
    order: str = "manifest-last",
    rng: random.Random | None = None,
    pause: Callable[[], None] | None = None,
) -> Path:
    """Copy bundle ``source`` into ``inbox`` the way rsync does: each file written under a
    ``.name.XXXXXX`` temp name in two chunks, then renamed. ``order``: ``manifest-last`` (the
    README's two rsync calls), ``manifest-first`` (one rsync call: it sorts, and ``bundle.yaml``
    sorts first), ``random``."""
    target = inbox / (name or source.name)
    target.mkdir()
    files = sorted(p.name for p in source.iterdir())
    if order == "manifest-last":
        files.sort(key=lambda n: n == "bundle.yaml")
    elif order == "manifest-first":
        files.sort(key=lambda n: n != "bundle.yaml")
    elif order == "random":
        (rng or random.Random(0)).shuffle(files)
    else:
        raise ValueError(order)
    for file_name in files:
        temp = target / f".{file_name}.{os.urandom(3).hex()}"
        if (source / file_name).is_symlink():  # rsync -a copies links and FIFOs as they are
            os.symlink(os.readlink(source / file_name), temp)
            os.rename(temp, target / file_name)
            continue
        if stat.S_ISFIFO((source / file_name).stat().st_mode):
            os.mkfifo(temp)
            os.rename(temp, target / file_name)
            continue
        data = (source / file_name).read_bytes()
        with temp.open("wb") as handle:
            handle.write(data[: len(data) // 2])
            handle.flush()
            if pause is not None:
                pause()
            handle.write(data[len(data) // 2 :])
        shutil.copystat(source / file_name, temp)
        os.rename(temp, target / file_name)
    return target


def wait_until(
    predicate: Callable[[], Any],
    *,
    timeout: float,
    what: str,
    interval: float = 0.02,
    context: Callable[[], str] | None = None,
) -> Any:
    """Poll ``predicate`` until it returns something true; fail after ``timeout`` seconds, with
    ``context()`` (what tells why: a log, a file) in the message."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            extra = f"\n{context()}" if context is not None else ""
            raise AssertionError(f"timed out after {timeout} s waiting for {what}{extra}")
        time.sleep(interval)


def digest(path: Path) -> dict[str, str]:
    """Relative path -> sha256 (or ``link:<target>``) of everything under ``path``."""
    out = {}
    for item in sorted(path.rglob("*")):
        rel = str(item.relative_to(path))
        if item.is_symlink():
            out[rel] = f"link:{os.readlink(item)}"
        elif stat.S_ISFIFO(item.lstat().st_mode):
            out[rel] = "fifo"
        elif item.is_file():
            out[rel] = hashlib.sha256(item.read_bytes()).hexdigest()
    return out


def layout(root: Path) -> dict[str, Path]:
    return {name: root / name for name in ("inbox", "outbox", "archive", "failed")}


def write_config(root: Path, **overrides: Any) -> Path:
    """A configuration for a daemon under ``root`` with test-friendly timings."""
    config: dict[str, Any] = {
        "inbox": "inbox",
        "outbox": "outbox",
        "archive": "archive",
        "failed": "failed",
        "settle_seconds": 0.2,
        "stale_after_seconds": 30,
        "rescan_seconds": 5,
        "workers": 2,
    }
    config.update(overrides)
    path = root / "mapserver.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def visible(path: Path) -> list[str]:
    return (
        sorted(p.name for p in path.iterdir() if not p.name.startswith("."))
        if path.exists()
        else []
    )


def assert_settled(root: Path, sources: dict[str, Path], *, failed: set[str] = frozenset()) -> None:
    """The invariants after every bundle is finished: each source is in archive/ (byte-identical,
    with exactly one complete result) or, for ids in ``failed``, in failed/ with error.yaml; the
    inbox and the daemon's own places are empty; nothing else exists."""
    dirs = layout(root)
    archived = set(sources) - set(failed)
    assert visible(dirs["inbox"]) == []
    taken = dirs["inbox"] / ".taken"
    assert not taken.exists() or list(taken.iterdir()) == []
    assert sorted(p.name for p in dirs["outbox"].iterdir()) == sorted(archived)
    assert visible(dirs["archive"]) == sorted(archived)
    assert visible(dirs["failed"]) == sorted(failed)
    for bundle_id in archived:
        assert digest(dirs["archive"] / bundle_id) == digest(sources[bundle_id]), bundle_id
        result = yaml.safe_load((dirs["outbox"] / bundle_id / "result.yaml").read_text())
        assert result["bundle"] == bundle_id
        assert {p.name for p in (dirs["outbox"] / bundle_id).iterdir()} == {
            "result.yaml",
            "overlay.png",
            "diff.png",
        }
    for bundle_id in failed:
        error = yaml.safe_load((dirs["failed"] / bundle_id / "error.yaml").read_text())
        assert set(error) == {"format", "bundle", "failed_at", "stage", "reason"}
        kept = digest(dirs["failed"] / bundle_id)
        del kept["error.yaml"]
        assert kept == digest(sources[bundle_id]), bundle_id


class Daemon:
    """A real ``mapserver run`` subprocess in its own process group (as systemd's cgroup: a kill
    reaches the workers too). Its output goes to ``root/daemon-<n>.log``."""

    def __init__(self, config: Path, *, env: dict[str, str] | None = None) -> None:
        self.config = config
        self.root = config.parent
        runs = len(list(self.root.glob("daemon-*.log")))
        self.log_path = self.root / f"daemon-{runs}.log"
        self._log = self.log_path.open("wb")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "mapserver.cli", "run", "--config", str(config)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env={**os.environ, **(env or {})},
            start_new_session=True,
        )

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, timeout: float = 30) -> None:
        wait_until(
            lambda: "ready:" in self.log() or self.process.poll() is not None,
            timeout=timeout,
            what="the daemon to be ready",
        )
        assert self.process.poll() is None, self.log()

    def wait_exit(self, timeout: float = 30) -> int:
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the daemon did not exit in {timeout} s:\n{self.log()}") from None

    def stop(self, timeout: float = 30) -> int:
        self.process.send_signal(signal.SIGTERM)
        return self.wait_exit(timeout)

    def group_gone(self) -> bool:
        """Whether no process of the daemon's group (workers, fork server) is left."""
        try:
            os.killpg(self.process.pid, 0)
        except ProcessLookupError:
            return True
        return False

    def kill_group(self) -> None:
        """kill -9 of the daemon and its workers."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()

    def close(self) -> None:
        if self.process.poll() is None:
            self.kill_group()
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.process.pid, signal.SIGKILL)  # workers of a daemon that killed itself
        self._log.close()

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def no_leaked_threads() -> Iterator[None]:
    """Fail a test that leaves threads behind (observers, pool managers)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 5
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"leaked threads: {leaked}")
        time.sleep(0.02)


def scripted_process(bundle_dir: Path, config: Any, *, bundle_id: str) -> Any:
    """A worker's process function for the tests: logs each call to ``<root>/calls.log``, then
    behaves as the manifest's robot says: ``crasher`` kills its worker (a crash in the image code,
    the OOM killer), ``slow`` takes 1.5 s more; any other runs the real pipeline."""
    from mapserver.pipeline import process_bundle

    root = bundle_dir.parents[2]  # <root>/inbox/.taken/<id>
    with (root / "calls.log").open("a") as log:
        log.write(bundle_id + "\n")
    robot = yaml.safe_load((bundle_dir / "bundle.yaml").read_text()).get("robot")
    if robot == "crasher":
        os.kill(os.getpid(), signal.SIGKILL)
    if robot == "slow":
        time.sleep(1.5)
    return process_bundle(bundle_dir, config, bundle_id=bundle_id)


def calls(root: Path) -> list[str]:
    path = root / "calls.log"
    return path.read_text().split() if path.exists() else []


@contextlib.contextmanager
def small_disk(path: Path, size: str = "8m") -> Iterator[Path]:
    """A real, small filesystem (tmpfs) at ``path``, to fill up (ENOSPC) or remount read-only
    (EROFS); the test is skipped, saying why, where none can be mounted (not root)."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("a real full disk needs a tmpfs, and mounting one needs root")
    command = ["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "mapserver-test", str(path)]
    mounted = subprocess.run(command, capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "--lazy", str(path)], check=False)


def fill_disk(folder: Path) -> Path:
    """Write ``folder/filler`` until the filesystem is full (not one more byte fits)."""
    filler = folder / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        for size in (1 << 20, 1 << 16, 1 << 12, 1):
            block = bytes(size)
            while True:
                try:
                    os.write(fd, block)
                except OSError as error:
                    assert error.errno == errno.ENOSPC, error
                    break
    finally:
        os.close(fd)
    return filler


def remount(path: Path, mode: str) -> None:
    """``mode``: ro (every write fails with EROFS) or rw. A remount to ro fails while a file is
    open for writing (the daemon rewriting its status file that very moment): tried again for
    up to 5 s."""
    deadline = time.monotonic() + 5.0
    while True:
        done = subprocess.run(
            ["mount", "-o", f"remount,{mode}", str(path)], capture_output=True, text=True
        )
        if done.returncode == 0:
            return
        if "busy" not in done.stderr or time.monotonic() > deadline:
            raise AssertionError(f"remount {mode} failed: {done.stderr}")
        time.sleep(0.05)
