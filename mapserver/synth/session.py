"""Session simulation: a 2-D lidar and a drifting SLAM estimate driving a route, and the local
map slam_toolbox would save (:func:`simulate_session`, :class:`Session`, :class:`DriftReport`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.geometry import Pose2D, Transform2D, fit_rigid, wrap_angle
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states
from mapserver.synth._common import Seed, _as_rng, _footprint, _Frame, _positive
from mapserver.synth.changes import Change
from mapserver.synth.route import _dedupe, _explore, _plan_grid


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
    walkers
        The people who walked near the route during the session (not in the true world).
    scan_times
        Seconds since the start at each scan (the ``scan_indices`` poses).
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
    walkers: tuple[Walker, ...] = ()
    scan_times: tuple[float, ...] = ()


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
    # A ray crosses at most |du| L + |dv| L + 2 <= sqrt(2) L + 2 cells, one step each at worst.
    max_steps = math.ceil(1.5 * max_t) + 4
    for step in range(max_steps + 1):
        if not idx.size:
            break
        col = np.floor(u0[idx] + t * du[idx]).astype(np.intp)
        row = np.floor(v0[idx] + t * dv[idx]).astype(np.intp)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        k = np.full(idx.size, 2, np.int8)
        k[inside] = code[row[inside], col[inside]]
        tx = np.where(zero_u[idx], np.inf, (col + step_u[idx] - u0[idx]) / du_safe[idx])
        ty = np.where(zero_v[idx], np.inf, (row + step_v[idx] - v0[idx]) / dv_safe[idx])
        # A ray running along a cell boundary (cos(pi/2) is 6e-17, not 0) can round onto the
        # wrong side of it: that boundary then lies behind the ray, and its next one is 1/|d| on.
        tx = np.where(tx <= t, tx + 1.0 / np.abs(du_safe[idx]), tx)
        ty = np.where(ty <= t, ty + 1.0 / np.abs(dv_safe[idx]), ty)
        t_exit = np.minimum(tx, ty)
        beyond = (t >= max_t) | (step == max_steps)
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
    yaw_walk: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """SLAM estimates (N, 3) of true nav2 poses (N, 3): each step's motion, seen from the previous
    pose, is scaled by ``scale`` and turned by ``yaw_rate`` times its length, or, with
    ``yaw_walk`` (N - 1,) given, by ``yaw_rate`` times the square root of its length times the
    step's ``yaw_walk`` (standard normal draws: the heading error a random walk)."""
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
        step = math.hypot(dx, dy)
        if yaw_walk is None:
            error = yaw_rate_rad_per_m * step
        else:
            error = yaw_rate_rad_per_m * math.sqrt(step) * float(yaw_walk[i - 1])
        est[i, 2] = est[i - 1, 2] + turn + error
    return est


@dataclass(frozen=True)
class Walker:
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


def _draw_walkers(
    world: OccupancyMap,
    state: NDArray[np.uint8],
    route_xy: NDArray[np.float64],
    times: NDArray[np.float64],
    count: int,
    rng: np.random.Generator,
) -> list[Walker]:
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
        out.append(Walker(path, arc, speed, t_start, t_start + duration, radius))
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
    drift_walk: bool = False,
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
    travelled (signs random), so a long route bends. With ``drift_walk`` the heading error is a
    random walk instead, ``drift_yaw_deg_per_m`` per square-root metre (a standard deviation): it
    wanders and partly cancels, as in the long sessions of ``shared/bench/public-realism``
    (their routes of 56-96 m end 0.03-1.4 degrees off, bent by at most 0.05-0.4 m against the
    best rigid fit). Each scan is inserted at the estimate plus
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
    walk = rng.standard_normal(max(len(route) - 1, 0)) if drift_walk else None
    est = _drifted(true, anchor, yaw_rate, scale, walk)
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
    people = tuple(_draw_walkers(world, state, true[:, :2], times, walkers, rng))
    t_scan = times[scans]
    for walker in people:
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
    fit = fit_rigid(est[:, :2], true[:, :2]) if len(route) > 1 else anchor
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
        walkers=people,
        scan_times=tuple(float(t) for t in times[scans]),
    )
