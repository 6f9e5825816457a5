"""Pure functions: added and removed obstacles between the aligned maps, and noise filtering.

Everything here works on arrays on one work grid (``[row, col]``, nav2 frame). The rules are
trinary-aware: added = occupied in the local map where the global map is free; removed = free in
the local map where the global map is occupied; unknown on either side is never a difference.
A wall seen within ``tolerance_m`` of where the other map has one is misalignment, not change.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.grid import (
    Grid,
    RouteDistance,
    any_along,
    box_around,
    box_of_cells,
    by_label,
    extent_along,
    grown,
    main_axis,
    nonzero_cells,
    square_to,
)
from mapserver.maps import FREE, OCCUPIED, UNKNOWN

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class DiffMasks:
    """(H, W) bool masks on the work grid: cells that became obstacles, and cells that stopped
    being obstacles."""

    added: BoolArray
    removed: BoolArray
    beside_walls: BoolArray | None = None
    """The cells of ``removed`` on small structures seen gone beside a wall, which the removed
    tolerance hid (:func:`small_structures_beside_walls`): each reported whole."""


def distance_to(mask: BoolArray) -> NDArray[np.float32]:
    """Distance in pixels from every cell to the nearest True cell of ``mask`` (large if none)."""
    if not mask.any():
        return np.full(mask.shape, 1e6, np.float32)
    return np.asarray(cv2.distanceTransform((~mask).view(np.uint8), cv2.DIST_L2, 5), np.float32)


@lru_cache(maxsize=32)
def offset_distances(reach_px: float) -> NDArray[np.float32]:
    """The distances :func:`distance_to` measures from one cell to the cells around it.

    Returns a read-only (2k+1, 2k+1) float32 array, ``k = ceil(reach_px) + 1``, indexed
    [row, col] with the cell itself at the centre. Every offset whose distance is at most
    ``reach_px`` lies inside (the 5x5 chamfer distance is never below the Chebyshev distance).

    ``distance_to`` is a 5x5 chamfer distance: the shortest path of fixed steps, the same
    whatever the position, so ``distance_to(mask)[p]`` is the smallest of these values over the
    offsets from ``p`` to the True cells of ``mask``. A threshold on it is therefore a dilation
    (see :func:`near`), exactly, at a fraction of the cost of the transform.
    """
    k = math.ceil(reach_px) + 1
    single = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    single[k, k] = 0
    out = np.asarray(cv2.distanceTransform(single, cv2.DIST_L2, 5), np.float32)
    out.flags.writeable = False
    return out


def near(mask: BoolArray, offsets: BoolArray) -> BoolArray:
    """Cells that have a True cell of ``mask`` at one of ``offsets`` from them.

    ``offsets`` is a centred, symmetric boolean kernel, for instance ``~(offset_distances(t) >
    t)``: then ``~near(mask, offsets)`` equals ``distance_to(mask) > t`` cell for cell (for any
    elementwise test written the same way on both). Returns a new (H, W) bool array.
    """
    grown = cv2.dilate(
        mask.astype(np.uint8),
        offsets.astype(np.uint8),
        borderType=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return grown > 0


def within(mask: BoolArray, reach_px: float) -> BoolArray:
    """Cells within ``reach_px`` of a True cell of ``mask``: :func:`near` by the offsets of
    :func:`offset_distances` up to ``reach_px`` (``distance_to(mask) <= reach_px`` cell for
    cell, by a dilation). Returns a new (H, W) bool array."""
    return near(mask, ~(offset_distances(reach_px) > reach_px))


def near_at(
    mask: BoolArray, offsets: BoolArray, grid: Grid, points_xy: NDArray[np.float64]
) -> BoolArray:
    """``grid.sample(near(mask, offsets), points_xy, False)``: for each world point of
    ``points_xy`` (N, 2), whether its cell of ``grid`` (``mask``'s) has a True cell of
    ``mask`` at one of ``offsets`` from it, False off the grid; worked out over the box around
    the points only, not a pass over the whole mask (a check that asks at a few places of a
    map hundreds of metres across)."""
    return near_at_box(lambda box: mask[box], offsets, grid, points_xy)


def near_at_box(
    mask_in: Callable[[tuple[slice, slice]], BoolArray],
    offsets: BoolArray,
    grid: Grid,
    points_xy: NDArray[np.float64],
    *,
    pad: int = 0,
) -> BoolArray:
    """:func:`near_at` of a mask made only over the box it needs: ``mask_in(box)`` returns the
    mask on ``box`` of ``grid``, the box around the points with the offsets' reach and ``pad``
    cells more (room for a mask that looks at a cell's neighbours)."""
    px = np.rint(grid.to_pixel(points_xy)).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < grid.width)
    inside &= (px[:, 1] >= 0) & (px[:, 1] < grid.height)
    out = np.zeros(len(px), bool)
    if not inside.any():
        return out
    cols, rows = px[inside, 0], px[inside, 1]
    box = box_of_cells(rows, cols, offsets.shape[0] // 2 + pad, (grid.height, grid.width))
    part = near(mask_in(box), offsets)
    out[inside] = part[rows - box[0].start, cols - box[1].start]
    return out


def raw_differences(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    roi: BoolArray,
    *,
    resolution: float,
    tolerance_m: float,
    removed_tolerance_m: float | None = None,
    global_walls: BoolArray | None = None,
    unknown_is_wall: bool = True,
    extra_tolerance_m: NDArray[np.float32] | None = None,
    end_tolerance_m: float | None = None,
    speck_m2: float = 0.0,
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
    unknown_is_wall
        A local wall within ``tolerance_m`` of the global map's unknown area is the edge of
        what the global map knows (its wall not drawn, or the robot saw it from another side),
        not a new obstacle.
    extra_tolerance_m
        Optional (H, W) float32 metres added to both tolerances, cell by cell, where the maps
        are known to fit less well (see :func:`misfit_tolerance`).
    end_tolerance_m
        Optional, smaller than the removed tolerance: the tolerance for removed cells past the
        end of a local wall, in line with the global wall (a gap in a wall), where the walls
        fit (no extra tolerance). The removed tolerance is for a wall seen off to one side.
    speck_m2
        With ``unknown_is_wall``: an unknown patch of the global map no larger than this, in
        the open (:func:`unknown_specks`), hides local walls within ``tolerance_m`` only, not
        within the extra tolerance: a speck is an object's size or nothing, not the edge of a
        map's knowledge that a drifted wall may be seen beyond. 0: every unknown patch alike.
    """
    if global_state.shape != local_state.shape or roi.shape != global_state.shape:
        raise ValueError(
            f"arrays must share one shape, got {global_state.shape}, {local_state.shape}, "
            f"{roi.shape}"
        )
    removed_tol_m = tolerance_m if removed_tolerance_m is None else removed_tolerance_m
    tol_px, removed_tol_px = tolerance_m / resolution, removed_tol_m / resolution
    # Only the ROI's bounding box can differ, and only walls within the tolerances of it count
    # (the widest, with the misfit's extra): work on that box plus their reach (the same cells,
    # less area).
    extra_m = float(extra_tolerance_m.max()) if extra_tolerance_m is not None else 0.0
    reach = offset_distances(max(tol_px, removed_tol_px) + extra_m / resolution).shape[0] // 2
    box = box_around(roi, reach)
    if box is None:
        return DiffMasks(np.zeros(roi.shape, bool), np.zeros(roi.shape, bool))
    shape = roi.shape
    g_state, l_state, roi = global_state[box], local_state[box], roi[box]
    g_occ = g_state == OCCUPIED
    l_occ = l_state == OCCUPIED
    g_unknown = g_state == UNKNOWN
    g_drawn = g_occ if global_walls is None else (g_occ | global_walls[box])
    g_walls = g_drawn | g_unknown if unknown_is_wall else g_drawn
    # ``distance_to(walls) > tol`` as a dilation by the offsets that are not beyond tol (same
    # cells, a fraction of the cost).
    added = l_occ & (g_state == FREE) & roi
    if added.any() and g_walls.any():
        added &= ~within(g_walls, tol_px)
        if extra_tolerance_m is not None and added.any():
            # The walls the misfit's extra tolerance reaches from: all but the unknown specks
            # (a speck drawn as a grey wall is a wall).
            far_walls = g_walls
            if unknown_is_wall and speck_m2 > 0:
                max_cells = max(1, math.floor(speck_m2 / resolution**2))
                far_walls = g_drawn | (g_unknown & ~unknown_specks(g_unknown, max_cells))
            _keep_far(added, far_walls, tolerance_m + extra_tolerance_m[box], resolution)
            del far_walls
    # The removed cells need none of the added ones' masks: each is a box-sized bool array, and
    # this function's temporaries are the pipeline's peak of memory (benchmarks/bench_speed.py).
    del g_unknown, g_drawn, g_walls
    removed = g_occ & (l_state == FREE) & roi
    if removed.any() and l_occ.any():
        seen = removed.copy()
        # The removed tolerance is for a local wall that stands for a drawn one, seen off by
        # misalignment: within the tolerance of the drawn structure's face. A local wall deeper
        # inside the drawn structure than that is a new face (a notch cut into a block), and
        # the cells between it and the open space are what was cut away.
        faces = l_occ & _near_face(g_occ, removed_tol_m, extra_tolerance_m, box, resolution)
        removed &= ~within(faces, removed_tol_px)
        if extra_tolerance_m is not None:
            _keep_far(removed, faces, removed_tol_m + extra_tolerance_m[box], resolution)
        del faces
        # The removed tolerance is for a wall seen off to one side of where it was drawn. Past
        # the end of a local wall, in line with it (a gap in a wall), a smaller one will do.
        end_px = (removed_tol_m if end_tolerance_m is None else end_tolerance_m) / resolution
        ends = seen & ~removed & ~within(l_occ, end_px)
        del seen
        if extra_tolerance_m is not None:  # only where the walls fit: no drift left there
            ends &= extra_tolerance_m[box] == 0
        if ends.any():
            reach_px = math.ceil(removed_tol_px + extra_m / resolution) + 2
            # A wall's end: a wall seen over at least 0.3 m.
            run = max(2, round(0.3 / resolution))
            removed |= _past_wall_ends(ends, l_occ, g_occ, pad=reach_px, min_run=run)
    added_full = np.zeros(shape, bool)
    added_full[box] = added
    del added
    removed_full = np.zeros(shape, bool)
    removed_full[box] = removed
    return DiffMasks(added_full, removed_full)


def unknown_specks(unknown: BoolArray, max_cells: int) -> BoolArray:
    """The patches of ``unknown`` (8-connected) of at most ``max_cells`` cells that do not touch
    the array's edge (a patch cut by it may be larger): specks the mapping rays missed in the
    open, or a pole they hit now and then. (H, W) bool."""
    labels, stats, clear = _components_clear_of_edge(unknown)
    return np.asarray((clear & (stats[:, cv2.CC_STAT_AREA] <= max_cells))[labels])


def _near_face(
    g_occ: BoolArray,
    tolerance_m: float,
    extra_tolerance_m: NDArray[np.float32] | None,
    box: tuple[slice, slice],
    resolution: float,
) -> BoolArray:
    """Cells within ``tolerance_m`` of a cell the global map does not draw occupied (outside its
    structures or along their faces), or of the edge of ``box`` (what lies past it is not
    looked at: taken as open), and every cell within the widest tolerance of a cell where the
    misfit adds to it. (H, W) bool on ``box``; ``g_occ`` is the global map's occupied cells
    there."""
    # Deep: every cell within the tolerance (a square: cheap, and never deeper than the disc
    # says) drawn occupied.
    k = math.ceil(tolerance_m / resolution)
    square = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    deep = cv2.erode(g_occ.view(np.uint8), square, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    face = deep == 0
    if extra_tolerance_m is not None:
        # Where the walls do not fit (drift left over), any wall may be one seen displaced: as
        # far from such a cell as its tolerance reaches.
        extra = extra_tolerance_m[box]
        loose = extra > 0
        if loose.any():
            reach = k + math.ceil(float(extra.max()) / resolution)
            grow = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach + 1, 2 * reach + 1))
            face |= cv2.dilate(loose.view(np.uint8), grow) > 0
    return np.asarray(face)


def _past_wall_ends(
    cells: BoolArray, local_walls: BoolArray, global_walls: BoolArray, *, pad: int, min_run: int
) -> BoolArray:
    """The True cells of ``cells`` (inside global walls) whose nearest local wall lies along
    the global wall from them, not across it: the direction to it is within 45 degrees of the
    wall's own direction (across it, the wall's normal, points to the nearest cell outside the
    global wall). A local wall across from a cell is the wall seen displaced; one along it is
    the end of what still stands. ``pad``: how far (pixels) the nearest local wall may be."""
    out = np.zeros(cells.shape, bool)
    for window, labels in _component_windows(cells, pad):
        rows, cols = nonzero_cells(labels > 0)
        along = _along_in(rows, cols, local_walls[window], global_walls[window], min_run)
        out[window][rows[along], cols[along]] = True
    return out


# More components than this are looked at in one window around them all.
_MAX_WINDOWS = 64


def _component_windows(
    mask: BoolArray, pad: int
) -> Iterator[tuple[tuple[slice, slice], NDArray[np.int32]]]:
    """Each 8-connected component of ``mask`` in a window of ``pad`` cells around it (clipped
    to the grid): the window, and there the component's label (> 0; 0 elsewhere, other
    components included). They are few and far apart on a large map; when there are more
    than ``_MAX_WINDOWS``, one window around them all, with all their labels."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    if w == 0:
        return
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        np.ascontiguousarray(mask[y : y + h, x : x + w]).view(np.uint8)
    )
    padded = np.pad(labels, pad)  # a window's labels, whatever its place on the grid
    groups = (
        [(0, 0, w, h, 0)] if n - 1 > _MAX_WINDOWS else [(*stats[k, :4], k) for k in range(1, n)]
    )
    for wx, wy, ww, wh, k in groups:
        r0, c0 = max(y + int(wy) - pad, 0), max(x + int(wx) - pad, 0)
        r1 = min(y + int(wy) + int(wh) + pad, mask.shape[0])
        c1 = min(x + int(wx) + int(ww) + pad, mask.shape[1])
        window = np.asarray(padded[r0 - y + pad : r1 - y + pad, c0 - x + pad : c1 - x + pad])
        if k:  # this component alone
            window = np.where(window == k, window, 0)
        yield (slice(r0, r1), slice(c0, c1)), window.astype(np.int32)


