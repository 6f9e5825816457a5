"""Retention: the daemon deletes what it is done with once it is older than ``retention:``
says (``archive_days``, ``failed_days``, ``outbox_days``; by default it keeps everything).

Every ``every_hours`` (1) a sweep starts: each folder with a limit is listed (names only, one
directory read), and its entries are looked at a few per turn of the main loop (one ``lstat``
each, at most ``per_turn``), so that a year of bundles costs the loop nothing it notices. An
entry's age runs from the later of its mtime and ctime, that is from the daemon's last change
to it: a result renamed into the outbox, a bundle moved into archive/ (a rename sets the
ctime), an error.yaml added in failed/. Each deletion is logged.

Never deleted: dot-names (the daemon's own: ``.taken``, ``.tmp-*``, its lock and status), and
the result and archived bundle of every bundle seen in a change of the map store that still
waits for a decision (pending or confirmed): the person who approves it may want to look at
them. The map store needs none of these files otherwise: what a bundle contributed (its
evidence, its sightings) is in its database, and published versions are in ``maps/``.
"""

from __future__ import annotations

import logging
import os
import shutil
import stat
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path

from mapserver.config import RetentionConfig

log = logging.getLogger(__name__)

DAY_S = 86400.0


def _nothing_kept() -> set[str]:
    return set()


class Retention:
    """The sweeps of one daemon. ``folders``: the archive, failed and outbox folders by their
    configuration name; ``keep()``: the bundle ids never to delete now (asked once per
    sweep)."""

    def __init__(
        self,
        settings: RetentionConfig,
        folders: Mapping[str, Path],
        *,
        keep: Callable[[], set[str]] = _nothing_kept,
        per_turn: int = 64,
        clock: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self._days = {
            name: days
            for name, days in (
                ("archive", settings.archive_days),
                ("failed", settings.failed_days),
                ("outbox", settings.outbox_days),
            )
            if days is not None
        }
        self._folders = {name: Path(folders[name]) for name in self._days}
        self._every_s = settings.every_hours * 3600.0
        self._keep = keep
        self._per_turn = per_turn
        self._clock = clock
        self._monotonic = monotonic
        self._todo: deque[tuple[str, str]] = deque()
        self._kept: set[str] = set()
        self._next_sweep = monotonic()
        self.deleted = 0
        """Entries deleted since the start."""

    @property
    def active(self) -> bool:
        return bool(self._days)

    def step(self) -> int:
        """One turn's share: start a sweep when one is due, look at up to ``per_turn``
        entries. Returns how many were looked at."""
        if not self._days:
            return 0
        if not self._todo:
            if self._monotonic() < self._next_sweep:
                return 0
            self._next_sweep = self._monotonic() + self._every_s
            self._start()
        looked = 0
        now = self._clock()
        while self._todo and looked < self._per_turn:
            name, entry = self._todo.popleft()
            looked += 1
            self._judge(name, entry, now)
        return looked

    def _start(self) -> None:
        self._kept = self._keep()
        for name, folder in self._folders.items():
            try:
                with os.scandir(folder) as entries:
                    names = [e.name for e in entries if not e.name.startswith(".")]
            except OSError as error:
                log.warning("retention: cannot list %s: %s", folder, error.strerror)
                continue
            self._todo.extend((name, entry) for entry in sorted(names))

    def _judge(self, name: str, entry: str, now: float) -> None:
        path = self._folders[name] / entry
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            return  # gone meanwhile (requeued, say)
        except OSError as error:
            log.warning("retention: cannot look at %s: %s", path, error.strerror)
            return
        age_days = (now - max(st.st_mtime, st.st_ctime)) / DAY_S
        if age_days <= self._days[name] or entry in self._kept:
            return
        try:
            if stat.S_ISDIR(st.st_mode):
                shutil.rmtree(path)
            else:
                os.unlink(path)
        except OSError as error:
            log.warning("retention: cannot delete %s: %s", path, error)
            return
        self.deleted += 1
        log.info(
            "retention: deleted %s/%s, %.1f days old (%s_days: %g)",
            name,
            entry,
            age_days,
            name,
            self._days[name],
        )
