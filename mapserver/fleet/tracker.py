"""Pure functions of the change tracker: which cells touch, what a bundle says of a change, and
the persistence rule (contract section 7).

Cells are flat indices on a stored map's :class:`~mapserver.fleet.lattice.Lattice`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from datetime import datetime
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import IntArray, Lattice, Window
from mapserver.maps import OCCUPIED

Verdict = Literal["unseen", "shows", "as_before", "unclear"]


@functools.lru_cache(maxsize=16)
def disk_offsets(radius_px: int) -> tuple[IntArray, IntArray]:
    """(d_row, d_col) of every cell within ``radius_px`` of a cell, itself included (read-only
    arrays, shared between calls)."""
    r = max(0, int(radius_px))
    dr, dc = np.mgrid[-r : r + 1, -r : r + 1]
    keep = dr**2 + dc**2 <= r * r
    out = dr[keep].astype(np.int64), dc[keep].astype(np.int64)
    for a in out:
        a.flags.writeable = False
    return out


def dilate(cells: IntArray, lattice: Lattice, radius_px: int) -> IntArray:
    """The cells within ``radius_px`` of any of ``cells`` (sorted, unique, on the map)."""
    if len(cells) == 0 or radius_px <= 0:
        return np.unique(np.asarray(cells, np.int64))
    rows, cols = lattice.unflat(cells)
    dr, dc = disk_offsets(radius_px)
    return lattice.flat((rows[:, None] + dr).ravel(), (cols[:, None] + dc).ravel())


def overlap(a: IntArray, b: IntArray, lattice: Lattice, radius_px: int) -> int:
    """How many cells of ``b`` lie within ``radius_px`` of a cell of ``a``."""
    if len(a) == 0 or len(b) == 0:
        return 0
    return int(np.isin(b, dilate(a, lattice, radius_px), assume_unique=False).sum())


def core_cells(cells: IntArray, hits: NDArray[np.integer]) -> IntArray:
    """The cells seen in at least half as many sessions as the most-seen cell: the part of a
    change that is really there (a walker brushing past adds cells seen once)."""
    if len(cells) == 0:
        return np.asarray(cells, np.int64)
    need = max(1, math.ceil(0.5 * int(hits.max())))
    return np.asarray(cells[hits >= need], np.int64)


def judge(
    kind: str,
    cells: IntArray,
    lattice: Lattice,
    window: Window,
    occupied: NDArray[np.bool_],
    free: NDArray[np.bool_],
    *,
    tolerance_px: int,
    min_cells: int = 4,
    min_seen_share: float = 0.5,
    as_before_share: float = 0.7,
    shows_share: float = 0.5,
    current: NDArray[np.uint8] | None = None,
) -> Verdict:
    """What one bundle's observation says of a tracked change's ``cells``.

    ``unseen``: the bundle observed too few of the cells (fewer than ``min_cells``, or less
    than ``min_seen_share`` of them). Otherwise, of the observed cells:

    - ``added``: ``shows`` when at least ``shows_share`` are occupied or have an occupied
      neighbour (the obstacle is there); ``as_before`` when at least ``as_before_share`` have no
      occupied cell within ``tolerance_px`` (it is gone: the area is as the map has it);
    - ``removed``: ``shows`` when at least ``as_before_share`` have no occupied cell within
      ``tolerance_px`` (the structure is still gone); ``as_before`` when at least
      ``shows_share`` are occupied or have an occupied neighbour (it is back);
    - else ``unclear``.

    Presence needs the cells themselves (a neighbour at most: one cell of misalignment);
    absence needs nothing occupied within the tolerance. A bundle that sees the thing a little
    off is ``unclear``, neither: it neither confirms nor contradicts.

    ``current`` (the map's current version, (lattice.height, lattice.width) FREE / OCCUPIED /
    UNKNOWN), for a removed change: the cells it has occupied besides the change's own
    ``cells`` do not count in either test (the rest of the wall a piece was cut from stands
    beside the gap), but the structure is gone only when under ``shows_share`` of the cells
    have their own cell or a 4-neighbour occupied, those included: a piece flush with a wall,
    back but seen a cell off onto the wall, must not show as gone, so a piece one or two cells
    deep against a wall is ``unclear`` from a session that does not report it.
    """
    rows, cols, inside = window.local(lattice, cells)
    rows, cols = rows[inside], cols[inside]
    seen = occupied[rows, cols] | free[rows, cols]
    n_seen = int(seen.sum())
    if n_seen < min_cells or n_seen < min_seen_share * len(cells):
        return "unseen"
    rows, cols = rows[seen], cols[seen]
    ignored = _Ignored.of(current, cells, lattice, window)
    present = float(_near_occupied(occupied, rows, cols, 1, ignored).mean())
    absent = 1.0 - float(_near_occupied(occupied, rows, cols, tolerance_px, ignored).mean())
    there, gone = present >= shows_share, absent >= as_before_share
    if gone and ignored is not None:
        # Gone only when what stands right beside the cells is not most of them: a piece flush
        # with a wall, back but seen a cell off onto the wall, would otherwise show as gone.
        gone = float(_near_occupied(occupied, rows, cols, 1).mean()) < shows_share
    if kind == "added":
        return "shows" if there else "as_before" if gone else "unclear"
    return "shows" if gone else "as_before" if there else "unclear"


def shown_cells(
    kind: str,
    cells: IntArray,
    lattice: Lattice,
    window: Window,
    occupied: NDArray[np.bool_],
    free: NDArray[np.bool_],
    *,
    tolerance_px: int,
    current: NDArray[np.uint8] | None = None,
) -> IntArray:
    """The cells of a change that one observation shows changed: an added obstacle's cells seen
    occupied, a removed structure's cells seen free with nothing occupied within
    ``tolerance_px`` (what a version paints counts these, session by session)."""
    rows, cols, inside = window.local(lattice, cells)
    kept = np.asarray(cells, np.int64)[inside]
    rows, cols = rows[inside], cols[inside]
    if kind == "added":
        return kept[occupied[rows, cols]]
    ignored = _Ignored.of(current, cells, lattice, window)
    clear = free[rows, cols] & ~_near_occupied(occupied, rows, cols, tolerance_px, ignored)
    return kept[clear]


@dataclass(frozen=True)
class _Ignored:
    """Occupied cells that do not count near a removed change: those the map's ``current``
    version still has occupied besides the change's own ``cells`` (the rest of a wall a piece
    was cut from: its ends stand beside a gap). Read where asked, never over a whole window."""

    current: NDArray[np.uint8]
    cells: IntArray
    lattice: Lattice
    window: Window

    @staticmethod
    def of(
        current: NDArray[np.uint8] | None, cells: IntArray, lattice: Lattice, window: Window
    ) -> _Ignored | None:
        return None if current is None else _Ignored(current, cells, lattice, window)

    def at(self, r: IntArray, c: IntArray) -> NDArray[np.bool_]:
        """Whether window cells ``(r, c)`` do not count."""
        rows, cols = r + self.window.row0, c + self.window.col0
        standing = self.current[rows, cols] == OCCUPIED
        return np.asarray(standing & ~np.isin(rows * self.lattice.width + cols, self.cells))


def _near_occupied(
    occupied: NDArray[np.bool_],
    rows: IntArray,
    cols: IntArray,
    radius_px: int,
    ignored: _Ignored | None = None,
) -> NDArray[np.bool_]:
    """For each cell, whether an occupied cell of the window lies within ``radius_px`` (one
    ``ignored`` says does not count)."""
    h, w = occupied.shape
    dr, dc = disk_offsets(radius_px)
    r = rows[:, None] + dr[None, :]
    c = cols[:, None] + dc[None, :]
    ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    near = np.zeros(r.shape, bool)
    hit = occupied[r[ok], c[ok]]
    if ignored is not None and hit.any():
        hit &= ~ignored.at(r[ok], c[ok])
    near[ok] = hit
    return np.asarray(near.any(axis=1))


@dataclass(frozen=True)
class Persistence:
    """The persistence rule's settings (contract section 7)."""

    confirm_sessions: int = 3
    confirm_span_hours: float = 12.0


def parse_stamp(stamp: str) -> datetime:
    """An ISO 8601 stamp with a zone (``Z`` accepted) as an aware datetime."""
    value = datetime.fromisoformat(stamp.replace("Z", "+00:00"))
    if value.tzinfo is None:
        raise ValueError(f"stamp {stamp!r} has no time zone")
    return value


def span_hours(first_seen: str, last_seen: str) -> float:
    return (parse_stamp(last_seen) - parse_stamp(first_seen)).total_seconds() / 3600.0


def confirmed(
    rule: Persistence, *, sessions: int, first_seen: str, last_seen: str, latest_shows: bool
) -> bool:
    """Whether a pending change is confirmed: seen in at least ``confirm_sessions`` sessions
    spread over at least ``confirm_span_hours``, and the latest bundle that observed its area
    shows it."""
    return (
        latest_shows
        and sessions >= rule.confirm_sessions
        and span_hours(first_seen, last_seen) >= rule.confirm_span_hours
    )
