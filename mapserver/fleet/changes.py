"""The tracked changes of a stored map, in the database: each difference a bundle found becomes a
change or supports one, each change the bundle observed is judged, and the persistence rule
confirms or expires them (FORMATS.md section 7). Runs inside the bundle's transaction; the rules
themselves are the pure functions of :mod:`mapserver.fleet.tracker`.
"""

from __future__ import annotations

import json
import logging
import math
import sqlite3
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapserver.config import UpdateConfig
from mapserver.errors import MapserverError
from mapserver.fleet import evidence, tracker
from mapserver.fleet.lattice import IntArray, Lattice, Window
from mapserver.fleet.model import now_utc, utc_stamp
from mapserver.fleet.observe import Observation

log = logging.getLogger(__name__)

# A found difference and a tracked change are one when their cells come this close (metres):
# DBSCAN's own neighbourhood, so that what one bundle would cluster together stays one change.
_MATCH_M = 0.3
# Absence needs nothing occupied this close (metres) to a change's cells: a bundle that sees an
# added obstacle a little off does not contradict it.
_JUDGE_TOLERANCE_M = 0.2


def _tolerance_px(lattice: Lattice) -> int:
    """:data:`_JUDGE_TOLERANCE_M` in cells of the map (one at least)."""
    return max(1, math.ceil(_JUDGE_TOLERANCE_M / lattice.resolution))


@dataclass
class _Change:
    id: int
    kind: str
    state: str
    version: int | None
    first_seen: str
    last_seen: str
    sessions: int
    contradicted: int
    last_observed: str
    latest_shows: bool
    cells: IntArray
    hits: NDArray[np.int64]
    touched: bool = False
    merged: list[int] = field(default_factory=list)


def _box(cells: IntArray, lattice: Lattice, grow: int) -> tuple[int, int, int, int]:
    """(row0, col0, row1, col1) around the cells, grown by ``grow`` cells (empty: nothing)."""
    if len(cells) == 0:
        return (0, 0, -1, -1)
    rows, cols = lattice.unflat(cells)
    return (
        int(rows.min()) - grow,
        int(cols.min()) - grow,
        int(rows.max()) + grow,
        int(cols.max()) + grow,
    )


def _shape(cells: IntArray, lattice: Lattice) -> tuple[int, int, int, int, str]:
    """What the ``changes`` row keeps of a change's cells: ``row0, col0, row1, col1`` (end
    exclusive) and its outline as JSON."""
    row0, col0, last_row, last_col = _box(cells, lattice, 0)
    return row0, col0, last_row + 1, last_col + 1, json.dumps(lattice.outline(cells))


