"""One daemon per inbox: ``mapserver run`` holds an exclusive ``flock`` on ``inbox/.mapserver.lock``.

A flock belongs to the open file, and the kernel drops it when the process ends, whatever the
way (kill -9 and power loss included): a restart needs no manual step, and a pid left in the file
by a dead daemon means nothing. The file holds the pid of the daemon that holds the lock, for the
messages and ``mapserver status``. It is never deleted: a daemon that unlinked it could race a
second one that had opened it a moment before, and each would then lock a different file.

The name starts with a dot, so the daemon never reads it as an upload (contract section 2), and
it lives in the inbox, the one folder every daemon on these folders must watch.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from mapserver.errors import ConfigError, MapserverError

if TYPE_CHECKING:
    from mapserver.config import Config

LOCK_NAME = ".mapserver.lock"

# A reader (daemon_pid) holds a shared lock for a few microseconds; a daemon starting at that
# moment tries again for this long before it concludes that another daemon runs.
_ACQUIRE_FOR_S = 0.3
# A daemon writes its pid right after it takes the lock; a reader waits this long for it.
_PID_WAIT_S = 0.5


class AlreadyRunning(MapserverError):
    """Another daemon holds the inbox's lock."""

    default_stage = "run"

    def __init__(self, pid: int | None, inbox: Path) -> None:
        self.pid = pid
        self.inbox = inbox
        shown = str(pid) if pid else "unknown"
        super().__init__(f"another mapserver (pid {shown}) is running on {inbox}")


def lock_path(config: Config) -> Path:
    """The lock file of the daemon that serves ``config``'s folders."""
    return config.inbox / LOCK_NAME


def daemon_pid(config: Config) -> int | None:
    """The pid of the ``mapserver run`` that serves ``config``'s inbox, or None when none does
    (test it with ``is None``: it is 0 for a daemon that has taken the lock this very moment and
    not yet written its pid).

    Raises :class:`~mapserver.errors.MapserverError` when the lock file cannot be read (no
    permission): "not running" would then be a guess.
    """
    path = lock_path(config)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    except OSError as error:
        raise MapserverError(
            f"cannot read the daemon's lock file: {error.strerror}", file=path, stage="status"
        ) from None
    try:
        if _try_lock(fd, fcntl.LOCK_SH):
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        return _read_pid(fd) or 0
    finally:
        os.close(fd)


@contextlib.contextmanager
def daemon_lock(config: Config) -> Iterator[Path]:
    """Hold the lock of ``config``'s inbox (created if missing) for the ``with`` block.

    Raises :class:`AlreadyRunning` at once when another process holds it.
    """
    try:
        config.inbox.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create the inbox: {error.strerror}", file=config.inbox) from None
    with _hold(lock_path(config), lambda pid: AlreadyRunning(pid, config.inbox)) as path:
        yield path


class StoreOwned(MapserverError):
    """Another process (a daemon, or a ``mapserver process``) feeds this map store."""

    default_stage = "update"

    def __init__(self, pid: int | None, root: Path) -> None:
        self.pid = pid
        shown = str(pid) if pid else "unknown"
        super().__init__(
            f"another mapserver (pid {shown}) feeds the map store {root}: bundles reach the "
            "store through one process only (upload them to its inbox instead)"
        )


@contextlib.contextmanager
def store_lock(root: Path) -> Iterator[Path]:
    """Hold the feeding lock of the map store at ``root`` for the ``with`` block: the one
    process that applies bundles to it (the daemon, or one ``mapserver process``). Review
    commands (approve, reject, rollback) need no lock: the database serialises them."""
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create the map store: {error.strerror}", file=root) from None
    with _hold(root / LOCK_NAME, lambda pid: StoreOwned(pid, root)) as path:
        yield path


@contextlib.contextmanager
def _hold(path: Path, busy: Callable[[int | None], MapserverError]) -> Iterator[Path]:
    try:
        # Held open read-only (a flock needs no more): a file held open for writing would keep
        # the filesystem from being remounted read-only.
        fd = os.open(path, os.O_RDONLY | os.O_CREAT | os.O_CLOEXEC, 0o664)
    except OSError as error:
        raise ConfigError(f"cannot open the lock file: {error.strerror}", file=path) from None
    try:
        deadline = time.monotonic() + _ACQUIRE_FOR_S
        while not _try_lock(fd, fcntl.LOCK_EX):
            if time.monotonic() >= deadline:
                raise busy(_read_pid(fd))
            time.sleep(0.01)
        _write_pid(path)
        yield path
    finally:
        os.close(fd)  # releases the lock


def _write_pid(path: Path) -> None:
    """Over the old pid first, then cut: on a full disk the file's block is reused; a pid that
    cannot be written (it is only for messages) does not stop the daemon."""
    text = f"{os.getpid()}\n".encode()
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
        try:
            os.pwrite(fd, text, 0)
            os.ftruncate(fd, len(text))
        finally:
            os.close(fd)


def _try_lock(fd: int, kind: int) -> bool:
    try:
        fcntl.flock(fd, kind | fcntl.LOCK_NB)
    except OSError as error:
        if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            return False
        raise
    return True


def _read_pid(fd: int) -> int | None:
    """The pid in the lock file; waits a moment for a daemon that has just taken the lock."""
    deadline = time.monotonic() + _PID_WAIT_S
    while True:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        if text.isdigit():
            return int(text)
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.01)
