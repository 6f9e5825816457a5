"""Annotated images: ``overlay.png`` (global map, local map, ROI, route, numbered boxes) and
``diff.png`` (the filtered difference mask), both over the ROI plus a margin, never the whole
global map."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.cluster import Difference
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED

BGR = tuple[int, int, int]
T = TypeVar("T", bound=np.generic)
ADDED: BGR = (0, 0, 230)
REMOVED: BGR = (230, 60, 0)
LOCAL: BGR = (40, 150, 40)
ROI_COLOUR: BGR = (0, 190, 255)
ROUTE: BGR = (200, 0, 200)
BANNER: BGR = (0, 0, 170)
LEFT_OUT: BGR = (150, 150, 150)


@dataclass(frozen=True)
class Window:
    """The part of the work grid an image shows, and the scale from grid pixels to image pixels."""

    row0: int
    col0: int
    rows: int
    cols: int
    scale: float

    def to_image(self, grid: Grid, xy: NDArray[np.float64]) -> NDArray[np.int32]:
        px = grid.to_pixel(xy) - np.array([self.col0, self.row0])
        return np.asarray(np.rint((px + 0.5) * self.scale - 0.5), dtype=np.int32)


def window_for(
    grid: Grid,
    roi_mask: NDArray[np.bool_],
    *,
    margin_m: float,
    max_side_px: int,
    min_side_px: int = 700,
) -> Window:
    """The ROI's bounding box plus ``margin_m``, clipped to the grid, with a display scale that
    makes small areas legible and large ones small enough."""
    x, y, w, h = cv2.boundingRect(roi_mask.view(np.uint8))
    if w == 0:
        x, y, w, h = 0, 0, grid.width, grid.height
    m = round(margin_m / grid.resolution)
    r0, r1 = max(y - m, 0), min(y + h + m, grid.height)
    c0, c1 = max(x - m, 0), min(x + w + m, grid.width)
    side = max(r1 - r0, c1 - c0)
    scale = 1.0
    if side > max_side_px:
        scale = max_side_px / side
    elif side < min_side_px:
        scale = float(math.ceil(min_side_px / side))
    return Window(r0, c0, r1 - r0, c1 - c0, scale)


def _crop(image: NDArray[T], window: Window) -> NDArray[T]:
    return image[window.row0 : window.row0 + window.rows, window.col0 : window.col0 + window.cols]


def _size(window: Window) -> tuple[int, int]:
    """(width, height) of the image of ``window``."""
    return max(1, round(window.cols * window.scale)), max(1, round(window.rows * window.scale))


def _state_scaled(state_crop: NDArray[np.uint8], window: Window) -> NDArray[np.uint8]:
    """Cell states cropped to the window, scaled: each image pixel takes one cell's state
    (states are categories, never averaged)."""
    size = _size(window)
    if size == (state_crop.shape[1], state_crop.shape[0]):
        return state_crop
    return np.asarray(cv2.resize(state_crop, size, interpolation=cv2.INTER_NEAREST), np.uint8)


def _mask_scaled(mask_crop: NDArray[np.bool_], window: Window) -> NDArray[np.bool_]:
    """A mask already cropped to the window, scaled. Max-pools when shrinking, so that thin
    walls and small differences stay visible."""
    size = _size(window)
    if size == (mask_crop.shape[1], mask_crop.shape[0]):
        return mask_crop.copy()
    interpolation = cv2.INTER_NEAREST if window.scale >= 1 else cv2.INTER_AREA
    return cv2.resize(mask_crop.astype(np.uint8) * 255, size, interpolation=interpolation) > 0


def _painted(
    state_crop: NDArray[np.uint8],
    window: Window,
    greys: tuple[int, int, int],
    layers: list[tuple[NDArray[np.bool_], BGR]],
) -> NDArray[np.uint8]:
    """A BGR image of the window's cell states in three greys (free, occupied, unknown), with
    each layer's cells painted over in its colour, later layers on top. Every pixel gets a
    colour number and one table lookup colours them all (not a pass per state or layer on
    three channels). Shrunk, the occupied cells are max-pooled like the layers: thin walls stay."""
    free, occupied, unknown = greys
    numbers = np.full(256, 2, np.uint8)
    numbers[FREE], numbers[OCCUPIED] = 0, 1
    colour_of = np.asarray(cv2.LUT(_state_scaled(state_crop, window), numbers), np.uint8)
    if window.scale < 1:
        np.putmask(colour_of, _mask_scaled(state_crop == OCCUPIED, window), 1)
    palette = np.zeros((256, 1, 3), np.uint8)
    palette[:3, 0] = [(free,) * 3, (occupied,) * 3, (unknown,) * 3]
    for number, (mask, colour) in enumerate(layers, start=3):
        np.putmask(colour_of, mask, number)
        palette[number, 0] = colour
    return np.asarray(cv2.LUT(cv2.merge([colour_of] * 3), palette), np.uint8)


def _legend(
    image: NDArray[np.uint8],
    items: list[tuple[str, BGR]],
    *,
    quiet: tuple[int, ...],
    boxes: Sequence[tuple[int, int, int, int]] = (),
    spare_bottom_left: bool = False,
) -> None:
    """The legend, in the corner of ``image`` where it hides the least: over none of the
    differences' ``boxes`` (x0, y0, x1, y1 pixels) if it can, and over the fewest pixels that
    are not one of the ``quiet`` greys (free floor, unknown), top left when they tie.
    ``spare_bottom_left``: a title is written there. (Session 58's review: always top left, it
    covered a corner of the depot's building, where a difference would have been hidden.)"""
    height = 22 * len(items) + 8
    width = (
        12 + max(cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0] for t, _ in items) + 30
    )
    h, w = image.shape[:2]
    right, bottom = w - width - 8, h - height - 8
    corners = [(8, 8)]
    if right > 8 + width and bottom > 8 + height:  # else the corners overlap: top left only
        corners += [(right, 8), (right, bottom)] + ([] if spare_bottom_left else [(8, bottom)])

    def hidden(corner: tuple[int, int]) -> tuple[int, int]:
        cx, cy = corner
        x0, y0, x1, y1 = cx - 4, cy - 4, cx + width, cy + height
        over = sum(
            bx0 <= x1 and x0 <= bx1 and by0 <= y1 and y0 <= by1 for bx0, by0, bx1, by1 in boxes
        )
        part = image[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1]
        grey = (part[..., 0] == part[..., 1]) & (part[..., 1] == part[..., 2])
        calm = grey & np.isin(part[..., 0], quiet)
        return over, int(np.count_nonzero(~calm))

    x, y = min(corners, key=hidden)  # the first of the least hidden: top left on a tie
    cv2.rectangle(image, (x - 4, y - 4), (x + width, y + height), (255, 255, 255), -1)
    cv2.rectangle(image, (x - 4, y - 4), (x + width, y + height), (90, 90, 90), 1)
    for i, (text, colour) in enumerate(items):
        cy = y + 12 + 22 * i
        cv2.rectangle(image, (x + 2, cy - 7), (x + 20, cy + 7), colour, -1)
        cv2.putText(
            image,
            text,
            (x + 28, cy + 5),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (20, 20, 20),
            1,
            cv2.LINE_AA,
        )