def _boxes_meet(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


class ChangeTracker:
    """The tracked changes of the store's database ``conn``. ``dirty`` collects the ids of the
    changes it touched (the store rewrites their lines of changes.yaml)."""

    def __init__(self, conn: sqlite3.Connection, settings: UpdateConfig, dirty: set[int]):
        self._conn = conn
        self.settings = settings
        self.rule = tracker.Persistence(settings.confirm_sessions, settings.confirm_span_hours)
        self._dirty = dirty
        self._map_state: Callable[[], NDArray[np.uint8]] | None = None

    def track(
        self,
        map_id: int,
        lattice: Lattice,
        obs: Observation,
        stamp: str,
        map_state: Callable[[], NDArray[np.uint8]] | None = None,
    ) -> dict[str, Any]:
        """Apply one bundle's observation to the tracked changes of a map. ``map_state()`` gives
        its current version's cells, read when a removed change is judged (the walls the map
        still has beside it do not count against it); None: not known."""
        self._map_state = map_state
        expired: list[int] = []
        # 1. Pending changes nobody has observed for long expire, first (a sighting after that
        # long begins a new run, as in stamp order): long before this bundle, or
        # before now when it is stamped ahead of this server's clock (a robot's clock weeks
        # ahead would expire every pending change of the map).
        now = min(tracker.parse_stamp(stamp), datetime.now(timezone.utc))
        limit = now - timedelta(days=self.settings.expire_unseen_days)
        cutoff = utc_stamp(limit.isoformat())
        for (cid,) in self._conn.execute(
            "SELECT id FROM changes WHERE map_id = ? AND state = 'pending' AND last_observed < ?",
            (map_id, cutoff),
        ).fetchall():
            self._conn.execute(
                "UPDATE changes SET state = 'expired', note = ?, updated_at = ? WHERE id = ?",
                (f"not observed for {self.settings.expire_unseen_days:g} days", now_utc(), cid),
            )
            expired.append(cid)
            self._dirty.add(cid)
        radius = max(1, round(_MATCH_M / lattice.resolution))
        win = obs.window
        live = self._load_changes(map_id, lattice, win, margin=radius)
        by_id = {c.id: c for c in live}
        created: list[int] = []
        # 2. Every difference found against the current version: one tracked change each.
        assigned: dict[int, list[IntArray]] = {}
        new: list[tuple[str, IntArray]] = []
        for found in obs.found:
            near = _box(found.cells, lattice, radius)
            cands = [
                c
                for c in live
                if c.kind == found.kind
                and _boxes_meet(near, _box(c.cells, lattice, 0))
                and (
                    c.state in ("pending", "confirmed", "rejected")
                    or (c.state == "published" and (c.version or 0) > obs.judged_version)
                )
                and tracker.overlap(found.cells, c.cells, lattice, radius) > 0
            ]
            if not cands:
                if not self._outdated(found.kind, found.cells, near, live, stamp, lattice, radius):
                    new.append((found.kind, found.cells))
                continue
            absorbing = [c for c in cands if c.state in ("rejected", "published")]
            if absorbing:
                target = absorbing[0]
            else:
                target = min(cands, key=lambda c: c.id)
                for other in cands:
                    if other.id != target.id and other.id in by_id:
                        self._merge(target, other)
                        live.remove(other)
                        del by_id[other.id]
                        if other.id in assigned:
                            assigned.setdefault(target.id, []).extend(assigned.pop(other.id))
            assigned.setdefault(target.id, []).append(found.cells)
        # Near new differences of one kind in one bundle stay separate changes, as DBSCAN made them.
        for kind, cells in new:
            created.append(self._create(map_id, lattice, kind, cells, obs, stamp))
        supported = []
        for cid, parts in assigned.items():
            c = by_id[cid]
            if c.state in ("published", "rejected"):
                # Published: judged against an older version, already in the map. Rejected:
                # an operator said no; its sightings are not counted (they would grow forever).
                continue
            if self._before_the_run(map_id, lattice, c, stamp):
                continue
            self._support(c, np.unique(np.concatenate(parts)), obs, stamp, lattice)
            supported.append(cid)
        # 3. Changes this bundle observed without finding them: shown, or as before?
        shown: list[int] = []
        for c in live:
            if c.id in assigned or c.state not in ("pending", "confirmed"):
                continue
            verdict, seen = self._judge(
                c.kind,
                tracker.core_cells(c.cells, c.hits),
                c.cells,
                lattice,
                win,
                obs.occupied,
                obs.free,
            )
            if verdict == "as_before":
                if self._seen_as_before(c.id, stamp, obs.bundle_id, obs.robot):
                    expired.append(c.id)
            elif verdict == "shows":
                # The local map shows it though the bundle's differences did not report it (too
                # few cells this time, an edge of the observed area): a session that saw it.
                if self._before_the_run(map_id, lattice, c, stamp):
                    continue
                self._support(c, seen, obs, stamp, lattice)
                shown.append(c.id)
        for cid in created:
            if self._state(cid) == "expired":
                expired.append(cid)
        # 4. The persistence rule.
        confirmed = []
        supported += shown
        for cid in sorted(set(supported) | set(created)):
            row = self._conn.execute(
                "SELECT state, sessions, first_seen, last_seen, latest_shows FROM changes WHERE id = ?",
                (cid,),
            ).fetchone()
            if row[0] == "pending" and tracker.confirmed(
                self.rule,
                sessions=row[1],
                first_seen=row[2],
                last_seen=row[3],
                latest_shows=bool(row[4]),
            ):
                self._conn.execute(
                    "UPDATE changes SET state = 'confirmed', updated_at = ? WHERE id = ?",
                    (now_utc(), cid),
                )
                confirmed.append(cid)
        self._dirty.update(created, supported)
        # 5. Which change each difference of the bundle's own result is.
        touched = set(supported) | set(created)
        refs = self._load_changes(
            map_id,
            lattice,
            win,
            margin=radius,
            states=("pending", "confirmed", "published", "rejected", "expired"),
            ids=touched,
        )
        refs += [
            c
            for c in self._load_changes(
                map_id, lattice, win, margin=radius, states=("published", "rejected")
            )
            if c.id not in touched
        ]
        result_changes: list[int | None] = []
        for kind, cells in obs.result_cells:
            best, best_n = None, 0
            near = _box(cells, lattice, radius)
            for c in refs:
                if c.kind != kind or not _boxes_meet(near, _box(c.cells, lattice, 0)):
                    continue
                n = tracker.overlap(cells, c.cells, lattice, radius)
                if n > best_n or (
                    n == best_n
                    and n > 0
                    and best is not None
                    and c.id in touched
                    and best not in touched
                ):
                    best, best_n = c.id, n
            result_changes.append(best)
        return {
            "changes": result_changes,
            "created": created,
            "supported": sorted(supported),
            "expired": sorted(expired),
            "confirmed": confirmed,
        }

    def _load_changes(
        self,
        map_id: int,
        lattice: Lattice,
        window: Any,
        *,
        margin: int,
        states: Sequence[str] = ("pending", "confirmed", "published", "rejected"),
        ids: Iterable[int] | None = None,
    ) -> list[_Change]:
        q = ",".join("?" * len(states))
        sql = (
            "SELECT id, kind, state, version, first_seen, last_seen, sessions, contradicted, "
            f"last_observed, latest_shows FROM changes WHERE map_id = ? AND state IN ({q}) "
            "AND row1 > ? AND row0 < ? AND col1 > ? AND col0 < ?"
        )
        args: list[Any] = [
            map_id,
            *states,
            window.row0 - margin,
            window.row0 + window.rows + margin,
            window.col0 - margin,
            window.col0 + window.cols + margin,
        ]
        if ids is not None:
            wanted = sorted(ids)
            if not wanted:
                return []
            sql += f" AND id IN ({','.join('?' * len(wanted))})"
            args += wanted
        out = []
        for row in self._conn.execute(sql + " ORDER BY id", args).fetchall():
            cells = np.array(
                self._conn.execute(
                    "SELECT cell, hits FROM change_cells WHERE change_id = ? ORDER BY cell",
                    (row[0],),
                ).fetchall(),
                dtype=np.int64,
            ).reshape(-1, 2)
            out.append(
                _Change(
                    row[0],
                    row[1],
                    row[2],
                    row[3],
                    row[4],
                    row[5],
                    row[6],
                    row[7],
                    row[8],
                    bool(row[9]),
                    cells[:, 0],
                    cells[:, 1],
                )
            )
        return out

    def _create(
        self,
        map_id: int,
        lattice: Lattice,
        kind: str,
        cells: IntArray,
        obs: Observation,
        stamp: str,
    ) -> int:
        cur = self._conn.execute(
            "INSERT INTO changes (map_id, kind, state, first_seen, last_seen, sessions, "
            "last_observed, latest_shows, row0, col0, row1, col1, polygon, updated_at) "
            "VALUES (?, ?, 'pending', ?, ?, 1, ?, 1, ?, ?, ?, ?, ?, ?)",
            (map_id, kind, stamp, stamp, stamp, *_shape(cells, lattice), now_utc()),
        )
        cid = int(cur.lastrowid or 0)
        window = self._judge_window(cells, lattice)
        counters = evidence.read_window(self._conn, map_id, window)
        later = self._observed_after(lattice, window, counters, cells, stamp)
        if later is not None:
            # A late bundle: one stamped after it already observed these cells (and found no
            # such change there, or this one would support it). Seen, not the latest to say so:
            # not confirmed until a bundle newer than that one shows it.
            self._conn.execute(
                "UPDATE changes SET latest_shows = 0, last_observed = ? WHERE id = ?",
                (later, cid),
            )
        self._conn.executemany(
            "INSERT INTO change_cells (change_id, cell, hits) VALUES (?, ?, 1)",
            ((cid, int(c)) for c in cells),
        )
        self._conn.execute(
            "INSERT INTO sightings (change_id, bundle_id, robot, stamp) VALUES (?, ?, ?, ?)",
            (cid, obs.bundle_id, obs.robot, stamp),
        )
        self._judge_kept(
            map_id,
            lattice,
            cid,
            kind,
            cells,
            stamp,
            obs.bundle_id,
            earlier=self._shown_before(kind, cells, lattice, window, counters),
        )
        return cid

    @staticmethod
    def _shown_before(
        kind: str,
        cells: IntArray,
        lattice: Lattice,
        window: Window,
        counters: evidence.TileEvidence,
    ) -> bool:
        """Whether a bundle besides the finder may have shown the change, by the evidence's
        counters (the finder counted in them): an added obstacle's cells, or their neighbours,
        seen occupied twice; a removed structure's cells seen free twice. When not, no kept
        observation needs reading back."""
        if kind == "added":
            rows, cols, inside = window.local(lattice, tracker.dilate(cells, lattice, 1))
            counts = counters.occupied
        else:
            rows, cols, inside = window.local(lattice, cells)
            counts = counters.free
        return bool((counts[rows[inside], cols[inside]] >= 2).any())

    def _judge_window(self, cells: IntArray, lattice: Lattice) -> Window:
        """The window a change's cells are judged on in a kept observation: their box grown by
        the judging tolerance and the presence neighbour (as the live judge sees the whole
        bundle), within the map."""
        row0, col0, last_row, last_col = _box(cells, lattice, _tolerance_px(lattice) + 1)
        row0, col0 = max(row0, 0), max(col0, 0)
        last_row, last_col = min(last_row, lattice.height - 1), min(last_col, lattice.width - 1)
        return Window(row0, col0, last_row - row0 + 1, last_col - col0 + 1)

    def _judge(
        self,
        kind: str,
        judged: IntArray,
        cells: IntArray,
        lattice: Lattice,
        window: Window,
        occupied: NDArray[np.bool_],
        free: NDArray[np.bool_],
    ) -> tuple[tracker.Verdict, IntArray]:
        """One observation's verdict on a change (on its cells ``judged``: all, or its core),
        and, when it shows the change, the cells of ``cells`` it shows changed."""
        tol = _tolerance_px(lattice)
        current = self._current(lattice) if kind == "removed" else None
        verdict = tracker.judge(
            kind, judged, lattice, window, occupied, free, tolerance_px=tol, current=current
        )
        if verdict != "shows":
            return verdict, np.zeros(0, np.int64)
        return verdict, tracker.shown_cells(
            kind, cells, lattice, window, occupied, free, tolerance_px=tol, current=current
        )

    def _current(self, lattice: Lattice) -> NDArray[np.uint8] | None:
        """The map's current version's cells (the store keeps them decoded). None when not
        known, or its file is unreadable or not of the map's size: then every occupied cell near
        a removed change counts as its structure standing."""
        if self._map_state is None:
            return None
        try:
            cells = self._map_state()
            if cells.shape != (lattice.height, lattice.width):
                raise MapserverError(f"its cells are {cells.shape[1]} x {cells.shape[0]}")
        except (OSError, MapserverError) as error:
            log.warning("the current version's cells are unreadable (%s): judged without", error)
            self._map_state = None
            return None
        return cells

    def _judge_kept(
        self,
        map_id: int,
        lattice: Lattice,
        cid: int,
        kind: str,
        cells: IntArray,
        stamp: str,
        finder: str,
        *,
        earlier: bool = True,
    ) -> None:
        """Judge a new change on the kept observations of the bundles applied before its
        finder, as if they had come after it: the sessions of contract section 7 are the
        bundles whose local map shows a change, not only those that reported it.

        Back from ``stamp``, newest first: each that shows it is a session (too few cells that
        time, a fold check, a drift kept its differences from reporting it); the first that
        saw the area as before ends the count (the change began after it: the box not yet
        there, the door still shut; one of the same second cannot tell and is passed over),
        and so does a gap of ``expire_unseen_days`` before the oldest counted (a run since
        ended).
        Then the bundles stamped after the finder (it arrived late: a daemon's workers finish
        out of order, an upload waits a day), oldest first, as the live judge would have taken
        them: a session that shows it, or one that saw it as before, which expires it."""
        window = self._judge_window(cells, lattice)
        shown = []
        kept = evidence.observations(self._conn, map_id, window, until=stamp) if earlier else ()
        # A change not observed for expire_unseen_days expires: a session further back than
        # that from the next one counted belongs to a run that ended.
        expire = timedelta(days=self.settings.expire_unseen_days)
        newest = tracker.parse_stamp(stamp)
        for seen in kept:
            if tracker.parse_stamp(seen.stamp) < newest - expire:
                break
            if seen.bundle_id == finder and seen.stamp == stamp:
                continue
            verdict, cells_shown = self._judge(
                kind, cells, cells, lattice, window, seen.occupied, seen.free
            )
            if verdict == "as_before" and seen.stamp < stamp:
                break
            if verdict == "shows":
                shown.append((seen.bundle_id, seen.robot, seen.stamp, cells_shown))
                newest = tracker.parse_stamp(seen.stamp)
        if self._sightings(cid, shown):
            self._refresh(cid, lattice)
        for seen in evidence.observations(
            self._conn, map_id, window, after=stamp, newest_first=False
        ):
            verdict, cells_shown = self._judge(
                kind, cells, cells, lattice, window, seen.occupied, seen.free
            )
            if verdict == "as_before":
                self._seen_as_before(cid, seen.stamp, seen.bundle_id, seen.robot)
                break
            if verdict == "shows" and self._sighting(
                cid, seen.bundle_id, seen.robot, seen.stamp, cells_shown
            ):
                self._refresh(cid, lattice, stamp_shown=seen.stamp)

    def _before_the_run(self, map_id: int, lattice: Lattice, c: _Change, stamp: str) -> bool:
        """Whether a late bundle (stamped before the change's first sighting) belongs to an
        earlier run, not this one: a kept bundle between them saw the area as before, or more
        than ``expire_unseen_days`` lie between them. In stamp order it would have been counted
        on an earlier change, which that bundle, or the time, expired."""
        if stamp >= c.first_seen:
            return False
        gap = tracker.span_hours(stamp, c.first_seen) / 24.0
        if gap > self.settings.expire_unseen_days:
            return True
        return self._as_before_between(map_id, lattice, c.kind, c.cells, stamp, c.first_seen)

    def _as_before_between(
        self, map_id: int, lattice: Lattice, kind: str, cells: IntArray, after: str, before: str
    ) -> bool:
        """Whether a kept observation stamped after ``after`` and before ``before`` saw the
        change's area as before."""
        window = self._judge_window(cells, lattice)
        for seen in evidence.observations(
            self._conn, map_id, window, after=after, newest_first=False
        ):
            if seen.stamp >= before:
                return False
            verdict, _ = self._judge(kind, cells, cells, lattice, window, seen.occupied, seen.free)
            if verdict == "as_before":
                return True
        return False

    def _seen_as_before(self, cid: int, stamp: str, bundle_id: str, robot: str) -> bool:
        """A bundle saw a pending or confirmed change's area as before: ``contradicted`` (when
        after its first sighting). The latest word on it expires it, and so does a late one
        stamped after every sighting of it. Returns whether the change expired."""
        first_seen, last_observed = self._conn.execute(
            "SELECT first_seen, last_observed FROM changes WHERE id = ?", (cid,)
        ).fetchone()
        self._dirty.add(cid)
        note = f"seen as before by {bundle_id} ({robot}, {stamp})"
        latest = bool(stamp >= last_observed)
        expire = latest
        if not expire and stamp > first_seen:
            # Late, after the first sighting: with none after it, in stamp order it was the
            # latest word on the change (the bundle of a later hour that observed the area
            # showed nothing either way). One inside the run only contradicts it: the cells a
            # session showed are counted together, not session by session, so the sessions
            # before it cannot be taken out again.
            expire = not self._conn.execute(
                "SELECT count(*) FROM sightings WHERE change_id = ? AND stamp > ?", (cid, stamp)
            ).fetchone()[0]
        self._conn.execute(
            "UPDATE changes SET contradicted = contradicted + ?, "
            "last_observed = CASE WHEN ? THEN ? ELSE last_observed END, "
            "latest_shows = CASE WHEN ? THEN 0 ELSE latest_shows END, "
            "state = CASE WHEN ? THEN 'expired' ELSE state END, "
            "note = CASE WHEN ? THEN ? ELSE note END, updated_at = ? WHERE id = ?",
            (
                int(stamp > first_seen),
                latest,
                stamp,
                latest,
                expire,
                expire,
                note,
                now_utc(),
                cid,
            ),
        )
        return expire

    def _state(self, cid: int) -> str:
        return str(
            self._conn.execute("SELECT state FROM changes WHERE id = ?", (cid,)).fetchone()[0]
        )

    @staticmethod
    def _observed_after(
        lattice: Lattice,
        window: Window,
        counters: evidence.TileEvidence,
        cells: IntArray,
        stamp: str,
    ) -> str | None:
        """When a bundle stamped in a later hour than ``stamp`` last observed any of ``cells``
        (the start of that hour: the evidence keeps hours), or None. Bundles are applied as
        they arrive; the fleet counts them by stamp, and a late one must not be the latest
        word on what a newer one saw (a daemon's two workers finish out of order, an upload
        waits a day). Within one hour it cannot tell; the kept observations, where they are
        still kept, tell exactly (:meth:`_judge_kept`)."""
        rows, cols, _ = window.local(lattice, cells)
        seen = counters.last_hour[rows, cols]
        hour = int(tracker.parse_stamp(stamp).timestamp() // 3600)
        latest = int(seen.max()) if len(seen) else 0
        if latest <= hour:
            return None
        return utc_stamp(datetime.fromtimestamp(latest * 3600, timezone.utc).isoformat())

    @staticmethod
    def _outdated(
        kind: str,
        cells: IntArray,
        near: tuple[int, int, int, int],
        live: list[_Change],
        stamp: str,
        lattice: Lattice,
        radius: int,
    ) -> bool:
        """A late bundle's difference that a published change first seen after it explains:
        the robot saw the area before the change (the wall not yet built, the shelf still
        there). Counted, it would undo the change."""
        return any(
            c.state == "published"
            and c.kind != kind
            and c.first_seen > stamp
            and _boxes_meet(near, _box(c.cells, lattice, 0))
            and tracker.overlap(cells, c.cells, lattice, radius) > 0
            for c in live
        )

    def _support(
        self, c: _Change, cells: IntArray, obs: Observation, stamp: str, lattice: Lattice
    ) -> None:
        if self._sighting(c.id, obs.bundle_id, obs.robot, stamp, cells):
            self._refresh(c.id, lattice, stamp_shown=stamp)

    def _sighting(self, cid: int, bundle_id: str, robot: str, stamp: str, cells: IntArray) -> bool:
        """Count one bundle's sighting of a change and the cells it showed; False when that
        bundle was counted on it already (merged changes)."""
        return self._sightings(cid, [(bundle_id, robot, stamp, cells)]) > 0

    def _sightings(self, cid: int, seen: Sequence[tuple[str, str, str, IntArray]]) -> int:
        """Count bundles' sightings of a change, ``(bundle_id, robot, stamp, cells shown)``
        each, and their cells' hits in one write; returns how many were new."""
        shown = []
        for bundle_id, robot, stamp, cells in seen:
            cur = self._conn.execute(
                "INSERT OR IGNORE INTO sightings (change_id, bundle_id, robot, stamp) "
                "VALUES (?, ?, ?, ?)",
                (cid, bundle_id, robot, stamp),
            )
            if cur.rowcount:
                shown.append(cells)
        if shown:
            cells, hits = np.unique(np.concatenate(shown), return_counts=True)
            self._conn.executemany(
                "INSERT INTO change_cells (change_id, cell, hits) VALUES (?, ?, ?) "
                "ON CONFLICT (change_id, cell) DO UPDATE SET hits = hits + excluded.hits",
                ((cid, int(c), int(n)) for c, n in zip(cells, hits, strict=True)),
            )
        return len(shown)

    def _merge(self, target: _Change, other: _Change) -> None:
        """Fold ``other`` into ``target`` (one thing seen in two parts): sightings, cells and
        counts move to the older change; the younger one's id is kept as an alias."""
        self._conn.execute(
            "INSERT OR IGNORE INTO sightings (change_id, bundle_id, robot, stamp) "
            "SELECT ?, bundle_id, robot, stamp FROM sightings WHERE change_id = ?",
            (target.id, other.id),
        )
        self._conn.execute(
            "INSERT INTO change_cells (change_id, cell, hits) SELECT ?, cell, hits FROM change_cells "
            "WHERE change_id = ? ON CONFLICT (change_id, cell) DO UPDATE SET hits = hits + excluded.hits",
            (target.id, other.id),
        )
        self._conn.execute(
            "UPDATE changes SET contradicted = contradicted + ?, "
            "latest_shows = CASE WHEN last_observed < ? THEN ? ELSE latest_shows END, "
            "last_observed = max(last_observed, ?) WHERE id = ?",
            (
                other.contradicted,
                other.last_observed,
                int(other.latest_shows),
                other.last_observed,
                target.id,
            ),
        )
        self._conn.execute("DELETE FROM changes WHERE id = ?", (other.id,))
        self._dirty.update((target.id, other.id))
        self._conn.execute("UPDATE merges SET new_id = ? WHERE new_id = ?", (target.id, other.id))
        self._conn.execute(
            "INSERT OR REPLACE INTO merges (old_id, new_id) VALUES (?, ?)", (other.id, target.id)
        )
        merged = np.unique(np.concatenate([target.cells, other.cells]))
        target.cells = merged
        target.hits = np.ones(len(merged), np.int64)

    def _refresh(self, cid: int, lattice: Lattice, *, stamp_shown: str | None = None) -> None:
        """Recompute a change's counts, times, box and outline from its sightings and cells."""
        sessions, first, last = self._conn.execute(
            "SELECT count(*), min(stamp), max(stamp) FROM sightings WHERE change_id = ?", (cid,)
        ).fetchone()
        cells = np.array(
            [
                r[0]
                for r in self._conn.execute(
                    "SELECT cell FROM change_cells WHERE change_id = ?", (cid,)
                )
            ],
            np.int64,
        )
        row0, col0, row1, col1, polygon = _shape(cells, lattice)
        self._conn.execute(
            "UPDATE changes SET sessions = :sessions, first_seen = :first, last_seen = :last, "
            "row0 = :row0, col0 = :col0, row1 = :row1, col1 = :col1, polygon = :polygon, "
            "updated_at = :now, "
            "latest_shows = CASE WHEN :shown >= last_observed THEN 1 ELSE latest_shows END, "
            "last_observed = CASE WHEN :shown >= last_observed THEN :shown ELSE last_observed END "
            "WHERE id = :id",
            {
                "sessions": sessions,
                "first": first,
                "last": last,
                "row0": row0,
                "col0": col0,
                "row1": row1,
                "col1": col1,
                "polygon": polygon,
                "now": now_utc(),
                "shown": stamp_shown,  # NULL: the comparisons are NULL, nothing changes
                "id": cid,
            },
        )

    def resolve_merged(self, change_id: int) -> int:
        row = self._conn.execute(
            "SELECT new_id FROM merges WHERE old_id = ?", (change_id,)
        ).fetchone()
        return int(row[0]) if row else change_id
