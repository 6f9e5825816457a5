"""Alignment of the local (slam) map onto the global (nav2) map.

Pure functions. The pose prior (one robot pose seen in both frames) gives a first
``nav2_from_slam``; a correlative search AROUND that prior (rotation and translation, rigid: two
maps of one building have no scale or shear) followed by an ICP polish refines it. Every candidate
is scored on the same cells, and the prior is kept unless the refinement clearly wins. A search
around the prior, rather than a global feature match, is what keeps rows of identical columns
from locking the map onto the wrong one.

Arrays are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)`` metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache, partial

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.diff import distance_to, near, near_at, near_at_box, offset_distances
from mapserver.geometry import Transform2D, wrap_angle
from mapserver.grid import (
    Grid,
    box_around,
    landing_box,
    nonzero_cells,
    resample,
)
from mapserver.maps import FREE, OCCUPIED, PGM_UNKNOWN, UNKNOWN, OccupancyMap

FloatArray = NDArray[np.float64]
# nearest_wall_near's room for the points to move between requests, metres.
_MOVE_ROOM_M = 0.5
# cv2.calcHist counts in float32, exact up to 2**24 per call.
_HIST_CHUNK = 1 << 24


@dataclass(frozen=True)
class GlobalView:
    """The part of the global map the local map can land on, resampled to the work grid.

    ``state`` is the global cell state and ``structure`` the walls used for alignment (occupied
    cells, plus walls a drawing shows in grey), both (grid.height, grid.width) on ``grid``
    (nav2 frame). ``wall_reach_m``: how far from its points any user of this view will look
    for the nearest wall (the drift estimate looks farther than ICP), so that one nearest-wall
    field serves them all.
    """

    grid: Grid
    state: NDArray[np.uint8]
    structure: NDArray[np.bool_]
    wall_reach_m: float = 0.0
    raw_state: NDArray[np.uint8] | None = None
    """The map's own cell states where ``state`` has walls a drawing shows (grey lines, grey
    walls' cores) made occupied; None when it has none (then it is ``state``)."""

    def near_walls(self, tolerance_m: float) -> NDArray[np.bool_]:
        """Cells within ``tolerance_m`` of a global wall: ``distance * resolution <=
        tolerance_m`` cell for cell, by a dilation (cheaper, and a byte a cell, not four).
        Cached per tolerance."""
        cache: dict[float, NDArray[np.bool_]] = self.__dict__.setdefault("_near", {})
        if tolerance_m not in cache:
            cache[tolerance_m] = near(self.structure, self._within(tolerance_m))
        return cache[tolerance_m]

    def near_edges_at(self, points_xy: FloatArray, distance_m: float) -> NDArray[np.bool_]:
        """(N,) bool: whether each of ``points_xy`` (nav2 metres) lies within ``distance_m`` of
        the edge of what the global map knows, an unknown cell beside (4-connected) a free one,
        where a map that does not draw a wall dark ends its floor; False off the grid. Worked
        out over the box around the points only: asked once, for a score near the trust bar."""
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))

        def edges(box: tuple[slice, slice]) -> NDArray[np.bool_]:
            state = self.state[box]
            free = cv2.dilate((state == FREE).view(np.uint8), cross) > 0
            return np.asarray((state == UNKNOWN) & free)

        # A cell more than the reach: the free neighbour of an edge cell within reach is in it.
        return near_at_box(edges, self._within(distance_m), self.grid, points_xy, pad=1)

    def near_walls_at(self, points_xy: FloatArray, distance_m: float) -> NDArray[np.bool_]:
        """(N,) bool: whether each of ``points_xy`` (nav2 metres) lies within ``distance_m``
        of a global wall, as ``near_walls(distance_m)`` sampled there (False off the grid),
        worked out over the box around the points only: for a distance asked once, at a few
        thousand points, not a pass over the whole view."""
        return near_at(self.structure, self._within(distance_m), self.grid, points_xy)

    def _within(self, distance_m: float) -> NDArray[np.bool_]:
        """The offsets within ``distance_m`` of a cell (for :func:`~mapserver.diff.near`): the
        float32 chamfer distance, in float64, times the resolution, as thresholding the
        distance transform of the walls would read it."""
        res = self.grid.resolution
        reach = offset_distances(distance_m / res).astype(np.float64)
        return np.asarray(~(reach * res > distance_m))

    def nearest_wall_near(self, points_xy: FloatArray, *, reach_m: float) -> NearestWall:
        """The (col, row) of the nearest global wall cell (a :class:`NearestWall`), computed
        only over the box that holds ``points_xy`` (nav2 metres) and ``reach_m`` around them
        (the correspondences ICP and the drift estimate can use), or the view's
        ``wall_reach_m`` if farther. Cached; a box outside the cached one is computed again, as
        their union."""
        px = self.grid.to_pixel(points_xy)
        lo_r, lo_c = int(np.floor(px[:, 1].min())), int(np.floor(px[:, 0].min()))
        hi_r, hi_c = int(np.ceil(px[:, 1].max())) + 1, int(np.ceil(px[:, 0].max())) + 1

        def around(margin_m: float) -> tuple[int, int, int, int]:
            k = math.ceil(margin_m / self.grid.resolution) + 2
            h, w = self.grid.shape
            return max(lo_r - k, 0), max(lo_c - k, 0), min(hi_r + k, h), min(hi_c + k, w)

        reach = max(reach_m, self.wall_reach_m)
        cached: NearestWall | None = self.__dict__.get("_nearest_box")
        if cached is not None and cached.covers(around(reach)):
            return cached
        # A new field: with room for the points to move before the next request (ICP's
        # candidates first, then the polished transform), so that one field serves them all.
        box = around(reach + _MOVE_ROOM_M)
        if cached is not None:
            r0, c0 = cached._origin
            h, w = cached._labels.shape
            box = (min(box[0], r0), min(box[1], c0), max(box[2], r0 + h), max(box[3], c0 + w))
        field = NearestWall.of(self.structure, box)
        self.__dict__["_nearest_box"] = field
        return field

    def cropped(self, box: tuple[int, int, int, int]) -> GlobalView:
        """The view over ``box`` = (row0, row1, col0, col1) of it only: copies of ``state`` and
        ``structure`` there, on the matching part of the grid, and no search fields. The later
        stages need only where the local map landed; the search needed room to move it."""
        r0, r1, c0, c1 = box
        raw = self.raw_state
        return GlobalView(
            self.grid.crop(box),
            np.ascontiguousarray(self.state[r0:r1, c0:c1]),
            np.ascontiguousarray(self.structure[r0:r1, c0:c1]),
            self.wall_reach_m,
            None if raw is None else np.ascontiguousarray(raw[r0:r1, c0:c1]),
        )

    def level(self, factor: int, pad: int) -> _Level:
        """The wall likelihood on cells ``factor`` times the grid's (cached: the wide search
        reuses it)."""
        key = (factor, pad)
        cache: dict[tuple[int, int], _Level] = self.__dict__.setdefault("_levels", {})
        if key not in cache:
            cache[key] = _make_level(self, factor, pad)
        return cache[key]


@dataclass(frozen=True)
class Alignment:
    """The result of aligning: ``nav2_from_slam`` and how far it can be trusted.

    ``score`` (0..1) is the geometric mean of two shares: the local map's walls that lie on a
    global wall, and the global walls (inside what the robot saw) that the local map does not
    see through; ``prior_score`` is the same for the pose prior. ``trusted`` is false when even the
    best transform agrees too little to compare the maps. ``unchanged_score``: set when the
    transform was trusted on the structure that did not change although ``score`` is under the
    minimum (see :func:`unchanged_score`); ``edges_score``: set when it was trusted with the
    edges of what the global map knows counted as walls (``edge_margin`` of :func:`align`).
    """

    nav2_from_slam: Transform2D
    method: str
    refined: bool
    score: float
    prior_score: float
    trusted: bool
    warnings: tuple[str, ...] = field(default=())
    unchanged_score: float | None = None
    edges_score: float | None = None


