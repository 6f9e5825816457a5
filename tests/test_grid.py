"""mapserver/grid.py: a raster over a metric frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapserver.grid import (
    Grid,
    RouteDistance,
    any_along,
    any_in_blocks,
    by_label,
    route_distance,
)


def test_sample_reads_the_nearest_pixel_and_fills_off_the_grid() -> None:
    grid = Grid(10.0, 20.0, 0.5, 4, 3)  # x 10..12 m, y 20..21.5 m; row 0 at the top
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    xy = np.array([[10.2, 21.4], [11.9, 20.1], [11.1, 20.7], [9.9, 20.5], [10.5, 21.6]])
    values = grid.sample(image, xy, 255)
    # (col 0, row 0), (col 3, row 2), (col 2, row 1); left of the grid; above it.
    assert values.tolist() == [0, 11, 6, 255, 255]
    assert values.dtype == np.uint8
    assert grid.sample(image > 5, xy, False).tolist() == [False, True, True, False, False]


def test_blocks_that_hold_a_cell_of_a_mask() -> None:
    """Blocks of 3 x 3 cells over a 7 x 8 mask: the last row and column of blocks are the
    padded ones (1 row, 2 columns of cells)."""
    mask = np.zeros((7, 8), bool)
    mask[6, 7] = True  # the corner cell, in the padded block
    mask[1, 4] = True
    blocks = any_in_blocks(mask, 3)
    assert blocks.shape == (3, 3)
    assert blocks.tolist() == [[False, True, False], [False, False, False], [False, False, True]]
    assert not any_in_blocks(np.zeros((7, 8), bool), 3).any()


def test_the_direction_from_a_cell_to_the_route() -> None:
    """A route down column 7 of a 60 x 60 grid at 0.05 m, rows 0-30 (0.25 m blocks of 5
    cells: the route's blocks are centred on column 7): a cell level with a block's centre
    points straight at it along the row, a cell below the route's end up at its last block,
    a cell down and to the right of it up and to the left at 45 degrees; without the nearest
    blocks, no direction."""
    route = route_distance(np.array([[7.0, 0.0], [7.0, 30.0]]), (60, 60), 0.05, nearest=True)
    assert route is not None and route.nearest is not None
    cells = np.array([12, 58, 52]), np.array([50, 7, 27])
    toward = route.toward(*cells)
    assert toward is not None and toward.shape == (3, 2)
    assert np.allclose(toward[0], [0.0, -1.0])  # row 12 is block 2's centre row
    assert np.allclose(toward[1], [-1.0, 0.0])  # the last block (rows 30-34) straight up
    assert np.allclose(toward[2], [-math.sqrt(0.5), -math.sqrt(0.5)])  # to (32, 7)
    rows, cols = np.nonzero(np.ones((60, 60), bool))
    assert np.allclose(np.hypot(*route.toward(rows, cols).T), 1.0)
    assert RouteDistance(route.blocks, route.block).toward(*cells) is None


def test_how_far_from_the_route_a_map_saw_anything() -> None:
    """A route along row 0 of a 40 x 40 grid at 0.1 m (0.2 m blocks of 2 cells): cells seen at
    row 30 lie 3.0 m from it; the reach is their distance on their block, never more and at
    most a block's diagonal less; nothing seen, 0; a mask not on the grid, an error."""
    route = route_distance(np.array([[0.0, 0.0], [39.0, 0.0]]), (40, 40), 0.1, block_m=0.2)
    assert isinstance(route, RouteDistance)
    seen = np.zeros((40, 40), bool)
    seen[30, 12:15] = True
    assert 3.0 - 0.2 * math.sqrt(2) <= route.farthest(seen) <= 3.0
    seen[5, 5] = True  # nearer cells do not lower it
    assert 3.0 - 0.2 * math.sqrt(2) <= route.farthest(seen) <= 3.0
    assert route.farthest(np.zeros((40, 40), bool)) == 0.0
    with pytest.raises(ValueError):
        route.farthest(np.ones((20, 40), bool))


def test_any_along_looks_the_given_steps_each_way_a_cell_points() -> None:
    """A True cell 3 cells east of (5, 5): seen within 3 steps east, not within 2, not west;
    south-west, (1, -1) / sqrt(2) steps round to the cells of the diagonal; a step off the
    array sees nothing; one direction per cell."""
    mask = np.zeros((10, 10), bool)
    mask[5, 8] = True
    mask[8, 2] = True
    rows, cols = np.array([5]), np.array([5])
    assert any_along(mask, rows, cols, 0.0, 1.0, 3).tolist() == [True]
    assert any_along(mask, rows, cols, 0.0, 1.0, 2).tolist() == [False]
    assert any_along(mask, rows, cols, 0.0, -1.0, 5).tolist() == [False]
    assert any_along(mask, rows, cols, 1.0, -1.0, 3, math.sqrt(2)).tolist() == [False]
    assert any_along(mask, rows, cols, 1.0, -1.0, 5, math.sqrt(2)).tolist() == [True]
    edge = np.array([0]), np.array([8])
    assert any_along(mask, *edge, -1.0, 0.0, 4).tolist() == [False]
    both = np.array([5, 5]), np.array([5, 5])
    dr, dc = np.array([0, 3]), np.array([3, -3])
    norm = np.hypot(dr, dc)
    assert any_along(mask, *both, dr, dc, 4, norm).tolist() == [True, True]


def test_by_label_gives_each_label_ascending_with_its_indices_in_order() -> None:
    labels = np.array([3, -1, 0, 3, 0, 7, -1, 3])
    found = [(k, idx.tolist()) for k, idx in by_label(labels)]
    assert found == [(-1, [1, 6]), (0, [2, 4]), (3, [0, 3, 7]), (7, [5])]
    assert list(by_label(np.zeros(0, np.int32))) == []
