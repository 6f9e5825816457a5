"""A difference that a small local re-fit of the walls around it explains is a wall seen twice
after drift, not a change (mapserver/refit.py)."""

from __future__ import annotations

import numpy as np

from mapserver.grid import nonzero_cells
from mapserver.refit import explained_by_refit

RES = 0.05
KW = {"resolution": RES, "tolerance_m": 0.15, "removed_tolerance_m": 0.25}


def room(shift_px: int = 0) -> np.ndarray:
    """A 4 m x 4 m room with a 1.5 m partition inside, walls 1 px, on a 6 m x 6 m grid, moved
    ``shift_px`` to the right."""
    m = np.zeros((120, 120), bool)
    c = 20 + shift_px
    m[20, c : c + 80] = m[99, c : c + 80] = True
    m[20:100, c] = m[20:100, c + 79] = True
    m[40:70, c + 40] = True  # the partition
    return m


def cells(mask: np.ndarray) -> np.ndarray:
    rows, cols = nonzero_cells(mask)
    return np.stack([rows, cols], axis=1)


def test_a_wall_seen_again_off_where_the_walls_around_it_are_off_too_is_explained() -> None:
    glob = room()
    local = room(shift_px=7)  # this corner of the session drifted 0.35 m
    ghost = np.zeros(glob.shape, bool)
    ghost[40:70, 67] = True  # the partition, seen 0.35 m off: beyond the tolerance
    assert explained_by_refit(cells(ghost), "added", glob, local, **KW)


def test_a_new_obstacle_among_walls_that_fit_is_not_explained() -> None:
    glob = room()
    local = room()
    box = np.zeros(glob.shape, bool)
    box[75:85, 40:50] = True  # 0.5 m box in the room, 1 m from every wall
    local |= box
    assert not explained_by_refit(cells(box), "added", glob, local, **KW)


def test_a_wall_gone_stays_gone_and_a_wall_only_moved_is_explained() -> None:
    glob = room()
    partition = np.zeros(glob.shape, bool)
    partition[40:70, 60] = True
    # The partition removed, the rest of the room where it was drawn: seen free, no fit helps.
    local = room() & ~partition
    assert not explained_by_refit(cells(partition), "removed", glob, local, **KW)
    # The whole room seen 0.35 m off: the partition's cells are free in the local map only
    # because its wall was drawn off with the rest.
    assert explained_by_refit(cells(partition), "removed", glob, room(shift_px=7), **KW)


def test_a_gap_in_a_straight_wall_is_not_explained_by_sliding_the_wall_over_it() -> None:
    """A 0.8 m piece of a long straight wall gone, the wall either side seen where it is drawn:
    sliding those walls 0.4 m along themselves fits them as well and would cover the gap, but
    a wall seen where it is drawn has not moved."""
    glob = np.zeros((120, 200), bool)
    glob[60, 10:190] = True
    gap = np.zeros(glob.shape, bool)
    gap[60, 92:108] = True
    local = glob & ~gap
    assert not explained_by_refit(cells(gap), "removed", glob, local, **KW)
    # The same wall seen 0.35 m off across itself: the gap's cells are free only because of
    # that, and the re-fit that moves it back explains them.
    off = np.roll(glob, 7, axis=0) & ~np.roll(gap, 7, axis=0)
    off_gap = gap & ~off
    assert explained_by_refit(cells(off_gap), "removed", glob, off | np.roll(gap, 7, axis=0), **KW)
