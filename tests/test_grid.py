"""mapserver/grid.py: a raster over a metric frame."""

from __future__ import annotations

import numpy as np

from mapserver.grid import Grid


def test_sample_reads_the_nearest_pixel_and_fills_off_the_grid() -> None:
    grid = Grid(10.0, 20.0, 0.5, 4, 3)  # x 10..12 m, y 20..21.5 m; row 0 at the top
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    xy = np.array([[10.2, 21.4], [11.9, 20.1], [11.1, 20.7], [9.9, 20.5], [10.5, 21.6]])
    values = grid.sample(image, xy, 255)
    # (col 0, row 0), (col 3, row 2), (col 2, row 1); left of the grid; above it.
    assert values.tolist() == [0, 11, 6, 255, 255]
    assert values.dtype == np.uint8
    assert grid.sample(image > 5, xy, False).tolist() == [False, True, True, False, False]
