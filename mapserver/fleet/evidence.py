"""Evidence: per cell of a stored map, how many sessions saw it occupied, how many saw it free,
and when it was last seen, kept in tiles so that a bundle touches only what it observed.

A tile is ``TILE`` x ``TILE`` cells. Two tables hold it:

- ``evidence_deltas``: what one bundle observed in one tile, packed by the worker that processed
  it (two bit planes, zlib) with the bundle's hour. Applying a bundle only inserts these rows,
  in its transaction: a few milliseconds, whatever the size of the map.
- ``evidence``: the counters, one zlib-compressed blob per tile of three arrays: occupied-seen
  (uint16), free-seen (uint16), last seen (uint32, hours since the Unix epoch). Counters
  saturate instead of wrapping. :func:`fold` adds a tile's pending deltas into its counters
  and deletes them; it runs for a tile once enough deltas wait on it (a bundle pays for a few
  tiles, not for every tile it saw), and when the daemon is idle.

:func:`read_window` returns the counters with the pending deltas added: readers never see a
difference between folded and pending evidence.
"""

from __future__ import annotations

import sqlite3
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import Window

TILE = 128
_CELLS = TILE * TILE
_BITS = _CELLS // 8
_MAX_COUNT = np.iinfo(np.uint16).max
# A tile is folded when this many deltas wait on it, plus up to FOLD_SPREAD more depending on
# the tile: neighbouring tiles (seen by the same bundles) fold at different bundles.
FOLD_AFTER = 8
FOLD_SPREAD = 8

TileDelta = tuple[int, int, bytes]
"""(tile_row, tile_col, packed bits) of one bundle's observation of one tile."""


@dataclass(frozen=True)
class TileEvidence:
    """One tile's counters, each (TILE, TILE) indexed [row, col] from the tile's corner."""

    occupied: NDArray[np.uint16]
    free: NDArray[np.uint16]
    last_hour: NDArray[np.uint32]

    @staticmethod
    def empty(shape: tuple[int, int] = (TILE, TILE)) -> TileEvidence:
        return TileEvidence(
            np.zeros(shape, np.uint16), np.zeros(shape, np.uint16), np.zeros(shape, np.uint32)
        )

    def encode(self) -> bytes:
        return zlib.compress(
            self.occupied.tobytes() + self.free.tobytes() + self.last_hour.tobytes(), 1
        )

    @staticmethod
    def decode(blob: bytes) -> TileEvidence:
        raw = zlib.decompress(blob)
        occ = np.frombuffer(raw, np.uint16, _CELLS, 0).reshape(TILE, TILE).copy()
        free = np.frombuffer(raw, np.uint16, _CELLS, 2 * _CELLS).reshape(TILE, TILE).copy()
        last = np.frombuffer(raw, np.uint32, _CELLS, 4 * _CELLS).reshape(TILE, TILE).copy()
        return TileEvidence(occ, free, last)

    def add(self, occupied: NDArray[np.bool_], free: NDArray[np.bool_], hour: int) -> None:
        """Count one session's observation (two (TILE, TILE) bool arrays) in place."""
        for counter, seen in ((self.occupied, occupied), (self.free, free)):
            np.minimum(counter.astype(np.uint32) + seen, _MAX_COUNT, out=counter, casting="unsafe")
        np.maximum(
            self.last_hour,
            np.where(occupied | free, np.uint32(hour), np.uint32(0)),
            out=self.last_hour,
        )


Slices = tuple[slice, slice]


def _overlap(window: Window, tr: int, tc: int) -> tuple[Slices, Slices]:
    """Where tile ``(tr, tc)`` overlaps the window: slices of a (window.rows, window.cols)
    array and of a (TILE, TILE) one."""
    r0, c0 = max(tr * TILE, window.row0), max(tc * TILE, window.col0)
    r1 = min((tr + 1) * TILE, window.row0 + window.rows)
    c1 = min((tc + 1) * TILE, window.col0 + window.cols)
    in_window = (
        slice(r0 - window.row0, r1 - window.row0),
        slice(c0 - window.col0, c1 - window.col0),
    )
    return in_window, (slice(r0 - tr * TILE, r1 - tr * TILE), slice(c0 - tc * TILE, c1 - tc * TILE))


def _tiles_over(window: Window) -> Iterator[tuple[int, int, Slices, Slices]]:
    """``(tile_row, tile_col, in_window, in_tile)`` of every tile the window overlaps: the
    overlap as slices of a (window.rows, window.cols) array and of a (TILE, TILE) one."""
    tr0, tc0, tr1, tc1 = _tile_range(window)
    for tr in range(tr0, tr1 + 1):
        for tc in range(tc0, tc1 + 1):
            yield tr, tc, *_overlap(window, tr, tc)


