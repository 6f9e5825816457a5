"""Region-of-interest strategies give the expected masks and polygons."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapserver import roi
from mapserver.geometry import Pose2D
from mapserver.grid import Grid
from mapserver.maps import FREE, UNKNOWN

GRID = Grid(0.0, 0.0, 0.1, 200, 200)  # 20 m x 20 m


def _contains(r: roi.Roi, x: float, y: float) -> bool:
    c, k = np.rint(GRID.to_pixel([[x, y]])[0]).astype(int)
    return bool(r.mask[k, c])


def test_box_is_centred_on_the_robot() -> None:
    r = roi.box(Pose2D(10.0, 10.0, 0.0), GRID, size_m=4.0)
    assert r.mask.sum() == pytest.approx(1600, rel=0.06)
    assert _contains(r, 11.9, 8.1) and not _contains(r, 12.3, 10.0)
    assert sorted(r.polygon) == [(8.0, 8.0), (8.0, 12.0), (12.0, 8.0), (12.0, 12.0)]


def test_heading_is_behind_the_robot() -> None:
    r = roi.heading(Pose2D(10.0, 10.0, math.pi / 2), GRID, size_m=4.0)  # facing +y
    assert _contains(r, 10.0, 7.0)  # behind
    assert not _contains(r, 10.0, 11.0)  # ahead


def test_trajectory_is_a_corridor_around_the_route() -> None:
    route = np.array([[2.0, 2.0], [18.0, 2.0], [18.0, 18.0]])
    r = roi.trajectory(route, GRID, radius_m=1.0)
    assert _contains(r, 10.0, 2.9) and not _contains(r, 10.0, 3.4)
    assert _contains(r, 17.2, 10.0) and not _contains(r, 15.0, 10.0)
    assert len(r.polygon) >= 4


def test_observed_is_what_the_local_map_knows() -> None:
    state = np.full(GRID.shape, UNKNOWN, np.uint8)
    state[50:150, 40:120] = FREE
    r = roi.observed(state, GRID)
    assert r.mask.sum() == 100 * 80
    xs = [p[0] for p in r.polygon]
    ys = [p[1] for p in r.polygon]
    assert min(xs) == pytest.approx(4.05, abs=0.11) and max(xs) == pytest.approx(11.95, abs=0.11)
    assert min(ys) == pytest.approx(5.05, abs=0.11) and max(ys) == pytest.approx(14.95, abs=0.11)


@pytest.mark.parametrize(("rows", "cols"), [(1, 1), (3, 3), (1, 6)])
def test_an_observed_region_a_few_cells_across_is_a_polygon_around_them(
    rows: int, cols: int
) -> None:
    # Session 53's review: a 1x1 or 3x3 local map's outline simplified (0.25 m) to one point.
    state = np.full(GRID.shape, UNKNOWN, np.uint8)
    state[100 : 100 + rows, 50 : 50 + cols] = FREE
    r = roi.observed(state, GRID)
    x0, y_top = GRID.x0 + 50 * 0.1, GRID.y0 + (200 - 100) * 0.1
    assert sorted(r.polygon) == sorted(
        [
            (x0, y_top),
            (x0 + cols * 0.1, y_top),
            (x0 + cols * 0.1, y_top - rows * 0.1),
            (x0, y_top - rows * 0.1),
        ]
    )
