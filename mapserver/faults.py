"""When the daemon's own folders fail, not a bundle: a full disk (ENOSPC, EDQUOT), an I/O error,
a folder it may not write (EACCES, EPERM, EROFS), a map store that is busy, full or damaged.

None of these is the bundle's fault, so none sends a bundle to ``failed/``. The bundle waits
where it is (in the inbox, or taken and finished by a worker but not yet written), the daemon
reports itself degraded (systemd ``STATUS=``, ``inbox/.mapserver.status``, :attr:`Health`),
says so in ONE warning a minute naming the folder and its free space, and tries again after a
pause that grows (1 s, 2 s, 4 s ... 20 s). When the cause goes, what waited is done, once.

Three pieces: :func:`is_transient` tells such an error from the bundle's own; :func:`fault_of`
names the folder it concerns; :class:`Health` keeps the degraded state, its warnings and the
retry schedule (the service keeps what waits, see ``Service._retry_waiting``).
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import sqlite3
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# The server's folders failing, not the bundle: the same write will work once the cause goes.
TRANSIENT_ERRNOS = frozenset(
    {
        errno.ENOSPC,
        errno.EDQUOT,
        errno.EIO,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.ENFILE,
        errno.EMFILE,
        errno.ENOMEM,
        errno.EBUSY,
        errno.ESTALE,
        errno.ETIMEDOUT,
    }
)

# SQLite's primary result codes that say the database (its file, its disk, another writer) is
# the problem: BUSY, LOCKED, NOMEM, READONLY, IOERR, CORRUPT, FULL, CANTOPEN, PROTOCOL, NOTADB.
_SQLITE_CODES = frozenset({5, 6, 7, 8, 10, 11, 13, 14, 15, 26})
_SQLITE_WORDS = ("locked", "busy", "disk", "full", "readonly", "unable to open", "malformed")


def is_transient(error: BaseException) -> bool:
    """Whether ``error`` is the server's folders or map store failing (retry later) rather than
    something about the bundle (fail it)."""
    if isinstance(error, sqlite3.Error):
        code = getattr(error, "sqlite_errorcode", None)  # Python >= 3.11
        if code is not None:
            return (int(code) & 0xFF) in _SQLITE_CODES
        return any(word in str(error) for word in _SQLITE_WORDS)
    return isinstance(error, OSError) and error.errno in TRANSIENT_ERRNOS


@dataclass(frozen=True)
class Fault:
    """A folder of the server that failed: its name in the configuration, its path, what went
    wrong, and its free space when the fault was seen."""

    folder: str
    path: Path
    reason: str
    free_bytes: int | None = None
    total_bytes: int | None = None

    def describe(self) -> str:
        """``outbox /var/lib/mapserver/outbox: No space left on device (0 B free of 20 GiB)``"""
        if self.free_bytes is None or self.total_bytes is None:
            space = "free space unknown"
        else:
            space = f"{format_size(self.free_bytes)} free of {format_size(self.total_bytes)}"
        return f"{self.folder} {self.path}: {self.reason} ({space})"

    def document(self) -> dict[str, Any]:
        return {
            "folder": self.folder,
            "path": str(self.path),
            "reason": self.reason,
            "free_bytes": self.free_bytes,
        }


def fault_of(error: BaseException, folders: Mapping[str, Path], default: str) -> Fault:
    """The :class:`Fault` that ``error`` is, with the folder's free space now. The folder is
    ``default`` (the one the failed step writes to) when the error names no file (SQLite's
    errors) or names a file in it (a rename names both ends); else the configured folder the
    named file lies in."""
    matches: dict[str, int] = {}
    for name in (getattr(error, "filename", None), getattr(error, "filename2", None)):
        if not name:
            continue
        named = os.path.abspath(os.fsdecode(name))
        for key, root in folders.items():
            text = str(root)
            if named == text or named.startswith(text + os.sep):
                matches[key] = max(matches.get(key, -1), len(text))
    folder = default
    if matches and default not in matches:
        folder = max(matches, key=lambda key: matches[key])
    if isinstance(error, OSError) and error.strerror:
        reason = error.strerror
    else:
        reason = str(error) or type(error).__name__
    return fault_in(folder, folders, reason)


def fault_in(folder: str, folders: Mapping[str, Path], reason: str) -> Fault:
    """The :class:`Fault` of configured ``folder`` (a key of ``folders``), with its free space
    now: for a fault a worker saw, which sends back only what it was."""
    path = folders.get(folder, Path(folder))
    try:
        usage = shutil.disk_usage(path)
    except OSError:
        return Fault(folder, path, reason)
    return Fault(folder, path, reason, usage.free, usage.total)


class Health:
    """The daemon's degraded state: the faults that keep work waiting, since when, and the
    retry schedule. Read by other threads (the metrics) through :attr:`degraded`,
    :attr:`faults`, :attr:`waiting` and :attr:`since`; changed only by the main loop through
    :meth:`update` and :meth:`retried`.

    Logs one WARNING when the daemon becomes degraded, one a minute while it stays so (never
    one per bundle), and one INFO line when it recovers.
    """

    def __init__(
        self,
        *,
        warn_every_s: float = 60.0,
        first_retry_s: float = 1.0,
        max_retry_s: float = 20.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._warn_every_s = warn_every_s
        self._first_retry_s = first_retry_s
        self._max_retry_s = max_retry_s
        self._clock = clock
        self.faults: tuple[Fault, ...] = ()
        """The current faults, one per folder (the latest seen)."""
        self.waiting = 0
        """Bundles that wait for the faults to clear."""
        self.since: str | None = None
        """When the daemon became degraded (UTC, ISO 8601); None while it is not."""
        self._since_clock = 0.0
        self._next_warning = 0.0
        self._retry_every = first_retry_s
        self._next_retry = 0.0

    @property
    def degraded(self) -> bool:
        return bool(self.faults)

    def update(self, faults: Sequence[Fault], waiting: int) -> None:
        """The faults that keep work waiting now (none: healthy), and how many bundles wait."""
        latest: dict[str, Fault] = {}
        for fault in faults:
            latest[fault.folder] = fault
        now = self._clock()
        was = self.degraded
        self.faults, self.waiting = tuple(latest.values()), waiting
        if not was and self.faults:
            self.since = _utc_now()
            self._since_clock = now
            self._retry_every = self._first_retry_s
            self._next_retry = now + self._retry_every
            self._next_warning = now + self._warn_every_s
            log.warning(
                "degraded: %s; %s, retried in %g s",
                self._faults_text(),
                self._waiting_text(),
                self._retry_every,
            )
        elif was and not self.faults:
            log.info(
                "recovered after %.0f s: the folders and the map store work again; the bundles "
                "that waited are done",
                now - self._since_clock,
            )
            self.since = None
        elif self.faults and now >= self._next_warning:
            self._next_warning = now + self._warn_every_s
            log.warning(
                "still degraded after %.0f s: %s; %s, retried every %g s",
                now - self._since_clock,
                self._faults_text(),
                self._waiting_text(),
                self._retry_every,
            )

    def due(self) -> bool:
        """Whether it is time to try what waits again."""
        return self.degraded and self._clock() >= self._next_retry

    def retried(self) -> None:
        """A retry was made (and did not clear everything): wait longer before the next."""
        self._retry_every = min(self._retry_every * 2.0, self._max_retry_s)
        self._next_retry = self._clock() + self._retry_every

    def seconds_to_retry(self) -> float | None:
        """How long until the next retry; None when healthy."""
        if not self.degraded:
            return None
        return max(0.0, self._next_retry - self._clock())

    def summary(self) -> str:
        """One line for systemd's STATUS= (empty when healthy)."""
        if not self.degraded:
            return ""
        return f"degraded since {self.since}: {self._faults_text()}; {self._waiting_text()}"

    def document(self) -> dict[str, Any] | None:
        """The ``degraded`` entry of the status file: None when healthy."""
        if not self.degraded:
            return None
        return {
            "since": self.since,
            "waiting": self.waiting,
            "faults": [f.document() for f in self.faults],
        }

    def _faults_text(self) -> str:
        return "; ".join(f.describe() for f in self.faults)

    def _waiting_text(self) -> str:
        n = self.waiting
        return f"{n} bundle{'' if n == 1 else 's'} wait{'s' if n == 1 else ''}"


def format_size(n: int) -> str:
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    raise AssertionError("unreachable")  # pragma: no cover


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")