def _tile_range(window: Window) -> tuple[int, int, int, int]:
    """(first tile row, first tile col, last tile row, last tile col) the window overlaps."""
    return (
        window.row0 // TILE,
        window.col0 // TILE,
        (window.row0 + window.rows - 1) // TILE,
        (window.col0 + window.cols - 1) // TILE,
    )


def pack_tiles(
    window: Window, occupied: NDArray[np.bool_], free: NDArray[np.bool_]
) -> tuple[TileDelta, ...]:
    """One bundle's observation (two (window.rows, window.cols) bool arrays on the lattice) as
    per-tile deltas: run in the worker, so that the main process only stores them."""
    out = []
    for tr, tc, in_window, in_tile in _tiles_over(window):
        occ, fr = occupied[in_window], free[in_window]
        if not (occ.any() or fr.any()):
            continue
        planes = np.zeros((2, TILE, TILE), bool)
        planes[0][in_tile], planes[1][in_tile] = occ, fr
        out.append((tr, tc, zlib.compress(np.packbits(planes).tobytes(), 1)))
    return tuple(out)


def unpack(blob: bytes) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(occupied, free) (TILE, TILE) bool arrays of a packed delta."""
    bits = np.unpackbits(np.frombuffer(zlib.decompress(blob), np.uint8), count=2 * _CELLS)
    planes = bits.view(bool).reshape(2, TILE, TILE)
    return planes[0], planes[1]


def add_deltas(
    conn: sqlite3.Connection, map_id: int, tiles: Iterable[TileDelta], hour: int
) -> list[tuple[int, int]]:
    """Store one bundle's deltas, inside the caller's transaction; then fold the tiles among
    them that have waited long enough. Returns the tiles touched."""
    touched = []
    for tr, tc, blob in tiles:
        conn.execute(
            "INSERT INTO evidence_deltas (map_id, tile_row, tile_col, hour, data) "
            "VALUES (?, ?, ?, ?, ?)",
            (map_id, tr, tc, hour, blob),
        )
        touched.append((tr, tc))
    due = []
    for tr, tc in touched:
        waiting = conn.execute(
            "SELECT count(*) FROM evidence_deltas WHERE map_id = ? AND tile_row = ? AND tile_col = ?",
            (map_id, tr, tc),
        ).fetchone()[0]
        if waiting >= FOLD_AFTER + (tr * 7 + tc * 13) % FOLD_SPREAD:
            due.append((tr, tc))
    fold(conn, map_id, due)
    return touched


def fold(conn: sqlite3.Connection, map_id: int, tiles: Iterable[tuple[int, int]]) -> int:
    """Add the pending deltas of these tiles into their counters and delete them, inside the
    caller's transaction. Returns the number of deltas folded."""
    folded = 0
    for tr, tc in tiles:
        rows = conn.execute(
            "SELECT id, hour, data FROM evidence_deltas WHERE map_id = ? AND tile_row = ? "
            "AND tile_col = ? ORDER BY id",
            (map_id, tr, tc),
        ).fetchall()
        if not rows:
            continue
        tile = _counters(conn, map_id, tr, tc)
        for _, hour, blob in rows:
            tile.add(*unpack(blob), hour)
        conn.execute(
            "INSERT OR REPLACE INTO evidence (map_id, tile_row, tile_col, data) VALUES (?, ?, ?, ?)",
            (map_id, tr, tc, tile.encode()),
        )
        conn.execute(
            "DELETE FROM evidence_deltas WHERE map_id = ? AND tile_row = ? AND tile_col = ? "
            "AND id <= ?",
            (map_id, tr, tc, rows[-1][0]),
        )
        folded += len(rows)
    return folded


def pending_tiles(conn: sqlite3.Connection, limit: int) -> list[tuple[int, int, int]]:
    """(map_id, tile_row, tile_col) of up to ``limit`` tiles with deltas waiting, the most
    waiting first."""
    return [
        (m, r, c)
        for m, r, c, _ in conn.execute(
            "SELECT map_id, tile_row, tile_col, count(*) AS n FROM evidence_deltas "
            "GROUP BY map_id, tile_row, tile_col ORDER BY n DESC LIMIT ?",
            (limit,),
        )
    ]


def _counters(conn: sqlite3.Connection, map_id: int, tr: int, tc: int) -> TileEvidence:
    row = conn.execute(
        "SELECT data FROM evidence WHERE map_id = ? AND tile_row = ? AND tile_col = ?",
        (map_id, tr, tc),
    ).fetchone()
    return TileEvidence.decode(row[0]) if row else TileEvidence.empty()


