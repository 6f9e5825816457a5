"""Synthetic bundles with known truth: generated buildings, planted changes, simulated SLAM sessions.

The simulator stands in for a robot and its fleet. It plans a route through a global map, changes
the true world along it (obstacles added, structures removed, people standing about), drives the
route with a 2-D lidar and a drifting SLAM pose estimate, and builds the local map slam_toolbox
would have saved. Unit tests, the demo data and the speed benchmarks use it.

Conventions (contract section 1): arrays are indexed ``[row, col]`` with row 0 at the top; metres
and radians; ``nav2_from_slam`` maps slam points to nav2 points, ``p_nav2 = R(theta) p_slam + t``.
A map's origin yaw is ignored, as Nav2 ignores it. Every random step takes ``rng``: a
``numpy.random.Generator`` or an int seed, so a seed fixes every output.

Inside, points are often handled in continuous pixel coordinates ``(u, v)`` of a map ``h`` rows
tall: ``u = (x - ox) / r`` and ``v = h - (y - oy) / r``, so that pixel ``(row k, col c)`` covers
``c <= u < c + 1`` and ``k <= v < k + 1``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from mapserver.bundle import is_valid_bundle_id, sha256_file
from mapserver.geometry import Pose2D, Transform2D, wrap_angle
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, save_map

__all__ = [
    "Change",
    "DriftReport",
    "Session",
    "SyntheticBundle",
    "make_airport_map",
    "make_office_map",
    "make_scenario",
    "plan_route",
    "plant_changes",
    "roughen_map",
    "simulate_session",
    "write_bundle",
    "write_scenario",
    "write_truth",
]

Seed = int | np.random.Generator
_SHIFT = 4  # sub-pixel bits for cv2 drawing
_ONE = 1 << _SHIFT


def _as_rng(rng: Seed) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, int | np.integer) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise TypeError(f"rng must be a numpy Generator or an int seed, got {type(rng).__name__}")


def _positive(name: str, value: float) -> None:
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be > 0, got {value}")


# --------------------------------------------------------------------------------------------
# Shapes and rasterisation
# --------------------------------------------------------------------------------------------


def _rect_poly(
    cx: float, cy: float, length: float, width: float, angle: float
) -> NDArray[np.float64]:
    """(4, 2) corners of a rectangle centred at (cx, cy), ``length`` along ``angle``."""
    c, s = math.cos(angle), math.sin(angle)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], float) * (length / 2, width / 2)
    return np.asarray(half @ np.array([[c, s], [-s, c]]) + (cx, cy), float)


def _circle_poly(cx: float, cy: float, radius: float, n: int = 16) -> NDArray[np.float64]:
    a = np.arange(n) * (2 * math.pi / n)
    return np.stack([cx + radius * np.cos(a), cy + radius * np.sin(a)], 1)


def _hull(points: NDArray[np.float64]) -> NDArray[np.float64]:
    hull = cv2.convexHull(np.asarray(points, np.float32))
    return np.asarray(hull, np.float64).reshape(-1, 2)


def _fill_uv(
    mask: NDArray[np.uint8], polys_uv: Sequence[NDArray[np.float64]], value: int = 1
) -> None:
    """Fill polygons given in continuous pixel coordinates of ``mask`` (pixel centres at +0.5)."""
    pts = [np.round((np.asarray(p, float) - 0.5) * _ONE).astype(np.int32) for p in polys_uv]
    cv2.fillPoly(mask, pts, value, cv2.LINE_8, _SHIFT)


@dataclass(frozen=True, eq=False)
class _Frame:
    """Pixel geometry of a window ``[row0:row0+h, col0:col0+w]`` of a map ``world_h`` rows tall."""

    resolution: float
    origin: tuple[float, float, float]
    world_h: int
    row0: int = 0
    col0: int = 0

    def uv(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Window pixel coordinates (u, v) of nav2 points (..., 2)."""
        xy = np.asarray(xy, float)
        u = (xy[..., 0] - self.origin[0]) / self.resolution - self.col0
        v = self.world_h - (xy[..., 1] - self.origin[1]) / self.resolution - self.row0
        return np.stack([u, v], -1)

    def xy(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        uv = np.asarray(uv, float)
        x = self.origin[0] + (uv[..., 0] + self.col0) * self.resolution
        y = self.origin[1] + (self.world_h - uv[..., 1] - self.row0) * self.resolution
        return np.stack([x, y], -1)


def _footprint(
    frame: _Frame, shape: tuple[int, int], polys_xy: Sequence[NDArray[np.float64]]
) -> tuple[int, int, NDArray[np.bool_]] | None:
    """Pixels of polygons (nav2 metres) in a window: ``(row, col, mask)`` of their bounding box,
    or None when they leave the window."""
    uvs = [frame.uv(p) for p in polys_xy]
    allp = np.concatenate(uvs)
    u0, v0 = np.floor(allp.min(0)).astype(int) - 1
    u1, v1 = np.ceil(allp.max(0)).astype(int) + 1
    if u0 < 0 or v0 < 0 or u1 > shape[1] or v1 > shape[0]:
        return None
    mask = np.zeros((v1 - v0, u1 - u0), np.uint8)
    _fill_uv(mask, [p - (u0, v0) for p in uvs])
    if not mask.any():
        return None
    return int(v0), int(u0), mask.astype(bool)


def _cells_hull(frame: _Frame, r0: int, c0: int, mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Convex hull (nav2 metres) of the squares of the ``True`` pixels of ``mask`` at (r0, c0)."""
    rr, cc = np.nonzero(mask)
    corners = np.concatenate(
        [np.stack([cc + du + c0, rr + dv + r0], 1) for du in (0, 1) for dv in (0, 1)]
    ).astype(float)
    return frame.xy(_hull(corners))


# --------------------------------------------------------------------------------------------
# Route planning
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Planted changes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Change:
    """A difference between the global map and the true world during a session.

    Attributes
    ----------
    id
        1, 2, ... within a scenario.
    kind
        ``added`` (occupied now, free in the global map), ``removed`` (the reverse) or
        ``temporary`` (a person or a group standing together).
    shape
        What it is: ``box``, ``column``, ``wall``, ``structure``, ``person`` or ``group``.
    polygon
        Outline in the nav2 frame, metres: the shape itself, or the convex hull of the erased
        cells (removed) or of the people of a group.
    observed
        The local map shows it (contract section 4); set by :func:`make_scenario`.
    """

    id: int
    kind: str
    shape: str
    polygon: tuple[tuple[float, float], ...]
    observed: bool = False


@dataclass(frozen=True, eq=False)
class _Site:
    """A window of the true world around the route, being changed."""

    frame: _Frame
    state: NDArray[np.uint8]  # view into the true world being built
    before: NDArray[np.uint8]  # the original map, same window
    d_route_m: NDArray[np.float32]  # distance to the route polyline
    blocked: NDArray[np.bool_]  # near an earlier change
    route_uv: NDArray[np.float64]  # (N, 2)

    def region(self, r0: int, c0: int, mask: NDArray[np.bool_]) -> tuple[slice, slice]:
        return slice(r0, r0 + mask.shape[0]), slice(c0, c0 + mask.shape[1])


def _visible(
    site: _Site, target_uv: NDArray[np.float64], r0: int, c0: int, mask: NDArray[np.bool_]
) -> bool:
    """Is the straight line from the nearest route pose to ``target_uv`` free until it meets the
    footprint ``mask`` at (r0, c0)?"""
    d = np.hypot(*(site.route_uv - target_uv).T)
    a = site.route_uv[int(np.argmin(d))]
    n = max(2, int(d.min() * 2))
    pts = np.floor(a + np.linspace(0, 1, n)[:, None] * (target_uv - a)).astype(int)
    for u, v in pts:
        if 0 <= v - r0 < mask.shape[0] and 0 <= u - c0 < mask.shape[1] and mask[v - r0, u - c0]:
            return True
        if site.state[v, u] != FREE:
            return False
    return True


def _candidates(site: _Site, lo_m: float, hi_m: float) -> NDArray[np.intp]:
    ok = (site.state == FREE) & (site.d_route_m >= lo_m) & (site.d_route_m <= hi_m) & ~site.blocked
    return np.flatnonzero(ok)


def _place_added(
    site: _Site,
    rng: np.random.Generator,
    clearance_m: float,
    distance_m: tuple[float, float],
    attempts: int,
) -> tuple[str, NDArray[np.float64], tuple[int, int, NDArray[np.bool_]]] | None:
    idx = _candidates(site, *distance_m)
    if idx.size == 0:
        return None
    w = site.state.shape[1]
    for attempt in range(attempts):
        r, c = divmod(int(idx[rng.integers(idx.size)]), w)
        cx, cy = site.frame.xy(np.array([c + 0.5, r + 0.5]))
        shape = str(rng.choice(["box", "column", "wall"], p=[0.45, 0.3, 0.25]))
        if shape == "box":
            poly = _rect_poly(
                cx, cy, rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2), rng.uniform(0, math.pi)
            )
        elif shape == "column":
            d = rng.uniform(0.3, 0.6)
            if rng.random() < 0.6:
                poly = _circle_poly(cx, cy, d / 2)
            else:
                poly = _rect_poly(cx, cy, d, d, rng.uniform(0, math.pi / 2))
        else:
            angle = (
                rng.choice([0.0, math.pi / 2]) if rng.random() < 0.6 else rng.uniform(0, math.pi)
            )
            poly = _rect_poly(cx, cy, rng.uniform(2.0, 4.0), rng.uniform(0.15, 0.25), angle)
        fp = _footprint(site.frame, site.state.shape, [poly])
        if fp is None:
            continue
        r0, c0, mask = fp
        reg = site.region(r0, c0, mask)
        if (
            np.any(site.state[reg][mask] != FREE)
            or site.d_route_m[reg][mask].min() < clearance_m + 0.1
            or site.blocked[reg][mask].any()
        ):
            continue
        # Most of the time insist on a line of sight from the route, so that most changes are seen.
        if attempt < 0.7 * attempts and not _visible(
            site, np.array([c + 0.5, r + 0.5]), r0, c0, mask
        ):
            continue
        return shape, poly, fp
    return None


def _place_removed(
    site: _Site, rng: np.random.Generator, distance_m: tuple[float, float], attempts: int
) -> tuple[str, NDArray[np.float64], tuple[int, int, NDArray[np.bool_]]] | None:
    res = site.frame.resolution
    occ = ((site.state == OCCUPIED) & (site.before == OCCUPIED)).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(occ, connectivity=8)
    free = (site.state == FREE).astype(np.uint8)
    near_free = cv2.dilate(free, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)) > 0
    ok = (occ > 0) & near_free & (site.d_route_m >= max(0.5, distance_m[0] - 0.5))
    ok &= (site.d_route_m <= distance_m[1]) & ~site.blocked
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return None
    h, w = occ.shape
    for _ in range(attempts):
        r, c = divmod(int(idx[rng.integers(idx.size)]), w)
        lab = labels[r, c]
        x, y, bw, bh, area = stats[lab]
        touches_edge = x == 0 or y == 0 or x + bw == w or y + bh == h
        if math.hypot(bw, bh) * res <= 3.5 and area * res * res <= 4.0 and not touches_edge:
            # A whole small structure (a column, a shelf): with any unknown cells it encloses.
            comp = (labels[y : y + bh, x : x + bw] == lab).astype(np.uint8)
            contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            filled = np.zeros_like(comp)
            cv2.drawContours(filled, contours, -1, 1, thickness=-1)
            r0, c0 = int(y), int(x)
            erase = (filled > 0) & (site.state[y : y + bh, x : x + bw] != FREE)
        else:
            # A piece of a long structure: the part within a disc around the chosen surface cell.
            rad = max(1.5, rng.uniform(0.3, 0.9) / res)
            ir = math.ceil(rad)
            r0, c0 = max(0, r - ir), max(0, c - ir)
            r1, c1 = min(h, r + ir + 1), min(w, c + ir + 1)
            rr, cc = np.mgrid[r0:r1, c0:c1]
            erase = ((rr - r) ** 2 + (cc - c) ** 2 <= rad * rad) & (labels[r0:r1, c0:c1] == lab)
        if erase.sum() < 3:
            continue
        # The structure must stand inside the known building: erasing it may not open onto
        # unknown space, nor touch an earlier change.
        p = 2
        if r0 - p < 0 or c0 - p < 0 or r0 + erase.shape[0] + p > h or c0 + erase.shape[1] + p > w:
            continue
        padded = np.pad(erase.astype(np.uint8), p)
        ring = (cv2.dilate(padded, np.ones((2 * p + 1, 2 * p + 1), np.uint8)) > 0) & (padded == 0)
        reg = (slice(r0 - p, r0 - p + padded.shape[0]), slice(c0 - p, c0 - p + padded.shape[1]))
        if np.any(site.before[reg][ring] == UNKNOWN) or site.blocked[reg][padded > 0].any():
            continue
        return "structure", _cells_hull(site.frame, r0, c0, erase), (r0, c0, erase)
    return None


def _place_people(
    site: _Site,
    rng: np.random.Generator,
    clearance_m: float,
    distance_m: tuple[float, float],
    attempts: int,
) -> tuple[str, NDArray[np.float64], tuple[int, int, NDArray[np.bool_]]] | None:
    idx = _candidates(site, *distance_m)
    if idx.size == 0:
        return None
    w = site.state.shape[1]
    for _ in range(attempts):
        r, c = divmod(int(idx[rng.integers(idx.size)]), w)
        cx, cy = site.frame.xy(np.array([c + 0.5, r + 0.5]))
        people = [(cx, cy, rng.uniform(0.2, 0.3))]
        size = 1 if rng.random() < 0.6 else int(rng.integers(2, 5))
        for _ in range(20 * size):
            if len(people) == size:
                break
            px, py, _pr = people[int(rng.integers(len(people)))]
            a, d, rad = rng.uniform(0, 2 * math.pi), rng.uniform(0.5, 0.9), rng.uniform(0.2, 0.3)
            qx, qy = px + d * math.cos(a), py + d * math.sin(a)
            if all(math.hypot(qx - ox, qy - oy) >= rad + orad + 0.05 for ox, oy, orad in people):
                people.append((qx, qy, rad))
        discs = [_circle_poly(x, y, rad, 24) for x, y, rad in people]
        fp = _footprint(site.frame, site.state.shape, discs)
        if fp is None:
            continue
        r0, c0, mask = fp
        reg = site.region(r0, c0, mask)
        if (
            np.any(site.state[reg][mask] != FREE)
            or site.d_route_m[reg][mask].min() < clearance_m + 0.1
            or site.blocked[reg][mask].any()
        ):
            continue
        if len(people) == 1:
            return "person", _circle_poly(cx, cy, people[0][2], 16), fp
        return "group", _hull(np.concatenate([_circle_poly(x, y, rad) for x, y, rad in people])), fp
    return None


def plant_changes(
    world: OccupancyMap,
    route: Sequence[Pose2D],
    *,
    n_added: int,
    n_removed: int,
    n_people: int,
    rng: Seed,
    clearance_m: float = 0.4,
    distance_m: tuple[float, float] = (1.0, 6.0),
    people_distance_m: tuple[float, float] = (0.8, 4.0),
    attempts: int = 200,
) -> tuple[NDArray[np.uint8], tuple[Change, ...]]:
    """Change the true world along a route.

    Added: boxes (0.4-1.2 m sides), columns (0.3-0.6 m, round or square) and short walls
    (2-4 m x 0.15-0.25 m), solid, in free space ``distance_m`` from the route. Removed: a whole
    small structure (a column, a shelf: a connected occupied component up to 4 m2, with any
    unknown cells it encloses) or a 0.6-1.8 m piece of a longer one, near the route and inside
    the building (its surroundings known). Temporary: a person (disc of radius 0.2-0.3 m) or a
    group of 2-4 standing together, ``people_distance_m`` from the route. Nothing comes within
    ``clearance_m + 0.1`` m of the route, and changes keep 0.5 m apart.

    Parameters
    ----------
    world
        The global map (not modified).
    route
        Nav2-frame poses the robot will drive.
    n_added, n_removed, n_people
        How many of each to plant; fewer when the space near the route has no room for them.
    rng
        Generator or seed.

    Returns
    -------
    truth_state : (H, W) uint8
        The world during the session, [row, col], FREE / OCCUPIED / UNKNOWN.
    changes : tuple of Change
        Ids 1, 2, ... in random order of kinds; ``observed`` False until a session sees them.
    """
    for name, n in (("n_added", n_added), ("n_removed", n_removed), ("n_people", n_people)):
        if n < 0:
            raise ValueError(f"{name} must be >= 0, got {n}")
    if len(route) == 0:
        raise ValueError("route must have at least one pose")
    rng = _as_rng(rng)
    res = world.resolution
    truth = world.state.copy()
    h, w = truth.shape
    frame0 = _Frame(res, world.origin, h)
    xy = np.array([(p.x, p.y) for p in route])
    uv = frame0.uv(xy)
    margin = (max(distance_m[1], people_distance_m[1]) + 4.0) / res
    r0, r1 = max(0, int(uv[:, 1].min() - margin)), min(h, int(uv[:, 1].max() + margin) + 1)
    c0, c1 = max(0, int(uv[:, 0].min() - margin)), min(w, int(uv[:, 0].max() + margin) + 1)
    frame = _Frame(res, world.origin, h, r0, c0)
    route_uv = uv - (c0, r0)
    line = np.ones((r1 - r0, c1 - c0), np.uint8)
    pts = np.round((route_uv - 0.5) * _ONE).astype(np.int32)
    cv2.polylines(line, [pts], False, 0, 1, cv2.LINE_8, _SHIFT)
    d_route = cv2.distanceTransform(line, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res
    site = _Site(
        frame,
        truth[r0:r1, c0:c1],
        world.state[r0:r1, c0:c1],
        d_route,
        np.zeros(line.shape, bool),
        route_uv,
    )
    kinds = ["added"] * n_added + ["removed"] * n_removed + ["temporary"] * n_people
    rng.shuffle(kinds)
    keep_apart = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * round(0.5 / res) + 1,) * 2)
    changes: list[Change] = []
    for kind in kinds:
        if kind == "added":
            placed = _place_added(site, rng, clearance_m, distance_m, attempts)
        elif kind == "removed":
            placed = _place_removed(site, rng, distance_m, attempts)
        else:
            placed = _place_people(site, rng, clearance_m, people_distance_m, attempts)
        if placed is None:
            continue
        shape, poly, (pr, pc, mask) = placed
        reg = site.region(pr, pc, mask)
        site.state[reg][mask] = FREE if kind == "removed" else OCCUPIED
        p = keep_apart.shape[0] // 2
        padded = np.pad(mask.astype(np.uint8), p)
        grown = cv2.dilate(padded, keep_apart) > 0
        gr0, gc0 = pr - p, pc - p
        sr0, sc0 = max(0, gr0), max(0, gc0)
        sr1 = min(site.blocked.shape[0], gr0 + grown.shape[0])
        sc1 = min(site.blocked.shape[1], gc0 + grown.shape[1])
        site.blocked[sr0:sr1, sc0:sc1] |= grown[sr0 - gr0 : sr1 - gr0, sc0 - gc0 : sc1 - gc0]
        polygon = tuple((round(float(x), 4), round(float(y), 4)) for x, y in poly)
        changes.append(Change(len(changes) + 1, kind, shape, polygon))
    return truth, tuple(changes)


# --------------------------------------------------------------------------------------------
# Session simulation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriftReport:
    """How far the SLAM estimate of a session drifted from the truth.

    Attributes
    ----------
    scale_factor
        Odometry scale of the estimate: 1 + the signed scale error.
    yaw_rate_deg_per_m
        Signed heading drift, degrees per metre travelled.
    end_position_error_m, end_yaw_error_deg
        Error of the final pose when the estimate is anchored at the first pose (metres, degrees).
    fit_rms_residual_m, fit_max_residual_m, fit_end_residual_m
        Position residuals (metres) of the route poses under the best-fit ``nav2_from_slam``:
        how much the local map is bent.
    """

    scale_factor: float
    yaw_rate_deg_per_m: float
    end_position_error_m: float
    end_yaw_error_deg: float
    fit_rms_residual_m: float
    fit_max_residual_m: float
    fit_end_residual_m: float


@dataclass(frozen=True, eq=False)
class Session:
    """One simulated mapping session.

    Attributes
    ----------
    slam_map
        The local map in the slam frame, cropped to the observed area plus a margin, origin at its
        lower-left corner with yaw 0 (as slam_toolbox saves it).
    nav2_from_slam
        The true transform: the least-squares fit of the SLAM estimates of all route poses onto
        the true poses (positions only). Without drift it equals ``nav2_from_slam_start``.
    nav2_from_slam_start
        Where the slam frame was anchored: the first route pose unless told otherwise.
    pose_nav2
        The prior: the true final pose plus AMCL noise (and the mislocalisation, if asked).
    pose_slam
        The SLAM estimate of the final pose (slam frame).
    true_pose_nav2
        The true final pose.
    trajectory
        SLAM estimates of every route pose, slam frame, oldest first.
    scan_indices
        Indices of the route poses where a scan was integrated.
    seen_cells
        Change id -> local cells showing it: occupied cells made by returns from the change
        (added, temporary), or free cells made by beams through its erased cells (removed).
        Counted through the simulation itself, so drift does not blur it.
    drift
        How much the estimate drifted.
    """

    slam_map: OccupancyMap
    nav2_from_slam: Transform2D
    nav2_from_slam_start: Transform2D
    pose_nav2: Pose2D
    pose_slam: Pose2D
    true_pose_nav2: Pose2D
    trajectory: tuple[Pose2D, ...]
    scan_indices: tuple[int, ...]
    seen_cells: Mapping[int, int]
    drift: DriftReport


def _cast(
    code: NDArray[np.int8],
    dist: NDArray[np.float32],
    u0: NDArray[np.float64],
    v0: NDArray[np.float64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    max_t: float,
) -> tuple[NDArray[np.float64], NDArray[np.int8], NDArray[np.intp], NDArray[np.intp]]:
    """Trace rays through a grid: exact cell-by-cell traversal, with safe jumps through open space.

    Parameters
    ----------
    code
        (H, W) int8 [row, col]: 0 free, 1 occupied (returns the beam), 2 stops it without a return.
    dist
        (H, W) float32: distance (pixels) from each pixel centre to the nearest non-free centre;
        no non-free pixel lies within ``dist - sqrt(2)`` of any point of a pixel.
    u0, v0, du, dv
        (R,) ray starts in continuous pixel coordinates and unit directions.
    max_t
        Maximum range, pixels.

    Returns
    -------
    t : (R,) float64
        Range in pixels: to the middle of the chord through the hit cell for a return.
    kind : (R,) int8
        0 nothing within range, 1 return, 2 stopped without a return (unknown or off the map).
    row, col : (R,) intp
        The hit cell of a return, else -1.
    """
    n = len(u0)
    h, w = code.shape
    t_out = np.full(n, float(max_t))
    kind = np.zeros(n, np.int8)
    hit_r = np.full(n, -1, np.intp)
    hit_c = np.full(n, -1, np.intp)
    zero_u, zero_v = du == 0, dv == 0
    du_safe, dv_safe = np.where(zero_u, 1.0, du), np.where(zero_v, 1.0, dv)
    step_u, step_v = (du > 0).astype(float), (dv > 0).astype(float)
    idx = np.arange(n)
    t = np.zeros(n)
    while idx.size:
        col = np.floor(u0[idx] + t * du[idx]).astype(np.intp)
        row = np.floor(v0[idx] + t * dv[idx]).astype(np.intp)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        k = np.full(idx.size, 2, np.int8)
        k[inside] = code[row[inside], col[inside]]
        tx = np.where(zero_u[idx], np.inf, (col + step_u[idx] - u0[idx]) / du_safe[idx])
        ty = np.where(zero_v[idx], np.inf, (row + step_v[idx] - v0[idx]) / dv_safe[idx])
        t_exit = np.minimum(tx, ty)
        beyond = t >= max_t
        done = (k != 0) | beyond
        if done.any():
            di = idx[done]
            hit = (k[done] == 1) & ~beyond[done]
            stopped = (k[done] == 2) & ~beyond[done]
            kind[di[hit]] = 1
            t_out[di[hit]] = np.minimum((t[done][hit] + t_exit[done][hit]) / 2, max_t)
            hit_r[di[hit]] = row[done][hit]
            hit_c[di[hit]] = col[done][hit]
            kind[di[stopped]] = 2
            t_out[di[stopped]] = t[done][stopped]
            keep = ~done
            idx, row, col, t, t_exit = idx[keep], row[keep], col[keep], t[keep], t_exit[keep]
        t = np.maximum(t + dist[row, col] - 1.4143, t_exit + 1e-6)
    return t_out, kind, hit_r, hit_c


def _drifted(
    true_xy_yaw: NDArray[np.float64],
    nav2_from_slam: Transform2D,
    yaw_rate_rad_per_m: float,
    scale: float,
) -> NDArray[np.float64]:
    """SLAM estimates (N, 3) of true nav2 poses (N, 3): each step's motion, seen from the previous
    pose, is scaled by ``scale`` and turned by ``yaw_rate`` times its length."""
    slam_from_nav2 = nav2_from_slam.inverse()
    q_xy = slam_from_nav2.apply(true_xy_yaw[:, :2])
    q_yaw = true_xy_yaw[:, 2] - nav2_from_slam.theta
    est = np.empty_like(true_xy_yaw)
    est[0] = (q_xy[0, 0], q_xy[0, 1], q_yaw[0])
    for i in range(1, len(est)):
        dx, dy = q_xy[i] - q_xy[i - 1]
        c, s = math.cos(q_yaw[i - 1]), math.sin(q_yaw[i - 1])
        fx, fy = c * dx + s * dy, -s * dx + c * dy  # motion in the robot frame
        ce, se = math.cos(est[i - 1, 2]), math.sin(est[i - 1, 2])
        est[i, 0] = est[i - 1, 0] + scale * (ce * fx - se * fy)
        est[i, 1] = est[i - 1, 1] + scale * (se * fx + ce * fy)
        turn = wrap_angle(q_yaw[i] - q_yaw[i - 1])
        est[i, 2] = est[i - 1, 2] + turn + yaw_rate_rad_per_m * math.hypot(dx, dy)
    return est


def _fit_rigid(src: NDArray[np.float64], dst: NDArray[np.float64]) -> Transform2D:
    """Least-squares rigid transform mapping points ``src`` (N, 2) onto ``dst`` (N, 2)."""
    cs, cd = src.mean(0), dst.mean(0)
    a, b = src - cs, dst - cd
    theta = math.atan2(float((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()), float((a * b).sum()))
    c, s = math.cos(theta), math.sin(theta)
    t = cd - np.array([[c, -s], [s, c]]) @ cs
    return Transform2D(theta, float(t[0]), float(t[1]))


@dataclass(frozen=True)
class _Walker:
    path: NDArray[np.float64]  # (M, 2) nav2 metres
    arc: NDArray[np.float64]  # (M,) metres along the path
    speed_mps: float
    t_start: float
    t_end: float
    radius_m: float

    def position(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        s = np.clip((t - self.t_start) * self.speed_mps, 0, self.arc[-1])
        return np.stack(
            [np.interp(s, self.arc, self.path[:, 0]), np.interp(s, self.arc, self.path[:, 1])], -1
        )


def _walkers(
    world: OccupancyMap,
    state: NDArray[np.uint8],
    route_xy: NDArray[np.float64],
    times: NDArray[np.float64],
    count: int,
    rng: np.random.Generator,
) -> list[_Walker]:
    """People walking near the route at some time of the session, each for 6-20 s."""
    if count == 0:
        return []
    h, w = state.shape
    uv = _Frame(world.resolution, world.origin, h).uv(route_xy)
    margin = 12.0 / world.resolution
    rows = (max(0, int(uv[:, 1].min() - margin)), min(h, int(uv[:, 1].max() + margin) + 1))
    cols = (max(0, int(uv[:, 0].min() - margin)), min(w, int(uv[:, 0].max() + margin) + 1))
    grid = _plan_grid(world, state, rows, cols, 0.3)
    cells = np.argwhere(grid.passable)
    pts = grid.point_xy[cells[:, 0], cells[:, 1]]
    out = []
    for _ in range(count):
        k = int(rng.integers(len(route_xy)))
        d = np.hypot(*(pts - route_xy[k]).T)
        near = np.flatnonzero((d >= 2.0) & (d <= 8.0))
        speed, duration = rng.uniform(0.8, 1.4), rng.uniform(6.0, 20.0)
        t_start, radius = times[k] - rng.uniform(0, 0.6 * duration), rng.uniform(0.2, 0.3)
        if near.size == 0:
            continue
        start = cells[near[rng.integers(near.size)]]
        path = _dedupe(
            _explore(grid, (int(start[0]), int(start[1])), speed * duration, rng, hop_m=(2.0, 10.0))
        )
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
        out.append(_Walker(path, arc, speed, t_start, t_start + duration, radius))
    return out


def simulate_session(
    world: OccupancyMap,
    route: Sequence[Pose2D],
    *,
    rng: Seed,
    true_state: NDArray[np.uint8] | None = None,
    changes: Sequence[Change] = (),
    nav2_from_slam: Transform2D | None = None,
    fov_deg: float = 360.0,
    angle_increment_deg: float = 0.5,
    max_range_m: float = 12.0,
    range_sigma_m: float = 0.02,
    drop_rate: float = 0.01,
    scan_every: int = 2,
    slam_resolution: float = 0.05,
    drift_yaw_deg_per_m: float = 0.0,
    drift_scale: float = 0.0,
    slam_xy_m: float = 0.0,
    slam_yaw_deg: float = 0.0,
    walkers: int = 0,
    robot_speed_mps: float = 0.5,
    amcl_xy_m: float = 0.05,
    amcl_yaw_deg: float = 1.0,
    mislocalize_m: float = 0.0,
    mislocalize_deg: float = 0.0,
    occupied_ratio: float = 0.2,
    margin_m: float = 0.25,
) -> Session:
    """Drive a route with a 2-D lidar and build the local map slam_toolbox would save.

    Every ``scan_every``-th route pose (and the last) takes a scan: beams every
    ``angle_increment_deg`` over ``fov_deg`` centred ahead, traced exactly through the true world
    at its resolution. An occupied cell returns the beam (range noise ``range_sigma_m``); unknown
    cells and the map's edge stop it without a return (free space up to there); nothing within
    ``max_range_m`` clears the whole beam. ``drop_rate`` of the beams return nothing at all.
    Walkers (people crossing the scene, 6-20 s each) return beams too.

    The SLAM estimate starts exactly at the slam frame's anchor and integrates the true motion with
    a scale error (``1 +- drift_scale``) and a heading error of ``+-drift_yaw_deg_per_m`` per metre
    travelled (signs random), so a long route bends; each scan is inserted at the estimate plus
    independent registration noise (``slam_xy_m``, ``slam_yaw_deg``, standard deviations). The
    local grid counts, per cell, the beams ending in it (hits) and passing through it (passes):
    occupied when ``hits >= occupied_ratio * (hits + passes)`` and hits > 0, free when only
    passed, unknown otherwise.

    Parameters
    ----------
    world
        The global map (nav2 frame): its geometry, and its state as the world before the changes.
    route
        True nav2-frame robot poses, oldest first (see :func:`plan_route`).
    rng
        Generator or seed.
    true_state
        (H, W) uint8 state of the world during the session (see :func:`plant_changes`); default
        ``world.state``.
    changes
        Planted changes whose visibility to count in ``Session.seen_cells``.
    nav2_from_slam
        Where the slam frame is; default the first route pose (the robot starts at slam (0, 0, 0)).
    slam_resolution
        Local map resolution, metres per cell.
    walkers
        Number of people walking about near the route.
    robot_speed_mps
        Robot speed, used to time the scans against the walkers.
    amcl_xy_m, amcl_yaw_deg
        Standard deviations of the noise on the reported nav2 pose (metres, degrees).
    mislocalize_m, mislocalize_deg
        An extra error of exactly this size (random direction and sign) on the reported nav2 pose.
    margin_m
        Unknown margin around the observed area of the local map.

    Returns
    -------
    Session
    """
    if len(route) == 0:
        raise ValueError("route must have at least one pose")
    if not 0 < fov_deg <= 360:
        raise ValueError(f"fov_deg must be in (0, 360], got {fov_deg}")
    for name, value in (
        ("angle_increment_deg", angle_increment_deg),
        ("max_range_m", max_range_m),
        ("slam_resolution", slam_resolution),
        ("robot_speed_mps", robot_speed_mps),
        ("occupied_ratio", occupied_ratio),
    ):
        _positive(name, value)
    if not 0 <= drop_rate < 1:
        raise ValueError(f"drop_rate must be in [0, 1), got {drop_rate}")
    if scan_every < 1:
        raise ValueError(f"scan_every must be >= 1, got {scan_every}")
    if walkers < 0:
        raise ValueError(f"walkers must be >= 0, got {walkers}")
    state = world.state if true_state is None else np.asarray(true_state)
    if state.shape != world.state.shape:
        raise ValueError(
            f"true_state must have the map's shape {world.state.shape}, got {state.shape}"
        )
    rng = _as_rng(rng)
    res, res_s = world.resolution, slam_resolution
    h, w = state.shape
    true = np.array([(p.x, p.y, p.yaw) for p in route], float)
    anchor = nav2_from_slam or Transform2D(route[0].yaw, route[0].x, route[0].y)

    # The SLAM estimate of every route pose.
    yaw_rate = math.radians(drift_yaw_deg_per_m) * (1 if rng.random() < 0.5 else -1)
    scale = 1.0 + drift_scale * (1 if rng.random() < 0.5 else -1)
    est = _drifted(true, anchor, yaw_rate, scale)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(true[:, :2], axis=0).T))])
    times = travelled / robot_speed_mps
    scans = np.array(sorted(set(range(0, len(route), scan_every)) | {len(route) - 1}))

    # Beams.
    inc = math.radians(angle_increment_deg)
    if fov_deg >= 360 - 1e-9:
        bearings = -math.pi + np.arange(round(2 * math.pi / inc)) * inc
    else:
        fov = math.radians(fov_deg)
        bearings = -fov / 2 + np.arange(math.floor(fov / inc + 1e-9) + 1) * inc
    n_beams = len(bearings)
    scan_of_ray = np.repeat(np.arange(len(scans)), n_beams)
    pose_of_ray = scans[scan_of_ray]
    ang_true = (true[scans, 2:3] + bearings).ravel()

    # Trace the beams through a window of the true world around the route.
    frame0 = _Frame(res, world.origin, h)
    uv = frame0.uv(true[:, :2])
    margin = max_range_m / res + 3
    r0, r1 = max(0, int(uv[:, 1].min() - margin)), min(h, int(uv[:, 1].max() + margin) + 1)
    c0, c1 = max(0, int(uv[:, 0].min() - margin)), min(w, int(uv[:, 0].max() + margin) + 1)
    frame = _Frame(res, world.origin, h, r0, c0)
    win = state[r0:r1, c0:c1]
    code = np.full(win.shape, 2, np.int8)
    code[win == FREE] = 0
    code[win == OCCUPIED] = 1
    dist = cv2.distanceTransform((code == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    start_uv = frame.uv(true[scans, :2])[scan_of_ray]
    cos_t, sin_t = np.cos(ang_true), np.sin(ang_true)
    t_px, kind, hit_r, hit_c = _cast(
        code, dist, start_uv[:, 0], start_uv[:, 1], cos_t, -sin_t, max_range_m / res
    )
    range_m = t_px * res
    world_hit = kind == 1

    # Walkers return the beams that reach them first.
    for walker in _walkers(world, state, true[:, :2], times, walkers, rng):
        t_scan = times[scans]
        pos = walker.position(t_scan)[scan_of_ray]
        active = ((t_scan >= walker.t_start) & (t_scan <= walker.t_end))[scan_of_ray]
        fx, fy = true[pose_of_ray, 0] - pos[:, 0], true[pose_of_ray, 1] - pos[:, 1]
        b = fx * cos_t + fy * sin_t
        c = fx * fx + fy * fy - walker.radius_m**2
        disc = b * b - c
        t_w = -b - np.sqrt(np.maximum(disc, 0)) + 0.5 * res
        closer = active & (disc >= 0) & (c > 0) & (t_w > 0) & (t_w < range_m)
        range_m = np.where(closer, t_w, range_m)
        kind = np.where(closer, np.int8(1), kind)
        world_hit &= ~closer
    hit = kind == 1
    valid = rng.random(len(range_m)) >= drop_rate
    noisy = np.maximum(range_m + np.where(hit, rng.normal(0, range_sigma_m, len(range_m)), 0), 0)

    # Where SLAM puts each scan: the estimate plus registration noise.
    at = est[scans] + np.column_stack(
        [
            rng.normal(0, slam_xy_m, (len(scans), 2)),
            rng.normal(0, math.radians(slam_yaw_deg), len(scans)),
        ]
    )
    ox, oy = at[scan_of_ray, 0], at[scan_of_ray, 1]
    ang = (at[:, 2:3] + bearings).ravel()
    ox, oy, ang, noisy, hit = ox[valid], oy[valid], ang[valid], noisy[valid], hit[valid]
    if not valid.any():
        raise ValueError("every beam was dropped: lower drop_rate")
    cos_e, sin_e = np.cos(ang), np.sin(ang)
    ex, ey = ox + noisy * cos_e, oy + noisy * sin_e

    # The local grid: cell (row, col) covers x in [(ix0 + col) r, +r), y in [(iy0 + gh - 1 - row) r, +r).
    pad = math.ceil(margin_m / res_s) + 2
    allx, ally = np.concatenate([ox, ex]), np.concatenate([oy, ey])
    ix0 = math.floor(allx.min() / res_s) - pad
    iy0 = math.floor(ally.min() / res_s) - pad
    gw = math.floor(allx.max() / res_s) - ix0 + pad + 1
    gh = math.floor(ally.max() / res_s) - iy0 + pad + 1

    def flat(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.intp]:
        col = np.floor(x / res_s).astype(np.intp) - ix0
        row = gh - 1 - (np.floor(y / res_s).astype(np.intp) - iy0)
        return np.asarray(row * gw + col, np.intp)

    # Which true cells belong to which change, to count what the local map shows of each.
    labels = np.zeros(win.shape, np.int32)
    removed_circles = []
    for ch in changes:
        fp = _footprint(frame, win.shape, [np.array(ch.polygon)])
        if fp is None:
            continue
        pr, pc, mask = fp
        reg = (slice(pr, pr + mask.shape[0]), slice(pc, pc + mask.shape[1]))
        before = world.state[r0:r1, c0:c1][reg]
        if ch.kind == "removed":
            mask = mask & (before != FREE) & (win[reg] == FREE)
            poly = frame.uv(np.array(ch.polygon))
            centre = poly.mean(0)
            removed_circles.append((centre, float(np.hypot(*(poly - centre).T).max()) + 2))
        else:
            mask = mask & (win[reg] == OCCUPIED)
        labels[reg][mask] = ch.id
    # Beams whose true path crosses a removed structure: their samples are traced back to it.
    track = np.zeros(len(range_m), bool)
    for centre, radius in removed_circles:
        along = np.clip(
            (centre[0] - start_uv[:, 0]) * cos_t - (centre[1] - start_uv[:, 1]) * sin_t, 0, t_px
        )
        gap = np.hypot(
            start_uv[:, 0] + along * cos_t - centre[0], start_uv[:, 1] - along * sin_t - centre[1]
        )
        track |= gap <= radius
    track = track[valid]
    tr_u, tr_v = start_uv[valid, 0], start_uv[valid, 1]
    tr_cos, tr_sin = cos_t[valid], sin_t[valid]

    size = gh * gw
    passes = np.zeros(size, np.int64)
    pairs: list[NDArray[np.int64]] = []
    # Pass samples at (i + 0.5) cells along each beam, stopping a cell short of a return.
    n_samples = np.floor(np.where(hit, noisy - res_s, noisy) / res_s + 0.5).clip(0).astype(np.intp)
    ends = np.cumsum(n_samples)
    chunk = 1 << 21
    lo = 0
    while lo < len(n_samples):
        base = ends[lo] - n_samples[lo]
        hi = max(lo + 1, int(np.searchsorted(ends, base + chunk, side="right")))
        nn = n_samples[lo:hi]
        total = int(nn.sum())
        if total:
            ray = np.repeat(np.arange(lo, hi), nn)
            i = np.arange(total) - np.repeat(ends[lo:hi] - nn - base, nn)
            t = (i + 0.5) * res_s
            cells = flat(ox[ray] + t * cos_e[ray], oy[ray] + t * sin_e[ray])
            passes += np.bincount(cells, minlength=size)
            sel = track[ray]
            if sel.any():
                rs, ts = ray[sel], t[sel] / res
                tu = np.floor(tr_u[rs] + ts * tr_cos[rs]).astype(np.intp)
                tv = np.floor(tr_v[rs] - ts * tr_sin[rs]).astype(np.intp)
                ok = (tu >= 0) & (tu < win.shape[1]) & (tv >= 0) & (tv < win.shape[0])
                lab = np.zeros(len(tu), np.int64)
                lab[ok] = labels[tv[ok], tu[ok]]
                keep = lab > 0
                pairs.append(lab[keep] * size + cells[sel][keep])
        lo = hi
    hit_cells = flat(ex[hit], ey[hit])
    hits = np.bincount(hit_cells, minlength=size)
    wh = world_hit[valid][hit]
    lab = labels[hit_r[valid][hit][wh], hit_c[valid][hit][wh]].astype(np.int64)
    pairs.append(lab[lab > 0] * size + hit_cells[wh][lab > 0])

    occupied = (hits > 0) & (hits >= occupied_ratio * (hits + passes))
    local = np.full(size, UNKNOWN, np.uint8)
    local[(passes > 0) & ~occupied] = FREE
    local[occupied] = OCCUPIED

    seen: dict[int, int] = {ch.id: 0 for ch in changes}
    if pairs:
        keys = np.unique(np.concatenate(pairs))
        ids, cells = keys // size, keys % size
        for ch in changes:
            want = FREE if ch.kind == "removed" else OCCUPIED
            seen[ch.id] = int(np.count_nonzero(local[cells[ids == ch.id]] == want))

    # Crop to the observed area plus the margin.
    grid = local.reshape(gh, gw)
    known_r = np.flatnonzero((grid != UNKNOWN).any(1))
    known_c = np.flatnonzero((grid != UNKNOWN).any(0))
    m = math.ceil(margin_m / res_s - 1e-9)
    a0, a1 = max(0, known_r[0] - m), min(gh, known_r[-1] + m + 1)
    b0, b1 = max(0, known_c[0] - m), min(gw, known_c[-1] + m + 1)
    origin = (round((ix0 + b0) * res_s, 9), round((iy0 + gh - a1) * res_s, 9), 0.0)
    slam_map = from_states(grid[a0:a1, b0:b1].copy(), res_s, origin)

    # The truth transform and how bent the map is.
    fit = _fit_rigid(est[:, :2], true[:, :2]) if len(route) > 1 else anchor
    residual = np.hypot(*(fit.apply(est[:, :2]) - true[:, :2]).T)
    end_anchor = anchor.apply(est[-1, :2])
    drift = DriftReport(
        scale_factor=scale,
        yaw_rate_deg_per_m=math.degrees(yaw_rate),
        end_position_error_m=float(np.hypot(*(end_anchor - true[-1, :2]))),
        end_yaw_error_deg=math.degrees(wrap_angle(est[-1, 2] + anchor.theta - true[-1, 2])),
        fit_rms_residual_m=float(np.sqrt(np.mean(residual**2))),
        fit_max_residual_m=float(residual.max()),
        fit_end_residual_m=float(residual[-1]),
    )

    # The prior: AMCL's pose, noisy, perhaps badly wrong.
    noise = rng.normal(0, 1, 3) * (amcl_xy_m, amcl_xy_m, math.radians(amcl_yaw_deg))
    direction, sign = rng.uniform(0, 2 * math.pi), 1 if rng.random() < 0.5 else -1
    end = route[-1]
    pose_nav2 = Pose2D(
        float(end.x + noise[0] + mislocalize_m * math.cos(direction)),
        float(end.y + noise[1] + mislocalize_m * math.sin(direction)),
        wrap_angle(float(end.yaw + noise[2] + sign * math.radians(mislocalize_deg))),
    )
    trajectory = tuple(Pose2D(float(x), float(y), wrap_angle(float(a))) for x, y, a in est)
    return Session(
        slam_map=slam_map,
        nav2_from_slam=fit,
        nav2_from_slam_start=anchor,
        pose_nav2=pose_nav2,
        pose_slam=trajectory[-1],
        true_pose_nav2=end,
        trajectory=trajectory,
        scan_indices=tuple(int(i) for i in scans),
        seen_cells=seen,
        drift=drift,
    )


# --------------------------------------------------------------------------------------------
# Scenarios and files
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SyntheticBundle:
    """Everything about one synthetic bundle, in memory.

    Attributes
    ----------
    world
        The global map as the fleet has it (without the changes): what ``nav2_map`` holds.
    true_state
        (H, W) uint8 [row, col]: the world during the session, in ``world``'s grid.
    route
        True nav2-frame robot poses, every ~0.25 m.
    changes
        The planted changes, ``observed`` set from the session.
    session
        The simulated session (local map, truth transform, prior poses, drift).
    trajectory
        SLAM-frame poses about every metre, for the manifest.
    """

    world: OccupancyMap
    true_state: NDArray[np.uint8]
    route: tuple[Pose2D, ...]
    changes: tuple[Change, ...]
    session: Session
    trajectory: tuple[Pose2D, ...]

    @property
    def slam_map(self) -> OccupancyMap:
        return self.session.slam_map

    @property
    def nav2_from_slam(self) -> Transform2D:
        """The true slam -> nav2 transform."""
        return self.session.nav2_from_slam

    @property
    def pose_nav2(self) -> Pose2D:
        """The prior nav2 pose the robot reports (noisy)."""
        return self.session.pose_nav2

    @property
    def pose_slam(self) -> Pose2D:
        return self.session.pose_slam


def make_scenario(
    world: OccupancyMap,
    *,
    seed: Seed,
    route_length_m: float = 20.0,
    n_added: int = 3,
    n_removed: int = 2,
    n_people: int = 1,
    clearance_m: float = 0.4,
    mislocalize: bool = False,
    min_seen_cells: int = 5,
    trajectory_spacing_m: float = 1.0,
    **session_options: Any,
) -> SyntheticBundle:
    """Plan a route, plant changes, simulate the session: one bundle with its truth.

    Parameters
    ----------
    world
        The global map (nav2 frame).
    seed
        Seed or Generator for every random step.
    route_length_m
        Route length, metres.
    n_added, n_removed, n_people
        Changes to plant (see :func:`plant_changes`).
    clearance_m
        Route clearance from non-free cells, metres.
    mislocalize
        Offset the reported nav2 pose by 0.5-2 m and 5-30 degrees (a failed localisation).
    min_seen_cells
        A change is ``observed`` when the local map shows at least this many cells of it.
    trajectory_spacing_m
        Spacing of the manifest trajectory, metres.
    **session_options
        Passed to :func:`simulate_session` (sensor, drift, walkers, AMCL noise ...).

    Returns
    -------
    SyntheticBundle
    """
    if mislocalize and ("mislocalize_m" in session_options or "mislocalize_deg" in session_options):
        raise ValueError(
            "give either mislocalize=True or mislocalize_m / mislocalize_deg, not both"
        )
    rng = _as_rng(seed)
    route = plan_route(world, length_m=route_length_m, rng=rng, clearance_m=clearance_m)
    truth, changes = plant_changes(
        world,
        route,
        n_added=n_added,
        n_removed=n_removed,
        n_people=n_people,
        rng=rng,
        clearance_m=clearance_m,
    )
    offset_m, offset_deg = rng.uniform(0.5, 2.0), rng.uniform(5.0, 30.0)
    if mislocalize:
        session_options = {
            **session_options,
            "mislocalize_m": offset_m,
            "mislocalize_deg": offset_deg,
        }
    session = simulate_session(
        world, route, rng=rng, true_state=truth, changes=changes, **session_options
    )
    changes = tuple(
        replace(c, observed=session.seen_cells.get(c.id, 0) >= min_seen_cells) for c in changes
    )
    xy = np.array([(p.x, p.y) for p in session.trajectory])
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    marks = np.floor(travelled / trajectory_spacing_m + 1e-9)
    keep = np.flatnonzero(np.diff(marks, prepend=-1) > 0).tolist()
    if keep[-1] != len(xy) - 1:
        keep.append(len(xy) - 1)
    return SyntheticBundle(
        world=world,
        true_state=truth,
        route=tuple(route),
        changes=changes,
        session=session,
        trajectory=tuple(session.trajectory[i] for i in keep),
    )


def _pose_dict(pose: Pose2D) -> dict[str, float]:
    return {
        "x": round(float(pose.x), 6),
        "y": round(float(pose.y), 6),
        "yaw": round(wrap_angle(float(pose.yaw)), 6),
    }


def _origin(m: OccupancyMap) -> tuple[float, float, float]:
    return (round(m.origin[0], 6), round(m.origin[1], 6), round(m.origin[2], 6))


def write_bundle(
    out_dir: str | Path,
    bundle_id: str,
    *,
    slam_map: OccupancyMap,
    nav2_map: OccupancyMap | None,
    pose_nav2: Pose2D,
    pose_slam: Pose2D,
    trajectory: Sequence[Pose2D] | None = None,
    robot: str = "sim-01",
    stamp: str | None = None,
) -> Path:
    """Write a bundle directory ``out_dir/bundle_id`` (contract section 2).

    Writes ``slam_map.yaml/.pgm``, ``nav2_map.yaml/.pgm`` (when ``nav2_map`` is given: the
    ORIGINAL global map, without the changes) and, last, ``bundle.yaml`` with the sha256 of every
    map file. ``stamp`` defaults to now (UTC). Existing files of the same names are replaced.

    Returns
    -------
    Path
        The bundle directory.
    """
    if not is_valid_bundle_id(bundle_id):
        raise ValueError(
            f"bundle_id must match [A-Za-z0-9][A-Za-z0-9._-]{{0,127}}, got {bundle_id!r}"
        )
    if not robot or not all(ch.isalnum() or ch in "._-" for ch in robot):
        raise ValueError(f"robot must match [A-Za-z0-9._-]+, got {robot!r}")
    if stamp is None:
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    directory = Path(out_dir) / bundle_id
    directory.mkdir(parents=True, exist_ok=True)
    files = ["slam_map.yaml", "slam_map.pgm"]
    save_map(directory / "slam_map.yaml", slam_map.state, slam_map.resolution, _origin(slam_map))
    if nav2_map is not None:
        save_map(
            directory / "nav2_map.yaml", nav2_map.state, nav2_map.resolution, _origin(nav2_map)
        )
        files += ["nav2_map.yaml", "nav2_map.pgm"]
    manifest: dict[str, object] = {
        "format": 1,
        "robot": robot,
        "stamp": stamp,
        "slam_map": "slam_map.yaml",
    }
    if nav2_map is not None:
        manifest["nav2_map"] = "nav2_map.yaml"
    manifest["pose"] = {"nav2": _pose_dict(pose_nav2), "slam": _pose_dict(pose_slam)}
    if trajectory:
        manifest["trajectory"] = [_pose_dict(p) for p in trajectory]
    manifest["checksums"] = {name: sha256_file(directory / name) for name in files}
    # The manifest last, under an in-flight name first: a watcher never sees a partial bundle.
    partial = directory / ".bundle.yaml.tmp"
    partial.write_text(
        yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None, width=100)
    )
    partial.replace(directory / "bundle.yaml")
    return directory


def write_truth(path: str | Path, transform: Transform2D, changes: Sequence[Change]) -> Path:
    """Write ``truth.yaml`` (contract section 4): the true slam -> nav2 transform and the changes.

    Returns
    -------
    Path
        ``path``.
    """
    document = {
        "format": 1,
        "transform": {
            "theta": round(float(transform.theta), 8),
            "tx": round(float(transform.tx), 6),
            "ty": round(float(transform.ty), 6),
        },
        "changes": [
            {
                "id": int(c.id),
                "kind": c.kind,
                "polygon": [[float(x), float(y)] for x, y in c.polygon],
                "observed": bool(c.observed),
            }
            for c in changes
        ],
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=100))
    return path


def write_scenario(
    scenario: SyntheticBundle,
    out_dir: str | Path,
    bundle_id: str,
    *,
    truth_path: str | Path | None = None,
    include_nav2_map: bool = True,
    robot: str = "sim-01",
    stamp: str | None = None,
) -> Path:
    """Write a scenario as a bundle (and its truth, when ``truth_path`` is given: keep it out of
    any inbox). Returns the bundle directory."""
    directory = write_bundle(
        out_dir,
        bundle_id,
        slam_map=scenario.slam_map,
        nav2_map=scenario.world if include_nav2_map else None,
        pose_nav2=scenario.pose_nav2,
        pose_slam=scenario.pose_slam,
        trajectory=scenario.trajectory,
        robot=robot,
        stamp=stamp,
    )
    if truth_path is not None:
        write_truth(truth_path, scenario.nav2_from_slam, scenario.changes)
    return directory


# --------------------------------------------------------------------------------------------
# Generated buildings
# --------------------------------------------------------------------------------------------

_Box = Callable[[float, float, float, float, int], None]


def _box(
    img: NDArray[np.uint8], res: float, x0: float, y0: float, x1: float, y1: float, value: int
) -> None:
    """Set the axis-aligned rectangle between corners (x0, y0) and (x1, y1) (metres from the
    image's lower-left corner) to ``value``; at least one pixel wide."""
    h = img.shape[0]
    xa, xb = sorted((x0, x1))
    ya, yb = sorted((y0, y1))
    c0 = round(xa / res)
    c1 = max(c0 + 1, round(xb / res))
    r0 = h - round(yb / res)
    r1 = max(r0 + 1, h - round(ya / res))
    img[max(r0, 0) : max(r1, 0), max(c0, 0) : max(c1, 0)] = value


def _all(
    img: NDArray[np.uint8], res: float, x0: float, y0: float, x1: float, y1: float, value: int
) -> bool:
    h, w = img.shape
    c0, c1 = max(0, round(min(x0, x1) / res)), min(w, round(max(x0, x1) / res))
    r0, r1 = max(0, h - round(max(y0, y1) / res)), min(h, h - round(min(y0, y1) / res))
    region = img[r0:r1, c0:c1]
    return bool(region.size) and bool(np.all(region == value))


def _finish(
    img: NDArray[np.uint8],
    rng: np.random.Generator,
    res: float,
    origin: tuple[float, float, float] | None,
    transpose: bool,
) -> OccupancyMap:
    """Mirror the drawing at random (the layouts are drawn long side along x) and give it an
    origin: a random one, as a real map's, unless one is given."""
    if transpose:
        img = img.T
    if rng.random() < 0.5:
        img = img[::-1]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    img = np.ascontiguousarray(img)
    if origin is None:
        h, w = img.shape
        origin = (round(-rng.uniform(0, w * res), 3), round(-rng.uniform(0, h * res), 3), 0.0)
    return from_states(img, res, origin)


def _lounges(
    img: NDArray[np.uint8],
    reserved: NDArray[np.uint8],
    res: float,
    rng: np.random.Generator,
    *,
    axis: str,
    wall_at: float,
    inward: int,
    along: tuple[float, float],
    depth: float,
) -> None:
    """Gate lounges along a wall: a partition wall between gates, a gate counter by the wall and
    rows of seats parallel to it. ``axis`` is the direction the wall runs ("x" or "y")."""

    def rect(
        a0: float, a1: float, b0: float, b1: float, value: int, target: NDArray[np.uint8] = img
    ) -> None:
        p0, p1 = wall_at + inward * b0, wall_at + inward * b1
        if axis == "y":
            _box(target, res, p0, a0, p1, a1, value)
        else:
            _box(target, res, a0, p0, a1, p1, value)

    a = along[0] + rng.uniform(0, 3)
    while a + 8 < along[1] - 2:
        gs = min(rng.uniform(15, 25), along[1] - 2 - a)
        rect(a, a + gs, 0, depth, 1, reserved)
        rect(a, a + 0.2, 0, depth * rng.uniform(0.4, 0.7), OCCUPIED)
        centre = a + gs / 2
        rect(centre - 1.0, centre + 1.0, 0.8, 1.5, OCCUPIED)
        b = 2.6
        mid = centre + rng.uniform(-2, 2)
        while b + 0.55 < depth - 1.2:
            rect(a + 2, mid - 0.6, b, b + 0.55, OCCUPIED)
            rect(mid + 0.6, a + gs - 2, b, b + 0.55, OCCUPIED)
            b += 1.9
        a += gs


def _shops(
    img: NDArray[np.uint8],
    reserved: NDArray[np.uint8],
    res: float,
    rng: np.random.Generator,
    x0: float,
    x1: float,
    front_y: float,
    back_y: float,
) -> None:
    """A row of shops against the back wall: open fronts, shelves inside, sometimes a gap."""
    t = rng.uniform(0.15, 0.2)
    x = x0 + rng.uniform(0, 6)
    depth = back_y - front_y
    while x + 4 < x1:
        sw = min(rng.uniform(5, 12), x1 - x)
        if rng.random() < 0.2:
            x += rng.uniform(4, 10)
            continue
        _box(reserved, res, x - 1, front_y - 1.5, x + sw + 1, back_y, 1)
        _box(img, res, x, front_y, x + t, back_y, OCCUPIED)
        _box(img, res, x + sw - t, front_y, x + sw, back_y, OCCUPIED)
        _box(img, res, x, front_y, x + sw, front_y + t, OCCUPIED)
        open_w = sw * rng.uniform(0.4, 0.9)
        oa = x + t + rng.uniform(0, max(0.0, sw - 2 * t - open_w))
        _box(img, res, oa, front_y, min(oa + open_w, x + sw - t), front_y + t, FREE)
        if sw >= 4 and depth >= 4:
            for _ in range(int(rng.integers(1, 3))):
                sx = x + rng.uniform(1.0, sw - 1.6)
                _box(img, res, sx, front_y + 1.5, sx + 0.5, back_y - 0.8, OCCUPIED)
        x += sw


def make_airport_map(
    *,
    width_px: int,
    height_px: int,
    resolution: float = 0.05,
    origin: tuple[float, float, float] | None = None,
    rng: Seed,
) -> OccupancyMap:
    """A generated airport terminal.

    A main hall (with piers of gates when the map is deep enough), outer walls 0.25-0.45 m thick,
    a regular grid of IDENTICAL columns (spacing 7-12 m, 0.45-0.9 m, all round or all square;
    the hard case for alignment: repeated structure), shops with open fronts along the back
    wall, check-in islands, gate lounges (partitions, counters, rows of seats), service rooms
    with doors and some clutter. Everything inside is known free, outside unknown. Large
    furniture is sometimes an outline with unknown inside, as in SLAM-built maps.

    Parameters
    ----------
    width_px, height_px
        Map size in pixels (200 to 20000 each; 8000 x 8000 draws in about a second).
    resolution
        Metres per pixel.
    origin
        Map origin ``(x, y, yaw)``; default random, like a real map's.
    rng
        Generator or seed.

    Returns
    -------
    OccupancyMap
    """
    for name, value in (("width_px", width_px), ("height_px", height_px)):
        if not 200 <= value <= 20000:
            raise ValueError(f"{name} must be in [200, 20000], got {value}")
    _positive("resolution", resolution)
    rng = _as_rng(rng)
    res = resolution
    img = np.full((min(width_px, height_px), max(width_px, height_px)), UNKNOWN, np.uint8)
    lx, ly = img.shape[1] * res, img.shape[0] * res
    m = float(np.clip(0.03 * ly, 1.0, 8.0))
    wall = rng.uniform(0.25, 0.45)
    has_piers = ly >= 60 and rng.random() < 0.8
    hall_y0 = ly * rng.uniform(0.4, 0.55) if has_piers else m
    interior = np.zeros_like(img)
    _box(interior, res, m, hall_y0, lx - m, ly - m, 1)
    piers = []
    if has_piers:
        n = int(np.clip((lx - 2 * m) // rng.uniform(45, 80), 1, 6))
        slot = (lx - 2 * m) / n
        for i in range(n):
            pw = min(rng.uniform(18, 28), 0.6 * slot)
            cx = m + (i + 0.5) * slot + rng.uniform(-0.15, 0.15) * (slot - pw)
            piers.append((cx - pw / 2, m, cx + pw / 2, hall_y0 + wall + res))
            _box(interior, res, *piers[-1], 1)
    wp = max(1, round(wall / res))
    inner = cv2.erode(interior, np.ones((2 * wp + 1, 2 * wp + 1), np.uint8))
    img[interior > 0] = OCCUPIED
    img[inner > 0] = FREE
    reserved = np.zeros_like(img)  # where the columns are left out
    hx0, hx1, hy0, hy1 = m + wall, lx - m - wall, hall_y0 + wall, ly - m - wall
    hall_w, hall_h = hx1 - hx0, hy1 - hy0

    # The column grid: one stamp, integer pixel steps, so every column is the same pixels.
    sx = min(rng.uniform(7, 12), max(3.0, hall_w / 4))
    sy = min(rng.uniform(7, 12), max(3.0, hall_h / 3))
    size_px = max(2, round(rng.uniform(0.45, 0.9) / res))
    if rng.random() < 0.5:
        yy, xx = np.mgrid[:size_px, :size_px] - (size_px - 1) / 2
        stamp = xx**2 + yy**2 <= (size_px / 2) ** 2
    else:
        stamp = np.ones((size_px, size_px), bool)
    step_x, step_y = round(sx / res), round(sy / res)
    first_x = round((hx0 + rng.uniform(2.0, max(2.0, min(sx, hall_w / 2)))) / res)
    first_y = round((hy0 + rng.uniform(2.0, max(2.0, min(sy, hall_h / 2)))) / res)
    col_x = list(range(first_x, round((hx1 - 1.5) / res), step_x))
    col_y = list(range(first_y, round((hy1 - 1.5) / res), step_y))

    # A big hall is split into halls by inner walls with wide openings.
    for lo, hi, along_x in ((hx0, hx1, True), (hy0, hy1, False)):
        at = lo + rng.uniform(60, 120)
        while hi - at > 40:
            a0, a1 = (hy0, hy1) if along_x else (hx0, hx1)
            parts = [(a0, a1, OCCUPIED)]
            for _ in range(int(rng.integers(2, 5))):
                centre, width = rng.uniform(a0 + 8, a1 - 8), rng.uniform(6, 15)
                parts.append((centre - width / 2, centre + width / 2, FREE))
            for a, b, value in parts:
                if along_x:
                    _box(img, res, at, a, at + wall, b, value)
                else:
                    _box(img, res, a, at, b, at + wall, value)
            if along_x:
                _box(reserved, res, at - 1.5, a0, at + wall + 1.5, a1, 1)
            else:
                _box(reserved, res, a0, at - 1.5, a1, at + wall + 1.5, 1)
            at += rng.uniform(60, 120)

    shop_depth = min(rng.uniform(5, 9), 0.3 * hall_h)
    if shop_depth >= 3.0 and hall_w >= 12:
        _shops(img, reserved, res, rng, hx0, hx1, hy1 - shop_depth, hy1)
    else:
        shop_depth = 0.0

    # Check-in islands in the middle of bays between column rows.
    depth = rng.uniform(0.8, 1.6)
    bays = [(a + b) / 2 * res for a, b in itertools.pairwise(col_y)]
    bays = [y for y in bays if y < hy1 - shop_depth - 3 and (not has_piers or y > hy0 + 6)]
    if bays and sy * 1.0 - size_px * res - 3 >= depth:
        for yc in rng.permutation(bays)[: int(rng.integers(1, 3))]:
            x = hx0 + rng.uniform(4, 10)
            while x + 10 < hx1 - 4:
                length = min(rng.uniform(10, 20), hx1 - 4 - x)
                _box(
                    reserved, res, x - 1, yc - depth / 2 - 1, x + length + 1, yc + depth / 2 + 1, 1
                )
                _box(img, res, x, yc - depth / 2, x + length, yc + depth / 2, OCCUPIED)
                if rng.random() < 0.5:  # an outline with unknown inside
                    _box(
                        img,
                        res,
                        x + 2 * res,
                        yc - depth / 2 + 2 * res,
                        x + length - 2 * res,
                        yc + depth / 2 - 2 * res,
                        UNKNOWN,
                    )
                x += length + rng.uniform(3, 6)

    # Gates: lounges along the piers' sides, or along the hall's front wall.
    pier_axes = []
    if has_piers:
        for px0, _py0, px1, py1 in piers:
            ix0, ix1 = px0 + wall, px1 - wall
            walk = rng.uniform(5, 8)
            ld = (ix1 - ix0 - walk) / 2
            pier_axes.append(((ix0 + ix1) / 2, m + wall, py1))
            if ld >= 3:
                for wall_x, inward in ((ix0, 1), (ix1, -1)):
                    _lounges(
                        img,
                        reserved,
                        res,
                        rng,
                        axis="y",
                        wall_at=wall_x,
                        inward=inward,
                        along=(m + wall, hall_y0),
                        depth=ld,
                    )
    elif hall_h >= 20:
        ld = min(rng.uniform(6, 10), 0.3 * hall_h)
        _lounges(
            img, reserved, res, rng, axis="x", wall_at=hy0, inward=1, along=(hx0, hx1), depth=ld
        )

    # Service rooms with a door and a partition.
    for _ in range(int(rng.integers(0, 3))):
        rw, rh = rng.uniform(6, 10), rng.uniform(4, 6)
        if hall_w < rw + 6 or hall_h < rh + 6:
            break
        x, y = rng.uniform(hx0 + 3, hx1 - rw - 3), rng.uniform(hy0 + 3, hy1 - rh - 3)
        if not _all(reserved, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, 0):
            continue
        if not _all(img, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, FREE):
            continue
        _box(reserved, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, 1)
        _box(img, res, x, y, x + rw, y + rh, OCCUPIED)
        _box(img, res, x + 0.2, y + 0.2, x + rw - 0.2, y + rh - 0.2, FREE)
        door = x + rng.uniform(0.5, rw - 1.7)
        _box(img, res, door, y, door + 1.2, y + 0.2, FREE)
        _box(img, res, x + rw / 2, y + 1.4, x + rw / 2 + 0.15, y + rh, OCCUPIED)

    # Columns, where nothing else stands.
    h = img.shape[0]
    half = size_px // 2
    gap = round(1.0 / res)

    def column(cx_px: int, cy_px: int) -> None:
        r, c = h - cy_px - half, cx_px - half
        if r - gap < 0 or c - gap < 0 or r + size_px + gap > h or c + size_px + gap > img.shape[1]:
            return
        if reserved[r - gap : r + size_px + gap, c - gap : c + size_px + gap].any():
            return
        if np.any(img[r - gap : r + size_px + gap, c - gap : c + size_px + gap] != FREE):
            return
        img[r : r + size_px, c : c + size_px][stamp] = OCCUPIED

    for cy in col_y:
        for cx in col_x:
            column(cx, cy)
    for axis_x, y_end, y_hall in pier_axes:
        for cy in range(round((y_end + 3) / res), round((y_hall - 1) / res), step_y):
            column(round(axis_x / res), cy)

    # Clutter: bins, benches, signs.
    for _ in range(int(hall_w * hall_h / rng.uniform(120, 250))):
        s = rng.uniform(0.3, 0.6)
        x, y = rng.uniform(hx0 + 1, hx1 - 1), rng.uniform(hy0 + 1, hy1 - 1)
        if _all(img, res, x - 1, y - 1, x + s + 1, y + s + 1, FREE) and _all(
            reserved, res, x - 1, y - 1, x + s + 1, y + s + 1, 0
        ):
            _box(img, res, x, y, x + s, y + s, OCCUPIED)
    return _finish(img, rng, res, origin, height_px > width_px)


def _furnish(
    rect: _Box,
    rng: np.random.Generator,
    x0: float,
    x1: float,
    b0: float,
    b1: float,
    door: tuple[float, float],
    hospital: bool,
) -> None:
    """Furniture in a room ``[x0, x1] x [b0, b1]`` (b from the corridor), clear of the door."""
    keep_out = [(door[0] - 0.3, 0.0, door[1] + 0.3, b0 + 1.6)]
    placed: list[tuple[float, float, float, float]] = []

    def fits(r: tuple[float, float, float, float]) -> bool:
        if r[0] < x0 or r[2] > x1 or r[1] < b0 or r[3] > b1:
            return False
        for k in keep_out:
            if r[0] < k[2] and k[0] < r[2] and r[1] < k[3] and k[1] < r[3]:
                return False
        return not any(
            r[0] < p[2] + 0.8 and p[0] - 0.8 < r[2] and r[1] < p[3] + 0.8 and p[1] - 0.8 < r[3]
            for p in placed
        )

    items = int(rng.integers(1, 3)) if hospital else int(rng.integers(1, 4))
    for _ in range(items):
        for _ in range(20):
            if hospital:
                x = rng.uniform(x0, max(x0, x1 - 0.95))
                r = (x, b1 - 2.0, x + 0.95, b1)
            elif rng.random() < 0.6:
                length, d = rng.uniform(1.2, 1.8), rng.uniform(0.6, 0.8)
                x = rng.uniform(x0, max(x0, x1 - length))
                r = (x, b1 - d, x + length, b1)
            else:
                length, d = rng.uniform(1.2, 1.8), rng.uniform(0.6, 0.8)
                b = rng.uniform(b0 + 1.7, max(b0 + 1.7, b1 - length))
                x = x0 if rng.random() < 0.5 else x1 - d
                r = (x, b, x + d, b + length)
            if fits(r):
                placed.append(r)
                rect(*r, OCCUPIED)
                break


def _office_block(
    box: _Box,
    rng: np.random.Generator,
    xa: float,
    xb: float,
    y_edge: float,
    y_far: float,
    wt: float,
    hospital: bool,
) -> None:
    """Rooms along one side of a corridor, from the corridor edge ``y_edge`` towards ``y_far``;
    when the block is deep, an open-plan area behind them reached through a passage."""
    sgn = 1 if y_far > y_edge else -1
    depth = abs(y_far - y_edge)

    def rect(x0: float, b0: float, x1: float, b1: float, value: int) -> None:
        box(x0, y_edge + sgn * b0, x1, y_edge + sgn * b1, value)

    rd = rng.uniform(5, 7) if hospital else rng.uniform(4, 7)
    if depth - rd < 3.5:
        rd = depth
    open_area = rd < depth
    rooms = []
    x = xa
    while x < xb - 1e-6:
        rw = rng.uniform(4, 7) if hospital else rng.uniform(3, 6)
        if xb - (x + rw) < 2.5:
            rw = xb - x
        rooms.append((x, x + rw))
        x += rw
    passage = int(rng.integers(len(rooms))) if open_area else -1
    rect(xa, 0, xb, wt, OCCUPIED)
    if open_area:
        rect(xa, rd - wt, xb, rd, OCCUPIED)
    for x0, _x1 in rooms:
        rect(x0, 0, x0 + wt, rd, OCCUPIED)
    rect(xb - wt, 0, xb, rd, OCCUPIED)
    for i, (x0, x1) in enumerate(rooms):
        right = x1 if i < len(rooms) - 1 else xb - wt
        if i == passage:
            rect(x0 + wt, 0, right, wt, FREE)
            rect(x0 + wt, rd - wt, right, rd, FREE)
            continue
        inner = right - x0 - wt
        dw = rng.uniform(1.2, 1.6) if hospital else rng.uniform(0.9, 1.2)
        dw = min(dw, max(0.8, inner - 0.4))
        dx = x0 + wt + rng.uniform(0.2, max(0.2, inner - dw - 0.2))
        rect(dx, 0, dx + dw, wt, FREE)
        far = rd - wt if open_area else depth
        _furnish(rect, rng, x0 + wt, right, wt, far, (dx, dx + dw), hospital)
    if open_area and passage >= 0:
        px0, px1 = rooms[passage]
        b = rd + 1.5
        while b + 1.6 < depth - 1.0:
            x = xa + 1.5
            while x + 2.8 < xb - 1.5:
                k = int(rng.integers(2, 5))
                width = min(k * 1.4, xb - 1.5 - x)
                clear_of_passage = x + width < px0 - 0.5 or x > px1 + 0.5 or b > rd + 2.5
                if clear_of_passage and rng.random() < 0.8:
                    rect(x, b, x + width, b + 1.6, OCCUPIED)
                x += width + 1.5
            b += 1.6 + 1.6


def make_office_map(
    *,
    width_m: float | None = None,
    height_m: float | None = None,
    resolution: float = 0.05,
    style: str | None = None,
    origin: tuple[float, float, float] | None = None,
    rng: Seed,
) -> OccupancyMap:
    """A generated office or hospital floor: corridors, rooms with doors, furniture.

    A main corridor (1.6-2.2 m wide; hospital 2.2-3.0 m) along the long side, often a cross
    corridor, rows of rooms 3-6 m wide (hospital 4-7 m) with a door (0.9-1.2 m; hospital
    1.2-1.6 m) onto the corridor, desks or beds inside, and behind the rooms of a deep block an
    open-plan area with desk clusters, reached through a passage. Inside known free, outside
    unknown, a 1 m unknown margin around the building.

    Parameters
    ----------
    width_m, height_m
        Building size in metres; default random in 20-40 m. At least 8 m each.
    resolution
        Metres per pixel.
    style
        ``office`` or ``hospital``; default random.
    origin
        Map origin ``(x, y, yaw)``; default random, like a real map's.
    rng
        Generator or seed.

    Returns
    -------
    OccupancyMap
    """
    _positive("resolution", resolution)
    rng = _as_rng(rng)
    if style is None:
        style = "office" if rng.random() < 0.6 else "hospital"
    if style not in ("office", "hospital"):
        raise ValueError(f"style must be 'office' or 'hospital', got {style!r}")
    wm = float(width_m) if width_m is not None else rng.uniform(20, 40)
    hm = float(height_m) if height_m is not None else rng.uniform(20, 40)
    if min(wm, hm) < 8:
        raise ValueError(f"width_m and height_m must be >= 8, got {wm} and {hm}")
    hospital = style == "hospital"
    res = resolution
    lx, ly = max(wm, hm), min(wm, hm)
    m = 1.0
    img = np.full((round((ly + 2 * m) / res), round((lx + 2 * m) / res)), UNKNOWN, np.uint8)

    def box(x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        _box(img, res, x0 + m, y0 + m, x1 + m, y1 + m, value)

    wt = rng.uniform(0.15, 0.25) if hospital else rng.uniform(0.1, 0.2)
    cw = rng.uniform(2.2, 3.0) if hospital else rng.uniform(1.6, 2.2)
    box(0, 0, lx, ly, OCCUPIED)
    box(wt, wt, lx - wt, ly - wt, FREE)
    yc = rng.uniform(0.35, 0.65) * ly
    cy0, cy1 = yc - cw / 2, yc + cw / 2
    spans = [(wt, lx - wt)]
    if lx >= 22 and rng.random() < 0.7:
        xc = rng.uniform(0.3, 0.7) * lx
        spans = [(wt, xc - cw / 2), (xc + cw / 2, lx - wt)]
    for xa, xb in spans:
        if xb - xa < 3:
            continue
        _office_block(box, rng, xa, xb, cy0, wt, wt, hospital)
        _office_block(box, rng, xa, xb, cy1, ly - wt, wt, hospital)
    # Cabinets and benches against the corridor walls, never in front of a door.
    for _ in range(int(rng.integers(0, 5))):
        length, d = rng.uniform(0.8, 2.0), rng.uniform(0.35, 0.5)
        x = rng.uniform(1.0, lx - 1.0 - length)
        if rng.random() < 0.5:
            behind, y0, y1 = cy0 - wt / 2, cy0, cy0 + d
        else:
            behind, y0, y1 = cy1 + wt / 2, cy1 - d, cy1
        wall_ok = _all(
            img,
            res,
            x - 0.5 + m,
            behind + m - res / 2,
            x + length + 0.5 + m,
            behind + m + res / 2,
            OCCUPIED,
        )
        if wall_ok and _all(img, res, x + m, y0 + m, x + length + m, y1 + m, FREE):
            box(x, y0, x + length, y1, OCCUPIED)
    return _finish(img, rng, res, origin, hm > wm)


def roughen_map(
    world: OccupancyMap,
    *,
    rng: Seed,
    edge_rate: float = 0.15,
    speckles_per_100m2: float = 1.0,
) -> OccupancyMap:
    """A generated map made to look SLAM-built: ragged wall faces and a few lone speckles.

    Parameters
    ----------
    world
        The map (not modified).
    rng
        Generator or seed.
    edge_rate
        Share of the free cells touching an occupied cell that become occupied.
    speckles_per_100m2
        Lone occupied cells per 100 m2 of free space.

    Returns
    -------
    OccupancyMap
        Same size, resolution and origin.
    """
    if not 0 <= edge_rate <= 1:
        raise ValueError(f"edge_rate must be in [0, 1], got {edge_rate}")
    if speckles_per_100m2 < 0:
        raise ValueError(f"speckles_per_100m2 must be >= 0, got {speckles_per_100m2}")
    rng = _as_rng(rng)
    state = world.state.copy()
    free = state == FREE
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
    touching = free & (cv2.dilate((state == OCCUPIED).astype(np.uint8), cross) > 0)
    edge = np.flatnonzero(touching)
    grown = edge[rng.random(edge.size) < edge_rate]
    n_free = int(np.count_nonzero(free))
    count = int(rng.poisson(speckles_per_100m2 * n_free * world.resolution**2 / 100))
    flat = state.reshape(-1)
    flat[grown] = OCCUPIED
    if count and n_free:
        # Uniform over the free cells, by rejection: no index array as big as the map.
        draws = rng.integers(0, flat.size, max(64, 4 * count * flat.size // n_free))
        flat[draws[free.reshape(-1)[draws]][:count]] = OCCUPIED
    return from_states(state, world.resolution, world.origin)