def _boxes(
    image: NDArray[np.uint8], grid: Grid, window: Window, diffs: list[Difference]
) -> list[tuple[int, int, int, int]]:
    """Each difference's numbered box; returns the boxes, (x0, y0, x1, y1) image pixels with
    their labels, for what is drawn after them to keep clear of."""
    drawn = []
    for number, d in enumerate(diffs, start=1):
        colour = ADDED if d.kind == "added" else REMOVED
        lo = window.to_image(grid, np.array([[d.bbox[0], d.bbox[3]]]))[0]
        hi = window.to_image(grid, np.array([[d.bbox[2], d.bbox[1]]]))[0]
        pad = 3
        p0, p1 = (int(lo[0]) - pad, int(lo[1]) - pad), (int(hi[0]) + pad, int(hi[1]) + pad)
        cv2.rectangle(image, p0, p1, colour, 2)
        label = str(number)
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 2)
        tl = (p0[0], max(p0[1] - th - 6, 0))
        drawn.append((min(p0[0], tl[0]), min(p0[1], tl[1]), max(p1[0], tl[0] + tw + 6), p1[1]))
        cv2.rectangle(image, tl, (tl[0] + tw + 6, tl[1] + th + 6), colour, -1)
        cv2.putText(
            image,
            label,
            (tl[0] + 3, tl[1] + th + 2),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.55,
            (255, 255, 255),
            2,
            cv2.LINE_AA,
        )
    return drawn


def with_banner(image: NDArray[np.uint8], text: str) -> NDArray[np.uint8]:
    """``image`` (H, W, 3) BGR with a band across the top saying ``text`` in white on dark red:
    a new (H + band, W, 3) image, its lines broken at "; " where the text is wider than the
    image, and a part still too wide broken between words; the letters shrink only when one
    word is wider than the image (down to a third of their size: a word wider still is cut)."""
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.6
    width = image.shape[1]
    room = width - 16

    def thickness(at_scale: float) -> int:
        return 2 if at_scale >= 0.5 else 1

    def text_px(line: str, at_scale: float) -> int:
        # Measured as drawn: the bold stroke adds width, and Hershey widths do not scale
        # linearly (session 55: a partly trusted banner ran 30 px off an 824 px overlay).
        return int(cv2.getTextSize(line, font, at_scale, thickness(at_scale))[0][0])

    def lines_at(at_scale: float) -> list[str]:
        return _wrapped(text, lambda line: text_px(line, at_scale) <= room)

    lines = lines_at(scale)
    while scale > 0.2 and max(text_px(t, scale) for t in lines) > room:
        # A word wider than a narrow image: smaller letters rather than cut ones, the lines
        # broken again at that size.
        scale = round(scale - 0.05, 2)
        lines = lines_at(scale)
    line_px = round(26 * scale / 0.6)
    band = np.empty((line_px * len(lines) + 10, width, 3), np.uint8)
    band[:] = BANNER
    for i, line in enumerate(lines):
        cv2.putText(
            band,
            line,
            (8, 5 + line_px * (i + 1) - round(7 * scale / 0.6)),
            font,
            scale,
            (255, 255, 255),
            thickness(scale),
            cv2.LINE_AA,
        )
    return np.concatenate([band, image], axis=0)


