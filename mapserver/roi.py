"""The region-of-interest strategies: where on the work grid differences are looked for.

``observed`` (default): the cells the aligned local map knows, free or occupied.
``box``: a square centred on the robot. ``trajectory``: a corridor around the route.
``heading``: the prototype's ROI, the square behind the robot along its heading (where it came
from). Each gives a mask on the work grid and a polygon in nav2 metres for ``result.yaml``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.geometry import Pose2D
from mapserver.grid import Grid, box_around
from mapserver.maps import UNKNOWN

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Roi:
    """``mask``: (H, W) bool on the work grid; ``polygon``: its outline in nav2 metres."""

    strategy: str
    mask: BoolArray
    polygon: list[tuple[float, float]]


def _fill(grid: Grid, polygon_xy: NDArray[np.float64]) -> BoolArray:
    mask = np.zeros(grid.shape, np.uint8)
    px = np.rint(grid.to_pixel(polygon_xy)).astype(np.int32)
    cv2.fillPoly(mask, [px], 1)
    return mask.astype(bool)


def _outline(
    mask: NDArray[np.bool_] | NDArray[np.uint8],
    grid: Grid,
    *,
    simplify_m: float,
    offset: tuple[int, int] = (0, 0),
) -> list[tuple[float, float]]:
    """The outer contour of the largest region of ``mask``, simplified, in metres. ``mask`` may
    be a part of the grid whose first cell is ``offset`` = (col, row)."""
    if not mask.any():
        return []
    contours, _ = cv2.findContours(
        mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )
    biggest = max(contours, key=cv2.contourArea)
    approx = cv2.approxPolyDP(biggest, simplify_m / grid.resolution, True).reshape(-1, 2)
    if len(approx) < 3:
        # A region a few cells across simplifies to a point or a line: its box instead, by the
        # cells' outer edges (a polygon, even around one cell).
        x, y, w, h = cv2.boundingRect(biggest)
        approx = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], float) - 0.5
    return [(round(float(x), 3), round(float(y), 3)) for x, y in grid.to_world(approx + offset)]


def observed(local_state: NDArray[np.uint8], grid: Grid) -> Roi:
    """The cells the aligned local map knows; the polygon outlines the largest known region."""
    known = local_state != UNKNOWN
    # The closing and the contour on the box around the known cells (plus more than the
    # closing's reach): the same outline as over the whole grid.
    box = box_around(known, 8)
    if box is None:
        return Roi("observed", known, [])
    part = known[box].view(np.uint8)
    closed = np.asarray(
        cv2.morphologyEx(part, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)), np.uint8
    )
    offset = (box[1].start, box[0].start)
    return Roi("observed", known, _outline(closed, grid, simplify_m=0.25, offset=offset))


def box(robot: Pose2D, grid: Grid, *, size_m: float) -> Roi:
    """A square of side ``size_m`` centred on the robot, aligned with its heading."""
    h = size_m / 2.0
    corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    return _polygon_roi("box", robot, corners, grid)


def heading(robot: Pose2D, grid: Grid, *, size_m: float) -> Roi:
    """The square of side ``size_m`` behind the robot along its heading (the prototype's ROI)."""
    h = size_m / 2.0
    corners = np.array([[-size_m, -h], [0.0, -h], [0.0, h], [-size_m, h]])
    return _polygon_roi("heading", robot, corners, grid)


def _polygon_roi(strategy: str, robot: Pose2D, corners: NDArray[np.float64], grid: Grid) -> Roi:
    c, s = math.cos(robot.yaw), math.sin(robot.yaw)
    world = corners @ np.array([[c, s], [-s, c]]) + np.array([robot.x, robot.y])
    polygon = [(round(float(x), 3), round(float(y), 3)) for x, y in world]
    return Roi(strategy, _fill(grid, world), polygon)


def trajectory(route_xy: NDArray[np.float64], grid: Grid, *, radius_m: float) -> Roi:
    """A corridor of half-width ``radius_m`` around the route (nav2 metres, oldest first)."""
    mask = np.zeros(grid.shape, np.uint8)
    px = np.rint(grid.to_pixel(route_xy)).astype(np.int32)
    thickness = max(1, round(2 * radius_m / grid.resolution))
    if len(px) == 1:
        cv2.circle(mask, (int(px[0, 0]), int(px[0, 1])), thickness // 2, 1, -1)
    else:
        cv2.polylines(mask, [px], False, 1, thickness=thickness, lineType=cv2.LINE_8)
        for x, y in px[[0, -1]]:
            cv2.circle(mask, (int(x), int(y)), thickness // 2, 1, -1)
    region = mask.astype(bool)
    return Roi("trajectory", region, _outline(region, grid, simplify_m=0.25))
