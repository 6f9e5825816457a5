"""Evidence: per cell of a stored map, how many sessions saw it occupied, how many saw it free,
and when it was last seen, kept in tiles so that a bundle touches only what it observed.

A tile is ``TILE`` x ``TILE`` cells; its row in the database holds one zlib-compressed blob of
three arrays: occupied-seen (uint16), free-seen (uint16), last seen (uint32, hours since the
Unix epoch). Counters saturate instead of wrapping. Tiles that no bundle observed have no row.
"""

from __future__ import annotations

import sqlite3
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import Window

TILE = 128
_CELLS = TILE * TILE
_MAX_COUNT = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class TileEvidence:
    """One tile's counters, each (TILE, TILE) indexed [row, col] from the tile's corner."""

    occupied: NDArray[np.uint16]
    free: NDArray[np.uint16]
    last_hour: NDArray[np.uint32]

    @staticmethod
    def empty() -> TileEvidence:
        return TileEvidence(
            np.zeros((TILE, TILE), np.uint16),
            np.zeros((TILE, TILE), np.uint16),
            np.zeros((TILE, TILE), np.uint32),
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


def _add(counter: NDArray[np.uint16], seen: NDArray[np.bool_]) -> None:
    np.minimum(counter.astype(np.uint32) + seen, _MAX_COUNT, out=counter, casting="unsafe")


def add_observation(
    conn: sqlite3.Connection,
    map_id: int,
    window: Window,
    occupied: NDArray[np.bool_],
    free: NDArray[np.bool_],
    hour: int,
) -> int:
    """Add one bundle's observation (two (window.rows, window.cols) bool arrays) to the
    evidence of map ``map_id``, inside the caller's transaction. Returns the tiles touched."""
    touched = 0
    for tr in range(window.row0 // TILE, (window.row0 + window.rows - 1) // TILE + 1):
        for tc in range(window.col0 // TILE, (window.col0 + window.cols - 1) // TILE + 1):
            # The part of the window inside this tile, in window and in tile coordinates.
            r0 = max(tr * TILE, window.row0)
            r1 = min((tr + 1) * TILE, window.row0 + window.rows)
            c0 = max(tc * TILE, window.col0)
            c1 = min((tc + 1) * TILE, window.col0 + window.cols)
            wr, wc = (
                slice(r0 - window.row0, r1 - window.row0),
                slice(c0 - window.col0, c1 - window.col0),
            )
            occ, fr = occupied[wr, wc], free[wr, wc]
            if not (occ.any() or fr.any()):
                continue
            row = conn.execute(
                "SELECT data FROM evidence WHERE map_id = ? AND tile_row = ? AND tile_col = ?",
                (map_id, tr, tc),
            ).fetchone()
            tile = TileEvidence.decode(row[0]) if row else TileEvidence.empty()
            tr_, tc_ = slice(r0 - tr * TILE, r1 - tr * TILE), slice(c0 - tc * TILE, c1 - tc * TILE)
            _add(tile.occupied[tr_, tc_], occ)
            _add(tile.free[tr_, tc_], fr)
            last = tile.last_hour[tr_, tc_]
            np.maximum(last, np.where(occ | fr, np.uint32(hour), np.uint32(0)), out=last)
            conn.execute(
                "INSERT OR REPLACE INTO evidence (map_id, tile_row, tile_col, data) "
                "VALUES (?, ?, ?, ?)",
                (map_id, tr, tc, tile.encode()),
            )
            touched += 1
    return touched


def read_window(conn: sqlite3.Connection, map_id: int, window: Window) -> TileEvidence:
    """The evidence over a window of the map, as three (window.rows, window.cols) arrays
    (zero where nothing was ever seen)."""
    out = TileEvidence(
        np.zeros((window.rows, window.cols), np.uint16),
        np.zeros((window.rows, window.cols), np.uint16),
        np.zeros((window.rows, window.cols), np.uint32),
    )
    rows = conn.execute(
        "SELECT tile_row, tile_col, data FROM evidence WHERE map_id = ? "
        "AND tile_row BETWEEN ? AND ? AND tile_col BETWEEN ? AND ?",
        (
            map_id,
            window.row0 // TILE,
            (window.row0 + window.rows - 1) // TILE,
            window.col0 // TILE,
            (window.col0 + window.cols - 1) // TILE,
        ),
    )
    for tr, tc, blob in rows:
        tile = TileEvidence.decode(blob)
        r0, c0 = max(tr * TILE, window.row0), max(tc * TILE, window.col0)
        r1 = min((tr + 1) * TILE, window.row0 + window.rows)
        c1 = min((tc + 1) * TILE, window.col0 + window.cols)
        dst = (slice(r0 - window.row0, r1 - window.row0), slice(c0 - window.col0, c1 - window.col0))
        src = (slice(r0 - tr * TILE, r1 - tr * TILE), slice(c0 - tc * TILE, c1 - tc * TILE))
        out.occupied[dst] = tile.occupied[src]
        out.free[dst] = tile.free[src]
        out.last_hour[dst] = tile.last_hour[src]
    return out