def _along_in(
    rr: NDArray[np.intp],
    cc: NDArray[np.intp],
    local_walls: BoolArray,
    global_walls: BoolArray,
    min_run: int,
) -> NDArray[np.bool_]:
    """:func:`_past_wall_ends` for the cells (rr, cc) of one window."""
    vectors = []
    for source in (~local_walls, global_walls):
        src = np.ascontiguousarray(source).view(np.uint8)
        if src.all():  # nothing to measure to inside the window
            return np.zeros(len(rr), bool)
        _, nearest = cv2.distanceTransformWithLabels(
            src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        zr, zc = np.nonzero(src == 0)  # label k is the k-th zero cell in raster order
        k = nearest[rr, cc] - 1
        vectors.append((zr[k] - rr, zc[k] - cc))
    (vr, vc), (nr, nc) = vectors
    dot = np.abs(vr * nr + vc * nc).astype(np.float64)
    norm = np.hypot(vr, vc) * np.hypot(nr, nc)
    along = dot < np.cos(np.pi / 4) * np.maximum(norm, 1e-9)
    # A wall's end, not a speck: the nearest local wall cell is part of a wall seen over at
    # least ``min_run`` cells (sparse hits on a wall seen at range are no end of anything).
    _, parts, stats, _ = cv2.connectedComponentsWithStats(
        np.ascontiguousarray(local_walls).view(np.uint8)
    )
    part = parts[rr + vr, cc + vc]
    return np.asarray(along & (stats[part, cv2.CC_STAT_AREA] >= min_run))


def _keep_far(
    cells: BoolArray, walls: BoolArray, limit_m: NDArray[np.float32], resolution: float
) -> None:
    """Clear the True cells of ``cells`` that have a True cell of ``walls`` within their
    ``limit_m``: in place, exactly as ``cells &= distance_to(walls) * resolution > limit_m``.

    Few cells are left by the time this runs (the fixed tolerance has removed most), so each
    is checked against the offsets within reach (see :func:`offset_distances`) instead of a
    distance transform of the whole box; many cells get the transform.
    """
    rows, cols = nonzero_cells(cells)
    if len(rows) == 0:
        return
    limit = limit_m[rows, cols]
    offsets = offset_distances(float(limit.max()) / resolution)
    k = offsets.shape[0] // 2
    reach_m = offsets * resolution  # float32, as distance_to(walls) * resolution is
    within = np.argwhere(~(reach_m > limit.max()))
    if len(rows) * len(within) > walls.size // 4:
        cells[rows, cols] = distance_to(walls)[rows, cols] * resolution > limit
        return
    padded = np.pad(walls, k)
    far = np.ones(len(rows), bool)
    for dr, dc in within:
        hit = padded[rows + dr, cols + dc]  # the wall at offset (dr - k, dc - k)
        far &= ~(hit & ~(reach_m[dr, dc] > limit))
    cells[rows, cols] = far


def misfit_tolerance(
    local_state: NDArray[np.uint8],
    global_walls: BoolArray,
    *,
    resolution: float,
    base_m: float,
    max_m: float,
    tile_m: float,
    quantile: float = 0.8,
    min_walls: int = 30,
    tile_offset_px: tuple[int, int] = (0, 0),
) -> NDArray[np.float32]:
    """Per-cell extra tolerance: how far local walls sit from global walls nearby.

    Where the alignment (with its drift correction) lays the local walls onto the global ones,
    the tolerance stays ``base_m`` (extra 0); where they still sit off (drift that could not be
    taken out, a wall seen doubled on a revisit), it grows to the ``quantile`` of the local
    walls' distance to their global counterpart, plus ``base_m`` / 2 of margin, up to ``max_m``.
    Measured over the walls in each tile of ``tile_m`` and its eight neighbours; tile edges lie
    where ``row + tile_offset_px[0]`` (and ``col + tile_offset_px[1]``) is a multiple of the tile
    size, so a lattice fixed in the map frame gives the same tiles on any crop. Returns the
    growth over ``base_m``: (H, W) float32 metres, 0 where the fit is good.
    """
    tol = np.zeros(local_state.shape, np.float32)
    local_walls = local_state == OCCUPIED
    # Distances on the box around the local walls, with room for the reach.
    box = box_around(local_walls, math.ceil(max_m / resolution) + 1)
    if box is None or not global_walls.any():
        return tol
    dist_m = distance_to(global_walls[box]) * resolution
    # Local walls with a global counterpart within reach: new obstacles far from any wall do
    # not count as misfit.
    counted = local_walls[box] & (dist_m <= max_m)
    rows, cols = nonzero_cells(counted)
    if len(rows) < min_walls:
        return tol
    dist_m_at = dist_m[rows, cols]
    rows, cols = rows + box[0].start, cols + box[1].start
    tile = max(1, round(tile_m / resolution))
    # Tiles on the lattice given by tile_offset_px, and a ring of empty ones around the walls'
    # (they borrow from their neighbours).
    ti = (rows + tile_offset_px[0]) // tile
    tj = (cols + tile_offset_px[1]) // tile
    i_lo, j_lo = int(ti.min()) - 1, int(tj.min()) - 1
    ti, tj = ti - i_lo, tj - j_lo
    n_i, n_j = int(ti.max()) + 2, int(tj.max()) + 2
    # Per tile, how many walls sit at each distance (a chamfer distance takes few distinct
    # values), summed over its 3 x 3 neighbourhood: order statistics without sorting per tile.
    levels, level_of = np.unique(dist_m_at, return_inverse=True)
    counts = np.zeros((n_i + 2, n_j + 2, len(levels)), np.int32)
    np.add.at(counts, (ti + 1, tj + 1, level_of.ravel()), 1)
    around = np.zeros((n_i, n_j, len(levels)), np.int32)
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            around += counts[di : di + n_i, dj : dj + n_j]
    n_around = around.sum(axis=2)
    ii, jj = np.nonzero(n_around >= min_walls)
    if len(ii) == 0:
        return tol
    cum = np.cumsum(around[ii, jj], axis=1)
    q = _linear_quantiles(levels, cum, n_around[ii, jj], quantile) + base_m / 2
    grown = np.zeros((n_i, n_j))
    grown[ii, jj] = np.minimum(np.maximum(q, base_m), max_m) - base_m
    # Paint the tiles: tile (i, j) covers rows from (i + i_lo) * tile - tile_offset_px[0].
    r_first = i_lo * tile - tile_offset_px[0]
    c_first = j_lo * tile - tile_offset_px[1]
    painted = np.repeat(np.repeat(grown.astype(np.float32), tile, axis=0), tile, axis=1)
    h, w = local_state.shape
    r0, c0 = max(r_first, 0), max(c_first, 0)
    r1, c1 = min(r_first + n_i * tile, h), min(c_first + n_j * tile, w)
    if r1 > r0 and c1 > c0:
        tol[r0:r1, c0:c1] = painted[r0 - r_first : r1 - r_first, c0 - c_first : c1 - c_first]
    return tol


def _linear_quantiles(
    levels: NDArray[np.floating], cum: NDArray[np.integer], n: NDArray[np.integer], q: float
) -> NDArray[np.float64]:
    """Per row of ``cum`` (K, L), the cumulative counts of a sample over the sorted distinct
    ``levels`` (L,) with ``n`` (K,) values in all: ``np.quantile(sample, q)`` (the default,
    linear method), from its two order statistics and numpy's own interpolation steps, in the
    levels' precision (the same value, bit for bit)."""
    index = (n - 1) * q
    lo = np.floor(index).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    # The k-th smallest value (0-based) is the first level whose cumulative count exceeds k.
    a = levels[np.argmax(cum > lo[:, None], axis=1)]
    b = levels[np.argmax(cum > hi[:, None], axis=1)]
    gamma = (index - lo).astype(levels.dtype)
    span = b - a
    one = levels.dtype.type(1)
    out = np.where(gamma >= 0.5, b - span * (one - gamma), a + span * gamma)
    return np.asarray(out, np.float64)


def removal_evidence(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    removed: BoolArray,
    *,
    resolution: float,
    depth_m: float,
    see_through_m: float,
    both_sides_m: float = 0.0,
    route: RouteDistance | None = None,
    depth_per_m: float = 0.0,
    ray_m: float = 0.0,
    across_per_m: float = 0.0,
) -> BoolArray:
    """Removed cells that show a structure is really gone, not a face eroded by grazing rays.

    A cell counts when it lies at least ``depth_m`` inside the global structure (rays crossed
    the structure's interior), or when the robot saw open space on both sides of it within
    ``see_through_m`` along a row, a column or a diagonal (it looked through where the
    structure was). A strip along a wall's face has open space on one side only and no depth:
    rays skimming a wall seen end-on or from far away erode its face in the local map.

    Open space on a side counts beyond the structure's fringe only (the cells next to it are
    its ragged face, holes a grazing ray erodes with it). A face cell also counts when a cell
    seen free well inside the structure lies in line behind it, open space before it
    (``_FACE_ANCHOR_DEPTH``): the rays that saw the inside crossed the face.

    With ``both_sides_m`` > 0, a cell also counts when open space lies on both sides of it
    within that distance along a line that crosses only the structure's cells the robot did not
    see occupied: it saw the structure from both sides, free on each, and nowhere a wall in it (a
    piece of a thick wall seen from the corridors on either side, its middle unseen). On each
    side the line must enter the structure through cells seen free past the face's own row
    (which grazing rays erode): two faces of a block standing, grazed and eroded, one of them a
    row deep only, with its middle unseen, are not a structure seen through (session 36). A
    face seen from one side only has no open space behind it.

    Open space on both sides does not count within ``depth_m`` of a structure's inside deeper
    than ``depth_m`` that the robot never saw: along a ragged face, not through the structure.

    The depth asked of a cell (by the depth rule and of the face rule's anchors) grows with
    the length of the rays that may have drawn it: a ray's drawn position is off across it by
    its length times the angle error of the scan that cast it (``depth_per_m``), and rays
    grazing a face from 20-30 m away draw free cells that many decimetres inside it. With
    ``route``, to ``depth_per_m`` times the cell's distance from the route where that is more;
    that distance understates the length of the rays that skim a face, which come along it from
    as far as the sensor reaches, so with ``ray_m`` (the longest rays' length), with or without
    a route, the depth asked is everywhere at least ``depth_per_m`` times :data:`_SKIM_SHARE`
    of it.

    Open space beyond the structure in a part the global map never saw (unknown there: the
    inside of a block drawn as its outline, a room behind a wall) counts only deeper into it
    than ``depth_m`` and than ``depth_per_m`` times ``ray_m``, the longest rays' length (how far
    from its route the robot saw anything): rays grazing the face from that far draw free cells
    that deep behind it, and a wall that is gone opens the view well beyond. Where the global
    map knew the space free, the robot saw it again through where the structure stood.

    Seen through, with ``across_per_m`` > 0 and a ``route`` that knows its nearest points: a
    ray drawn from r metres away may lie ``across_per_m`` times r to one side of where it
    went (the angle error of its scan), so a ray that passed beside a structure may be drawn
    across it. The cell must lie that far inside the structure across the direction to the
    route's nearest point (the shortest rays that saw it; r its distance from the route),
    counted to the edge of its outermost cell plus one cell of slack (:func:`_across_m`). A
    thin wall the robot looked along from far off, its rays drawn on both sides of it and
    through it, is only its own thickness across them; one the robot looked across is as
    long as the wall across them.

    Either way, a cell counts only when the robot could have seen it: connected to open space
    through cells seen free, not across a wall seen standing (a solid block whose faces are
    seen all round, its inside free only in a part of a drifted map laid over it).

    Returns a new (H, W) bool array, True only on cells of ``removed``.
    """
    evidence = np.zeros(removed.shape, bool)
    reach = max(1, round(see_through_m / resolution))
    across = round(both_sides_m / resolution)
    behind_m = max(depth_m, depth_per_m * ray_m)
    longer = reach + math.ceil(behind_m / resolution)
    box = box_around(removed, max(longer, across, math.ceil(depth_m / resolution) + 2))
    if box is None:
        return evidence
    g_occ = global_state[box] == OCCUPIED
    cand = removed[box]
    depth = cv2.distanceTransform(g_occ.astype(np.uint8), cv2.DIST_L2, 5) * resolution
    need: float | NDArray[np.float32] = max(depth_m, depth_per_m * _SKIM_SHARE * ray_m)
    if route is not None and depth_per_m > 0:
        need = np.maximum(np.float32(need), np.float32(depth_per_m) * route.of_box(box))
    found = cand & (depth >= need)
    open_space = ((local_state[box] == FREE) & ~g_occ).astype(np.uint8)
    # Seen through: open space on either side beyond the structure's fringe. The cells next to
    # it are its ragged face (holes between the global map's hits, free or unknown), which
    # grazing rays erode with the face itself: free there and unknown beyond is a face, not a
    # structure looked through.
    fringe = cv2.dilate(g_occ.view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    far_space = np.where(fringe, 0, open_space).astype(np.uint8)
    # Behind it, in a part the global map never saw: only deeper than grazing rays draw, and
    # looked for within `reach` beyond that depth.
    g_unknown = global_state[box] == UNKNOWN
    far_unseen: NDArray[np.uint8] | None = None
    if (far_space.view(bool) & g_unknown).any():  # the depth only where there is space to ask
        deep = far_space & _deep_inside(global_state, UNKNOWN, box, behind_m / resolution)
        far_unseen = deep if deep.any() else None
    far_space[g_unknown] = 0
    # Cells seen free well inside a structure too thick to see through: the rays that reached
    # them crossed its face in front of them (_FACE_ANCHOR_DEPTH).
    anchors = cand & (depth >= _FACE_ANCHOR_DEPTH * need)
    seen_free = local_state[box] == FREE
    # The face cells it can reach lie within `reach` of an anchor: its work in that window.
    near = box_around(anchors, reach)
    # Seen through only deep enough inside the structure across the rays that saw it.
    through = cand
    if route is not None and route.nearest is not None and across_per_m > 0:
        # Asked only where it asks more than any cell has (_ACROSS_SLACK_STEPS along a grid
        # line): beyond 14 m from the route for 0.05 m cells.
        far_m = _ACROSS_SLACK_STEPS * resolution / across_per_m
        rows, cols = np.nonzero(cand & route.beyond(box, far_m))
        if len(rows):
            at = (rows + box[0].start, cols + box[1].start)
            toward = route.toward(*at)
            assert toward is not None
            need_m = np.float32(across_per_m) * route.at(*at)
            inside = _inside_across_rays(g_occ, rows, cols, toward, need_m, resolution)
            through = cand.copy()
            through[rows[~inside], cols[~inside]] = False
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        # Open space within `reach` before, and after, the cell.
        seen_before = _seen_in_line(far_space, far_unseen, (dr, dc), reach, longer)
        seen_after = _seen_in_line(far_space, far_unseen, (-dr, -dc), reach, longer)
        found |= through & seen_before & seen_after
        # A face cell with open space on one side and, in line on the other, a cell seen
        # free deep inside with only cells seen free between (no wall seen standing): on the
        # path of the rays that saw that cell.
        if near is not None:
            deep_after, _ = _reached(anchors[near], seen_free[near], None, (-dr, -dc), reach)
            deep_before, _ = _reached(anchors[near], seen_free[near], None, (dr, dc), reach)
            found[near] |= cand[near] & (
                (seen_before[near] & deep_after) | (deep_before & seen_after[near])
            )
    # Seen through along a line, but beside a structure too thick to see through whose inside
    # the robot never saw: the line ran along its face (a ragged face's notches are open space
    # on both sides of the cells between them), not through it. The depth rule decides there.
    thick_unseen = g_occ & (depth >= depth_m) & (local_state[box] == UNKNOWN)
    if thick_unseen.any():
        k = max(1, round(depth_m / resolution))
        beside = cv2.dilate(thick_unseen.view(np.uint8), np.ones((2 * k + 1,) * 2, np.uint8)) > 0
        found &= ~beside | (depth >= need)
    if across > 0:
        # Through the structure: its cells not seen occupied; across it, not along its face (a
        # line through a face eroded a cell deep reaches open space at the structure's ends):
        # the line passes a cell deeper inside than depth_m. And not the face's own row of
        # cells, the one grazing rays erode.
        past_face = depth > 1.5 * resolution
        rest = cand & ~found & past_face
        if rest.any():
            passable = g_occ & (local_state[box] != OCCUPIED)
            deep = depth >= depth_m
            start = open_space > 0
            # On each side the robot saw into the structure past that row: cells seen free
            # beyond it, in line with open space through cells seen free. Two faces eroded a
            # row deep, the middle unseen, are what grazing rays draw of a block standing.
            inside_free = g_occ & seen_free
            entered = inside_free & past_face
            # Each piece in a window around it (pieces lie far apart on a large map).
            n, labels, stats, _ = cv2.connectedComponentsWithStats(rest.view(np.uint8))
            for k in range(1, n):
                px, py, pw, ph = (int(v) for v in stats[k, :4])
                win = (
                    slice(max(py - across, 0), py + ph + across),
                    slice(max(px - across, 0), px + pw + across),
                )
                piece = labels[win] == k
                for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
                    args = (start[win], passable[win], deep[win])
                    ahead, ahead_deep = _reached(*args, (dr, dc), across)
                    behind, behind_deep = _reached(*args, (-dr, -dc), across)
                    through_cells = piece & ahead & behind & (ahead_deep | behind_deep)
                    if not through_cells.any():
                        continue
                    # ... and on each side through the cells seen free past the face's row.
                    # Asked on top of the reach above, never instead: a line is still as long
                    # as both_sides_m, from open space to open space.
                    for step in ((dr, dc), (-dr, -dc)):
                        walked, _ = _reached(start[win], inside_free[win], None, step, across)
                        entry = walked & entered[win]
                        beyond, _ = _reached(entry, passable[win], None, step, across)
                        through_cells &= entry | beyond
                    found[win] |= through_cells
    # Nothing behind a face seen standing: the robot saw a cell free only along a ray that
    # came from open space; where the face between them is seen intact, the free cells inside
    # came from a part of the local map laid over the wrong place, not from a ray.
    found &= _reached_from_open_space(global_state[box], local_state[box], resolution)
    evidence[box] = found
    return evidence


# The share of the longest rays' length (ray_m) that removal_evidence takes for the rays that
# skim a face near the route, which come along it from afar: the depth asked of a removed cell
# is everywhere at least depth_per_m times this much of ray_m. The pipeline's ray_m is how far
# from the route the local map saw anything (piecewise.seen_reach_m: a lower bound of the
# range, 11.9-12.3 m for a 12 m lidar, less among walls that close in). 0.75 keeps the depth
# under depth_m (0.15 m) up to 12.7 m, so with a 12 m lidar nothing changes; a 20 m one asks
# 0.24 m, a 30 m one 0.35 m. Session 14, with the pipeline's depth_per_m (0.0157): the 30 m
# lidar's ordinary sessions (seed 1307) 26 -> 16 false removals, F1 0.884 -> 0.918, the 20 m
# drift set (seed 1303) 11 -> 9, no change lost in either. The whole length (1.0) took 3 and
# 2 more false removals off those two, but a 12 m set then asks 0.19 m and lost 2 of seed
# 99's 152 changes (F1 0.960 -> 0.953); half (0.5) kept 1 and 2 of these false removals more
# than 0.75.
_SKIM_SHARE = 0.75


# What _across_m adds to the whole steps it counts inside a structure: half a step to the
# edge of the cell's outermost cell, and one step of slack (each map draws a face anywhere in
# the cell it falls in).
_ACROSS_SLACK_STEPS = 1.5
# The four line directions (row, col) a structure's thickness is measured along, at 0, 45, 90
# and 135 degrees from the grid's rows (angles measured from the +col axis towards +row).
_LINES = ((0, 1), (1, 1), (1, 0), (1, -1))


def _inside_across_rays(
    solid: BoolArray,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    toward: NDArray[np.float32],
    need_m: NDArray[np.float32],
    resolution: float,
) -> BoolArray:
    """(N,) bool: whether each cell (``rows``, ``cols``: (N,) of ``solid``) lies at least
    ``need_m`` ((N,)) inside ``solid`` across the direction ``toward`` ((N, 2) unit (row, col)
    vectors: the rays that saw it), measured along the nearest of the four grid lines
    (:data:`_LINES`) by :func:`_across_m`."""
    angle = np.degrees(np.arctan2(-toward[:, 1], toward[:, 0])) % 180.0  # across them
    line = np.round(angle / 45.0).astype(np.intp) % 4
    inside = np.zeros(len(rows), bool)
    for i, step in enumerate(_LINES):
        on_line = line == i
        if on_line.any():
            r, c, need = rows[on_line], cols[on_line], need_m[on_line]
            inside[on_line] = _across_m(solid, step, resolution, float(need.max()), r, c) >= need
    return inside


def _across_m(
    solid: BoolArray,
    step: tuple[int, int],
    resolution: float,
    up_to_m: float,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
) -> NDArray[np.float32]:
    """How far each cell (``rows``, ``cols``: (N,)) of ``solid`` lies inside it along the line
    ``step`` ((dr, dc)) both ways, metres ((N,)): whole steps to its last cell on the nearer
    side plus :data:`_ACROSS_SLACK_STEPS`, counted until it passes ``up_to_m``. Cells off
    ``solid`` get the slack too; the caller asks of cells on it."""
    step_m = resolution * math.hypot(*step)
    steps = np.zeros(len(rows), np.float32)
    if len(rows) == 0:
        return steps
    kernel = np.zeros((3, 3), np.uint8)
    kernel[1, 1] = kernel[1 + step[0], 1 + step[1]] = kernel[1 - step[0], 1 - step[1]] = 1
    # Eroded around the cells only: k erosions reach k steps from a cell.
    k = math.ceil(up_to_m / step_m)
    r0, c0 = max(int(rows.min()) - k - 1, 0), max(int(cols.min()) - k - 1, 0)
    rows, cols = rows - r0, cols - c0
    around = solid[r0 : r0 + int(rows.max()) + k + 2, c0 : c0 + int(cols.max()) + k + 2]
    left: NDArray[np.uint8] = around.astype(np.uint8)
    for _ in range(k):
        left = np.asarray(
            cv2.erode(left, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0), np.uint8
        )
        if not left.any():
            break
        steps += left[rows, cols]
    return (steps + np.float32(_ACROSS_SLACK_STEPS)) * np.float32(step_m)


def _seen_in_line(
    space: NDArray[np.uint8],
    deep: NDArray[np.uint8] | None,
    step: tuple[int, int],
    reach: int,
    longer: int,
) -> BoolArray:
    """Cells with a cell of ``space`` within ``reach`` steps of them, or one of ``deep`` (when
    given) within ``longer`` steps, going back along ``step`` ((dr, dc)): the open space before
    each cell."""
    seen = cv2.dilate(space, _line_kernel(step, reach)) > 0
    if deep is not None:
        seen |= cv2.dilate(deep, _line_kernel(step, longer)) > 0
    return np.asarray(seen)


def _line_kernel(step: tuple[int, int], length: int) -> NDArray[np.uint8]:
    """A one-sided line kernel for cv2.dilate, which reads the source at each kernel cell's
    offset from the centre: the ``length`` cells at ``-t * step``, t = 1 .. length."""
    dr, dc = step
    kernel = np.zeros((2 * length + 1, 2 * length + 1), np.uint8)
    for t in range(1, length + 1):
        kernel[length - dr * t, length - dc * t] = 1
    return kernel


def _deep_inside(
    state: NDArray[np.uint8], value: int, box: tuple[slice, slice], depth_px: float
) -> BoolArray:
    """On ``box`` of ``state``: whether each cell holds ``value`` and lies at least
    ``depth_px`` from any cell that does not (measured on the box grown by that depth, so that
    cells near the box's edge are not taken as deeper than they are)."""
    outer = grown(box, math.ceil(depth_px) + 1, state.shape)
    window = (state[outer] == value).view(np.uint8)
    depth = cv2.distanceTransform(window, cv2.DIST_L2, 5)
    (rows, cols), (r0, c0) = box, (outer[0].start, outer[1].start)
    inner = (slice(rows.start - r0, rows.stop - r0), slice(cols.start - c0, cols.stop - c0))
    return np.asarray((depth[inner] >= depth_px) & (window[inner] > 0))


# How deep (in depth_m) a free cell lies inside a structure for the rays that saw it to count
# for the face cells in front of it (a notch carved into a block, seen from the open side: its
# cells past depth_m are evidence by depth, its face's are not, and a removal whose face is
# half its cells failed the evidence share). 1.5: a structure at least 0.45 m thick, too thick
# to see through; in the middle of a thinner one (0.25 m: a row at exactly depth_m), free
# streaks of a 270-degree scanner across a block that stood gave false removals. Measured: 1.0
# found 8 more changes for 7 more false positives over 10 sets, 1.5 found 7 for 1, 2.0 found 6
# for 1 but lost a removed wall piece of a site history (a notch 0.25 m deep in a 0.55 m block).
_FACE_ANCHOR_DEPTH = 1.5

# Gaps between the hits on a face seen from afar that rays did not pass through.
_FACE_GAP_M = 0.1


def _reached_from_open_space(
    global_state: NDArray[np.uint8], local_state: NDArray[np.uint8], resolution: float
) -> BoolArray:
    """Cells connected to open space (free in both maps) through cells the local map sees
    free, without crossing a wall it sees (its hits grown by ``_FACE_GAP_M``, closing the
    gaps between sparse hits on one face); then the free cells of that grown band next to
    them, up to ``_FACE_GAP_M`` away in steps along rows and columns (the foot of the wall a
    ray ended at). (H, W) bool."""
    k = max(1, round(_FACE_GAP_M / resolution))
    walls = (local_state == OCCUPIED).view(np.uint8)
    barrier = cv2.dilate(walls, np.ones((2 * k + 1, 2 * k + 1), np.uint8)) > 0
    passable = (local_state == FREE) & ~barrier
    n, labels = cv2.connectedComponents(passable.view(np.uint8), connectivity=4)
    reached = np.zeros(n, bool)
    reached[labels[passable & (global_state == FREE)]] = True
    reached[0] = False  # the barrier, and everything not seen free
    out = np.asarray(reached[labels])
    # The free cells of the barrier next to what was reached (the foot of a wall a ray ended
    # at): grown through cells seen free, step by step, never across a wall seen.
    free = (local_state == FREE).view(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    grown = out.view(np.uint8)
    for _ in range(k):
        grown = cv2.dilate(grown, cross) & free
    return np.asarray((grown > 0) | out)


def _reached(
    start: BoolArray,
    passable: BoolArray,
    deep: BoolArray | None,
    step: tuple[int, int],
    n: int,
) -> tuple[BoolArray, BoolArray]:
    """The cells reached from ``start`` in at most ``n`` steps of ``step`` (row, col), every
    cell passed on the way (not the last) ``passable``; and those of them reached through a
    ``deep`` cell (none when ``deep`` is None, which skips that work)."""
    seen = np.zeros(start.shape, bool)
    seen_deep = np.zeros(start.shape, bool)
    front, front_deep = start, np.zeros(start.shape, bool)
    dr, dc = step
    h, w = start.shape
    to = (slice(max(dr, 0), h + min(dr, 0)), slice(max(dc, 0), w + min(dc, 0)))
    source = (slice(max(-dr, 0), h + min(-dr, 0)), slice(max(-dc, 0), w + min(-dc, 0)))
    for _ in range(n):
        moved = np.zeros(start.shape, bool)
        moved[to] = front[source]
        seen |= moved
        front = moved & passable
        if deep is not None:
            moved_deep = np.zeros(start.shape, bool)
            moved_deep[to] = front_deep[source]
            seen_deep |= moved_deep
            front_deep = (moved_deep | (front & deep)) & passable
        if not front.any():
            break
    return seen, seen_deep


def small_structures_gone(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    removed: BoolArray,
    *,
    resolution: float,
    smaller_than_px: int,
    max_extent_m: float,
    min_px: float,
    min_share: float,
    clear_m: float,
    unseen_m: float,
) -> BoolArray:
    """The cells of ``removed`` on small structures the robot saw gone whole, around the pieces
    of ``removed`` under ``smaller_than_px`` cells (8-connected; a larger piece needs no help).

    A structure is a component of the global map's occupied cells (8-connected) of at least
    ``min_px`` cells of this grid, no wider than ``max_extent_m`` either way, at least
    ``min_share`` of whose cells are in ``removed``, with no wall of the local map in the square
    of half-width ``clear_m`` around any of its cells (nothing seen standing there), and no
    cell of the global map's unknown area ``unseen_m`` deep (that far from any known cell) in
    the square of half-width ``2 * unseen_m`` around it: a short dash of a structure's face
    whose inside the map never saw is not a thing of its own (a real map draws a block's face
    seen from afar as a dotted line). An object drawn as a few cells counts; a bite out of a
    wall's face, a part of a large component, does not. (H, W) bool, True only on cells of
    ``removed``; the inputs are not modified.
    """
    out = np.zeros(removed.shape, bool)
    reach = max(1, round(2 * unseen_m / resolution))
    depth_px = unseen_m / resolution
    pad = math.ceil(depth_px) + 1  # the unknown's depth measured exactly up to depth_px
    # A structure through a piece that reaches this window's edge is wider than max_extent_m.
    margin = math.ceil(max_extent_m / resolution) + reach + pad + 1
    rules = _SmallRules(
        max_extent_px=max_extent_m / resolution,
        min_px=min_px,
        min_share=min_share,
        clear_px=max(1, round(clear_m / resolution)),
        reach_px=reach,
        depth_px=depth_px if unseen_m > 0 else None,
        pad_px=pad,
    )
    for win, at in _small_pieces(removed, smaller_than_px, margin):
        out[win] |= _small_gone_in(global_state[win], local_state[win], removed[win], at, rules)
    return out


def _small_pieces(
    removed: BoolArray, smaller_than_px: int, margin_px: int
) -> Iterator[tuple[tuple[slice, slice], tuple[NDArray[np.intp], NDArray[np.intp]]]]:
    """``removed``'s pieces (8-connected) under ``smaller_than_px`` cells, each in a window of
    its own (the pieces lie far apart on a large map): the window, its box around the piece
    grown by ``margin_px``, and the piece's (rows, cols) in it."""
    pieces = box_around(removed, 0)
    if pieces is None:
        return
    _, labels, stats, _ = cv2.connectedComponentsWithStats(
        removed[pieces].view(np.uint8), connectivity=8
    )
    for piece in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < smaller_than_px) + 1:
        x, y, w, h = (int(v) for v in stats[piece, :4])
        rows, cols = np.nonzero(labels[y : y + h, x : x + w] == piece)
        rows, cols = rows + pieces[0].start + y, cols + pieces[1].start + x
        win = box_of_cells(rows, cols, margin_px, removed.shape)
        yield win, (rows - win[0].start, cols - win[1].start)


@dataclass(frozen=True)
class _SmallRules:
    """:func:`small_structures_gone`'s thresholds in cells of its grid (``depth_px`` None:
    no rule on the unknown)."""

    max_extent_px: float
    min_px: float
    min_share: float
    clear_px: int
    reach_px: int
    depth_px: float | None
    pad_px: int


def _small_gone_in(
    g_state: NDArray[np.uint8],
    l_state: NDArray[np.uint8],
    cand: BoolArray,
    piece: tuple[NDArray[np.intp], NDArray[np.intp]],
    rules: _SmallRules,
) -> BoolArray:
    """The cells of ``cand`` on small structures seen gone whole through ``piece`` (the rows
    and columns of a small piece of it), in one window (the arrays' shape)."""
    occupied = (g_state == OCCUPIED).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(occupied, connectivity=8)
    size = stats[:, cv2.CC_STAT_AREA]
    keep = (
        (stats[:, cv2.CC_STAT_WIDTH] <= rules.max_extent_px)
        & (stats[:, cv2.CC_STAT_HEIGHT] <= rules.max_extent_px)
        & (size >= rules.min_px)
        & (np.bincount(labels[cand], minlength=n) >= rules.min_share * size)
        & (np.bincount(labels[piece], minlength=n) > 0)
    )
    keep[0] = False  # the background
    clear = np.ones((2 * rules.clear_px + 1,) * 2, np.uint8)
    for label in np.flatnonzero(keep):
        x, y, w, h = (int(v) for v in stats[label, :4])
        room = max(rules.clear_px, rules.reach_px) + rules.pad_px
        win = grown((slice(y, y + h), slice(x, x + w)), room, labels.shape)
        own = (labels[win] == label).view(np.uint8)
        if (cv2.dilate(own, clear).view(bool) & (l_state[win] == OCCUPIED)).any():
            keep[label] = False
        elif rules.depth_px is not None:
            keep[label] = not _near_deep_unknown(g_state[win], own, rules.depth_px, rules.reach_px)
    return np.asarray(cand & keep[labels])


def _near_deep_unknown(
    g_state: NDArray[np.uint8], mask: NDArray[np.uint8], depth_px: float, reach_px: int
) -> bool:
    """Whether a cell of the global map's unknown area ``depth_px`` deep (:func:`_deep_unknown`)
    lies in the square of half-width ``reach_px`` around a cell of ``mask`` (0/1 uint8)."""
    return bool((_deep_unknown(g_state, depth_px) & _grown_by(mask, reach_px)).any())


def _deep_unknown(g_state: NDArray[np.uint8], depth_px: float) -> BoolArray:
    """The cells of the global map's unknown area ``depth_px`` deep or more (that far from
    any known cell, within the array: what lies beyond it counts as far)."""
    unknown = (g_state == UNKNOWN).view(np.uint8)
    return np.asarray(cv2.distanceTransform(unknown, cv2.DIST_L2, 5) >= depth_px)


@dataclass(frozen=True)
class CutRules:
    """What :func:`walls_cut_through` asks of a piece, in metres (squares of these half-widths
    where it says "within"): the wall either side of it in two parts of at least
    ``min_part_m / resolution`` cells each (0.3 m of a line one cell wide); of each part's cells
    within ``near_gap_m`` of the piece, ``standing_share`` with a local wall within ``seen_m``
    (the robot saw it standing: one cell of the 0.05 m work grid); for ``side_share`` of the
    piece's cells, a cell within ``side_m`` that is floor in both maps, on each side of the
    wall; no cell of the global map unknown ``unseen_m`` deep within twice that."""

    min_part_m: float = 0.3
    near_gap_m: float = 0.5
    seen_m: float = 0.05
    standing_share: float = 0.65
    side_m: float = 0.25
    side_share: float = 0.5
    unseen_m: float = 0.25


def walls_cut_through(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    removed: BoolArray,
    *,
    resolution: float,
    smaller_than_px: int,
    rules: CutRules,
) -> BoolArray:
    """The cells of ``removed``'s small pieces (under ``smaller_than_px`` cells, 8-connected)
    that cut a thin wall of the global map in two, a wall the robot saw standing on both sides
    of the piece, with floor on both sides of it in both maps (``rules``).

    A gap made in a partition: after a drifting session the end tolerance trims each end of
    the gap by 0.2 m, and what stays of a gap 0.5 m wide in a wall 0.1 m thick is 4 cells
    across it, under the removed floor of 8. A bite out of a thicker wall's face, a fold along
    it and the end of a wall cut nothing; a face of a structure whose inside the map never saw
    is no partition; a thin wall the local map drew as specks beside the piece was not seen
    standing. (H, W) bool, True only on cells of ``removed``; the inputs are not modified. The
    evidence the removal needs is the caller's to ask.
    """
    out = np.zeros(removed.shape, bool)
    margin_px = math.ceil(2 * rules.near_gap_m / resolution)
    for win, at in _small_pieces(removed, smaller_than_px, margin_px):
        if _cuts_in(global_state[win], local_state[win], at, resolution, rules):
            out[win][at] = True
    return out


def _cuts_in(
    g_state: NDArray[np.uint8],
    l_state: NDArray[np.uint8],
    at: tuple[NDArray[np.intp], NDArray[np.intp]],
    resolution: float,
    rules: CutRules,
) -> bool:
    """Whether the piece at cells ``at`` ((rows, cols) in this window of both maps' states)
    cuts a wall in two (:func:`walls_cut_through`)."""
    piece = np.zeros(g_state.shape, np.uint8)
    piece[at] = 1
    reach_px = max(1, round(2 * rules.unseen_m / resolution))
    if _near_deep_unknown(g_state, piece, rules.unseen_m / resolution, reach_px):
        return False  # a face of a structure whose inside the map never saw
    ends = _parts_standing(g_state, l_state, piece, resolution, rules)
    if ends is None:
        return False
    # Across the line through the two parts: floor on both sides of the wall.
    along = ends[1] - ends[0]
    across = np.array([-along[1], along[0]]) / max(float(np.hypot(*along)), 1e-9)
    floor = (g_state == FREE) & (l_state == FREE)
    steps = max(1, round(rules.side_m / resolution))
    return all(
        any_along(floor, at[0], at[1], sign * across[0], sign * across[1], steps).mean()
        >= rules.side_share
        for sign in (1, -1)
    )


def _parts_standing(
    g_state: NDArray[np.uint8],
    l_state: NDArray[np.uint8],
    piece: NDArray[np.uint8],
    resolution: float,
    rules: CutRules,
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The (row, col) centroids of the first two parts (in label order) that the global wall
    ``piece`` (a 0/1 mask) lies on falls apart into without it and that the local map saw
    standing near it; None when fewer than two."""
    _, walls = cv2.connectedComponents((g_state == OCCUPIED).view(np.uint8), connectivity=8)
    on = walls[piece > 0]
    on = on[on > 0]
    if len(on) == 0:
        return None
    rest = (walls == np.bincount(on).argmax()).view(np.uint8)
    rest[piece > 0] = 0
    _, parts, stats, centroids = cv2.connectedComponentsWithStats(rest, connectivity=8)
    seen_px = max(1, round(rules.seen_m / resolution))
    seen = _grown_by((l_state == OCCUPIED).view(np.uint8), seen_px)
    near_gap = _grown_by(piece, round(rules.near_gap_m / resolution))
    standing = []
    for k in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= rules.min_part_m / resolution) + 1:
        part = (parts == k) & near_gap
        n = np.count_nonzero(part)
        if n and np.count_nonzero(part & seen) >= rules.standing_share * n:
            standing.append(centroids[k][::-1])  # OpenCV's centroids are (x, y)
    return (standing[0], standing[1]) if len(standing) >= 2 else None


@dataclass(frozen=True)
class LineRules:
    """What :func:`thin_walls_seen_free` asks of a stretch of a thin wall, in metres: the
    global map's walls with gaps up to ``2 * close_m`` bridged (a line drawn dotted) and
    thinner than ``thick_m``; seen free by the local map, with no local wall within
    ``clear_m`` (a square of that half-width), over at least ``min_length_m`` along the line
    and no wider across it than ``thick_m`` and a cell (a straight line, no corner); for
    ``side_share`` of its cells, a cell of the local map's floor and none of its walls within
    ``side_m`` on each side of it (the robot saw through it, and drew no wall beside it); no
    cell of the global map unknown ``unseen_m`` deep within twice that."""

    close_m: float = 0.1
    thick_m: float = 0.15
    clear_m: float = 0.05
    min_length_m: float = 0.6
    side_m: float = 0.25
    side_share: float = 0.5
    unseen_m: float = 0.25


def thin_walls_seen_free(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    removed: BoolArray,
    *,
    resolution: float,
    smaller_than_px: int,
    rules: LineRules,
) -> BoolArray:
    """The cells of ``removed`` on stretches of thin walls of the global map that the local
    map saw free along their length and through (``rules``), through ``removed``'s small
    pieces (under ``smaller_than_px`` cells, 8-connected).

    A thin wall drawn as a dotted line (a real map's partition seen from afar, a floor plan's
    thin line on a coarser grid) leaves only its dots to the removed mask, and the tolerances
    trim a gap's ends by 0.1-0.25 m each: what stays of a piece of wall 0.5-1.5 m long seen
    gone is a few specks under the removed floor, though the robot saw the whole stretch of
    the line free. Its line, bridged, is the wall's extent. Not: a stretch the local map
    draws specks along (rays through a wall seen standing), one shorter than the length, a
    corner, a line seen free with nothing seen behind it (rays grazing a wall) or with a local
    wall drawn beside it (the wall seen displaced, its line free), a line whose
    inside the global map never saw (a block's face drawn dotted). (H, W) bool, True only on
    cells of ``removed``; the inputs are not modified. The evidence the removal needs is the
    caller's to ask.
    """
    out = np.zeros(removed.shape, bool)
    px = _LinePx.of(rules, resolution)
    small = removed & ~drop_small(removed, min_pixels=smaller_than_px)
    if not small.any():
        return out
    # One window, the local map's floor grown by as far as the rules look: a stretch lies on
    # that floor, so each one is measured once and whole there, whatever the number of dots
    # on it and wherever the other pieces lie; the morphology and the side and unknown rules
    # around it see what they would on the whole map.
    margin_px = px.close + px.thick + px.around + 2
    win = box_around(local_state == FREE, margin_px)
    if win is not None:
        out[win] = _lines_seen_free_in(
            global_state[win], local_state[win], removed[win], small[win], px
        )
    return out


@dataclass(frozen=True)
class _LinePx:
    """:class:`LineRules` in cells of the work grid (``depth`` the unknown's, as a float), and
    the length asked in metres, on cells of ``resolution``."""

    close: int
    thick: int
    clear: int
    side: int
    reach: int
    depth: float
    min_length_m: float
    resolution: float
    side_share: float

    @property
    def around(self) -> int:
        """How far from a stretch its rules look: across it, and for the unknown."""
        return max(self.side + self.thick, self.reach)

    @staticmethod
    def of(rules: LineRules, resolution: float) -> _LinePx:
        return _LinePx(
            close=max(1, round(rules.close_m / resolution)),
            thick=max(2, round(rules.thick_m / resolution)),
            clear=max(1, round(rules.clear_m / resolution)),
            side=max(1, round(rules.side_m / resolution)),
            reach=max(1, round(2 * rules.unseen_m / resolution)),
            depth=rules.unseen_m / resolution,
            min_length_m=rules.min_length_m,
            resolution=resolution,
            side_share=rules.side_share,
        )


def _lines_seen_free_in(
    g_state: NDArray[np.uint8],
    l_state: NDArray[np.uint8],
    removed: BoolArray,
    small: BoolArray,
    px: _LinePx,
) -> BoolArray:
    """The cells of ``removed`` on the stretches of thin wall seen free through its small
    pieces ``small``, in this window of both maps' states (:func:`thin_walls_seen_free`)."""
    out = np.zeros(removed.shape, bool)
    occupied = (g_state == OCCUPIED).view(np.uint8)
    closed = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, np.ones((2 * px.close + 1,) * 2, np.uint8))
    thick = cv2.morphologyEx(closed, cv2.MORPH_OPEN, np.ones((px.thick,) * 2, np.uint8))
    floor, local_walls = l_state == FREE, l_state == OCCUPIED
    stretch = (closed > thick) & floor & ~_grown_by(local_walls.view(np.uint8), px.clear)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(stretch.view(np.uint8), connectivity=8)
    through = np.unique(labels[small])
    through = through[through > 0]
    if len(through) == 0:
        return out
    deep = _deep_unknown(g_state, px.depth)
    beside = floor & (closed == 0)
    for label in through:
        x, y, w, h = (int(v) for v in stats[label, :4])
        # The stretch's box, and around it as far as its rules look.
        box = grown((slice(y, y + h), slice(x, x + w)), px.around, removed.shape)
        own = labels[box] == label
        rows, cols = np.nonzero(own)
        points = np.column_stack((rows, cols)).astype(np.float64)
        centre, axis = main_axis(points)
        across = square_to(axis)
        # Both counted in cells (end to end, both ends in): a row of cells is one wide.
        length_px = extent_along(points, centre, axis) + 1
        width_px = extent_along(points, centre, across) + 1
        if length_px * px.resolution < px.min_length_m or width_px > px.thick + 1:
            continue
        # Beside the line, not on it: from a cell on one edge the far side is the line's
        # width across.
        steps = px.side + round(width_px) - 1
        if not all(
            _seen_through(beside[box], local_walls[box], rows, cols, sign * across, steps).mean()
            >= px.side_share
            for sign in (1, -1)
        ):
            # Rays grazing the wall, nothing seen behind it; or the wall drawn beside its
            # line (drift left over), seen free where it is drawn.
            continue
        if (deep[box] & _grown_by(own.view(np.uint8), px.reach)).any():
            continue  # a face of a structure whose inside the map never saw
        out[box] |= own & removed[box]
    return out


def _seen_through(
    floor: BoolArray,
    walls: BoolArray,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    across: NDArray[np.float64],
    steps: int,
) -> BoolArray:
    """(N,) bool: for each cell, a cell of ``floor`` and none of ``walls`` within ``steps``
    cells along the unit (row, col) direction ``across``."""
    return any_along(floor, rows, cols, across[0], across[1], steps) & ~any_along(
        walls, rows, cols, across[0], across[1], steps
    )


def _grown_by(mask: NDArray[np.uint8], px: int) -> BoolArray:
    """``mask`` (0/1 uint8) grown by ``px`` cells each way (a square), as bool."""
    if px <= 0:
        return mask.view(bool).copy()
    return np.asarray(cv2.dilate(mask, np.ones((2 * px + 1,) * 2, np.uint8))).view(bool)


def drop_small(mask: BoolArray, *, min_pixels: int) -> BoolArray:
    """``mask`` without its 8-connected components smaller than ``min_pixels``."""
    out = mask.copy()
    # Label only the box around the True cells, and clear the small components where they are.
    x, y, w, h = cv2.boundingRect(out.view(np.uint8))
    if w == 0:
        return out
    box = out[y : y + h, x : x + w]
    _, labels, stats, _ = cv2.connectedComponentsWithStats(box.view(np.uint8), connectivity=8)
    small = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < min_pixels) + 1
    if len(small) > 64:
        keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
        keep[0] = False
        box[...] = keep[labels]
        return out
    for k in small:
        bx, by, bw, bh = stats[k, :4]
        part = (slice(by, by + bh), slice(bx, bx + bw))
        box[part][labels[part] == k] = False
    return out


def drop_along_walls(
    added: BoolArray,
    walls: BoolArray,
    *,
    resolution: float,
    within_m: float,
    min_agreement: float = 0.85,
    local_state: NDArray[np.uint8] | None = None,
) -> BoolArray:
    """``added`` without its components that lie along one wall of the global map: every cell
    within ``within_m`` of a wall, all on the same side of it (the directions to their nearest
    wall agree: the mean of their unit vectors is at least ``min_agreement`` long).

    That is a wall of the global map seen displaced: drift the warp did not take out, or a
    wall's face seen a cell or two further out than it was drawn. It runs parallel to the wall
    it came from and never gets further from it than the displacement. A new obstacle reaches
    further out, and a piece that closes a gap between two walls lies between them (its cells'
    nearest walls are on opposite sides): both are kept. Returns a new (H, W) bool array.

    With ``local_state`` (the aligned local map's cell states on the same grid), a component
    that stands in front of the wall is kept too (:func:`_stands_in_front`): a face that steps
    out from the wall seen in place and back in beyond both its ends, nothing seen free behind
    it. Shelves or a lining put along a wall; drift displaces a face smoothly, over metres.
    """
    out = added.copy()
    if not walls.any():
        return out
    # Room for the reach, and for the nearest wall to be found inside the window.
    m = math.ceil(within_m / resolution) + 2
    dropped: list[tuple[NDArray[np.intp], NDArray[np.intp]]] = []  # on the whole grid
    for window, labels in _component_windows(out, m):
        n = int(labels.max()) + 1
        along = _along_one_wall(labels, walls[window], n, resolution, within_m, min_agreement)
        if local_state is not None and along.any():
            rows, cols = nonzero_cells(along[labels] & (labels > 0))
            label = labels[rows, cols]
            rows, cols = rows + window[0].start, cols + window[1].start  # on the whole grid
            for k, at in by_label(label):
                if _stands_in_front(rows[at], cols[at], walls, local_state, resolution):
                    along[k] = False
                else:
                    dropped.append((rows[at], cols[at]))
        out[window][along[labels] & (labels > 0)] = False
    if local_state is not None:
        strips = _dashes_in_front(dropped, walls, local_state, resolution, within_m)
        for rows, cols in strips:
            out[rows, cols] = True
    return out


# Pieces of one strip that the tolerance cut into dashes (its line drawn dotted, or half its
# cells within the tolerance of the wall), each too short to tell, are judged together: those
# within twice this of each other (session 55, mis4040's gen-16-mislocalized: a wall 2.8 m long
# built 0.25 m in front of another, its added cells three dashes of 0.6-0.9 m, dropped). Over
# the 67 sets, that change found and nothing else moved.
_BRIDGE_M = 0.1


def _dashes_in_front(
    dropped: list[tuple[NDArray[np.intp], NDArray[np.intp]]],
    walls: BoolArray,
    local_state: NDArray[np.uint8],
    resolution: float,
    within_m: float,
) -> list[tuple[NDArray[np.intp], NDArray[np.intp]]]:
    """Of the components ``dropped`` as walls seen displaced (each its rows and cols), those
    that make with others within ``2 * _BRIDGE_M`` of them one strip standing in front of its
    wall (:func:`_stands_in_front`), a strip each: (rows, cols) of its cells. A group that is
    no strip, spread across its own line over more than the ``within_m`` its cells keep from
    their wall (dashes along the four walls of a room, chained round its corners), is not
    asked: the check would span its whole box (a review of session 55: 2.4 s and 660 MB for a
    room 200 m square)."""
    if len(dropped) < 2:
        return []
    groups = _groups_within(dropped, 2 * _BRIDGE_M / resolution)
    strip_px = within_m / resolution + 2
    out = []
    for members in groups:
        if len(members) < 2:  # one component: judged alone already
            continue
        rows = np.concatenate([dropped[i][0] for i in members])
        cols = np.concatenate([dropped[i][1] for i in members])
        points = np.stack([rows, cols], axis=1).astype(np.float64)
        centre, axis = main_axis(points)
        across = (points - centre) @ square_to(axis)
        if float(across.max() - across.min()) > strip_px:
            continue
        if _stands_in_front(rows, cols, walls, local_state, resolution):
            out.append((rows, cols))
    return out


def _groups_within(
    components: list[tuple[NDArray[np.intp], NDArray[np.intp]]], reach: float
) -> list[list[int]]:
    """The components (rows, cols each) in groups, two in one when a cell of each lies within
    ``reach`` cells of the other (and so on, transitively): indices into ``components``.

    Worked out on the cells, bucketed in squares of ``reach`` (a cell's neighbours within
    reach lie in its square or the eight around it), never on the grid nor over all pairs of
    components: on a large map they may be thousands, far apart (a grid of 8000 x 8000 cells
    made 1.1 s of a first version that dilated the box around them all)."""
    size = max(1, math.ceil(reach))
    rows = np.concatenate([r for r, _ in components])
    cols = np.concatenate([c for _, c in components])
    owner = np.repeat(np.arange(len(components)), [len(r) for r, _ in components])
    order = np.lexsort((cols // size, rows // size))
    rows, cols, owner = rows[order], cols[order], owner[order]
    keys = np.stack([rows // size, cols // size], axis=1)
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
    ends = np.r_[starts[1:], len(rows)]
    bucket = {(int(keys[a, 0]), int(keys[a, 1])): (a, b) for a, b in zip(starts, ends, strict=True)}
    parent = list(range(len(components)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for (br, bc), (a, b) in bucket.items():
        # This square against itself and the four after it (each pair of squares once).
        for dr, dc in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
            other = bucket.get((br + dr, bc + dc))
            if other is None:
                continue
            c0, c1 = other
            mine, theirs = owner[a:b], owner[c0:c1]
            if np.all(mine[:, None] == theirs[None, :]):
                continue
            d_r = rows[a:b, None] - rows[None, c0:c1]
            d_c = cols[a:b, None] - cols[None, c0:c1]
            close = (d_r * d_r + d_c * d_c <= reach * reach) & (mine[:, None] != theirs[None, :])
            near_r, near_c = np.nonzero(close)
            pairs = zip(mine[near_r].tolist(), theirs[near_c].tolist(), strict=True)
            for first, second in set(pairs):
                top_first, top_second = root(first), root(second)
                if top_first != top_second:
                    parent[top_first] = top_second
    groups: dict[int, list[int]] = {}
    for k in range(len(components)):
        groups.setdefault(root(k), []).append(k)
    return list(groups.values())


# An obstacle standing in front of a wall (_stands_in_front): at least this long along it (a
# face drawn a cell or two out over a shorter run is a scan's own error: session 46, with 0.5 m
# over the 59 sets, one false positive more, a shelf's face drawn 0.1 m out over 0.7 m on a
# 0.1 m local map)...
_IN_FRONT_MIN_LENGTH_M = 1.0
# ... its face looked for this far beyond its component's ends (a part of its face may lie
# within the tolerance of the wall, not added)...
_FACE_RUN_M = 2.0
# ... where the local face steps back from where it stands (less a cell of slack) at least this
# far towards the wall (and two cells: on a 0.1 m map a 0.2 m shelf is too shallow to tell)...
_STEP_BACK_M = 0.1
# ... within this distance along the wall (drift displaces a face over metres, never back this
# close to where it stood out)...
_STEP_M = 0.15
# ... and stays back over this distance beyond the step, seen at this share of it at least...
_BEYOND_STEP_M = 0.3
_IN_PLACE_SHARE = 0.6
# ... a face seen back in place anywhere from less than this far behind the global wall's
# face (a wall drawn thicker than a lidar sees it, a floor plan's thickened line: the local
# face lies 0.1-0.2 m inside it) out to the component...
_FACE_BEHIND_M = 0.3
# ... and at most this share of the known cells between it and the wall seen free (the robot
# did not see behind it: a face drawn twice by drift has the floor seen between its lines).
_BEHIND_FREE_SHARE = 0.25
# ... the cells beside an end where no face was seen (its shadow) not counted in the step, up
# to this far along the wall (or its depth, if more). Bounded by the strip's depth until
# session 55: a wall 2.3 m long built 0.2 m in front of a block, seen at a grazing angle with
# 0.85 m of the block's face beside one end in its shadow, was dropped (gh55's hist-01-hospital,
# three sessions, never confirmed). Over the 67 generated and public sets, no result changed;
# over the nine history sets, that change confirmed and nothing else moved. A face drift
# displaced is seen at every offset between, not in a step; unseen exactly over its way back,
# it would pass.
_SHADOW_M = 1.0


def _stands_in_front(
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    walls: BoolArray,
    local_state: NDArray[np.uint8],
    resolution: float,
) -> bool:
    """Whether the added cells at ``rows``, ``cols`` (one component lying along one wall of
    ``walls``, or the dashes of one strip, :func:`_dashes_in_front`; on the whole grid; worked
    out in a box around them) are an obstacle standing in
    front of that wall rather than the wall's face seen displaced: at least ``_IN_FRONT_MIN_LENGTH_M`` long along the wall, the
    floor between it and the wall not seen free (``_BEHIND_FREE_SHARE``), and on each side,
    within ``_FACE_RUN_M`` beyond its end, the local map's face stepping back towards the wall
    by ``_STEP_BACK_M`` (two cells at least) within ``_STEP_M`` along it and staying back,
    seen, for ``_BEYOND_STEP_M``.

    Measured across the component's own line (its cells' main axis), from the wall's face
    there (where its cells' distance to the wall puts it): a slanted wall is measured as a
    straight one, and the component's typical offset, not its farthest cell, is where it
    stands (a box on a shelf reaches further)."""
    res = resolution
    centre, axis = main_axis(np.stack([rows, cols], 1).astype(np.float64))
    along = (rows - centre[0]) * axis[0] + (cols - centre[1]) * axis[1]
    if (along.max() - along.min() + 1) * res < _IN_FRONT_MIN_LENGTH_M:
        return False
    box = box_of_cells(rows, cols, math.ceil((_FACE_RUN_M + _BEYOND_STEP_M) / res) + 2, walls.shape)
    walls, local_state = walls[box], local_state[box]
    rows, cols = rows - box[0].start, cols - box[1].start
    centre = centre - (box[0].start, box[1].start)
    cells = np.zeros(walls.shape, bool)
    cells[rows, cols] = True
    dist = distance_to(walls)[rows, cols]
    # Every cell of the box along the component's line (ss) and across it, away from the wall
    # (uu: the way the cells' distance to the wall grows).
    rr, cc = np.mgrid[0 : walls.shape[0], 0 : walls.shape[1]]
    ss = (rr - centre[0]) * axis[0] + (cc - centre[1]) * axis[1]
    normal = square_to(axis)
    uu = (rr - centre[0]) * normal[0] + (cc - centre[1]) * normal[1]
    offset = uu[rows, cols]
    if np.dot(offset - offset.mean(), dist - dist.mean()) < 0:
        uu, offset = -uu, -offset
    face = float(np.median(offset - dist))
    depth = float(np.median(offset)) - face  # where it stands, in cells from the face
    farthest = float(offset.max()) - face
    uu -= face
    behind = (ss >= along.min()) & (ss <= along.max()) & (uu > 0.5) & (uu < depth - 0.5)
    behind &= ~walls & ~cells
    known = behind & (local_state != UNKNOWN)
    if known.any() and np.mean(local_state[known] == FREE) > _BEHIND_FREE_SHARE:
        return False
    # The local face's profile beyond each end: per whole cell along the wall, the outermost
    # local wall cell in the band from the global face out to the component.
    band = (uu > -_FACE_BEHIND_M / res) & (uu <= farthest + 1) & (local_state == OCCUPIED)
    out_px = depth - 1  # still standing out (a cell of slack)
    back_px = out_px - max(2.0, _STEP_BACK_M / res)
    step_px, run_px = max(1, round(_STEP_M / res)), max(2, round(_BEYOND_STEP_M / res))
    reach = round(_FACE_RUN_M / res) + run_px
    for start, sign in ((along.max(), 1.0), (along.min(), -1.0)):
        beyond = np.round((ss - start) * sign).astype(np.intp)
        sel = band & (beyond >= 0) & (beyond <= reach)
        profile = np.full(reach + 1, -np.inf)
        np.maximum.at(profile, beyond[sel], uu[sel])
        # The wall beside an end may lie in the obstacle's shadow: as far along the wall as it
        # stands out, seen from 45 degrees or more; farther, seen at a grazing angle.
        shadow_px = max(math.floor(depth), round(_SHADOW_M / res))
        if not _steps_back(profile, out_px, back_px, step_px, run_px, shadow_px):
            return False
    return True


def _steps_back(
    profile: NDArray[np.float64],
    out_px: float,
    back_px: float,
    step_px: int,
    run_px: int,
    shadow_px: int = 0,
) -> bool:
    """Whether a face's ``profile`` (its offset from the wall per cell along it, -inf where no
    wall was seen) goes from standing out (``out_px`` or more) back (to ``back_px`` or less)
    within ``step_px`` cells and stays back over the ``run_px`` cells from there, at
    ``_IN_PLACE_SHARE`` of them (seen and back). Cells where no wall was seen between the two
    do not count as cells of the step, up to ``shadow_px``."""
    out = np.flatnonzero(profile >= out_px)
    for last in out[::-1]:
        after = profile[last + 1 : last + 1 + step_px + shadow_px + run_px]
        first = np.flatnonzero(np.isfinite(after) & (after <= back_px))  # seen back
        # Cells where no wall was seen (the obstacle's shadow on the wall beside its end) do
        # not count against the step, up to shadow_px of them.
        if not len(first) or np.isfinite(after[: first[0]]).sum() >= step_px:
            continue
        if first[0] >= step_px + shadow_px:
            continue
        run = after[first[0] : first[0] + run_px]
        seen_back = np.isfinite(run) & (run <= back_px)
        if len(run) == run_px and np.mean(seen_back) >= _IN_PLACE_SHARE:
            return bool(np.all(profile[last + 1 :][: first[0] + run_px] < out_px))
    return False


def _along_one_wall(
    labels: NDArray[np.int32],
    walls: BoolArray,
    n: int,
    resolution: float,
    within_m: float,
    min_agreement: float,
) -> NDArray[np.bool_]:
    """Per label (0..n-1) of ``labels`` (one window): whether its cells lie along one wall of
    ``walls`` (see :func:`drop_along_walls`)."""
    rows, cols = nonzero_cells(labels > 0)
    label = labels[rows, cols]
    dist = distance_to(walls)
    # The unit vectors away from the nearest wall: the distance field's gradient (a 3x3 Sobel),
    # at the cells only.
    d = np.pad(dist, 1, mode="reflect")
    r, c = rows + 1, cols + 1
    gx = (d[r - 1, c + 1] + 2 * d[r, c + 1] + d[r + 1, c + 1]) - (
        d[r - 1, c - 1] + 2 * d[r, c - 1] + d[r + 1, c - 1]
    )
    gy = (d[r + 1, c - 1] + 2 * d[r + 1, c] + d[r + 1, c + 1]) - (
        d[r - 1, c - 1] + 2 * d[r - 1, c] + d[r - 1, c + 1]
    )
    norm = np.hypot(gx, gy)
    norm[norm == 0] = 1.0
    count = np.bincount(label, minlength=n).astype(np.float64)
    count[count == 0] = 1.0
    mean_x = np.bincount(label, gx / norm, minlength=n) / count
    mean_y = np.bincount(label, gy / norm, minlength=n) / count
    farthest = np.full(n, np.inf, np.float32)
    order = np.argsort(label, kind="stable")
    sorted_labels = label[order]
    starts = np.flatnonzero(np.r_[True, sorted_labels[1:] != sorted_labels[:-1]])
    farthest[sorted_labels[starts]] = np.maximum.reduceat(dist[rows, cols][order], starts)
    along = (farthest * resolution <= within_m) & (np.hypot(mean_x, mean_y) >= min_agreement)
    along[0] = False
    return np.asarray(along)


def filter_noise(masks: DiffMasks, *, min_pixels: int) -> DiffMasks:
    """Remove specks: components smaller than ``min_pixels`` (a few local cells of scan noise).

    No morphological opening: a new obstacle seen from one side is a line one cell thick.
    """
    return DiffMasks(
        drop_small(masks.added, min_pixels=min_pixels),
        drop_small(masks.removed, min_pixels=min_pixels),
    )


# The side of the tiles small_structures_beside_walls works in windows around, in cells.
_BESIDE_TILE_PX = 64


@dataclass(frozen=True)
class BesideRules:
    """What :func:`small_structures_beside_walls` asks of a structure, in metres: no wider than
    ``max_extent_m`` either way, ``min_share`` of its cells seen free, every local wall within
    ``reach_m`` of it nearer other structure by more than ``margin_m``, no unknown ``unseen_m``
    deep in the square of half-width twice that around it."""

    max_extent_m: float = 0.5
    min_share: float = 0.5
    reach_m: float = 0.35
    margin_m: float = 0.05
    unseen_m: float = 0.25


def small_structures_beside_walls(
    global_state: NDArray[np.uint8],
    local_state: NDArray[np.uint8],
    roi: BoolArray,
    *,
    resolution: float,
    min_px: float,
    rules: BesideRules,
    global_walls: BoolArray | None = None,
) -> BoolArray:
    """The cells of small structures of the global map seen gone, judged by whom the local
    walls near them belong to: made for a post or a box a few centimetres from a wall, which
    the removed tolerance (no removed cell within 0.25 m of a local wall) hides from the
    comparison, the wall beside it drawn where it stands. No wall need stand near: a post in
    the open seen gone is marked too (as :func:`small_structures_gone` marks it).

    A structure is a component of the global map's occupied cells (8-connected) with a cell in
    ``roi``, of at least ``min_px`` cells of this grid and no wider than ``rules.max_extent_m``
    either way; none of its cells a wall of the local map and at least ``rules.min_share`` of
    those in ``roi`` seen free; every local wall within ``rules.reach_m`` of it nearer to other
    structure of the global map than to it by more than ``rules.margin_m``: the walls the robot
    drew there are its neighbours', not this thing drawn off. Other structure: the global map's
    other occupied cells, ``global_walls`` (its walls drawn grey, as :func:`raw_differences`
    takes them) and its specks of unknown no wider than a structure (a scanned map's noise,
    where the robot may see something standing), not the edge of a larger unknown area. And no
    cell of the global map's unknown area ``rules.unseen_m`` deep in the square of half-width
    twice that around it (a dash of a face whose inside the map never saw is no thing of its
    own, as for :func:`small_structures_gone`). A structure touching the grid's edge is not
    looked at (it may be wider than the grid shows). (H, W) bool, True on the structures' cells
    the local map saw free in ``roi``; the inputs are not modified.
    """
    out = np.zeros(roi.shape, bool)
    box = box_around(roi, 0)
    if box is None:
        return out
    at = np.flatnonzero(_seen_free(global_state[box], local_state[box], roi[box]))
    if at.size == 0:
        return out
    # (np.flatnonzero: np.nonzero on a 2-D array takes ten times as long)
    rows, cols = np.divmod(at, box[1].stop - box[1].start)
    rows, cols = rows + box[0].start, cols + box[1].start
    height, width = (int(v) for v in roi.shape)
    reach_px = rules.reach_m / resolution
    around_px = max(1, round(2 * rules.unseen_m / resolution))
    rules_px = _BesidePx(
        max_px=rules.max_extent_m / resolution,
        min_px=min_px,
        min_share=rules.min_share,
        reach_px=reach_px,
        margin_px=rules.margin_m / resolution,
        around_px=around_px,
        depth_px=rules.unseen_m / resolution,
        room_px=math.ceil(max(reach_px, around_px + rules.unseen_m / resolution)) + 2,
    )
    # On a large map the cells seen free lie in a few places (781 cells in 46 of 552 tiles of
    # 64 cells on bench_speed's airport): each group of tiles with some is worked on in a
    # window of its own, grown by what a structure there may reach.
    tile = _BESIDE_TILE_PX
    tiles = np.zeros((-(-height // tile), -(-width // tile)), np.uint8)
    tiles[rows // tile, cols // tile] = 1
    _, _, stats, _ = cv2.connectedComponentsWithStats(tiles, connectivity=8)
    grow = math.ceil(rules_px.max_px) + rules_px.room_px
    for x, y, w, h, _ in stats[1:]:
        place = (slice(y * tile, (y + h) * tile), slice(x * tile, (x + w) * tile))
        win = grown(place, grow, out.shape)
        # Candidates through this group's own cells seen free only: one through a cell in the
        # margin (another group's) may lie too near this window's edge to be judged here.
        (r0, r1), (c0, c1) = (
            (inner.start - outer.start, min(inner.stop, outer.stop) - outer.start)
            for inner, outer in zip(place, win, strict=True)
        )
        g_win, l_win, roi_win = global_state[win], local_state[win], roi[win]
        free = _seen_free(g_win, l_win, roi_win)
        candidates = np.zeros(free.shape, bool)
        candidates[r0:r1, c0:c1] = free[r0:r1, c0:c1]
        out[win] |= _beside_in(
            g_win,
            l_win,
            roi_win,
            free,
            candidates,
            None if global_walls is None else global_walls[win],
            rules_px,
        )
    return out


def _seen_free(g_state: NDArray[np.uint8], l_state: NDArray[np.uint8], roi: BoolArray) -> BoolArray:
    """The global map's occupied cells the local map saw free, in ``roi``."""
    return np.asarray((g_state == OCCUPIED) & roi & (l_state == FREE))


@dataclass(frozen=True)
class _BesidePx:
    """:func:`small_structures_beside_walls`'s thresholds in cells of its grid."""

    max_px: float
    min_px: float
    min_share: float
    reach_px: float
    margin_px: float
    around_px: int
    depth_px: float
    room_px: int


def _beside_in(
    g_state: NDArray[np.uint8],
    l_state: NDArray[np.uint8],
    roi: BoolArray,
    free: BoolArray,
    candidates: BoolArray,
    global_walls: BoolArray | None,
    rules: _BesidePx,
) -> BoolArray:
    """:func:`small_structures_beside_walls` in one window (the arrays' shape; ``free``: the
    global map's occupied cells seen free in ``roi``; only structures through a cell of
    ``candidates``, cells of ``free``, are looked at)."""
    found = np.zeros(free.shape, bool)
    labels, stats, small = _small_components(g_state == OCCUPIED, rules.max_px)
    keep = (
        small
        & (stats[:, cv2.CC_STAT_AREA] >= rules.min_px)
        & (np.bincount(labels[candidates], minlength=len(small)) > 0)
    )
    for label in np.flatnonzero(keep):
        x, y, w, h = (int(v) for v in stats[label, :4])
        win = grown((slice(y, y + h), slice(x, x + w)), rules.room_px, labels.shape)
        own = labels[win] == label
        shown, compared = free[win][own], roi[win][own]
        if (l_state[win][own] == OCCUPIED).any() or shown.sum() < rules.min_share * compared.sum():
            continue
        g_win = g_state[win]
        if _near_deep_unknown(g_win, own.view(np.uint8), rules.depth_px, rules.around_px):
            continue
        others = ((labels[win] > 0) & ~own) | _unknown_specks(g_win, rules.max_px)
        if global_walls is not None:
            others |= global_walls[win] & ~own
        to_own = cv2.distanceTransform((~own).view(np.uint8), cv2.DIST_L2, 5)
        walls = (l_state[win] == OCCUPIED) & (to_own <= rules.reach_px)
        if (walls & (to_own <= distance_to(others) + rules.margin_px)).any():
            continue
        found[win] |= own & free[win]
    return found


def _unknown_specks(g_state: NDArray[np.uint8], max_px: float) -> BoolArray:
    """The global map's unknown cells in components (8-connected) no wider than ``max_px``
    either way and clear of the array's edge (:func:`_small_components`)."""
    labels, _, small = _small_components(g_state == UNKNOWN, max_px)
    return np.asarray(small[labels])


def _small_components(
    mask: BoolArray, max_px: float
) -> tuple[NDArray[np.int32], NDArray[np.int32], BoolArray]:
    """``mask``'s components (8-connected): their labels, OpenCV's stats, and per label
    whether it is no wider than ``max_px`` either way and clear of the array's edge (one
    through it may be wider than it shows); the background (label 0) is not."""
    labels, stats, clear = _components_clear_of_edge(mask)
    width, height = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    return labels, stats, clear & (width <= max_px) & (height <= max_px)


def _components_clear_of_edge(
    mask: BoolArray,
) -> tuple[NDArray[np.int32], NDArray[np.int32], BoolArray]:
    """``mask``'s components (8-connected): their labels, OpenCV's stats, and per label
    whether it stays clear of the array's edge (one through it may go on beyond); the
    background (label 0) does not."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    left, top = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    width, height = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    clear = (left > 0) & (top > 0)
    clear &= (left + width < labels.shape[1]) & (top + height < labels.shape[0])
    clear[0] = False
    return np.asarray(labels, np.int32), np.asarray(stats, np.int32), clear


__all__ = [
    "BesideRules",
    "CutRules",
    "DiffMasks",
    "LineRules",
    "distance_to",
    "drop_along_walls",
    "drop_small",
    "filter_noise",
    "misfit_tolerance",
    "near",
    "offset_distances",
    "raw_differences",
    "removal_evidence",
    "small_structures_beside_walls",
    "small_structures_gone",
    "thin_walls_seen_free",
    "walls_cut_through",
]