def read_window(conn: sqlite3.Connection, map_id: int, window: Window) -> TileEvidence:
    """The evidence over a window of the map (pending deltas included), as three
    (window.rows, window.cols) arrays, zero where nothing was ever seen."""
    out = TileEvidence.empty((window.rows, window.cols))
    for tr, tc, in_window, in_tile in _tiles_over(window):
        tile = _counters(conn, map_id, tr, tc)
        for hour, blob in conn.execute(
            "SELECT hour, data FROM evidence_deltas WHERE map_id = ? AND tile_row = ? "
            "AND tile_col = ? ORDER BY id",
            (map_id, tr, tc),
        ):
            tile.add(*unpack(blob), hour)
        out.occupied[in_window] = tile.occupied[in_tile]
        out.free[in_window] = tile.free[in_tile]
        out.last_hour[in_window] = tile.last_hour[in_tile]
    return out


# How many bundles' observations each tile keeps (the newest, by stamp): what a change found
# late is judged on, back and forth from its finder. About 300 bytes a tile and bundle on the
# airport of bench_fleet.py (measured after a checkpoint): 64 x ~300 B x the map's tiles, under
# 20 MiB for a 5000 x 3000 map. On a busy tile 64 bundles may span less than
# update.confirm_span_hours (ten robots passing every hour: 6 hours); the sessions a finder's
# predecessors missed are the latest ones, and those are kept.
KEEP_OBSERVATIONS = 64


@dataclass(frozen=True)
class Seen:
    """One bundle's observation of a window: who, when, and its (rows, cols) bool arrays."""

    stamp: str
    bundle_id: str
    robot: str
    occupied: NDArray[np.bool_]
    free: NDArray[np.bool_]


def keep_observation(
    conn: sqlite3.Connection,
    map_id: int,
    tiles: Iterable[TileDelta],
    *,
    stamp: str,
    bundle_id: str,
    robot: str,
    keep: int | None = None,
) -> None:
    """Keep one bundle's packed tiles with its stamp, bundle id and robot, inside the caller's
    transaction; each tile keeps the newest ``keep`` (default :data:`KEEP_OBSERVATIONS`)
    bundles' observations, by stamp, then bundle id."""
    keep = KEEP_OBSERVATIONS if keep is None else keep
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    for tr, tc, blob in tiles:
        conn.execute(
            "INSERT OR REPLACE INTO observations "
            "(map_id, tile_row, tile_col, stamp, bundle_id, robot, data) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (map_id, tr, tc, stamp, bundle_id, robot, blob),
        )
        oldest_kept = conn.execute(
            "SELECT stamp, bundle_id FROM observations WHERE map_id = ? AND tile_row = ? "
            "AND tile_col = ? ORDER BY stamp DESC, bundle_id DESC LIMIT 1 OFFSET ?",
            (map_id, tr, tc, keep - 1),
        ).fetchone()
        if oldest_kept is not None:
            conn.execute(
                "DELETE FROM observations WHERE map_id = ? AND tile_row = ? AND tile_col = ? "
                "AND (stamp < ? OR (stamp = ? AND bundle_id < ?))",
                (map_id, tr, tc, oldest_kept[0], oldest_kept[0], oldest_kept[1]),
            )


def observations(
    conn: sqlite3.Connection,
    map_id: int,
    window: Window,
    *,
    until: str | None = None,
    after: str | None = None,
    newest_first: bool = True,
) -> Iterator[Seen]:
    """The kept observations of the window, one bundle at a time: those stamped at or before
    ``until`` and after ``after`` (None: no bound), newest first or oldest first, each over the
    whole window (cells of tiles it did not observe: neither occupied nor free). Read as the
    caller goes: a caller that stops early reads no further."""
    tr0, tc0, tr1, tc1 = _tile_range(window)
    order = "DESC" if newest_first else "ASC"
    sql = (
        "SELECT stamp, bundle_id, robot, tile_row, tile_col, data FROM observations "
        "WHERE map_id = ? AND tile_row BETWEEN ? AND ? AND tile_col BETWEEN ? AND ?"
    )
    args: list[object] = [map_id, tr0, tr1, tc0, tc1]
    if until is not None:
        sql += " AND stamp <= ?"
        args.append(until)
    if after is not None:
        sql += " AND stamp > ?"
        args.append(after)
    sql += f" ORDER BY stamp {order}, bundle_id {order}"
    shape = (window.rows, window.cols)
    current: Seen | None = None
    for stamp, bundle_id, robot, tr, tc, blob in conn.execute(sql, args):
        if current is None or (current.stamp, current.bundle_id) != (stamp, bundle_id):
            if current is not None:
                yield current
            current = Seen(stamp, bundle_id, robot, np.zeros(shape, bool), np.zeros(shape, bool))
        in_window, in_tile = _overlap(window, tr, tc)
        occupied, free = unpack(blob)
        current.occupied[in_window] = occupied[in_tile]
        current.free[in_window] = free[in_tile]
    if current is not None:
        yield current
