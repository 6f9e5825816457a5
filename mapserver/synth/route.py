"""Route planning: a robot route through the free space of a map (:func:`plan_route`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.geometry import Pose2D
from mapserver.maps import FREE, OccupancyMap
from mapserver.synth._common import Seed, _as_rng, _Frame, _positive


@dataclass(frozen=True, eq=False)
class _PlanGrid:
    """A coarse planning grid over a window of a map: cells of ``k x k`` map pixels."""

    passable: NDArray[np.bool_]  # (h, w) [row, col]: some pixel of the cell has the clearance
    point_xy: NDArray[np.float64]  # (h, w, 2) nav2 metres of each cell's waypoint
    clearance_m: NDArray[np.float32]  # (H, W) window pixels: distance to the nearest non-free pixel
    frame: _Frame
    k: int

    @property
    def cell_m(self) -> float:
        return self.k * self.frame.resolution

    def clearance_at(self, xy: NDArray[np.float64]) -> NDArray[np.float32]:
        uv = np.floor(self.frame.uv(xy)).astype(int)
        h, w = self.clearance_m.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        out = np.full(len(uv), -1.0, np.float32)
        out[inside] = self.clearance_m[uv[inside, 1], uv[inside, 0]]
        return out


def _plan_grid(
    world: OccupancyMap,
    state: NDArray[np.uint8],
    rows: tuple[int, int],
    cols: tuple[int, int],
    clearance_m: float,
) -> _PlanGrid:
    res = world.resolution
    free = (state[rows[0] : rows[1], cols[0] : cols[1]] == FREE).astype(np.uint8)
    free[0, :] = free[-1, :] = 0  # the window's edge counts as a wall
    free[:, 0] = free[:, -1] = 0
    dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    clearance = ((dist - 0.5) * res).astype(np.float32)
    # A cell a third of the clearance wide: neighbouring waypoints are close enough that the
    # straight line between them keeps well clear of walls (the distance map is 1-Lipschitz).
    k = max(1, round(min(0.25, clearance_m / 3) / res))
    h, w = clearance.shape[0] // k, clearance.shape[1] // k
    if h < 1 or w < 1:
        raise ValueError("the map is too small to plan a route on")
    blocks = clearance[: h * k, : w * k].reshape(h, k, w, k).transpose(0, 2, 1, 3).reshape(h, w, -1)
    best = blocks.argmax(axis=2)
    best_val = np.take_along_axis(blocks, best[..., None], 2)[..., 0]
    mid = k // 2
    use_mid = clearance[mid : h * k : k, mid : w * k : k] >= clearance_m
    br = np.where(use_mid, mid, best // k) + np.arange(h)[:, None] * k
    bc = np.where(use_mid, mid, best % k) + np.arange(w)[None, :] * k
    frame = _Frame(res, world.origin, world.height, rows[0], cols[0])
    point_xy = frame.xy(np.stack([bc + 0.5, br + 0.5], -1))
    return _PlanGrid(best_val >= clearance_m, point_xy, clearance, frame, k)


def _wavefront(
    passable: NDArray[np.bool_], start: tuple[int, int], max_steps: int
) -> tuple[NDArray[np.int32], int, int]:
    """Grid steps (8-connected) from ``start`` within ``max_steps``; -1 where not reached.
    Returns the distances over a sub-window and its (row, col) offset."""
    h, w = passable.shape
    r0, c0 = max(0, start[0] - max_steps), max(0, start[1] - max_steps)
    r1, c1 = min(h, start[0] + max_steps + 1), min(w, start[1] + max_steps + 1)
    sub = passable[r0:r1, c0:c1]
    dist = np.full(sub.shape, -1, np.int32)
    front = np.zeros(sub.shape, np.uint8)
    front[start[0] - r0, start[1] - c0] = 1
    dist[start[0] - r0, start[1] - c0] = 0
    seen = front.astype(bool)
    kernel = np.ones((3, 3), np.uint8)
    for step in range(1, max_steps + 1):
        grown = (cv2.dilate(front, kernel) > 0) & sub & ~seen
        if not grown.any():
            break
        dist[grown] = step
        seen |= grown
        front = grown.astype(np.uint8)
    return dist, r0, c0


def _backtrack(
    dist: NDArray[np.int32], goal: tuple[int, int], start: tuple[int, int]
) -> list[tuple[int, int]]:
    """Cells from ``start`` to ``goal`` down the wavefront, preferring the straightest steps."""
    h, w = dist.shape
    path = [goal]
    r, c = goal
    while dist[r, c] > 0:
        d = dist[r, c]
        best: tuple[int, int] | None = None
        best_score = math.inf
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if 0 <= rr < h and 0 <= cc < w and dist[rr, cc] == d - 1:
                    score = (rr - start[0]) ** 2 + (cc - start[1]) ** 2
                    if score < best_score:
                        best, best_score = (rr, cc), score
        assert best is not None
        r, c = best
        path.append(best)
    return path[::-1]


def _explore(
    grid: _PlanGrid,
    start: tuple[int, int],
    length_m: float,
    rng: np.random.Generator,
    *,
    hop_m: tuple[float, float] = (2.0, 12.0),
) -> NDArray[np.float64]:
    """Waypoints (N, 2) of a walk from cell ``start``: hops of ``hop_m`` to goals away from where
    the walk has been, joined by shortest grid paths, until ``length_m`` is covered."""
    dmin = max(1, round(hop_m[0] / grid.cell_m))
    dmax = max(dmin + 1, round(hop_m[1] / grid.cell_m))
    visited = np.zeros(grid.passable.shape, np.uint8)
    visited[start] = 1
    cells = [start]
    total, current = 0.0, start
    for _ in range(10_000):
        if total >= length_m:
            break
        dist, r0, c0 = _wavefront(grid.passable, current, dmax)
        candidates = np.argwhere(dist >= dmin)
        if len(candidates) == 0:
            candidates = np.argwhere(dist >= 1)
            if len(candidates) == 0:
                break
        seen = visited[r0 : r0 + dist.shape[0], c0 : c0 + dist.shape[1]]
        novelty = cv2.distanceTransform((seen == 0).astype(np.uint8), cv2.DIST_L2, 3)
        weight = (novelty[candidates[:, 0], candidates[:, 1]].astype(float) + 0.5) ** 2
        goal = candidates[rng.choice(len(candidates), p=weight / weight.sum())]
        segment = _backtrack(dist, (int(goal[0]), int(goal[1])), (current[0] - r0, current[1] - c0))
        segment = [(r + r0, c + c0) for r, c in segment]
        rr, cc = np.array(segment).T
        pts = grid.point_xy[rr, cc]
        total += float(np.hypot(*np.diff(pts, axis=0).T).sum())
        cells.extend(segment[1:])
        visited[rr, cc] = 1
        current = segment[-1]
    rr, cc = np.array(cells).T
    return np.asarray(grid.point_xy[rr, cc])


def _dedupe(pts: NDArray[np.float64]) -> NDArray[np.float64]:
    keep = np.ones(len(pts), bool)
    keep[1:] = np.hypot(*np.diff(pts, axis=0).T) > 1e-9
    return pts[keep]


def _path_to_poses(
    grid: _PlanGrid, pts: NDArray[np.float64], length_m: float, step_m: float, clearance_m: float
) -> list[Pose2D]:
    raw = _dedupe(pts)
    smooth = raw.copy()
    for _ in range(6):
        smooth[1:-1] = (smooth[:-2] + 2 * smooth[1:-1] + smooth[2:]) / 4
    too_close = grid.clearance_at(smooth) < 0.75 * clearance_m
    smooth[too_close] = raw[too_close]
    smooth = _dedupe(smooth)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(smooth, axis=0).T))])
    total = min(length_m, float(arc[-1]))
    s = np.arange(math.floor(total / step_m + 1e-9) + 1) * step_m
    if total - s[-1] > 0.5 * step_m:
        s = np.append(s, total)
    x, y = np.interp(s, arc, smooth[:, 0]), np.interp(s, arc, smooth[:, 1])
    if len(s) < 2:
        return [Pose2D(float(x[0]), float(y[0]), 0.0)]
    yaw = np.arctan2(np.diff(y), np.diff(x))
    yaw = np.append(yaw, yaw[-1])
    return [Pose2D(float(a), float(b), float(c)) for a, b, c in zip(x, y, yaw, strict=True)]


def _random_free_pixel(state: NDArray[np.uint8], rng: np.random.Generator) -> tuple[int, int]:
    h, w = state.shape
    for _ in range(64):
        rows, cols = rng.integers(0, h, 4096), rng.integers(0, w, 4096)
        hit = np.flatnonzero(state[rows, cols] == FREE)
        if hit.size:
            return int(rows[hit[0]]), int(cols[hit[0]])
    idx = np.flatnonzero(state == FREE)
    if idx.size == 0:
        raise ValueError("the map has no free cells")
    r, c = divmod(int(idx[rng.integers(idx.size)]), w)
    return r, c


def plan_route(
    world: OccupancyMap,
    *,
    length_m: float,
    rng: Seed,
    clearance_m: float = 0.4,
    step_m: float = 0.25,
) -> list[Pose2D]:
    """Plan a robot route through the free space of a map.

    The route hops between random goals 2-12 m apart, each chosen away from where the route has
    already been, joined by shortest paths on a coarse grid of cells with ``clearance_m`` to the
    nearest occupied or unknown cell, smoothed, and resampled every ``step_m``.

    Parameters
    ----------
    world
        The map (nav2 frame). Only FREE cells are driven through.
    length_m
        Route length in metres (shorter when the reachable space cannot give it without running
        out of goals, which only happens in a space a few cells wide).
    rng
        Generator or seed.
    clearance_m
        Waypoints keep this distance (metres) from non-free cells; the interpolated poses
        between them keep at least a quarter of it.
    step_m
        Spacing of the poses along the route, metres.

    Returns
    -------
    list of Pose2D
        Nav2-frame poses, oldest first, ``yaw`` along the direction of travel (radians).
    """
    _positive("length_m", length_m)
    _positive("clearance_m", clearance_m)
    _positive("step_m", step_m)
    rng = _as_rng(rng)
    state, res = world.state, world.resolution
    h, w = state.shape
    half = math.ceil((length_m + 2 * clearance_m + 1.0) / res)
    for _ in range(30):
        sr, sc = _random_free_pixel(state, rng)
        rows = (max(0, sr - half), min(h, sr + half + 1))
        cols = (max(0, sc - half), min(w, sc + half + 1))
        grid = _plan_grid(world, state, rows, cols, clearance_m)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(
            grid.passable.astype(np.uint8), connectivity=8
        )
        if n < 2:
            continue
        biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if stats[biggest, cv2.CC_STAT_AREA] < 2:
            continue
        cells = np.argwhere(labels == biggest)
        seed_cell = np.array([(sr - rows[0]) // grid.k, (sc - cols[0]) // grid.k])
        start = cells[int(np.argmin(((cells - seed_cell) ** 2).sum(1)))]
        pts = _explore(grid, (int(start[0]), int(start[1])), length_m + 1.0, rng)
        poses = _path_to_poses(grid, pts, length_m, step_m, clearance_m)
        xy = np.array([(p.x, p.y) for p in poses])
        if np.all(grid.clearance_at(xy) > 0):
            return poses
    raise ValueError(f"no free space with clearance {clearance_m} m to plan a route in")