def structure_mask(m: OccupancyMap) -> NDArray[np.bool_]:
    """Walls for alignment: occupied cells, cells clearly darker than the map's unknown grey,
    and the walls a drawing shows as thin lines (:func:`drawn_walls`).

    Some maps draw walls as grey anti-aliased lines that read as unknown by the trinary rule;
    they still show where the walls are. Returns a new (H, W) bool array.
    """
    return _structure(m, _drawn(m))


def _structure(
    m: OccupancyMap, drawn: NDArray[np.bool_] | None, unknown_level: int | None = None
) -> NDArray[np.bool_]:
    if unknown_level is None:
        unknown_level = _unknown_level(m)
    level = unknown_level + 0.2 * (255 - unknown_level)
    # occ >= level for whole numbers occ: an 8-bit comparison, not a float one per cell.
    out = (m.state == OCCUPIED) | (m.occupancy >= np.uint8(math.ceil(level)))
    if drawn is not None:
        out |= drawn
    return np.asarray(out, dtype=bool)


def _unknown_level(m: OccupancyMap) -> int:
    """The map's unknown grey: the commonest occupancy of its unknown cells (127 if none)."""
    counts = _histogram_where(m.occupancy, m.state == UNKNOWN)
    return int(np.argmax(counts)) if counts.any() else 127


