"""The images: what a person looks at must show what the maps hold, at any scale."""

from __future__ import annotations

import numpy as np

from mapserver import render
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED


def _scene() -> tuple[Grid, np.ndarray, np.ndarray]:
    grid = Grid(0.0, 0.0, 0.05, 3000, 800)
    global_state = np.full(grid.shape, FREE, np.uint8)
    global_state[:, 1501] = OCCUPIED  # a wall one cell thick
    roi = np.ones(grid.shape, bool)
    return grid, global_state, roi


def test_a_shrunk_image_still_shows_a_thin_global_wall() -> None:
    grid, global_state, roi = _scene()
    window = render.window_for(grid, roi, margin_m=0.0, max_side_px=1000)
    assert window.scale < 1
    empty = np.zeros(grid.shape, bool)
    over = render.overlay(grid, window, global_state, np.full_like(global_state, FREE), [], [])
    diff = render.diff_image(grid, window, global_state, empty, empty, [])
    # Image columns 499-501 hold the wall (3000 cells to 1000 pixels): it is drawn in the
    # occupied grey of each image, on every row below the legend.
    rows = slice(200, 260)
    assert (over[rows, 499:502] == 60).all(axis=2).any(axis=1).all()
    assert (diff[rows, 499:502] == 215).all(axis=2).any(axis=1).all()
    # Elsewhere: free space, not walls.
    assert (over[rows, 100] == 255).all() and (diff[rows, 100] == 255).all()


def test_at_full_scale_each_cell_is_one_pixel_of_its_state() -> None:
    grid, global_state, roi = _scene()
    window = render.window_for(grid, roi, margin_m=0.0, max_side_px=4000)
    assert window.scale == 1
    empty = np.zeros(grid.shape, bool)
    diff = render.diff_image(grid, window, global_state, empty, empty, [])
    assert diff.shape[:2] == grid.shape
    assert (diff[300:700, 1501] == 215).all() and (diff[300:700, 1502] == 255).all()
