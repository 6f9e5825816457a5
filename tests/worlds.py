"""Small worlds with a known truth for the image-processing tests.

A world is a global map drawn with OpenCV (walls, rooms, pillars). A local map is cut out of a
(possibly changed) copy of it and expressed in a slam frame related to nav2 by a known transform,
so that every test knows the exact answer it must recover.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from mapserver.bundle import sha256_file
from mapserver.geometry import Transform2D
from mapserver.grid import Grid, resample
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, save_map


def office(
    *, width_m: float = 30.0, height_m: float = 20.0, resolution: float = 0.05, seed: int = 0
) -> OccupancyMap:
    """An office floor: outer walls, a corridor, irregular rooms with doors, a few pillars.

    Origin (-2, -3); unknown outside the building.
    """
    rng = np.random.default_rng(seed)
    w, h = round(width_m / resolution), round(height_m / resolution)
    state = np.full((h, w), UNKNOWN, np.uint8)
    px = lambda m: round(m / resolution)  # noqa: E731
    cv2.rectangle(state, (px(1), px(1)), (w - px(1), h - px(1)), FREE, -1)
    t = max(2, px(0.15))
    cv2.rectangle(state, (px(1), px(1)), (w - px(1), h - px(1)), OCCUPIED, t)
    # A corridor wall along the middle with doors, and room walls of varied spacing.
    y_mid = h // 2
    cv2.line(state, (px(1), y_mid), (w - px(1), y_mid), OCCUPIED, t)
    x = px(1)
    while x < w - px(5):
        x += px(rng.uniform(3.5, 6.5))
        cv2.line(state, (x, px(1)), (x, h - px(1)), OCCUPIED, t)
        for y0 in (y_mid - px(1.6), y_mid + px(0.6)):  # doors next to the corridor
            cv2.rectangle(state, (x - t, y0), (x + t, y0 + px(1.0)), FREE, -1)
    for _ in range(6):  # doors in the corridor wall
        dx = px(rng.uniform(2, width_m - 3))
        cv2.rectangle(state, (dx, y_mid - t), (dx + px(1.0), y_mid + t), FREE, -1)
    for _ in range(5):  # pillars and furniture
        cx, cy = px(rng.uniform(3, width_m - 3)), px(rng.uniform(3, height_m - 3))
        s = px(rng.uniform(0.3, 0.6))
        cv2.rectangle(state, (cx, cy), (cx + s, cy + s), OCCUPIED, -1)
    return from_states(state, resolution, (-2.0, -3.0, 0.0))


def colonnade(*, resolution: float = 0.05, spacing_m: float = 4.0) -> OccupancyMap:
    """An airport-like hall: walls around, and rows of identical columns on a regular grid."""
    width_m, height_m = 60.0, 30.0
    w, h = round(width_m / resolution), round(height_m / resolution)
    state = np.full((h, w), FREE, np.uint8)
    px = lambda m: round(m / resolution)  # noqa: E731
    cv2.rectangle(state, (0, 0), (w - 1, h - 1), OCCUPIED, px(0.2))
    s = px(0.5)
    for cx in np.arange(4.0, width_m - 3.0, spacing_m):
        for cy in np.arange(4.0, height_m - 3.0, spacing_m):
            cv2.rectangle(state, (px(cx), px(cy)), (px(cx) + s, px(cy) + s), OCCUPIED, -1)
    # One irregular feature so that the hall is not perfectly periodic.
    cv2.rectangle(state, (px(20), px(1)), (px(27), px(2.2)), OCCUPIED, -1)
    return from_states(state, resolution, (0.0, 0.0, 0.0))


def doorway_cut() -> tuple[np.ndarray, np.ndarray]:
    """A global state (100 x 100 cells of 0.05 m) with a wall 0.35 m thick (cols 45-51), and a
    local state the same but for a doorway 0.5 m wide cut through it (rows 40-49), seen free
    from both sides: the robot looked through it, the wall ends either side seen where drawn."""
    g = np.full((100, 100), FREE, np.uint8)
    g[:, 45:52] = OCCUPIED
    loc = g.copy()
    loc[40:50, 45:52] = FREE
    return g, loc


@dataclass(frozen=True)
class Cut:
    """A local map cut from a world, with the truth."""

    local: OccupancyMap
    nav2_from_slam: Transform2D


def cut_local(
    world: OccupancyMap,
    *,
    centre_xy: tuple[float, float],
    radius_m: float,
    nav2_from_slam: Transform2D,
    resolution: float | None = None,
) -> Cut:
    """What a robot at ``centre_xy`` (nav2) knows: the world within ``radius_m``, in a slam frame.

    Walls' far sides are left unknown (a lidar sees only the faces), so that the local map looks
    like a SLAM map, not like a crop of the global one.
    """
    resolution = resolution or world.resolution
    to_slam = nav2_from_slam.inverse()
    c = to_slam.apply(np.array(centre_xy))
    grid = Grid.covering(
        c[0] - radius_m, c[1] - radius_m, c[0] + radius_m, c[1] + radius_m, resolution
    )
    state = resample(world.state, Grid.of_map(world), grid, to_slam)
    xy = grid.to_world(
        np.stack(np.meshgrid(np.arange(grid.width), np.arange(grid.height)), axis=-1).reshape(-1, 2)
    )
    far = (np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1]) > radius_m).reshape(grid.shape)
    state[far] = UNKNOWN
    # Keep only occupied cells that touch free space (the faces a lidar sees).
    occ = (state == OCCUPIED).astype(np.uint8)
    free = (state == FREE).astype(np.uint8)
    face = cv2.dilate(free, np.ones((3, 3), np.uint8)) > 0
    state[(occ > 0) & ~face] = UNKNOWN
    local = from_states(state, grid.resolution, (grid.x0, grid.y0, 0.0))
    return Cut(local, nav2_from_slam)


def changed(
    world: OccupancyMap, edits: list[tuple[str, float, float, float, float]]
) -> OccupancyMap:
    """A copy of ``world`` with boxes set to occupied (``"add"``) or free (``"clear"``):
    ``(op, min_x, min_y, max_x, max_y)`` in metres."""
    state = world.state.copy()
    grid = Grid.of_map(world)
    for op, x0, y0, x1, y1 in edits:
        (c0, r1), (c1, r0) = np.rint(grid.to_pixel([[x0, y0], [x1, y1]])).astype(int)
        state[r0 : r1 + 1, c0 : c1 + 1] = OCCUPIED if op == "add" else FREE
    return from_states(state, world.resolution, world.origin)


# A hall of columns 6 m apart (colonnade), seen over 8 m around HALL_CENTRE: two of its six
# columns there gone and three new objects in open floor, more change than building.
HALL_TRUTH = Transform2D(0.4, 20.0, 8.0)
HALL_CENTRE = (31.0, 15.0)
HALL_GONE = [(28.0, 13.5), (34.0, 19.5)]  # columns' lower left corners (0.5 m squares)
HALL_NEW = [(30.0, 11.0, 31.0, 11.6), (25.0, 17.0, 25.8, 17.6), (36.5, 16.0, 37.1, 16.6)]


def changed_hall(gone: list[tuple[float, float]]) -> tuple[OccupancyMap, Cut]:
    """The hall as drawn, and what a robot at HALL_CENTRE knows of it with the columns at
    ``gone`` cleared and HALL_NEW added."""
    world = colonnade(spacing_m=6.0)
    edits = [("clear", x, y, x + 0.5, y + 0.5) for x, y in gone]
    edits += [("add", *box) for box in HALL_NEW]
    cut = cut_local(
        changed(world, edits), centre_xy=HALL_CENTRE, radius_m=8.0, nav2_from_slam=HALL_TRUTH
    )
    return world, cut


def offset(
    t: Transform2D, dx: float, dy: float, dtheta_deg: float, about: tuple[float, float]
) -> Transform2D:
    """``t`` disturbed by a rotation about the nav2 point ``about`` and a translation."""
    a = np.array(about)
    d = math.radians(dtheta_deg)
    rot = Transform2D(d, *(a - Transform2D(d, 0.0, 0.0).apply(a)))
    return Transform2D(0.0, dx, dy).compose(rot).compose(t)


def write_bundle(
    directory: Path,
    world: OccupancyMap,
    cut: Cut,
    *,
    prior: Transform2D | None = None,
    slam_pose: tuple[float, float, float] = (0.5, 0.2, 0.1),
    trajectory: bool = True,
    checksums: bool = True,
) -> Path:
    """Write a bundle directory (maps as map_saver writes them, bundle.yaml) for ``cut``.

    The nav2 pose in the manifest is the slam pose mapped through ``prior`` (default: the truth).
    """
    directory.mkdir(parents=True, exist_ok=True)
    save_map(directory / "slam_map.yaml", cut.local.state, cut.local.resolution, cut.local.origin)
    save_map(directory / "nav2_map.yaml", world.state, world.resolution, world.origin)
    prior = prior or cut.nav2_from_slam
    sx, sy, syaw = slam_pose
    nx, ny = prior.apply(np.array([sx, sy]))
    manifest: dict[str, object] = {
        "format": 1,
        "robot": "test-01",
        "stamp": "2026-11-21T10:15:00Z",
        "slam_map": "slam_map.yaml",
        "nav2_map": "nav2_map.yaml",
        "pose": {
            "nav2": {"x": float(nx), "y": float(ny), "yaw": syaw + prior.theta},
            "slam": {"x": sx, "y": sy, "yaw": syaw},
        },
    }
    if trajectory:
        manifest["trajectory"] = [
            {"x": float(x), "y": float(y), "yaw": 0.0} for x, y in np.linspace([0, 0], [sx, sy], 5)
        ]
    if checksums:
        names = ["slam_map.yaml", "slam_map.pgm", "nav2_map.yaml", "nav2_map.pgm"]
        manifest["checksums"] = {n: sha256_file(directory / n) for n in names}
    (directory / "bundle.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return directory
