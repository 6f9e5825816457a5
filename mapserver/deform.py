"""SLAM drift: small, smooth corrections on top of the rigid alignment.

slam_toolbox without loop closure bends a long session's map, so no single rigid transform fits
it everywhere (0.1-0.3 m off at the far end of a 100 m route). A wall doubled by drift is not a
change. This module estimates, on a lattice of nodes over the local map, the small translation
that best lays each neighbourhood's walls onto the global walls, smooths those shifts, and warps
the local map with the resulting displacement field.

Pure functions; points are (N, 2) arrays of metres, arrays are indexed ``[row, col]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.align import NearestWall
from mapserver.geometry import Transform2D
from mapserver.grid import Grid, landing_box, resample
from mapserver.maps import UNKNOWN, OccupancyMap

FloatArray = NDArray[np.float64]
# warp_local's node spacing, a power of two: a grid cropped at multiples of it warps to the
# same cells.
WARP_STEP_PX = 8


@dataclass(frozen=True)
class DriftField:
    """Shifts (nav2 metres) to add after ``nav2_from_slam``, on a lattice in the slam frame.

    ``shifts`` has shape (rows, cols, 2); node (i, j) sits at slam ``(x0 + j * spacing,
    y0 + i * spacing)``.
    """

    x0: float
    y0: float
    spacing: float
    shifts: NDArray[np.float32]

    def at(self, xy_slam: FloatArray) -> FloatArray:
        """Bilinearly interpolated shifts at slam points (N, 2) -> (N, 2)."""
        rows, cols = self.shifts.shape[:2]
        u = np.clip((xy_slam[:, 0] - self.x0) / self.spacing, 0.0, cols - 1.0)
        v = np.clip((xy_slam[:, 1] - self.y0) / self.spacing, 0.0, rows - 1.0)
        j0 = np.minimum(np.floor(u).astype(np.int64), cols - 2)
        i0 = np.minimum(np.floor(v).astype(np.int64), rows - 2)
        fu, fv = (u - j0)[:, None], (v - i0)[:, None]
        s = self.shifts.astype(np.float64)
        top = s[i0, j0] * (1 - fu) + s[i0, j0 + 1] * fu
        bottom = s[i0 + 1, j0] * (1 - fu) + s[i0 + 1, j0 + 1] * fu
        return np.asarray(top * (1 - fv) + bottom * fv)

    def max_shift_m(self) -> float:
        return float(np.sqrt((self.shifts**2).sum(axis=2)).max()) if self.shifts.size else 0.0


@dataclass(frozen=True)
class DriftStack:
    """Several drift fields applied together: their shifts add up (coarse, then finer)."""

    fields: tuple[DriftField, ...]

    def at(self, xy_slam: FloatArray) -> FloatArray:
        out = np.zeros((len(xy_slam), 2))
        for f in self.fields:
            out += f.at(xy_slam)
        return out

    def max_shift_m(self) -> float:
        """The largest combined shift, read at the nodes of the finest field."""
        if not self.fields:
            return 0.0
        finest = min(self.fields, key=lambda f: f.spacing)
        rows, cols = finest.shifts.shape[:2]
        jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
        nodes = np.stack(
            [finest.x0 + jj.ravel() * finest.spacing, finest.y0 + ii.ravel() * finest.spacing], 1
        )
        return float(np.hypot(*self.at(nodes).T).max())


def _fill_missing(values: NDArray[np.float32], valid: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Fill nodes without an estimate from their valid neighbours (normalised blur, repeated)."""
    out = values.copy()
    weight = valid.astype(np.float32)
    known = valid.copy()
    for _ in range(max(values.shape[:2])):
        if known.all():
            break
        w = cv2.blur(weight, (3, 3), borderType=cv2.BORDER_CONSTANT)
        grown = (w > 0) & ~known
        for k in range(2):
            s = cv2.blur(out[:, :, k] * weight, (3, 3), borderType=cv2.BORDER_CONSTANT)
            out[:, :, k] = np.where(grown, s / np.maximum(w, 1e-6), out[:, :, k])
        weight = np.where(grown, 1.0, weight).astype(np.float32)
        known |= grown
    return out


