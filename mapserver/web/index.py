"""What the web pages list: every result in the outbox and every failure in failed/, kept in
memory and brought up to date from the folders without reading what it has read before.

A refresh lists the two folders (names only) and reads the ``result.yaml`` / the daemon's error
document of the entries it has not seen or whose file changed; no request reads the whole
archive. Lists are sorted newest first and paginated by key (the processing time, then the id),
so a page costs the same on the first day and after a year.
"""

from __future__ import annotations

import bisect
import logging
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mapserver.bundle import is_valid_bundle_id
from mapserver.outbox import daemon_error

log = logging.getLogger(__name__)

_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
RESULT = "result.yaml"


@dataclass(frozen=True)
class ResultRow:
    """One bundle's result, as the lists show it."""

    bundle_id: str
    robot: str
    stamp: str
    processed_at: str
    status: str
    added: int
    removed: int
    score: float | None
    prior_score: float | None
    drift_m: float | None
    trusted: bool | None
    map_name: str | None
    map_version: int | None
    warnings: int
    seconds: float | None
    timings_ms: dict[str, float]

    @property
    def key(self) -> tuple[str, str]:
        return (self.processed_at, self.bundle_id)


@dataclass(frozen=True)
class FailureRow:
    bundle_id: str
    failed_at: str
    stage: str
    reason: str

    @property
    def key(self) -> tuple[str, str]:
        return (self.failed_at, self.bundle_id)


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def result_row(bundle_id: str, doc: dict[str, Any]) -> ResultRow:
    differences = doc.get("differences") or []
    alignment = doc.get("alignment") or {}
    mapping = doc.get("map") or {}
    timings = {
        str(k): float(v) for k, v in (doc.get("timings_ms") or {}).items() if _number(v) is not None
    }
    trusted = alignment.get("trusted")
    version = mapping.get("version")
    return ResultRow(
        bundle_id=bundle_id,
        robot=str(doc.get("robot", "?")),
        stamp=str(doc.get("stamp", "")),
        processed_at=str(doc.get("processed_at", "")),
        status=str(doc.get("status", "ok")),
        added=sum(1 for d in differences if isinstance(d, dict) and d.get("kind") == "added"),
        removed=sum(1 for d in differences if isinstance(d, dict) and d.get("kind") == "removed"),
        score=_number(alignment.get("score")),
        prior_score=_number(alignment.get("prior_score")),
        drift_m=_number(alignment.get("drift_m")),
        trusted=trusted if isinstance(trusted, bool) else None,
        map_name=str(mapping["name"]) if mapping.get("name") else None,
        map_version=version if isinstance(version, int) else None,
        warnings=len(doc.get("warnings") or []),
        seconds=sum(timings.values()) / 1000.0 if timings else None,
        timings_ms=timings,
    )


def failure_row(bundle_id: str, doc: dict[str, Any]) -> FailureRow:
    return FailureRow(
        bundle_id,
        str(doc.get("failed_at", "")),
        str(doc.get("stage", "?")),
        str(doc.get("reason", "(no reason given)")),
    )


def read_yaml(path: Path) -> dict[str, Any] | None:
    try:
        doc = yaml.load(path.read_text(encoding="utf-8"), Loader=_LOADER)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return doc if isinstance(doc, dict) else None


class _Sorted:
    """Rows kept newest first, by key, with the files they came from."""

    def __init__(self) -> None:
        self.rows: dict[str, Any] = {}
        self.seen: dict[str, tuple[int, int]] = {}  # id -> (mtime_ns, size) of its file
        self.keys: list[tuple[str, str]] = []  # ascending; pages walk it backwards

    def put(self, bundle_id: str, row: Any, sig: tuple[int, int]) -> None:
        self.drop(bundle_id)
        self.rows[bundle_id] = row
        self.seen[bundle_id] = sig
        bisect.insort(self.keys, row.key)

    def drop(self, bundle_id: str) -> None:
        old = self.rows.pop(bundle_id, None)
        self.seen.pop(bundle_id, None)
        if old is not None:
            i = bisect.bisect_left(self.keys, old.key)
            if i < len(self.keys) and self.keys[i] == old.key:
                del self.keys[i]

    def page(self, limit: int, before: tuple[str, str] | None) -> list[Any]:
        end = len(self.keys) if before is None else bisect.bisect_left(self.keys, before)
        return [self.rows[k[1]] for k in reversed(self.keys[max(0, end - limit) : end])]

    def since(self, stamp: str) -> Iterator[Any]:
        start = bisect.bisect_left(self.keys, (stamp, ""))
        for k in self.keys[start:]:
            yield self.rows[k[1]]