def _histogram_where(grey: NDArray[np.uint8], mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    """(256,) int64 counts of the grey levels of the cells where ``mask`` is True, exact
    (cv2.calcHist counts in float32: at most 2**24 cells a call)."""
    h, w = grey.shape
    if w > _HIST_CHUNK:
        return np.bincount(grey[mask], minlength=256).astype(np.int64)
    counts = np.zeros(256, np.int64)
    step = _HIST_CHUNK // max(w, 1)
    for r in range(0, h, step):
        part = cv2.calcHist(
            [grey[r : r + step]], [0], mask[r : r + step].view(np.uint8), [256], [0, 256]
        )
        counts += part.reshape(-1).astype(np.int64)
    return counts


def _median_ink(m: OccupancyMap, labels: NDArray[np.int32], n: int) -> NDArray[np.float64]:
    """Per label 0..n-1: the median occupancy of its cells that are not read as free (a drawn
    line's ink, without the paper around it); 0 where it has none."""
    cells = (labels > 0) & (m.state != FREE)
    label, ink = labels[cells], m.occupancy[cells]
    out = np.zeros(n)
    if label.size == 0:
        return out
    order = np.lexsort((ink, label))
    label, ink = label[order], ink[order]
    starts = np.flatnonzero(np.r_[True, label[1:] != label[:-1]])
    ends = np.r_[starts[1:], label.size]
    out[label[starts]] = ink[(starts + ends - 1) // 2]
    return out


def _grey_levels(counts: _Levels) -> tuple[NDArray[np.bool_], NDArray[np.bool_], bool]:
    """The occupancies a drawn line's pixels may have (darker than anything read as free, not
    the unknown grey), those clearly darker than free, and whether more cells that are not
    black have the clear ones than cells are black (a drawing, not a scan).

    A line's own pixels need only be darker than what the thresholds read as free: a line
    drawn thin and slanted spreads its ink over two pixels, each lighter than the line. What
    makes it a line is its contrast with what lies beside it (the top-hat); the map's
    thresholds say what is not floor. Whether the map is a drawing at all is told by the clear
    ones only, so that a scan's faint greys do not make it one."""
    unknown_level = counts.unknown_level()
    levels = np.arange(256)
    not_unknown = np.abs(levels - unknown_level) > _UNKNOWN_BAND
    free_top = counts.free_top()
    grey = not_unknown & (levels > min(free_top, 254))
    clearly = not_unknown & (levels > min(free_top + _LINE_CONTRAST // 3, 254))
    n_black = int(counts.occupied.sum())
    return grey, clearly, int((counts.free + counts.unknown)[clearly].sum()) > n_black


def drawn_walls(m: OccupancyMap) -> NDArray[np.bool_]:
    """The walls a floor-plan drawing shows as thin grey lines, as thick as a lidar sees them.

    Floor plans draw walls one pixel wide and anti-aliased, often lighter than their grey label
    boxes, on white or pastel fills that read as free; the trinary rule reads the lines as
    unknown or free. A line is what a top-hat of the occupancy over a few pixels picks out:
    clearly darker than what lies beside it, darker than anything the thresholds read as free,
    not the unknown grey itself, and not the grey rim of a black wall. Only a drawing has them:
    where such lines are fewer than the black wall cells (a scan, whose grey marks are its
    uncertain cells), there are none. Each is grown by half a thin wall's thickness, where the
    lidar sees the wall's faces. Returns a new (H, W) bool array.
    """
    drawn = _drawn(m)
    return np.zeros(m.state.shape, bool) if drawn is None else drawn


def _drawn(
    m: OccupancyMap, line_cells: Callable[[], NDArray[np.bool_]] | None = None
) -> NDArray[np.bool_] | None:
    """:func:`drawn_walls`, None when the map is no drawing. ``line_cells()``: ``m``'s
    :func:`_line_cells`, when the caller has them (or may need them again)."""
    occ, state = m.occupancy, m.state
    # A scan has few cells of a line's grey levels and a trinary map none: a look at every
    # fourth row and column tells, before anything is counted exactly.
    if not _grey_levels(_Levels.of(occ[::4, ::4], state[::4, ::4]))[2]:
        return None
    counts = _Levels.of(occ, state)
    grey_levels, clearly, enough = _grey_levels(counts)
    if not enough:
        return None
    n_black = int(counts.occupied.sum())
    lines = (line_cells() if line_cells is not None else _line_cells(m)) & grey_levels[occ]
    # A drawing has more clear line pixels than black cells (a scan, its walls black, fewer).
    if np.count_nonzero(lines & clearly[occ]) <= n_black:
        return None
    return _grown(lines, m.resolution)


def _line_cells(m: OccupancyMap) -> NDArray[np.bool_]:
    """(H, W) bool: the cells of ``m`` on a line: clearly darker (``_LINE_CONTRAST``) than what
    lies beside them, by the top-hat (what an opening over a few pixels takes away), and not
    within two cells of a black wall (its grey rim, or a second trace of it)."""
    hat = cv2.morphologyEx(m.occupancy, cv2.MORPH_TOPHAT, _LINE_KERNEL)
    near_black = cv2.dilate((m.state == OCCUPIED).view(np.uint8), _LINE_KERNEL) > 0
    return np.asarray((hat >= _LINE_CONTRAST) & ~near_black)


def _long_runs(
    mask: NDArray[np.bool_], resolution: float
) -> tuple[NDArray[np.int32], NDArray[np.bool_]]:
    """The 8-connected runs of ``mask`` (H, W): their labels (H, W), 0 off them, and per label
    whether the run's longer side reaches a wall's length (``_LINE_MIN_LENGTH_M``: not a mark,
    not noise; False for label 0)."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    longest = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    long = longest * resolution >= _LINE_MIN_LENGTH_M
    long[0] = False
    return np.asarray(labels, np.int32), long


def _grown(mask: NDArray[np.bool_], resolution: float) -> NDArray[np.bool_]:
    """(H, W) bool: ``mask`` grown by half a thin wall (``_LINE_HALF_WALL_M``, rounded to whole
    cells: 2 at 0.05 m, 1 at the RMF drawing's 0.082 m, none over 0.16 m), where a lidar sees
    the faces of what a drawing draws."""
    grow = round(_LINE_HALF_WALL_M / resolution)
    if grow == 0:
        return np.asarray(mask, dtype=bool)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    return np.asarray(cv2.dilate(mask.view(np.uint8), kernel) > 0, dtype=bool)


# A line is at most a few pixels wide and at least this much darker (0..255 occupancy) than
# what lies beside it; anti-aliasing and scan noise on a uniform fill stay well below.
_LINE_KERNEL = np.ones((5, 5), np.uint8)
_LINE_CONTRAST = 30
# A drawn line shorter than this (its longer side) is a mark, not a wall.
_LINE_MIN_LENGTH_M = 0.6
# Half a wall's thickness (a thin one's): how far from a drawn line a lidar sees its faces.
_LINE_HALF_WALL_M = 0.08
# Occupancies this close to the unknown grey are that grey (resampled or re-encoded maps).
_UNKNOWN_BAND = 3
# map_saver's unknown grey (PGM 205) as an occupancy 0..255.
_SAVER_UNKNOWN = 255 - PGM_UNKNOWN


@dataclass(frozen=True)
class _Levels:
    """How many cells of a map have each occupancy (0..255), by state."""

    free: NDArray[np.int64]
    occupied: NDArray[np.int64]
    unknown: NDArray[np.int64]

    @staticmethod
    def of(occ: NDArray[np.uint8], state: NDArray[np.uint8]) -> _Levels:
        """In one pass (a 2-D histogram of occupancy and state), exact (cv2.calcHist counts in
        float32: at most 2**24 cells a call)."""
        occ, state = np.ascontiguousarray(occ), np.ascontiguousarray(state)
        h, w = occ.shape
        joint = np.zeros((256, 256), np.int64)
        if w > _HIST_CHUNK:
            np.add.at(joint, (occ.ravel(), state.ravel()), 1)
        else:
            step = _HIST_CHUNK // max(w, 1)
            for r in range(0, h, step):
                part = cv2.calcHist(
                    [occ[r : r + step], state[r : r + step]],
                    [0, 1],
                    None,
                    [256, 256],
                    [0, 256, 0, 256],
                )
                joint += part.astype(np.int64)
        return _Levels(joint[:, FREE], joint[:, OCCUPIED], joint[:, UNKNOWN])

    def unknown_level(self) -> int:
        """The map's unknown grey: the commonest occupancy of its unknown cells (127 if none)."""
        return int(np.argmax(self.unknown)) if self.unknown.any() else 127

    def free_top(self) -> int:
        """The largest occupancy a free cell has (0 if none)."""
        return int(np.flatnonzero(self.free)[-1]) if self.free.any() else 0


def known_points(m: OccupancyMap, *, state: int | None = None) -> FloatArray:
    """Centres (x, y) in the map's frame of its cells with ``state`` (default: all known)."""
    mask = (m.state != UNKNOWN) if state is None else (m.state == state)
    rows, cols = nonzero_cells(mask)
    x, y = m.pixel_to_world(cols, rows)
    return np.stack([x, y], axis=1)


def _known_corners(local: OccupancyMap) -> FloatArray:
    """The four corners (slam metres) of the bounding box of the local map's known cells."""
    x, y, w, h = cv2.boundingRect((local.state != UNKNOWN).view(np.uint8))
    grid = Grid.of_map(local)
    pts = grid.to_world(np.array([[x, y], [x + w - 1, y], [x, y + h - 1], [x + w - 1, y + h - 1]]))
    half = local.resolution / 2
    return np.asarray(pts + np.array([[-half, half], [half, half], [-half, -half], [half, -half]]))


def make_view(
    global_map: OccupancyMap,
    local: OccupancyMap,
    prior: Transform2D,
    *,
    search_xy_m: float,
    search_theta_rad: float = math.pi,
    margin_m: float = 1.0,
    pivot_slam: tuple[float, float] | None = None,
    wall_reach_m: float = 0.0,
    drawing: OccupancyMap | None = None,
) -> GlobalView:
    """Crop and resample the global map around where the prior puts the local map (a
    :class:`GlobalView` with ``wall_reach_m``).

    ``drawing``: another map of the same lattice to read the drawn walls from, where its cell
    states are the global map's (the stored map's version 1, a floor-plan drawing, when the
    global map is a later version written by map_saver's rules, which keep only states).

    The work resolution is the finer of the two maps' resolutions, so that neither map loses
    detail. Only the crop is touched, never the whole global map. The crop holds the local map
    turned about ``pivot_slam`` (default: its centroid) by up to ``search_theta_rad`` either way
    and shifted by up to ``search_xy_m``. Its pixels coincide with the global map's.
    """
    if pivot_slam is None:
        centre = known_points(local).mean(axis=0)
    else:
        centre = np.asarray(pivot_slam, dtype=float)
    # The box that holds the local map's known area turned by any angle the search tries about
    # the pivot (and a little more), wherever the prior puts the pivot.
    corners = _known_corners(local) - centre
    angles = np.linspace(-search_theta_rad - 0.1, search_theta_rad + 0.1, 15)
    xs, ys = [], []
    for a in angles:
        c, s_ = math.cos(prior.theta + a), math.sin(prior.theta + a)
        xs.append(c * corners[:, 0] - s_ * corners[:, 1])
        ys.append(s_ * corners[:, 0] + c * corners[:, 1])
    # Chords between sampled angles cut inside the arcs: grow by the largest sagitta.
    sagitta = float(np.hypot(corners[:, 0], corners[:, 1]).max()) * (
        1 - math.cos((angles[1] - angles[0]) / 2)
    )
    pad = search_xy_m + margin_m + sagitta + local.resolution
    px, py = prior.apply(centre)
    lo_x, hi_x = px + np.min(xs) - pad, px + np.max(xs) + pad
    lo_y, hi_y = py + np.min(ys) - pad, py + np.max(ys) + pad
    resolution = min(global_map.resolution, local.resolution)
    # Snap the grid to the global map's pixel lattice: resampling it is then an exact copy (or
    # an exact split of its pixels), whatever the view's size or place.
    ox, oy = global_map.origin[0], global_map.origin[1]
    x0 = ox + math.floor((lo_x - ox) / resolution) * resolution
    y0 = oy + math.floor((lo_y - oy) / resolution) * resolution
    grid = Grid.covering(x0, y0, hi_x, hi_y, resolution)
    cx, cy = (lo_x + hi_x) / 2, (lo_y + hi_y) / 2
    half = max(hi_x - lo_x, hi_y - lo_y) / 2 + resolution
    src = Grid.of_map(global_map)
    # Crop the source to the box first: the warp then reads only the pixels it needs.
    c0, r0 = np.floor(src.to_pixel([[cx - half, cy + half]])[0]).astype(int) - 1
    c1, r1 = np.ceil(src.to_pixel([[cx + half, cy - half]])[0]).astype(int) + 2
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, global_map.width), min(r1, global_map.height)
    if c1 <= c0 or r1 <= r0:
        state = np.full(grid.shape, UNKNOWN, np.uint8)
        return GlobalView(grid, state, np.zeros(grid.shape, bool), wall_reach_m)
    crop_grid = src.crop((r0, r1, c0, c1))
    crop = OccupancyMap(
        global_map.state[r0:r1, c0:c1],
        global_map.occupancy[r0:r1, c0:c1],
        global_map.resolution,
        (crop_grid.x0, crop_grid.y0, 0.0),
    )
    source, same = crop, None
    if drawing is not None and (drawing.width, drawing.height) == (
        global_map.width,
        global_map.height,
    ):
        source = OccupancyMap(
            drawing.state[r0:r1, c0:c1],
            drawing.occupancy[r0:r1, c0:c1],
            drawing.resolution,
            (crop_grid.x0, crop_grid.y0, 0.0),
        )
        same = source.state == crop.state  # not where a published change differs
    whole = global_map if source is crop else drawing
    assert whole is not None
    structure_u8, walls, box_rims = _drawn_structure(source, same, whole=whole)
    if source is not crop:
        structure_u8 |= _structure(crop, None).astype(np.uint8)
    state = resample(crop.state, crop_grid, grid)
    raw = None
    if walls is not None:
        raw = state
        states = np.where(walls, OCCUPIED, crop.state)
        if box_rims is not None:
            states[box_rims & (states == FREE)] = UNKNOWN
        state = resample(states.astype(np.uint8), crop_grid, grid)
    structure = resample(structure_u8, crop_grid, grid, fill=0).astype(bool)
    return GlobalView(grid, state, structure, wall_reach_m, raw)


def _saver_unknown(m: OccupancyMap) -> bool:
    """Whether the unknown grey of the whole map ``m`` is map_saver's (PGM 205), read on every
    fourth row and column: a scan (or a map written by map_saver's rules), not a drawing with
    an unknown grey of its own. Asked of the whole map, not of a crop, which may hold none of
    its unknown but the grey walls themselves."""
    occ = np.ascontiguousarray(m.occupancy[::4, ::4])
    unknown = np.ascontiguousarray(m.state[::4, ::4]) == UNKNOWN
    counts = _histogram_where(occ, unknown)
    return bool(counts.any()) and abs(int(np.argmax(counts)) - _SAVER_UNKNOWN) <= _UNKNOWN_BAND


def _drawn_structure(
    m: OccupancyMap, same: NDArray[np.bool_] | None, *, whole: OccupancyMap
) -> tuple[NDArray[np.uint8], NDArray[np.bool_] | None, NDArray[np.bool_] | None]:
    """The alignment's walls of ``m`` (uint8 0/1, a crop of ``whole``), the cells its
    drawing makes walls for the differences, and the rims of a drawing's grey boxes (each
    (H, W) bool, None if none), all only where ``same`` (when given)."""
    # The line cells, for the drawing's lines and for the ridges of walls drawn grey: a
    # top-hat of the whole map, worked out once, and only if either asks.
    line_cells = cache(partial(_line_cells, m))
    drawn = _drawn(m, line_cells)
    if drawn is not None and same is not None:
        drawn &= same
    unknown_level = _unknown_level(m)
    structure = _structure(m, drawn, unknown_level)
    if same is not None:
        structure &= same | (m.state == OCCUPIED)
    walls = np.zeros(m.state.shape, bool)
    box_rims = None
    if drawn is not None:
        # A drawing's walls are walls, for the differences as for the search: a wall drawn
        # and then seen gone is a removed one. Not its marks (a cross, a dot, a letter): the
        # lines that run at least a while. In a map whose unknown grey is map_saver's (a scan
        # whose walls came out grey passes for a drawing), only lines drawn lighter than that
        # grey: darker ones are its grey walls, measured against as any wall drawn grey is
        # (below). A drawing with an unknown grey of its own (label boxes) was never through
        # map_saver: every line is ink.
        labels, long_lines = _long_runs(drawn, m.resolution)
        if _saver_unknown(whole):
            long_lines &= _median_ink(m, labels, len(long_lines)) < _SAVER_UNKNOWN - _UNKNOWN_BAND
        else:
            # Its grey boxes (labels, icons, in its unknown grey) are drawn as its lines are,
            # their edges anti-aliased into cells read as free: what a box stands for reaches
            # as far beyond its grey as a line's wall beyond its ink. Those cells are unknown
            # for the differences (a face seen there is the box's), not floor.
            box_rims = _grown(m.state == UNKNOWN, m.resolution) & (m.state == FREE)
        walls |= long_lines[labels]
    # Walls drawn grey (darker than the unknown grey, read as unknown): their cores are walls
    # for the differences too, a wall drawn and seen gone is removed; not their blurred rims.
    # A thin wall has no core (two pixels wide, an erosion leaves nothing): its darkest line.
    grey_walls = structure & (m.state == UNKNOWN)
    if grey_walls.any():
        walls |= cv2.erode(grey_walls.view(np.uint8), np.ones((3, 3), np.uint8)) > 0
        walls |= _grey_ridges(m, grey_walls, line_cells())
    if same is not None:
        walls &= same
        if box_rims is not None:
            box_rims &= same
    return structure.astype(np.uint8), (walls if walls.any() else None), box_rims


def _grey_ridges(
    m: OccupancyMap, grey_walls: NDArray[np.bool_], line_cells: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """(H, W) bool: the cells of ``grey_walls`` (H, W) on the ridge of a line, where a wall
    drawn grey stands. A cell on it is as dark as the darkest cell beside it but for
    ``_RIDGE_DROP`` (a line drawn two pixels wide has two such cells across it), is on a line
    as a drawing's are (``line_cells``, ``m``'s :func:`_line_cells`: a gentle slope of grey is
    none, however flat; a black wall's rim or second trace is none), and lies in a run of a
    wall's length
    (:func:`_long_runs`: not a mark, not scan noise)."""
    occ = m.occupancy
    darkest = cv2.dilate(occ, np.ones((3, 3), np.uint8))  # never lighter than the cell
    ridge = grey_walls & ((darkest - occ) <= _RIDGE_DROP) & line_cells
    labels, long = _long_runs(ridge, m.resolution)
    return np.asarray(long[labels], dtype=bool)


# How much lighter (0..255 occupancy) than the darkest cell beside it a cell on a grey wall's
# ridge may be: a line's two pixels, or a flat core's noise; a blurred rim drops far more.
_RIDGE_DROP = 12


# --- scoring ---------------------------------------------------------------------------------


def agreement(
    points_slam: FloatArray,
    nav2_from_slam: Transform2D,
    grid: Grid,
    near_walls: NDArray[np.bool_],
) -> float:
    """Share of local wall points that land on ``near_walls`` (the cells within the tolerance
    of a global wall, :meth:`GlobalView.near_walls`)."""
    if len(points_slam) == 0:
        return 0.0
    return float(np.mean(grid.sample(near_walls, nav2_from_slam.apply(points_slam), False)))


def consistency(
    local: OccupancyMap,
    nav2_from_slam: Transform2D,
    view: GlobalView,
    *,
    tolerance_m: float,
) -> float:
    """Share of the global walls inside the local map's known area that the local map does not
    contradict (sees free, with no local wall within ``tolerance_m``).

    The counterpart of :func:`agreement`: a wrong alignment in a building of right angles can
    put many local walls on global walls, but it also runs global walls through space the robot
    saw empty.
    """
    res = view.grid.resolution
    reach = offset_distances(tolerance_m / res)
    k = reach.shape[0] // 2
    landed = _landed(local, nav2_from_slam, view, k)
    if landed is None:
        return 0.0
    local_state, structure = landed
    # Only the box around the local map's known cells (and the tolerance's reach) counts.
    box = box_around(local_state != UNKNOWN, k)
    if box is None:
        return 0.0
    local_state = local_state[box]
    walls = structure[box] & (local_state != UNKNOWN)
    n = int(np.count_nonzero(walls))
    if n == 0:
        return 0.0
    seen_free = _seen_through(walls, local_state, reach, res, tolerance_m)
    return 1.0 - float(np.count_nonzero(seen_free)) / n


def _landed(
    local: OccupancyMap, nav2_from_slam: Transform2D, view: GlobalView, reach_px: int
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]] | None:
    """The local map's states warped onto the box of ``view``'s grid its known cells land in
    (with ``reach_px`` and two pixels more around), and the view's structure there; None when
    none lands on the grid."""
    landing = landing_box(local, view.grid, nav2_from_slam, margin_px=reach_px + 2)
    if landing is None:
        return None
    r0, r1, c0, c1 = landing
    local_state = resample(local.state, Grid.of_map(local), view.grid.crop(landing), nav2_from_slam)
    return local_state, view.structure[r0:r1, c0:c1]


def _seen_through(
    walls: NDArray[np.bool_],
    local_state: NDArray[np.uint8],
    reach: NDArray[np.float32],
    res: float,
    tolerance_m: float,
) -> NDArray[np.bool_]:
    """The cells of ``walls`` (global walls the local map knows) that it sees free with no
    local wall within ``tolerance_m`` (``reach``: :func:`~mapserver.diff.offset_distances`
    for it at ``res``)."""
    seen_free = walls & (local_state == FREE)
    if seen_free.any():
        local_walls = local_state == OCCUPIED
        if local_walls.any():
            # "No local wall within tolerance" as a dilation: the same cells as thresholding
            # the distance transform, several times cheaper (see diff.offset_distances).
            seen_free &= ~near(local_walls, ~(reach * res > tolerance_m))
    return np.asarray(seen_free, dtype=bool)


# A transform whose score is under the minimum is still trusted when its unchanged_score is at
# least this much over the minimum (0.85 for the default 0.6; a minimum over 0.75 leaves no
# room): a stricter bar, since it leaves out what disagrees as changes.
UNCHANGED_MARGIN = 0.25
# Local walls farther than this from every drawn structure are new objects in open floor (or
# walls no alignment nearby explains); nearer, a wall the alignment put off a drawn one counts.
_NEAR_STRUCTURE_M = 1.0
# ... and at least this share of the local walls must lie that near, so that most of the map
# is checked at all.
_MIN_NEAR_SHARE = 0.3
# A drawn structure (a connected group of cells) seen free over this share of its cells inside
# what the robot saw is gone as a whole: a removal, not a misfit, which cuts structures partly.
_GONE_SHARE = 0.8
# ... and no more than this share of the drawn structures the robot saw may be gone.
_MAX_GONE_SHARE = 0.4
# Only an object can be gone whole: a structure whose bounding box is at most this across
# (a column, a shelf, a kiosk; not a building's joined walls, one structure of the map).
_MAX_GONE_M = 2.0
# A structure of which the robot saw fewer cells than this (a sliver at the edge of what it
# saw) is not counted among the structures seen, gone or standing.
_MIN_SEEN_CELLS = 20


def unchanged_score(
    local: OccupancyMap,
    walls_slam: FloatArray,
    nav2_from_slam: Transform2D,
    view: GlobalView,
    *,
    tolerance_m: float,
) -> float:
    """The score of an alignment (as :func:`agreement` and :func:`consistency` make it) on the
    structure that did not change: 0..1.

    In a sparse hall the changes can outweigh the building: new objects in open floor pull the
    agreement down, drawn columns seen gone the consistency, and a transform right to a few
    centimetres scores under the minimum. A person sees at once that what is left fits. Here:

    - the agreement counts only the local walls (``walls_slam``, slam metres) within
      ``_NEAR_STRUCTURE_M`` of a drawn structure, and at least ``_MIN_NEAR_SHARE`` of them
      must lie there (else 0);
    - the consistency leaves out each drawn structure (8-connected drawn cells) at most
      ``_MAX_GONE_M`` across that the robot saw free over ``_GONE_SHARE`` of its seen cells,
      up to ``_MAX_GONE_SHARE`` of the structures it saw (``_MIN_SEEN_CELLS`` or more of their
      cells; else 0).

    A wrong transform puts local walls beside the drawn ones (within reach, off the tolerance)
    and runs drawn walls partly through seen floor: both still count against it. Not a wrong
    one by a whole period of repeated structure (a hall of identical columns, a prior off by
    their spacing): there, as for a hall that did not change, nothing in view tells them apart.
    """
    if len(walls_slam) == 0:
        return 0.0
    on_slam = nav2_from_slam.apply(walls_slam)
    on = view.grid.sample(view.near_walls(tolerance_m), on_slam, False)
    near_structure = view.near_walls_at(on_slam, _NEAR_STRUCTURE_M)
    checked = int(np.count_nonzero(near_structure))
    if checked < 20 or checked < _MIN_NEAR_SHARE * len(walls_slam):
        return 0.0
    agree = float(np.count_nonzero(on & near_structure)) / checked
    res = view.grid.resolution
    reach = offset_distances(tolerance_m / res)
    landed = _landed(local, nav2_from_slam, view, reach.shape[0] // 2)
    if landed is None:
        return 0.0
    local_state, structure = landed
    walls = structure & (local_state != UNKNOWN)
    seen_free = _seen_through(walls, local_state, reach, res, tolerance_m)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(structure.view(np.uint8), connectivity=8)
    seen = np.bincount(labels[walls], minlength=n)
    free = np.bincount(labels[seen_free], minlength=n)
    seen[0] = 0  # label 0: no structure
    counted = seen >= _MIN_SEEN_CELLS
    across = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) * res
    gone = counted & (across <= _MAX_GONE_M) & (free >= _GONE_SHARE * seen)
    # Counted in structures, not cells: one seen gone shows all its cells, one standing only its
    # faces.
    left = int(seen[~gone].sum())
    if left == 0 or np.count_nonzero(gone) > _MAX_GONE_SHARE * np.count_nonzero(counted):
        return 0.0
    consistent = 1.0 - float(free[~gone].sum()) / left
    return math.sqrt(agree * consistent)


# --- correlative search ----------------------------------------------------------------------


@dataclass(frozen=True)
class _Level:
    grid: Grid
    field: NDArray[np.float32]  # likelihood of a wall, 0..1, padded by `pad` pixels
    pad: int


def _make_level(view: GlobalView, factor: int, pad: int) -> _Level:
    g = view.grid
    if factor > 1:
        # Max-pool the walls over factor x factor blocks (from the top-left corner) so that thin
        # ones survive the downsampling: a dilation read at every factor-th cell.
        pooled = cv2.dilate(
            view.structure.view(np.uint8),
            np.ones((factor, factor), np.uint8),
            anchor=(0, 0),
            borderType=cv2.BORDER_CONSTANT,
            borderValue=0,
        )[::factor, ::factor]
        h, w = pooled.shape
        top = g.y0 + g.height * g.resolution
        grid = Grid(g.x0, top - h * factor * g.resolution, factor * g.resolution, w, h)
        structure = pooled > 0
    else:
        structure, grid = view.structure, g
    d = distance_to(structure)
    field = np.exp(-0.5 * (d / 1.0) ** 2).astype(np.float32)
    field = cv2.copyMakeBorder(field, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    return _Level(grid, field, pad)


def thin_points(points: FloatArray, resolution: float, *, mean: bool = False) -> FloatArray:
    """One point per cell of side ``resolution`` (keeps the cloud's shape, bounds its size),
    cells in the order of their first point: that first point, or with ``mean`` the mean of
    the cell's points.

    The first point is a point of the cloud, but in a raster's row-major order it is the
    cell's top-left one: where a cell holds a wall two cells thick, half a map cell off the
    wall's middle. An ICP or a drift estimate on such points carries that offset into the
    transform (a few millimetres, always the same way along the local map's axes); on the mean,
    not that offset. The mean of a cell that holds a corner lies off the walls, though: ``mean``
    for cells of a few map cells, not for the coarse ones of a search.
    """
    keys = np.floor(points / resolution).astype(np.int64)
    if len(keys) == 0:
        return points[:0]
    # One integer per cell (rows of keys as one number: a 1-D unique, far faster than axis=0).
    keys -= keys.min(axis=0)
    cell = keys[:, 0] * (int(keys[:, 1].max()) + 1) + keys[:, 1]
    if not mean:
        _, index = np.unique(cell, return_index=True)
        return np.asarray(points[np.sort(index)], dtype=np.float64)
    _, first, inverse, counts = np.unique(
        cell, return_index=True, return_inverse=True, return_counts=True
    )
    x = np.bincount(inverse, weights=points[:, 0]) / counts
    y = np.bincount(inverse, weights=points[:, 1]) / counts
    order = np.argsort(first)
    return np.column_stack([x[order], y[order]])


def _search_level(
    level: _Level,
    points: FloatArray,
    centre: FloatArray,
    target: FloatArray,
    thetas: FloatArray,
    shift_px: int,
) -> list[tuple[float, float, float, float]]:
    """For every rotation, the best translation of the cloud within +-shift_px pixels.

    The candidate maps the local centroid ``centre`` to ``target`` + shift after rotating the
    cloud by theta about it. Returns (score, theta, target_x, target_y) per theta.
    """
    grid, field, pad = level.grid, level.field, level.pad
    assert shift_px <= pad
    rel = points - centre
    width = field.shape[1]
    flat_field = field.ravel()
    span = np.arange(-shift_px, shift_px + 1)
    shifts = (span[:, None] * width + span[None, :]).ravel()  # row-major (i, j)
    out = []
    for theta in thetas:
        c, s = math.cos(theta), math.sin(theta)
        q = np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], 1) + target
        px = np.rint(grid.to_pixel(q)).astype(np.int64) + pad
        cmin, rmin = px.min(axis=0)
        cmax, rmax = px.max(axis=0)
        cmin, rmin = max(cmin, shift_px), max(rmin, shift_px)
        cmax = min(cmax, field.shape[1] - 1 - shift_px)
        rmax = min(rmax, field.shape[0] - 1 - shift_px)
        if cmax < cmin or rmax < rmin:
            out.append((0.0, float(theta), float(target[0]), float(target[1])))
            continue
        keep = (px[:, 0] >= cmin) & (px[:, 0] <= cmax) & (px[:, 1] >= rmin) & (px[:, 1] <= rmax)
        # The correlation of the field with the cloud's cells (each cell once) at every shift.
        cells = np.unique(px[keep, 1] * width + px[keep, 0])
        area = (rmax - rmin + 1) * (cmax - cmin + 1)
        if len(shifts) * len(cells) <= area:
            # Few shifts (a fine level): the sums of the field at the moved cells, directly.
            sums = flat_field[cells[None, :] + shifts[:, None]].sum(axis=1, dtype=np.float64)
            k = int(np.argmax(sums))  # the first best, in row-major order as cv2.minMaxLoc
            best = sums[k] / max(len(points), 1)
            i, j = divmod(k, 2 * shift_px + 1)
        else:
            template = np.zeros((rmax - rmin + 1, cmax - cmin + 1), np.float32)
            template[px[keep, 1] - rmin, px[keep, 0] - cmin] = 1.0
            region = field[
                rmin - shift_px : rmax + shift_px + 1, cmin - shift_px : cmax + shift_px + 1
            ]
            response = cv2.matchTemplate(region, template, cv2.TM_CCORR) / max(len(points), 1)
            _, best, _, (j, i) = cv2.minMaxLoc(response)
        dx = (j - shift_px) * grid.resolution
        dy = -(i - shift_px) * grid.resolution
        out.append((float(best), float(theta), float(target[0] + dx), float(target[1] + dy)))
    return out


def _to_transform(theta: float, centre: FloatArray, target_xy: FloatArray) -> Transform2D:
    c, s = math.cos(theta), math.sin(theta)
    tx = target_xy[0] - (c * centre[0] - s * centre[1])
    ty = target_xy[1] - (s * centre[0] + c * centre[1])
    return Transform2D(wrap_angle(theta), float(tx), float(ty))


def _local_maxima(rows: list[tuple[float, float, float, float]], keep: int) -> list[int]:
    """Indices of the best rotation candidates: local maxima over theta, best first."""
    scores = np.array([r[0] for r in rows])
    n = len(scores)
    idx = [
        i
        for i in range(n)
        if scores[i] >= scores[max(i - 1, 0)] and scores[i] >= scores[min(i + 1, n - 1)]
    ]
    idx.sort(key=lambda i: -scores[i])
    return idx[:keep]


# --- ICP polish ------------------------------------------------------------------------------


class NearestWall:
    """The (col, row) of the nearest structure cell (5x5 chamfer distance), for every cell.

    Indexed like an (H, W, 2) float array with two integer arrays: ``field[rows, cols]`` is
    (N, 2). It keeps the distance transform's labels (4 bytes a cell) and a table of the
    structure cells, and looks cells up on demand, instead of building that array (16 bytes a
    cell, mostly never read).
    """

    def __init__(
        self,
        labels: NDArray[np.int32],
        table: FloatArray,
        *,
        shape: tuple[int, int] | None = None,
        origin: tuple[int, int] = (0, 0),
    ) -> None:
        self._labels = labels
        self._table = table
        self._origin = origin
        self.shape = (*(shape or labels.shape), 2)
        # The labels with a ring of label 0 around them (built on the first lookup): a lookup
        # clips its cells onto the ring instead of testing which lie off the box.
        self._ring: NDArray[np.int32] | None = None
        self._xy: dict[Grid, tuple[FloatArray, FloatArray]] = {}

    @staticmethod
    def of(
        structure: NDArray[np.bool_], box: tuple[int, int, int, int] | None = None
    ) -> NearestWall:
        """The field over ``structure``, or only over ``box`` = (row0, col0, row1, col1) of it
        (cells outside the box then have no nearest wall: it reads as infinitely far)."""
        r0, c0, r1, c1 = box or (0, 0, *structure.shape)
        part = np.ascontiguousarray(structure[r0:r1, c0:c1])
        _, labels = cv2.distanceTransformWithLabels(
            (~part).view(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        # Labels of zero pixels are numbered in row-major scan order, starting at 1; label 0
        # (no wall in the box at all) reads as a wall infinitely far away.
        rows, cols = nonzero_cells(part)
        table = np.full((len(rows) + 1, 2), 1e9)
        table[1:, 0], table[1:, 1] = cols + c0, rows + r0  # (col, row) on the grid
        return NearestWall(
            np.asarray(labels, np.int32),
            table,
            shape=(structure.shape[0], structure.shape[1]),
            origin=(r0, c0),
        )

    def _label_at(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.intp]:
        """The nearest wall's row of the table for each cell; 0 (no wall) off the box."""
        if self._ring is None:
            self._ring = np.pad(self._labels, 1)
        h, w = self._ring.shape
        # Flat lookups (take) of cells clipped onto the ring: ICP and the drift estimate call
        # this every iteration, so in place where it can be.
        r = rows - (self._origin[0] - 1)
        c = cols - (self._origin[1] - 1)
        np.clip(r, 0, h - 1, out=r)
        np.clip(c, 0, w - 1, out=c)
        r *= w
        r += c
        return np.asarray(self._ring.ravel().take(r))

    def __getitem__(self, index: tuple[NDArray[np.intp], NDArray[np.intp]]) -> FloatArray:
        return np.asarray(self._table.take(self._label_at(*index), axis=0))

    def covers(self, box: tuple[int, int, int, int]) -> bool:
        r0, c0 = self._origin
        h, w = self._labels.shape
        return box[0] >= r0 and box[1] >= c0 and box[2] <= r0 + h and box[3] <= c0 + w

    def nearest_xy(self, x: FloatArray, y: FloatArray, grid: Grid) -> tuple[FloatArray, FloatArray]:
        """The x and the y (metres, (N,) each) of the wall cell nearest the cells that hold
        points ``(x, y)`` (metres on ``grid``, the field's grid); 1e9 for points off the field,
        as far as no wall. ``grid.to_world`` is done once per wall cell (and kept), not per
        lookup."""
        if grid not in self._xy:
            table = grid.to_world(self._table)
            table[0] = 1e9  # no wall in the box: infinitely far, in metres too
            self._xy[grid] = (np.ascontiguousarray(table[:, 0]), np.ascontiguousarray(table[:, 1]))
        tx, ty = self._xy[grid]
        res = grid.resolution
        col = np.rint((x - grid.x0) / res - 0.5).astype(np.int64)
        row = np.rint(grid.height - (y - grid.y0) / res - 0.5).astype(np.int64)
        label = self._label_at(row, col)
        return np.asarray(tx.take(label)), np.asarray(ty.take(label))


def icp(
    points_slam: FloatArray,
    start: Transform2D,
    grid: Grid,
    nearest: NearestWall,
    *,
    max_distance_m: float,
    iterations: int = 30,
) -> Transform2D:
    """Point-to-point ICP of local wall points onto the nearest global wall cells: one start
    (see :func:`icp_many`)."""
    (found,) = icp_many(
        points_slam, [start], grid, nearest, max_distance_m=max_distance_m, iterations=iterations
    )
    return found


def icp_many(
    points_slam: FloatArray,
    starts: Sequence[Transform2D],
    grid: Grid,
    nearest: NearestWall,
    *,
    max_distance_m: float,
    iterations: int = 30,
) -> list[Transform2D]:
    """Point-to-point ICP of local wall points onto the nearest global wall cells, from each of
    ``starts`` on its own; the polished transforms in the same order.

    Correspondences come from a precomputed nearest-wall field, so every iteration is one lookup
    and one closed-form rigid fit (no scale). Pairs farther than ``max_distance_m`` (new
    obstacles, people, drift) are left out; the threshold shrinks to a third over the iterations.
    A start stops when fewer than 10 pairs are left (its transform as it was) or when a step
    moves it less than 0.1 mm.

    All starts run as rows of one array: a piece's few hundred wall points make each numpy
    operation cost more in its call than in its arithmetic, so one call for every start, not
    one per start. A pair left out weighs zero in the sums instead of being dropped, which keeps
    the rows rectangular.
    """
    theta = np.array([t.theta for t in starts], dtype=float)
    tx = np.array([t.tx for t in starts], dtype=float)
    ty = np.array([t.ty for t in starts], dtype=float)
    sx, sy = np.ascontiguousarray(points_slam[:, 0]), np.ascontiguousarray(points_slam[:, 1])
    live = np.arange(len(starts))
    for k in range(iterations):
        if len(live) == 0:
            break
        limit = max_distance_m * (1.0 - 0.66 * k / max(iterations - 1, 1))
        c, s = np.cos(theta[live])[:, None], np.sin(theta[live])[:, None]
        qx = c * sx - s * sy + tx[live, None]
        qy = s * sx + c * sy + ty[live, None]
        wx, wy = nearest.nearest_xy(qx.ravel(), qy.ravel(), grid)  # off the field: never near
        wx, wy = wx.reshape(qx.shape), wy.reshape(qx.shape)
        ex, ey = wx - qx, wy - qy
        use = (ex * ex + ey * ey <= limit * limit).astype(float)
        n = use.sum(axis=1)
        fits = n >= 10
        live, use, n, wx, wy = live[fits], use[fits], n[fits], wx[fits], wy[fits]
        if len(live) == 0:
            break
        # Sums of products, not matrix products (see Transform2D.apply).
        msx, msy = (use * sx).sum(axis=1) / n, (use * sy).sum(axis=1) / n
        mdx, mdy = (use * wx).sum(axis=1) / n, (use * wy).sum(axis=1) / n
        ux, uy = sx - msx[:, None], sy - msy[:, None]
        vx, vy = (wx - mdx[:, None]) * use, (wy - mdy[:, None]) * use
        # The closed-form rigid fit: the rotation from the cross-covariance of the pairs.
        sxy = (ux * vy).sum(axis=1) - (uy * vx).sum(axis=1)
        new = np.arctan2(sxy, (ux * vx).sum(axis=1) + (uy * vy).sum(axis=1))
        c1, s1 = np.cos(new), np.sin(new)
        ntx = mdx - (c1 * msx - s1 * msy)
        nty = mdy - (s1 * msx + c1 * msy)
        step = np.hypot(ntx - tx[live], nty - ty[live])
        theta[live], tx[live], ty[live] = new, ntx, nty
        if k > 5:
            live = live[step >= 1e-4]
    return [
        Transform2D(float(a), float(b), float(c)) for a, b, c in zip(theta, tx, ty, strict=True)
    ]


# --- the whole refinement --------------------------------------------------------------------


def _distance(a: Transform2D, b: Transform2D, centre: FloatArray, radius: float) -> float:
    """How far apart two transforms put the local map: metres at the centroid, plus the arc."""
    da = a.apply(centre) - b.apply(centre)
    return float(math.hypot(da[0], da[1]) + radius * abs(wrap_angle(a.theta - b.theta)))


def _search(
    walls: FloatArray,
    view: GlobalView,
    prior: Transform2D,
    *,
    theta_half_rad: float,
    search_xy_m: float,
    candidates: int,
    fine_levels: int,
    pivot: FloatArray | None = None,
) -> list[Transform2D]:
    """Correlative search around the prior; returns the candidates before the ICP polish.

    Rotations turn the map about ``pivot`` (slam frame; default the walls' centroid): about the
    robot's pose, a mislocalised prior's error is a rotation plus a small shift. The coarse
    level has about 60 pixels across the wall cloud (never finer than the work grid), so its
    cost is bounded whatever the map size; the best rotation candidates, and the prior, then
    descend ``fine_levels`` halvings of the resolution.
    """
    centroid = np.asarray(walls.mean(axis=0), dtype=np.float64)
    size = max(float(np.sqrt(((walls - centroid) ** 2).sum(axis=1)).max()), 1.0)
    centre = centroid if pivot is None else np.asarray(pivot, dtype=float)
    radius = max(float(np.sqrt(((walls - centre) ** 2).sum(axis=1)).max()), 1.0)
    target0 = prior.apply(centre)
    # Level cells are whole numbers of work cells (pooling is then exact, and cheap).
    vres = view.grid.resolution
    factors = [int(np.clip(round(size / 30.0 / vres), 1, max(1, math.floor(0.5 / vres + 1e-9))))]
    while len(factors) <= fine_levels and factors[-1] / 2.0 >= 1.5:
        factors.append(round(factors[-1] / 2.0))
    res0 = factors[0] * vres
    shift0 = math.ceil(search_xy_m / res0) + 1
    levels = [view.level(f, shift0 + 4) for f in factors]

    step0 = res0 / radius
    n = max(1, math.ceil(theta_half_rad / step0))
    thetas = np.asarray(prior.theta + step0 * np.arange(-n, n + 1), dtype=np.float64)
    coarse = _search_level(levels[0], thin_points(walls, res0), centre, target0, thetas, shift0)
    seeds = [(coarse[i][1], np.array(coarse[i][2:])) for i in _local_maxima(coarse, candidates)]
    seeds.append((prior.theta, target0))
    fine_points = [thin_points(walls, level.grid.resolution) for level in levels[1:]]
    out = []
    for theta, target in seeds:
        step = step0
        for level, pts in zip(levels[1:], fine_points, strict=True):
            step /= 2.0
            turns = np.asarray(theta + step * np.arange(-2, 3), dtype=np.float64)
            rows = _search_level(level, pts, centre, target, turns, 2)
            best = max(rows)
            theta, target = best[1], np.array(best[2:])
        out.append(_to_transform(theta, centre, target))
    return out


def align(
    local: OccupancyMap,
    view: GlobalView,
    prior: Transform2D,
    *,
    refine: bool = True,
    search_xy_m: float = 2.5,
    search_theta_rad: float = math.radians(35.0),
    min_score: float = 0.6,
    min_gain: float = 0.02,
    jump_m: float = 0.5,
    tolerance_m: float = 0.1,
    candidates: int = 4,
    narrow_theta_rad: float = math.radians(8.0),
    pivot_slam: tuple[float, float] | None = None,
    widen: Callable[[], GlobalView] | None = None,
    prior_confirmed: Callable[[Transform2D], bool] | None = None,
    edge_margin: float = 0.0,
) -> Alignment:
    """Refine ``prior`` (nav2_from_slam) by matching the local map's walls to the global map's.

    1. Correlative search over rotation and translation around the prior (:func:`_search`),
       first within ``narrow_theta_rad`` (priors are usually within a few degrees), and over the
       whole ``search_theta_rad`` only when that finds no convincing fit (a mislocalised robot).
    2. Each candidate is polished with ICP and scored on the same cells: the geometric mean of
       :func:`agreement` and :func:`consistency`. Among candidates within a whisker of the best,
       a distinct one nearer the prior wins (repeated structure). It replaces the prior when it
       scores better; when it lies more than ``jump_m`` away from the prior (a distinct
       solution, not a polish of the prior) it must score ``min_gain`` more.

    Rotations are searched about ``pivot_slam``, the robot's position in the slam frame when
    known (the prior comes from the robot's pose there), else about the walls' centroid.

    ``view`` must cover the narrow search at least. When it covers only that, ``widen`` gives
    the view the wide search needs (built only if the wide search runs).

    ``prior_confirmed(narrow_best)``, when given, is asked before the wide search when the
    narrow search's best fit is not trusted: True says the prior holds after all (a part of the
    map aligned on its own put the robot where the prior does: the map is bent, the prior is
    not off), and the wide search is skipped.

    A transform scoring under ``min_score`` by at most ``edge_margin`` is trusted when its score
    with the edges of what the global map knows counted as walls (:meth:`GlobalView.near_edges_at`)
    reaches ``min_score``: a map that ends its floor where a wall stands without drawing the
    wall dark. Near the bar only: edges are everywhere in such a map, and far under it they
    would lift a wrong transform too.

    A failed alignment is a value, not an exception: ``trusted`` is false and a warning says why.
    """
    walls = known_points(local, state=OCCUPIED)
    warnings: list[str] = []
    near_walls = view.near_walls(tolerance_m)

    def agree(t: Transform2D) -> float:
        return agreement(walls, t, view.grid, near_walls)

    def score(t: Transform2D, p: float | None = None) -> float:
        p = agree(t) if p is None else p
        q = consistency(local, t, view, tolerance_m=tolerance_m) if p > 0 else 0.0
        return math.sqrt(p * q)

    prior_score = score(prior)

    def trust(t: Transform2D, s: float) -> tuple[bool, float | None, float | None]:
        """Trusted, and the unchanged score or the score with the known floor's edges when
        that is what trusts it."""
        if s >= min_score:
            return True, None, None
        if edge_margin > 0 and s >= min_score - edge_margin:
            at = t.apply(walls)
            on = view.grid.sample(near_walls, at, False) | view.near_edges_at(at, tolerance_m)
            with_edges = score(t, float(np.mean(on)))
            if with_edges >= min_score:
                warnings.append(_trusted_on_edges(s, min_score, with_edges))
                return True, None, with_edges
        unchanged = unchanged_score(local, walls, t, view, tolerance_m=tolerance_m)
        if unchanged < min_score + UNCHANGED_MARGIN:
            warnings.append(_untrusted(s, min_score))
            return False, None, None
        warnings.append(_trusted_unchanged(s, min_score, unchanged))
        return True, unchanged, None

    def keep_prior(reason: str | None) -> Alignment:
        if reason:
            warnings.append(reason)
            trusted, unchanged, edges = False, None, None
        else:
            trusted, unchanged, edges = trust(prior, prior_score)
        return Alignment(
            prior,
            "pose",
            False,
            prior_score,
            prior_score,
            trusted,
            tuple(warnings),
            unchanged_score=unchanged,
            edges_score=edges,
        )

    if len(walls) < 20 or not view.structure.any():
        return keep_prior("too few walls in the local or global map to check the alignment")
    if not refine:
        return keep_prior(None)

    centre = walls.mean(axis=0)
    radius = max(float(np.sqrt(((walls - centre) ** 2).sum(axis=1)).max()), 1.0)
    icp_walls = thin_points(walls, 2.0 * view.grid.resolution, mean=True)
    icp_reach = max(0.3, 4 * view.grid.resolution)

    def evaluate(theta_half: float) -> tuple[float, Transform2D]:
        found = _search(
            walls,
            view,
            prior,
            theta_half_rad=theta_half,
            search_xy_m=search_xy_m,
            candidates=candidates,
            fine_levels=1,
            pivot=None if pivot_slam is None else np.asarray(pivot_slam, dtype=float),
        )
        polished: list[tuple[float, Transform2D]] = []
        nearest = view.nearest_wall_near(
            np.concatenate([t.apply(icp_walls) for t in found]), reach_m=icp_reach + 0.5
        )
        for t in icp_many(icp_walls, found, view.grid, nearest, max_distance_m=icp_reach):
            if all(_distance(t, u, centre, radius) > 0.05 for _, u in polished):
                polished.append((agree(t), t))
        # The consistency check warps the whole local map: only for the likeliest few, and not
        # for one that cannot be chosen below. A score is at most sqrt(agreement), and the
        # choice below takes nothing more than 0.02 under the best per candidate before it.
        polished.sort(key=lambda pt: -pt[0])
        likeliest = polished[:3]
        reach = 0.02 * (len(likeliest) - 1)
        scored: list[tuple[float, Transform2D]] = []
        for p, t in likeliest:
            if not scored or math.sqrt(p) >= max(st[0] for st in scored) - reach:
                scored.append((score(t, p), t))
        best_score, best = max(scored, key=lambda st: st[0])
        for s_, t in scored:
            # Repeated structure: a distinct solution that scores about as well but lies
            # nearer the prior is the one to believe. Within one basin, the best score wins.
            distinct = _distance(t, best, centre, radius) > jump_m
            nearer = _distance(t, prior, centre, radius) < _distance(best, prior, centre, radius)
            if distinct and nearer and s_ >= best_score - 0.02:
                best_score, best = s_, t
        return best_score, best

    chosen_score, chosen = evaluate(min(narrow_theta_rad, search_theta_rad))
    if (
        chosen_score < min_score + 0.1
        and search_theta_rad > narrow_theta_rad
        and (prior_confirmed is None or chosen_score >= min_score or not prior_confirmed(chosen))
    ):
        if widen is not None:
            # The scores and the searches below read these two.
            view = widen()
            near_walls = view.near_walls(tolerance_m)
        wide_score, wide = evaluate(search_theta_rad)
        if wide_score > chosen_score + min_gain:
            chosen_score, chosen = wide_score, wide
    # A last polish with every wall cell, not only the thinned ones.
    nearest = view.nearest_wall_near(chosen.apply(walls), reach_m=icp_reach)
    final = icp(walls, chosen, view.grid, nearest, max_distance_m=icp_reach / 2, iterations=8)
    final_agreement = agree(final)
    if math.sqrt(final_agreement) >= chosen_score:  # else it cannot score as well
        final_score = score(final, final_agreement)
        if final_score >= chosen_score:
            chosen_score, chosen = final_score, final

    jump = _distance(chosen, prior, centre, radius) > jump_m
    if chosen_score < prior_score + (min_gain if jump else 1e-6):
        return keep_prior(None)
    trusted, unchanged, edges = trust(chosen, chosen_score)
    return Alignment(
        chosen,
        "pose+correlative+icp",
        True,
        chosen_score,
        prior_score,
        trusted,
        tuple(warnings),
        unchanged_score=unchanged,
        edges_score=edges,
    )


def _untrusted(score: float, min_score: float) -> str:
    return (
        f"could not align the local map onto the global map (agreement {score:.2f} < "
        f"{min_score:.2f}): no differences reported; check the robot's localisation"
    )


def _trusted_on_edges(score: float, min_score: float, with_edges: float) -> str:
    return (
        f"aligned on the edges of what the global map knows: score {score:.2f} < "
        f"{min_score:.2f} on its drawn walls, {with_edges:.2f} with the edges of its known floor "
        "taken as walls (a map that ends its floor at a wall without drawing it dark)"
    )


def _trusted_unchanged(score: float, min_score: float, unchanged: float) -> str:
    return (
        f"aligned on the structure that did not change: score {score:.2f} < {min_score:.2f} over "
        f"all walls, {unchanged:.2f} over the drawn structure still standing and the local walls "
        "near it (many changes: new objects in open floor, drawn structure seen gone)"
    )


__all__ = [
    "Alignment",
    "GlobalView",
    "NearestWall",
    "agreement",
    "align",
    "consistency",
    "drawn_walls",
    "icp",
    "known_points",
    "make_view",
    "structure_mask",
    "thin_points",
    "unchanged_score",
]
