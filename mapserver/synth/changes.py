"""Planted changes: obstacles added, structures removed and people standing about along a
route (:class:`Change`, :func:`plant_changes`)."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.geometry import Pose2D
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from mapserver.synth._common import _ONE, _SHIFT, Seed, _as_rng, _footprint, _Frame


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


def _cells_hull(frame: _Frame, r0: int, c0: int, mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Convex hull (nav2 metres) of the squares of the ``True`` pixels of ``mask`` at (r0, c0)."""
    rr, cc = np.nonzero(mask)
    corners = np.concatenate(
        [np.stack([cc + du + c0, rr + dv + r0], 1) for du in (0, 1) for dv in (0, 1)]
    ).astype(float)
    return frame.xy(_hull(corners))


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


def _free_cells(
    site: _Site, rng: np.random.Generator, distance_m: tuple[float, float], attempts: int
) -> Iterator[tuple[int, int, int]]:
    """``(attempt, row, col)``: up to ``attempts`` free cells drawn at random among those
    ``distance_m`` from the route and away from earlier changes (none if there are none)."""
    lo_m, hi_m = distance_m
    ok = (site.state == FREE) & (site.d_route_m >= lo_m) & (site.d_route_m <= hi_m) & ~site.blocked
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return
    w = site.state.shape[1]
    for attempt in range(attempts):
        r, c = divmod(int(idx[rng.integers(idx.size)]), w)
        yield attempt, r, c


def _fits(site: _Site, footprint: tuple[int, int, NDArray[np.bool_]], clearance_m: float) -> bool:
    """Whether a new obstacle's footprint lies on free cells, clear of the route and of earlier
    changes."""
    r0, c0, mask = footprint
    reg = site.region(r0, c0, mask)
    return not (
        np.any(site.state[reg][mask] != FREE)
        or site.d_route_m[reg][mask].min() < clearance_m + 0.1
        or site.blocked[reg][mask].any()
    )


def _place_added(
    site: _Site,
    rng: np.random.Generator,
    clearance_m: float,
    distance_m: tuple[float, float],
    attempts: int,
) -> tuple[str, NDArray[np.float64], tuple[int, int, NDArray[np.bool_]]] | None:
    for attempt, r, c in _free_cells(site, rng, distance_m, attempts):
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
        if fp is None or not _fits(site, fp, clearance_m):
            continue
        r0, c0, mask = fp
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
    for _, r, c in _free_cells(site, rng, distance_m, attempts):
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
        if fp is None or not _fits(site, fp, clearance_m):
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
