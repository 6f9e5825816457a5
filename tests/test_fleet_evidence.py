"""Evidence tiles from known observations: the counters a reader sees are the sums of what the
bundles observed, cell by cell, whether their deltas are still pending or folded."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from mapserver.fleet import evidence
from mapserver.fleet.db import connect, transaction
from mapserver.fleet.lattice import Lattice, Window, states_on_lattice
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED, UNKNOWN


@pytest.fixture
def conn(tmp_path: Path) -> sqlite3.Connection:
    c = connect(tmp_path, create=True)
    c.execute(
        "INSERT INTO maps (id, name, width, height, resolution, origin_x, origin_y, origin_yaw, "
        "created_at) VALUES (1, 'm', 400, 300, 0.05, 0, 0, 0, 'now')"
    )
    return c


def observation(rng: np.random.Generator, window: Window) -> tuple[np.ndarray, np.ndarray]:
    state = rng.choice(
        [FREE, OCCUPIED, UNKNOWN], size=(window.rows, window.cols), p=[0.5, 0.1, 0.4]
    )
    return state == OCCUPIED, state == FREE


def test_counters_are_the_sums_of_the_observations_before_and_after_folding(
    conn: sqlite3.Connection,
) -> None:
    rng = np.random.default_rng(3)
    whole = Window(0, 0, 300, 400)
    occ_sum = np.zeros((300, 400), int)
    free_sum = np.zeros((300, 400), int)
    last = np.zeros((300, 400), int)
    n_deltas = 0
    # Windows that straddle tile edges, off the tile grid.
    for hour, window in enumerate(
        [Window(10, 20, 200, 250), Window(100, 90, 150, 300), Window(0, 0, 300, 400)]
    ):
        occupied, free = observation(rng, window)
        rows, cols = (
            slice(window.row0, window.row0 + window.rows),
            slice(window.col0, window.col0 + window.cols),
        )
        occ_sum[rows, cols] += occupied
        free_sum[rows, cols] += free
        last[rows, cols] = np.where(occupied | free, 1000 + hour, last[rows, cols])
        tiles = evidence.pack_tiles(window, occupied, free)
        n_deltas += len(tiles)
        with transaction(conn):
            evidence.add_deltas(conn, 1, tiles, 1000 + hour)
    seen = evidence.read_window(conn, 1, whole)
    assert np.array_equal(seen.occupied, occ_sum) and np.array_equal(seen.free, free_sum)
    assert np.array_equal(seen.last_hour, last)
    assert conn.execute("SELECT count(*) FROM evidence").fetchone()[0] == 0  # all still pending
    with transaction(conn):
        folded = evidence.fold(conn, 1, [(r, c) for r in range(3) for c in range(4)])
    assert folded == n_deltas == 6 + 8 + 12  # tiles each window touched
    assert conn.execute("SELECT count(*) FROM evidence_deltas").fetchone()[0] == 0
    again = evidence.read_window(conn, 1, Window(50, 60, 120, 130))
    assert np.array_equal(again.occupied, occ_sum[50:170, 60:190])
    assert np.array_equal(again.free, free_sum[50:170, 60:190])


def test_a_tile_folds_by_itself_once_enough_deltas_wait(conn: sqlite3.Connection) -> None:
    window = Window(0, 0, 128, 128)  # exactly tile (0, 0)
    occupied = np.zeros((128, 128), bool)
    free = np.ones((128, 128), bool)
    due = evidence.FOLD_AFTER + (0 * 7 + 0 * 13) % evidence.FOLD_SPREAD
    for hour in range(due):
        with transaction(conn):
            evidence.add_deltas(conn, 1, evidence.pack_tiles(window, occupied, free), hour)
    assert conn.execute("SELECT count(*) FROM evidence_deltas").fetchone()[0] == 0
    tile = evidence.read_window(conn, 1, window)
    assert (
        (tile.free == due).all()
        and (tile.occupied == 0).all()
        and (tile.last_hour == due - 1).all()
    )


def test_states_on_a_coarser_lattice_vote_occupied_first() -> None:
    # A 0.05 m local raster on a 0.1 m lattice: 2 x 2 cells per lattice cell.
    lattice = Lattice(10, 10, 0.1, 0.0, 0.0)
    grid = Grid(0.0, 0.0, 0.05, 20, 20)
    state = np.full((20, 20), UNKNOWN, np.uint8)
    state[0:2, 0:2] = FREE
    state[0, 0] = OCCUPIED  # one occupied vote wins the cell: walls are thin
    state[2:4, 2:4] = FREE
    state[4, 4] = FREE  # a single free vote
    found = states_on_lattice(state, grid, lattice)
    assert found is not None
    window, occupied, free = found
    assert (window.row0, window.col0, window.rows, window.cols) == (0, 0, 3, 3)
    assert occupied.tolist() == [[True, False, False], [False, False, False], [False, False, False]]
    assert free.tolist() == [[False, False, False], [False, True, False], [False, False, True]]


def test_each_tile_keeps_the_newest_observations_and_a_reader_gets_them_newest_first(
    conn: sqlite3.Connection,
) -> None:
    rng = np.random.default_rng(5)
    window = Window(100, 120, 60, 200)  # over 2 x 3 tiles
    seen = {}
    for hour in (3, 1, 4, 2, 5):  # applied out of stamp order
        occupied, free = observation(rng, window)
        seen[hour] = (occupied, free)
        with transaction(conn):
            evidence.keep_observation(
                conn,
                1,
                evidence.pack_tiles(window, occupied, free),
                stamp=f"2026-11-21T0{hour}:00:00Z",
                bundle_id=f"b{hour}",
                robot="r1",
                keep=3,
            )
    got = list(evidence.observations(conn, 1, window, until="2026-11-21T04:00:00Z"))
    assert [s.bundle_id for s in got] == ["b4", "b3"]  # b5 is after; b1 and b2 dropped
    for s in got:
        occupied, free = seen[int(s.bundle_id[1:])]
        assert np.array_equal(s.occupied, occupied) and np.array_equal(s.free, free)
        assert s.robot == "r1"
    rows = conn.execute("SELECT count(*) FROM observations").fetchone()[0]
    assert rows == 3 * 6
    later = evidence.observations(conn, 1, window, after="2026-11-21T03:00:00Z", newest_first=False)
    assert [s.bundle_id for s in later] == ["b4", "b5"]
    part = Window(130, 150, 10, 10)  # inside one tile: the same cells, cut
    newest = next(evidence.observations(conn, 1, part))
    assert newest.bundle_id == "b5"
    assert np.array_equal(newest.occupied, seen[5][0][30:40, 30:40])
