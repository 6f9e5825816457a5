"""Pure functions: added and removed obstacles between the aligned maps, and noise filtering.

Everything here works on arrays on one work grid (``[row, col]``, nav2 frame). The rules are
trinary-aware: added = occupied in the local map where the global map is free; removed = free in
the local map where the global map is occupied; unknown on either side is never a difference.
A wall seen within ``tolerance_m`` of where the other map has one is misalignment, not change.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.maps import FREE, OCCUPIED

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class DiffMasks:
    """(H, W) bool masks on the work grid: cells that became obstacles, and cells that stopped
    being obstacles."""

    added: BoolArray
    removed: BoolArray


def distance_to(mask: BoolArray) -> NDArray[np.float32]:
    """Distance in pixels from every cell to the nearest True cell of ``mask`` (large if none)."""
    if not mask.any():
        return np.full(mask.shape, 1e6, np.float32)
    return cv2.distanceTransform(np.where(mask, 0, 255).astype(np.uint8), cv2.DIST_L2, 5)


def raw_differences(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    roi: BoolArray,
    *,
    resolution: float,
    tolerance_m: float,
    removed_tolerance_m: float | None = None,
    global_walls: BoolArray | None = None,
) -> DiffMasks:
    """Cells that differ between the maps, before noise filtering.

    Parameters
    ----------
    global_state, local_state
        (H, W) uint8 cell states (FREE / OCCUPIED / UNKNOWN) on the same grid.
    roi
        (H, W) bool: where to compare.
    resolution
        Metres per pixel of the grid.
    tolerance_m
        A cell within this distance of a wall in the other map is not a difference.
    removed_tolerance_m
        The same for removed cells (default ``tolerance_m``). Worth setting wider: a wall seen
        at a grazing angle gets few hits, and rays skimming its face mark a sliver of it free.
    global_walls
        Optional (H, W) bool: walls of the global map beyond its occupied cells (grey lines);
        a local wall on them is not new.
    """
    if global_state.shape != local_state.shape or roi.shape != global_state.shape:
        raise ValueError(
            f"arrays must share one shape, got {global_state.shape}, {local_state.shape}, "
            f"{roi.shape}"
        )
    tol_px = tolerance_m / resolution
    g_occ = global_state == OCCUPIED
    l_occ = local_state == OCCUPIED
    g_walls = g_occ if global_walls is None else (g_occ | global_walls)
    added = l_occ & (global_state == FREE) & roi
    if added.any():
        added &= distance_to(g_walls) > tol_px
    removed = g_occ & (local_state == FREE) & roi
    if removed.any():
        removed_tol_px = (
            tolerance_m if removed_tolerance_m is None else removed_tolerance_m
        ) / resolution
        removed &= distance_to(l_occ) > removed_tol_px
    return DiffMasks(added, removed)


def drop_small(mask: BoolArray, *, min_pixels: int) -> BoolArray:
    """``mask`` without its 8-connected components smaller than ``min_pixels``."""
    if not mask.any():
        return mask.copy()
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
    keep[0] = False
    return keep[labels]


def filter_noise(masks: DiffMasks, *, min_pixels: int) -> DiffMasks:
    """Remove specks: components smaller than ``min_pixels`` (a few local cells of scan noise).

    No morphological opening: a new obstacle seen from one side is a line one cell thick.
    """
    return DiffMasks(
        drop_small(masks.added, min_pixels=min_pixels),
        drop_small(masks.removed, min_pixels=min_pixels),
    )


__all__ = [
    "FREE",
    "DiffMasks",
    "distance_to",
    "drop_small",
    "filter_noise",
    "raw_differences",
]
