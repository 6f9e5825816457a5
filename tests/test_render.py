"""The images: what a person looks at must show what the maps hold, at any scale."""

from __future__ import annotations

import numpy as np

from mapserver import render
from mapserver.cluster import Difference
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


def _banner_text_columns(image: np.ndarray, band_rows: int) -> np.ndarray:
    """The columns of the top ``band_rows`` rows that hold the banner's white letters."""
    return np.flatnonzero((image[:band_rows].min(axis=2) > 200).any(axis=0))


def test_a_long_banner_breaks_between_words_inside_the_image() -> None:
    # Session 55: a partly trusted bundle's banner ran ~30 px off an 824 px overlay (its one
    # long part was measured thin while drawn bold, and shrunk on a width that Hershey letters
    # do not follow linearly), cutting "only" off the end.
    text = (
        "PARTLY TRUSTED alignment: 51% of the observed area (257 m2) compared, "
        "differences reported there only; the rest was left out"
    )
    for width in (824, 500, 1600):
        image = np.zeros((40, width, 3), np.uint8)
        out = render.with_banner(image, text)
        band_rows = out.shape[0] - 40
        columns = _banner_text_columns(out, band_rows)
        assert columns.min() >= 4 and columns.max() <= width - 5, width
        assert np.array_equal(out[band_rows:], image)
    # Wide enough for it all: one line; on a narrow image more lines, not smaller letters.
    wide = render.with_banner(np.zeros((40, 1600, 3), np.uint8), text).shape[0] - 40
    narrow = render.with_banner(np.zeros((40, 500, 3), np.uint8), text).shape[0] - 40
    assert narrow >= 3 * (wide - 10)


def test_banner_lines_keep_whole_parts_and_words() -> None:
    lines = render._wrapped("aaa bbb; cc; dddd eeee ffff", lambda line: len(line) <= 9)
    assert lines == ["aaa bbb", "cc", "dddd eeee", "ffff"]
    assert render._wrapped("averyveryverylongword x", lambda line: len(line) <= 5) == [
        "averyveryverylongword",
        "x",
    ]


def _legend_corner(image: np.ndarray) -> str:
    """Which quarter of ``image`` holds the legend's frame (its (90, 90, 90) outline)."""
    rows, cols = np.nonzero((image == 90).all(axis=2))
    h, w = image.shape[:2]
    return ("top" if rows.mean() < h / 2 else "bottom") + (
        " left" if cols.mean() < w / 2 else " right"
    )


def test_the_legend_goes_where_it_hides_the_least() -> None:
    """Session 58's review: always top left, the legend covered a corner of the building in
    the demo's overlay, where a difference would have been hidden."""
    grid = Grid(0.0, 0.0, 0.05, 400, 300)  # 20 m x 15 m, drawn at one pixel a cell
    window = render.window_for(grid, np.ones(grid.shape, bool), margin_m=0.0, max_side_px=4000)
    global_state = np.full(grid.shape, FREE, np.uint8)
    local = np.full(grid.shape, FREE, np.uint8)
    empty = render.overlay(grid, window, global_state, local, [], [])
    assert _legend_corner(empty) == "top left"  # nothing anywhere: where it always was
    # A difference in the top left corner (x 0.5-3 m, y 12.5-14.5 m): the legend moves away.
    box = Difference("added", (1.75, 13.5), (0.5, 12.5, 3.0, 14.5), 5.0, 2000)
    over = render.overlay(grid, window, global_state, local, [], [box])
    assert _legend_corner(over) == "top right"
    # Walls along the top too: the bottom right (the bottom left holds the title).
    global_state[:60, :] = OCCUPIED
    titled = render.overlay(grid, window, global_state, local, [], [box], title="run-1")
    assert _legend_corner(titled) == "bottom right"
    diff = render.diff_image(grid, window, global_state, *(np.zeros(grid.shape, bool),) * 2, [box])
    # Ties go top left, top right, bottom right, bottom left, in that order.
    assert _legend_corner(diff) == "bottom right"
    # Walls everywhere: it hides walls, never the difference (which has the fewest pixels).
    walls = np.full(grid.shape, OCCUPIED, np.uint8)
    assert _legend_corner(render.overlay(grid, window, walls, local, [], [box])) == "top right"