def _wrapped(text: str, fits: Callable[[str], bool]) -> list[str]:
    """``text`` in lines that each ``fits``: parts joined by "; " while they fit, a part that
    does not fit alone broken between words (a word wider than a line stays whole)."""
    lines: list[str] = []
    for part in text.split("; "):
        if lines and fits(f"{lines[-1]}; {part}"):
            lines[-1] = f"{lines[-1]}; {part}"
            continue
        line = ""
        for word in part.split(" "):
            if line and not fits(f"{line} {word}"):
                lines.append(line)
                line = word
            else:
                line = f"{line} {word}" if line else word
        lines.append(line)
    return lines


def overlay(
    grid: Grid,
    window: Window,
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    roi_polygon: list[tuple[float, float]],
    differences: list[Difference],
    *,
    route_xy: NDArray[np.float64] | None = None,
    title: str = "",
    banner: str | None = None,
    left_out: NDArray[np.bool_] | None = None,
) -> NDArray[np.uint8]:
    """The overlay as a (H, W, 3) BGR image: global map in greys, the local map's walls green,
    the ROI outline, the route, and numbered boxes (ids as in ``result.yaml``).

    ``banner``: a band across the top saying so (an alignment not or only partly trusted).
    ``left_out``: (rows, cols) bool on ``grid``, the local map's cells not compared, hatched.
    """
    local_occ = _mask_scaled(_crop(local_state, window) == OCCUPIED, window)
    image = _painted(_crop(global_state, window), window, (255, 60, 205), [(local_occ, LOCAL)])
    if left_out is not None and left_out.any():
        shade = _mask_scaled(_crop(left_out, window), window)
        h, w = shade.shape
        rows, cols = np.ogrid[:h, :w]
        hatch = shade & ((rows + cols) % 8 < 3)
        image[hatch] = LEFT_OUT
    if roi_polygon:
        pts = window.to_image(grid, np.array(roi_polygon))
        cv2.polylines(image, [pts], True, ROI_COLOUR, 2, cv2.LINE_AA)
    if route_xy is not None and len(route_xy) > 1:
        cv2.polylines(image, [window.to_image(grid, route_xy)], False, ROUTE, 2, cv2.LINE_AA)
    boxes = _boxes(image, grid, window, differences)
    n_added = sum(d.kind == "added" for d in differences)
    items = [
        (f"added obstacle ({n_added})", ADDED),
        (f"removed obstacle ({len(differences) - n_added})", REMOVED),
        ("local map walls", LOCAL),
        ("region of interest", ROI_COLOUR),
    ]
    if route_xy is not None and len(route_xy) > 1:
        items.append(("robot route", ROUTE))
    if left_out is not None and left_out.any():
        items.append(("not compared (alignment not trusted there)", LEFT_OUT))
    _legend(image, items, quiet=(255, 205), boxes=boxes, spare_bottom_left=bool(title))
    if title:
        h = image.shape[0]
        cv2.putText(
            image, title, (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1, cv2.LINE_AA
        )
    return with_banner(image, banner) if banner else image


def diff_image(
    grid: Grid,
    window: Window,
    global_state: NDArray[np.uint8],
    added: NDArray[np.bool_],
    removed: NDArray[np.bool_],
    differences: list[Difference],
    *,
    banner: str | None = None,
) -> NDArray[np.uint8]:
    """The filtered difference mask (added red, removed blue) over faint global walls; with
    ``banner``, the overlay's band across the top too (the two images keep one extent)."""
    image = _painted(
        _crop(global_state, window),
        window,
        (255, 215, 255),
        [
            (_mask_scaled(_crop(added, window), window), ADDED),
            (_mask_scaled(_crop(removed, window), window), REMOVED),
        ],
    )
    boxes = _boxes(image, grid, window, differences)
    _legend(image, [("added", ADDED), ("removed", REMOVED)], quiet=(255,), boxes=boxes)
    return with_banner(image, banner) if banner else image


# Flat colours with a few lines: the "up" filter and run-length coding encode them 3x faster
# than libpng's adaptive filters (the overlay of a 1500 px window: 14 ms instead of 41 ms, and
# 170 KB instead of 120 KB).
_PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    6,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_UP,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]


def encode_png(image: NDArray[np.uint8]) -> bytes:
    ok, data = cv2.imencode(".png", image, _PNG_PARAMS)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return bytes(data.tobytes())