def estimate_drift(
    walls_slam: FloatArray,
    nav2_from_slam: Transform2D,
    grid: Grid,
    nearest: NearestWall,
    *,
    tile_m: float = 6.0,
    max_shift_m: float = 0.4,
    min_points: int = 40,
    iterations: int = 12,
    initial: DriftField | DriftStack | None = None,
) -> DriftField:
    """Per-node translation (nav2 metres) that lays nearby local walls onto global walls.

    Each node uses the walls within a square of side ``tile_m`` around it; nodes with fewer than
    ``min_points`` walls, or whose walls barely match, borrow from their neighbours. The shifts
    are median-filtered (an odd node is an outlier, not drift) and clipped to ``max_shift_m``.
    ``nearest`` is the field of the nearest global walls on ``grid``. With ``initial``, the shifts are estimated on top of that field's (a finer pass
    after a coarse one).
    """
    spacing = tile_m / 2.0
    lo = walls_slam.min(axis=0) - spacing
    hi = walls_slam.max(axis=0) + spacing
    cols = max(2, math.ceil((hi[0] - lo[0]) / spacing) + 1)
    rows = max(2, math.ceil((hi[1] - lo[1]) / spacing) + 1)
    base = nav2_from_slam.apply(walls_slam)
    if initial is not None:
        base = base + initial.at(walls_slam)
    node_i = np.floor((walls_slam[:, 1] - lo[1]) / spacing + 0.5).astype(int)
    node_j = np.floor((walls_slam[:, 0] - lo[0]) / spacing + 0.5).astype(int)
    # All nodes at once: one (node, point) pair for every wall point and each of the 3 x 3
    # nodes around its nearest one, sorted by node and then point, so that the per-node sums
    # below add the same numbers in the same order as a loop over the nodes would.
    nodes, points = [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            i, j = node_i + di, node_j + dj
            ok = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
            nodes.append((i * cols + j)[ok])
            points.append(np.flatnonzero(ok))
    node, point = np.concatenate(nodes), np.concatenate(points)
    order = np.lexsort((point, node))
    node, point = node[order], point[order]
    n_nodes = rows * cols
    active = np.bincount(node, minlength=n_nodes) >= min_points
    shift_x, shift_y = np.zeros(n_nodes), np.zeros(n_nodes)
    used = np.zeros(n_nodes, np.int64)
    bx, by = base[:, 0].copy(), base[:, 1].copy()
    for k in range(iterations):
        keep = active[node]
        node, point = node[keep], point[keep]
        if len(node) == 0:
            break
        limit = max_shift_m * (1.0 - 0.5 * k / max(iterations - 1, 1))
        qx = bx[point] + shift_x[node]
        qy = by[point] + shift_y[node]
        wx, wy = nearest.nearest_xy(qx, qy, grid)  # points off the field: never within limit
        rx, ry = wx - qx, wy - qy
        use = rx * rx + ry * ry <= limit * limit
        node_used = node[use]
        counted = np.bincount(node_used, minlength=n_nodes)
        used[active] = counted[active]
        active &= counted >= min_points // 2
        sum_x = np.bincount(node_used, weights=rx[use], minlength=n_nodes)
        sum_y = np.bincount(node_used, weights=ry[use], minlength=n_nodes)
        n_act = counted[active]
        step_x = shift_x[active] + sum_x[active] / n_act
        step_y = shift_y[active] + sum_y[active] / n_act
        norm = np.hypot(step_x, step_y)
        scale = np.where(norm > max_shift_m, max_shift_m / np.maximum(norm, 1e-12), 1.0)
        shift_x[active] = step_x * scale
        shift_y[active] = step_y * scale
    shift = np.stack([shift_x, shift_y], axis=1)
    valid = (used >= min_points // 2).reshape(rows, cols)
    shifts = np.where(valid[:, :, None], shift.reshape(rows, cols, 2), 0.0).astype(np.float32)
    if not valid.any():
        return DriftField(
            float(lo[0]), float(lo[1]), spacing, np.zeros((rows, cols, 2), np.float32)
        )
    shifts = _fill_missing(shifts, valid)
    for k in range(2):
        shifts[:, :, k] = cv2.medianBlur(np.ascontiguousarray(shifts[:, :, k]), 3)
    return DriftField(float(lo[0]), float(lo[1]), spacing, shifts)


def _source_coords(
    cols: FloatArray,
    rows: FloatArray,
    local: OccupancyMap,
    grid: Grid,
    nav2_from_slam: Transform2D,
    drift: DriftField | DriftStack | None,
) -> tuple[FloatArray, FloatArray]:
    """Fractional local-map (col, row) that lands on grid pixels (cols, rows)."""
    m = nav2_from_slam.inverse().matrix() @ grid.world_from_pixel()
    sx = m[0, 0] * cols + m[0, 1] * rows + m[0, 2]
    sy = m[1, 0] * cols + m[1, 1] * rows + m[1, 2]
    if drift is not None:
        shape = sx.shape
        d = drift.at(np.stack([sx.ravel(), sy.ravel()], axis=1))
        c, s = math.cos(nav2_from_slam.theta), math.sin(nav2_from_slam.theta)
        # The shift is in nav2; bring it into the slam frame and move the source back by it.
        sx = sx - (c * d[:, 0] + s * d[:, 1]).reshape(shape)
        sy = sy - (-s * d[:, 0] + c * d[:, 1]).reshape(shape)
    u, v = local.world_to_pixel(sx, sy)
    return u, v


# A box of a grid, (row0, row1, col0, col1), and the states a warp puts in it.
Landed = tuple[tuple[int, int, int, int], NDArray[np.uint8]]


def warp_local(
    local: OccupancyMap,
    grid: Grid,
    nav2_from_slam: Transform2D,
    drift: DriftField | DriftStack | None = None,
) -> NDArray[np.uint8]:
    """The local map's states on ``grid`` (nav2), through the rigid transform and the drift
    (see :func:`warp_local_box`; every cell off its box is unknown)."""
    if drift is None:
        return resample(local.state, Grid.of_map(local), grid, nav2_from_slam)
    out = np.full(grid.shape, UNKNOWN, np.uint8)
    landed = warp_local_box(local, grid, nav2_from_slam, drift)
    if landed is not None:
        (r0, r1, c0, c1), states = landed
        out[r0:r1, c0:c1] = states
    return out


def warp_local_box(
    local: OccupancyMap,
    grid: Grid,
    nav2_from_slam: Transform2D,
    drift: DriftField | DriftStack | None = None,
) -> Landed | None:
    """The box of ``grid`` (nav2) the local map's known cells land in, through the rigid
    transform and the drift, and the states there; None when none lands on the grid. Only that
    box is computed and held: a piece of a long route lands on a small part of the view.

    For a grid cell at nav2 point ``x`` the source is ``T^-1(x - shift(T^-1 x))``: the shift is
    small and smooth, so evaluating it at the rigid pre-image is exact enough. The source
    coordinates are computed on nodes every ``WARP_STEP_PX`` pixels and interpolated linearly in
    between, which is exact for the rigid part and as smooth as the drift field itself. The box
    starts on a multiple of the step (a power of two), so the nodes and their interpolation
    weights are those of the whole grid.
    """
    if drift is None:
        box = landing_box(local, grid, nav2_from_slam)
        if box is None:
            return None
        return box, resample(local.state, Grid.of_map(local), grid.crop(box), nav2_from_slam)
    s = WARP_STEP_PX
    margin_px = drift.max_shift_m() / grid.resolution + 2.0
    box = landing_box(local, grid, nav2_from_slam, margin_px=margin_px, step_px=s)
    if box is None:
        return None
    r0, r1, c0, c1 = box
    # Nodes at the positions cv2.resize samples for an upscale by s, starting one step before
    # the box so that its border replication never reaches a kept pixel. The box starts on a
    # multiple of s, so these are the nodes (and the pixels) of the whole grid's warp.
    n_cols = math.ceil((c1 - c0) / s) + 2
    n_rows = math.ceil((r1 - r0) / s) + 2
    node_c = (np.arange(n_cols) + 0.5) * s - 0.5 - s + c0
    node_r = (np.arange(n_rows) + 0.5) * s - 0.5 - s + r0
    cc, rr = np.meshgrid(node_c, node_r)
    u, v = _source_coords(cc, rr, local, grid, nav2_from_slam, drift)
    size = (n_cols * s, n_rows * s)
    full_u = cv2.resize(u.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    full_v = cv2.resize(v.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    full_u = np.ascontiguousarray(full_u[s : s + r1 - r0, s : s + c1 - c0])
    full_v = np.ascontiguousarray(full_v[s : s + r1 - r0, s : s + c1 - c0])
    states = cv2.remap(
        local.state,
        full_u,
        full_v,
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=UNKNOWN,
    )
    return box, np.asarray(states, np.uint8)