class BundleIndex:
    """The results and failures of ``outbox`` and ``failed``, refreshed at most every
    ``every_s`` seconds (a background thread keeps it fresh between requests)."""

    def __init__(self, outbox: Path, failed: Path, *, every_s: float = 2.0) -> None:
        self.outbox = outbox
        self.failed = failed
        self.every_s = every_s
        self._results = _Sorted()
        self._failures = _Sorted()
        self._lock = threading.Lock()
        self._refreshed = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- keeping it fresh -------------------------------------------------------------------

    def refresh(self) -> None:
        with self._lock:
            self._scan(self.outbox, RESULT, self._results, result_row)
            self._scan(self.failed, None, self._failures, failure_row)
            self._refreshed = time.monotonic()

    def fresh(self) -> None:
        """Refresh now when the last refresh is older than ``every_s``."""
        if time.monotonic() - self._refreshed >= self.every_s:
            self.refresh()

    def start(self) -> None:
        """Refresh in a background thread until :meth:`stop`."""
        if self._thread is not None:
            return

        def loop() -> None:
            while not self._stop.is_set():
                try:
                    self.refresh()
                except Exception:  # a bug must not end the thread: the pages would go stale
                    log.exception("web: refreshing the bundle index failed")
                self._stop.wait(self.every_s)

        self._thread = threading.Thread(target=loop, name="mapserver-web-index", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def _scan(self, folder: Path, name: str | None, into: _Sorted, make: Any) -> None:
        present = set()
        try:
            entries = list(os.scandir(folder))
        except OSError:
            entries = []
        for entry in entries:
            bundle_id = entry.name
            if not is_valid_bundle_id(bundle_id) or not entry.is_dir(follow_symlinks=False):
                continue
            present.add(bundle_id)
            # A failed bundle may hold files named like the daemon's error document (a robot
            # can upload anything): only the one the daemon wrote says why it failed, found
            # by the rule the daemon names it by (and mapserver requeue reads it by).
            path = Path(entry.path) / name if name else daemon_error(Path(entry.path))
            if path is None:
                continue
            # Stat first, parse only what is new or changed: a refresh of a year of bundles
            # reads directories, not files.
            try:
                st = path.stat()
            except OSError:
                continue
            sig = (st.st_mtime_ns, st.st_size)
            if into.seen.get(bundle_id) == sig:
                continue
            doc = read_yaml(path)
            if doc is not None:
                into.put(bundle_id, make(bundle_id, doc), sig)
        for gone in set(into.rows) - present:
            into.drop(gone)

    # -- reading ----------------------------------------------------------------------------

    def results(self, limit: int, before: tuple[str, str] | None = None) -> list[ResultRow]:
        self.fresh()
        with self._lock:
            return list(self._results.page(limit, before))

    def failures(self, limit: int, before: tuple[str, str] | None = None) -> list[FailureRow]:
        self.fresh()
        with self._lock:
            return list(self._failures.page(limit, before))

    def result(self, bundle_id: str) -> ResultRow | None:
        self.fresh()
        with self._lock:
            row = self._results.rows.get(bundle_id)
            return row if isinstance(row, ResultRow) else None

    def failure(self, bundle_id: str) -> FailureRow | None:
        self.fresh()
        with self._lock:
            row = self._failures.rows.get(bundle_id)
            return row if isinstance(row, FailureRow) else None

    def counts_since(self, stamp: str) -> tuple[int, int]:
        """(results, failures) processed since ``stamp`` (ISO 8601 UTC)."""
        self.fresh()
        with self._lock:
            return (
                sum(1 for _ in self._results.since(stamp)),
                sum(1 for _ in self._failures.since(stamp)),
            )

    def robots(self) -> list[ResultRow]:
        """Each robot's newest result (by stamp), robots sorted by name."""
        self.fresh()
        with self._lock:
            newest: dict[str, ResultRow] = {}
            for row in self._results.rows.values():
                if row.robot not in newest or row.stamp > newest[row.robot].stamp:
                    newest[row.robot] = row
        return [newest[r] for r in sorted(newest)]

    def all_results(self) -> list[ResultRow]:
        """Every result (for the metrics' histograms), in no particular order."""
        self.fresh()
        with self._lock:
            return list(self._results.rows.values())

    def all_failures(self) -> list[FailureRow]:
        self.fresh()
        with self._lock:
            return list(self._failures.rows.values())

    def __len__(self) -> int:
        with self._lock:
            return len(self._results.rows)


def parse_cursor(text: str | None) -> tuple[str, str] | None:
    """A page cursor ``<time>|<id>`` (what the previous page's last row gives) or None."""
    if not text or "|" not in text:
        return None
    when, _, bundle_id = text.rpartition("|")
    return (when, bundle_id) if is_valid_bundle_id(bundle_id) else None


def cursor(key: tuple[str, str]) -> str:
    return f"{key[0]}|{key[1]}"
