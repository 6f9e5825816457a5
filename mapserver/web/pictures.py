"""Pictures for the map pages: a stored map with its tracked changes outlined by state, and what
one version changed (before and after, side by side). Pure functions of arrays to PNG bytes."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import Lattice
from mapserver.maps import FREE, OCCUPIED
from mapserver.render import encode_png

BGR = tuple[int, int, int]
# The colours of a change's outline, by state (also the legend on the page).
STATE_COLOURS: dict[str, BGR] = {
    "pending": (0, 165, 255),  # orange
    "confirmed": (200, 0, 200),  # magenta: waits for a person
    "published": (40, 160, 40),  # green: in the map
    "rejected": (90, 90, 90),
    "expired": (170, 170, 170),
}
ADDED: BGR = (0, 0, 230)
REMOVED: BGR = (230, 60, 0)


def _greys(state: NDArray[np.uint8]) -> NDArray[np.uint8]:
    out = np.full(state.shape, 200, np.uint8)
    out[state == FREE] = 255
    out[state == OCCUPIED] = 40
    return out


def _shrunk(state: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """Every ``factor`` x ``factor`` block as one pixel: occupied wins (thin walls stay), then
    free, then unknown."""
    if factor <= 1:
        return state
    h, w = state.shape
    hh, ww = math.ceil(h / factor), math.ceil(w / factor)
    padded = np.full((hh * factor, ww * factor), 255, np.uint8)
    padded[:h, :w] = state
    blocks = padded.reshape(hh, factor, ww, factor)
    out = np.full((hh, ww), 255, np.uint8)
    out[(blocks == FREE).any(axis=(1, 3))] = FREE
    out[(blocks == OCCUPIED).any(axis=(1, 3))] = OCCUPIED
    return out


def map_with_changes(
    state: NDArray[np.uint8],
    lattice: Lattice,
    changes: Sequence[tuple[int, str, list[list[float]]]],
    *,
    max_side_px: int = 1600,
) -> bytes:
    """The map (free white, occupied dark, unknown grey), scaled down to at most
    ``max_side_px``, with each change's outline in its state's colour and its id."""
    factor = max(1, math.ceil(max(state.shape) / max_side_px))
    image = cv2.cvtColor(_greys(_shrunk(state, factor)), cv2.COLOR_GRAY2BGR)
    upscale = max(1, min(4, max_side_px // max(image.shape)))
    if upscale > 1:
        image = cv2.resize(image, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_NEAREST)
    px_per_cell = upscale / factor
    for cid, change_state, polygon in changes:
        if len(polygon) < 2:
            continue
        xy = np.array(polygon, float)
        cols = (xy[:, 0] - lattice.x0) / lattice.resolution * px_per_cell
        rows = (lattice.height - (xy[:, 1] - lattice.y0) / lattice.resolution) * px_per_cell
        pts = np.round(np.stack([cols, rows], 1)).astype(np.int32)
        colour = STATE_COLOURS.get(change_state, (0, 0, 0))
        cv2.polylines(image, [pts], True, colour, 2, cv2.LINE_AA)
        x, y = pts.min(axis=0)
        cv2.putText(
            image,
            str(cid),
            (int(x), max(10, int(y) - 3)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            colour,
            1,
            cv2.LINE_AA,
        )
    return encode_png(np.asarray(image, np.uint8))


def version_change(
    before: NDArray[np.uint8],
    after: NDArray[np.uint8],
    *,
    margin_px: int = 40,
    max_side_px: int = 700,
    labels: tuple[str, str] = ("before", "after"),
) -> bytes | None:
    """Before and after of what a version changed, side by side, cropped around the changed
    cells (added red, removed blue on the right); None when nothing changed."""
    changed = before != after
    if not changed.any():
        return None
    rows, cols = np.nonzero(changed)
    r0, r1 = max(0, rows.min() - margin_px), min(before.shape[0], rows.max() + margin_px + 1)
    c0, c1 = max(0, cols.min() - margin_px), min(before.shape[1], cols.max() + margin_px + 1)
    left = cv2.cvtColor(_greys(before[r0:r1, c0:c1]), cv2.COLOR_GRAY2BGR)
    right = cv2.cvtColor(_greys(after[r0:r1, c0:c1]), cv2.COLOR_GRAY2BGR)
    crop_b, crop_a = before[r0:r1, c0:c1], after[r0:r1, c0:c1]
    right[(crop_a == OCCUPIED) & (crop_b != OCCUPIED)] = ADDED
    right[(crop_b == OCCUPIED) & (crop_a != OCCUPIED)] = REMOVED
    scale = max(1, min(8, max_side_px // max(left.shape[:2])))
    if scale > 1:
        left = cv2.resize(left, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        right = cv2.resize(right, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    gap = np.full((left.shape[0], 12, 3), 255, np.uint8)
    body = np.concatenate([left, gap, right], axis=1)
    head = np.full((28, body.shape[1], 3), 255, np.uint8)
    for text, x in ((labels[0], 4), (labels[1], left.shape[1] + 16)):
        cv2.putText(
            head, text, (x, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (30, 30, 30), 1, cv2.LINE_AA
        )
    return encode_png(np.asarray(np.concatenate([head, body], axis=0), np.uint8))
