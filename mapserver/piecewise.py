"""Piecewise alignment: a local map that no single rigid transform explains, aligned in pieces.

A long session whose slam drift bends its map beyond what the smooth warp absorbs (or whose loop
slam_toolbox closed badly) fails the rigid alignment as a whole, yet most of it fits the
building. Here the local map is cut into pieces along the robot's route (each cell belongs to
the piece of the route nearest to it through free space: the one that saw it), and each piece
is aligned on its own, starting from its neighbour's transform (drift grows slowly along the
route) and, for the first, from the whole-map transform. The trusted pieces are the largest
chain of pieces that align on their own (a score of at least ``min_score``, or under it on the
structure that did not change) and agree with each other where they meet (or across a piece
between them that does not), grown outwards along the route. Only trusted pieces are
compared.

Pure functions on arrays; ``[row, col]`` indexing throughout, row 0 at the top.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver import align as align_stage
from mapserver.deform import Landed, warp_local_box
from mapserver.geometry import Transform2D, wrap_angle
from mapserver.geometry import fit_rigid as fit_rigid_points
from mapserver.grid import Grid, any_in_blocks, box_of_cells, densify, route_distance
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Piece:
    """One piece of the local map and its own alignment.

    ``mask`` is (H, W) bool on the local map's grid: the known cells of this piece. ``junction``
    is the slam-frame point where the piece's route starts (where it meets the previous piece),
    ``run`` the piece's stretch of the route (M, 2), slam frame.

    ``score`` is its own alignment's (0 when it had too few walls to be aligned), ``aligned``
    whether that alignment is trusted on its own (``score`` at least ``min_score``, or under
    it on the structure that did not change: :func:`mapserver.align.unchanged_score`), and
    ``trusted`` whether the piece is compared (aligned, and in the chain of pieces that agree).
    """

    index: int
    mask: NDArray[np.bool_]
    nav2_from_slam: Transform2D
    score: float
    trusted: bool
    area_m2: float
    junction: tuple[float, float]
    run: FloatArray
    aligned: bool


@dataclass(frozen=True)
class Pieces:
    """The pieces of a local map; ``trusted_area_m2`` over ``observed_area_m2`` is the share of
    what the robot saw that is compared."""

    pieces: tuple[Piece, ...]
    observed_area_m2: float

    @property
    def trusted(self) -> tuple[Piece, ...]:
        return tuple(p for p in self.pieces if p.trusted)

    @property
    def trusted_area_m2(self) -> float:
        return float(sum(p.area_m2 for p in self.trusted))

    @property
    def trusted_share(self) -> float:
        return self.trusted_area_m2 / self.observed_area_m2 if self.observed_area_m2 > 0 else 0.0


# Blocks (metres) on which cells are given to the run that saw them.
_BLOCK_M = 0.2


def route_pieces(route_slam: FloatArray, *, piece_m: float) -> list[FloatArray]:
    """Cut a route (N, 2) slam-frame metres into consecutive runs of about ``piece_m`` of path
    each (the last one joined to its predecessor when shorter than half of that). Neighbouring
    runs share their end point."""
    if piece_m <= 0:
        raise ValueError(f"piece_m must be > 0, got {piece_m}")
    route = np.asarray(route_slam, dtype=float).reshape(-1, 2)
    if len(route) < 2:
        return [route]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])
    n = max(1, round(s[-1] / piece_m))
    bounds = np.searchsorted(s, np.linspace(0.0, s[-1], n + 1)[1:-1])
    cuts = [0, *sorted(set(int(b) for b in bounds if 0 < b < len(route) - 1)), len(route) - 1]
    return [route[a : b + 1] for a, b in itertools.pairwise(cuts)]


def label_cells(local: OccupancyMap, runs: Sequence[FloatArray]) -> NDArray[np.int32]:
    """(H, W) int32 on the local map's grid: the index of the run each known cell was most
    likely seen from, -1 for unknown cells.

    That is the run nearest to it through free space, never through a wall: a ray does not
    cross one, and a cell behind a wall from the run nearest in a straight line was seen from
    another part of the route (a revisit, whose drift the pieces are there to undo). It is
    worked out on blocks of about ``_BLOCK_M`` (a block with a wall cell is a wall). Walls take
    the run of a free block beside them; known cells that no run reaches through free space,
    the run of the nearest block that one does.
    """
    h, w = local.state.shape
    labels = np.full((h, w), -1, np.int32)
    known = local.state != UNKNOWN
    f = max(1, round(_BLOCK_M / local.resolution))
    wall = any_in_blocks(local.state == OCCUPIED, f)
    hh, ww = wall.shape
    passable = (any_in_blocks(local.state == FREE, f) & ~wall).astype(np.float32)
    grid = Grid.of_map(local)
    plus = np.zeros((hh, ww), np.float32)  # run index + 1; 0: not reached yet
    for i, run in enumerate(runs):
        # Dense points along the run, so that its whole path is a seed, not only its poses.
        px = np.rint(grid.to_pixel(densify(run, local.resolution))).astype(np.int64)
        ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        plus[px[ok, 1] // f, px[ok, 0] // f] = i + 1
    if not plus.any():
        return labels
    # Breadth first through free blocks from every run at once, each step only around the
    # blocks the last one reached.
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    front = plus > 0
    while True:
        x, y, bw, bh = cv2.boundingRect(front.view(np.uint8))
        if bw == 0:
            break
        win = (slice(max(y - 1, 0), y + bh + 1), slice(max(x - 1, 0), x + bw + 1))
        grown = cv2.dilate(plus[win], cross) * passable[win]
        new = (plus[win] == 0) & (grown > 0)
        front = np.zeros_like(front)
        front[win] = new
        plus[win][new] = grown[new]
    plus = np.where((plus == 0) & wall, cv2.dilate(plus, np.ones((3, 3), np.uint8)), plus)
    if (plus == 0).any():
        _, nearest = cv2.distanceTransformWithLabels(
            (plus == 0).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        rows, cols = np.nonzero(plus)
        run_of = np.zeros(int(nearest.max()) + 1, np.float32)
        run_of[nearest[rows, cols]] = plus[rows, cols]
        plus = run_of[nearest]
    fine = np.repeat(np.repeat(plus.astype(np.int32) - 1, f, axis=0), f, axis=1)[:h, :w]
    labels[known] = fine[known]
    return labels


def seen_reach_m(local: OccupancyMap, route: FloatArray) -> float:
    """How far from the robot's route ``route`` (M, 2, slam frame) the local map saw anything:
    the largest distance of a known cell from it, metres (0 with nothing known or no route).

    Where the building leaves long views open, that is the sensor's range (a 12 m lidar's map
    reaches 12 m from the route, a 20 m one's 20 m); among walls that close in, the farthest
    the robot saw. Either way a lower bound of the range: no cell was seen from farther.
    Worked out on blocks of ``_BLOCK_M`` by :func:`mapserver.grid.route_distance` (never
    more than the distance, up to a block's diagonal less; a route off the map taken at its
    edge).
    """
    px = Grid.of_map(local).to_pixel(np.asarray(route, float).reshape(-1, 2))
    distance = route_distance(px, local.state.shape, local.resolution, block_m=_BLOCK_M)
    return 0.0 if distance is None else distance.farthest(local.state != UNKNOWN)


def along_route(route: FloatArray, step_m: float) -> FloatArray:
    """Points every ``step_m`` of path along the polyline ``route`` (N, 2), its start first:
    the route weighted by the ground it covered, not by the time the robot spent (poses
    recorded while it stood still collapse into one point). One point when it never moved."""
    route = np.asarray(route, dtype=float).reshape(-1, 2)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])
    if len(route) < 2 or s[-1] <= 0.0:
        return route[:1]
    at = np.arange(0.0, s[-1] + 1e-9, step_m)
    return np.stack([np.interp(at, s, route[:, 0]), np.interp(at, s, route[:, 1])], axis=1)


def _sub_map(local: OccupancyMap, mask: NDArray[np.bool_]) -> OccupancyMap:
    """The local map with only ``mask``'s cells known, cropped to their bounding box."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    box = (slice(y, y + h), slice(x, x + w))
    state = np.where(mask[box], local.state[box], UNKNOWN)
    grid = Grid.of_map(local).crop((y, y + h, x, x + w))
    occ = np.where(state == OCCUPIED, 100, np.where(state == UNKNOWN, 205, 0)).astype(np.uint8)
    return OccupancyMap(state, occ, local.resolution, (grid.x0, grid.y0, 0.0))


def align_pieces(
    local: OccupancyMap,
    view: align_stage.GlobalView,
    route_slam: FloatArray,
    start: Transform2D,
    *,
    also_from: Transform2D | None = None,
    piece_m: float = 20.0,
    min_score: float = 0.6,
    search_xy_m: float = 1.5,
    search_theta_rad: float = math.radians(10.0),
    agree_m: float = 0.5,
    min_walls: int = 60,
    anchored: Callable[[Piece], bool] | None = None,
) -> Pieces | None:
    """Align the local map in pieces along ``route_slam`` (N, 2), slam frame, metres.

    Pieces are aligned in route order from the end (where the robot was when it reported its
    pose), each starting from the transform of the last one after it that aligned (its own
    alignment trusted: ``Piece.aligned``), and those before the first such from ``start`` (and
    from ``also_from`` too when given, keeping the better fit, a trusted one before a better
    score: the whole map's alignment, for a prior that is off).

    The trusted pieces are the largest (by area) chain of aligned pieces that agree with each
    other: where each meets the one before it in the chain, the two transforms put that point
    within ``agree_m`` of each other, or across one piece between them left out
    (:func:`largest_chain`). A piece that found a wrong match jumps; drift does not. Not the
    chain that holds the last piece: when the prior is off and the last piece took a wrong
    match (repeated rooms), the rest of the route, consistent with itself, was left out with
    it. The chain then grows outwards with the pieces beyond it aligned again from its ends
    (:func:`grow_chain`). A piece still left out beside the chain is aligned again in halves,
    which drift bends half as far (:func:`_split_left_out`): the pieces are then numbered
    again in route order. ``view`` must cover where the pieces land.

    With ``anchored``, the last piece (aligned first) must satisfy it, else None: nothing more
    is aligned.
    """
    runs = route_pieces(route_slam, piece_m=piece_m)
    labels = label_cells(local, runs)
    cell_m2 = local.resolution**2
    seen = labels >= 0
    observed = float(np.count_nonzero(seen)) * cell_m2
    # Each piece's cells, and its wall cells, counted once for all.
    cells = np.bincount(labels[seen], minlength=len(runs))
    walls_of = np.bincount(labels[seen & (local.state == OCCUPIED)], minlength=len(runs))
    found: list[Piece] = []
    prior, from_piece = start, False

    def fit(i: int, starts: list[Transform2D], pivot_at: int = -1) -> Piece:
        """Piece ``i`` aligned from the best of ``starts``, turned about its run's point
        ``pivot_at`` (where it meets the piece its start came from: the end of its run, the
        route's next piece; the start, the one before)."""
        area = float(cells[i]) * cell_m2
        return fit_cells(i, labels == i, runs[i], area, int(walls_of[i]), starts, pivot_at)

    def fit_cells(
        i: int,
        mask: NDArray[np.bool_],
        run: FloatArray,
        area: float,
        walls: int,
        starts: list[Transform2D],
        pivot_at: int,
    ) -> Piece:
        """The cells ``mask`` seen from ``run`` aligned as piece ``i`` (see ``fit``)."""
        junction = (float(run[0, 0]), float(run[0, 1]))
        if walls < min_walls:
            # Too few walls to align: the piece keeps its start, never scores.
            return Piece(i, mask, starts[0], 0.0, False, area, junction, run, aligned=False)
        sub = _sub_map(local, mask)
        result = max(
            (
                align_stage.align(
                    sub,
                    view,
                    t0,
                    search_xy_m=search_xy_m,
                    search_theta_rad=search_theta_rad,
                    narrow_theta_rad=search_theta_rad,
                    min_score=min_score,
                    pivot_slam=(float(run[pivot_at, 0]), float(run[pivot_at, 1])),
                )
                for t0 in starts
            ),
            # A fit trusted on what did not change beats an untrusted one that scores more.
            key=lambda r: (r.trusted, r.score),
        )
        # Compared or not, the chain decides below.
        t, ok = result.nav2_from_slam, result.trusted
        return Piece(i, mask, t, result.score, False, area, junction, run, aligned=ok)

    for i in reversed(range(len(runs))):
        starts = [prior] if from_piece or also_from is None else [prior, also_from]
        piece = fit(i, starts)
        if piece.aligned:
            prior, from_piece = piece.nav2_from_slam, True
        if anchored is not None and i == len(runs) - 1 and not anchored(piece):
            return None
        found.append(piece)
    found.reverse()
    keep = largest_chain(found, agree_m)
    if keep:
        found, keep = grow_chain(found, keep, lambda i, t, at: fit(i, [t], at), agree_m)
    found = [dataclasses.replace(p, trusted=p.index in keep) for p in found]
    if keep:
        # A piece left out beside the chain, aligned again in halves (drift bends each less).
        found = _split_left_out(local, found, fit_cells, agree_m, min_walls)
    return Pieces(tuple(found), observed)


# A piece left out of the chain is cut in two when its run is this long (metres): each half
# at least half of it, a stretch of route a drift of 0.1 degree per metre turns by 0.5-1
# degree, where a whole piece, bent twice as far, fitted nowhere well enough.
_SPLIT_MIN_RUN_M = 10.0


def _run_length_m(run: FloatArray) -> float:
    return float(np.hypot(*np.diff(run, axis=0).T).sum()) if len(run) > 1 else 0.0


def _split_left_out(
    local: OccupancyMap,
    pieces: list[Piece],
    fit_cells: Callable[..., Piece],
    agree_m: float,
    min_walls: int,
) -> list[Piece]:
    """The pieces with each one left out of the chain, next to a trusted one on the route,
    replaced by its two halves when a half joins the chain (:func:`_halves_joined`); a piece
    whose halves join nothing stays as it was. The pieces are numbered again in route order.

    A long route's drift bends a 20 m piece twice as far as either half: a piece that aligned
    nowhere well enough as a whole may in halves, and the half next to the chain, the one its
    neighbour's transform carries best, first."""
    out: list[Piece] = []
    for i, piece in enumerate(pieces):
        before = pieces[i - 1] if i > 0 and pieces[i - 1].trusted else None
        after = pieces[i + 1] if i + 1 < len(pieces) and pieces[i + 1].trusted else None
        split = None
        if not piece.trusted and (before or after):
            split = _halves_joined(local, piece, before, after, fit_cells, agree_m, min_walls)
        out.extend(split or [piece])
    return [dataclasses.replace(p, index=n) for n, p in enumerate(out)]


def _halves_joined(
    local: OccupancyMap,
    piece: Piece,
    before: Piece | None,
    after: Piece | None,
    fit_cells: Callable[..., Piece],
    agree_m: float,
    min_walls: int,
) -> list[Piece] | None:
    """``piece`` (left out) cut in two at the middle of its run (of ``_SPLIT_MIN_RUN_M`` or
    more), its cells given to the half that saw them (:func:`label_cells`), when a half joins
    the trusted piece next to it on the route (``before`` or ``after``, None when not trusted):
    aligned from that neighbour's transform (``fit_cells``, turned about the point where they
    meet), it aligns, meets the neighbour within ``agree_m`` there and turns no more than
    ``_MAX_TURN_RAD`` from it. A half that joined nothing so is aligned from the other half and
    joins it the same way at the middle, when it also meets its own side (if trusted) at its
    end; two halves joined from either side must meet at the middle, else only the better
    scoring one is kept. A half left out keeps the piece's transform. None when no half joins
    (and for a piece with no cells)."""
    length = _run_length_m(piece.run)
    if length < _SPLIT_MIN_RUN_M or not piece.mask.any():  # no cells: another run took them
        return None
    # Cut at the middle of its path, as the route is cut into pieces (sharing the middle pose).
    halves = route_pieces(piece.run, piece_m=length / 2)
    if len(halves) != 2:
        return None
    # Each half's cells, its wall cells and its area, worked out on the piece's box only.
    x, y, w, h = cv2.boundingRect(piece.mask.view(np.uint8))
    sub = _sub_map(local, piece.mask)
    sub_labels = label_cells(sub, halves)  # the piece's own cells only: -1 elsewhere
    sub_walls = sub.state == OCCUPIED
    masks, walls, areas = [], [], []
    for k in range(2):
        mine = sub_labels == k
        m = np.zeros_like(piece.mask)
        m[y : y + h, x : x + w] = mine
        masks.append(m)
        walls.append(int(np.count_nonzero(mine & sub_walls)))
        areas.append(float(np.count_nonzero(mine)) * local.resolution**2)

    def half(k: int, start: Transform2D, pivot_at: int) -> Piece:
        return fit_cells(piece.index, masks[k], halves[k], areas[k], walls[k], [start], pivot_at)

    def joins(p: Piece, end: Piece, at: FloatArray) -> bool:
        return _joins(p, end, at, end.nav2_from_slam.theta, agree_m, _MAX_TURN_RAD)

    got: list[Piece | None] = [None, None]
    sides = (before, after)
    # Where each half meets what lies beyond it: the run's start, its end; and the other half.
    outer, middle = (halves[0][:1], halves[1][-1:]), halves[1][:1]
    pivots = (0, -1)  # each half turned about its outer end, where it meets its side
    # The half next to each trusted side, from that side's transform.
    for k, side in enumerate(sides):
        if side is not None:
            p = half(k, side.nav2_from_slam, pivots[k])
            got[k] = dataclasses.replace(p, trusted=True) if joins(p, side, outer[k]) else None
    # A half beside no trusted side, or that did not join its side, from the other half,
    # turned about the middle where they meet; it must meet its own side too, if trusted.
    for k in (0, 1):
        near, side = got[1 - k], sides[k]
        if got[k] is None and near is not None:
            q = half(k, near.nav2_from_slam, -1 if k == 0 else 0)
            if joins(q, near, middle) and (side is None or _meet(q, side, outer[k], agree_m)):
                got[k] = dataclasses.replace(q, trusted=True)
    # Two halves joined from either side must meet at the middle (session 58's review), as
    # neighbours along the chain do: else the better scoring one is kept.
    first, second = got
    if first is not None and second is not None and not _meet(first, second, middle, agree_m):
        got[0 if first.score < second.score else 1] = None
    if got[0] is None and got[1] is None:
        return None
    out = []
    for k, kept in enumerate(got):
        if kept is None:  # the half nothing joined: left out, as its piece was
            run = halves[k]
            kept = dataclasses.replace(
                piece,
                mask=masks[k],
                area_m2=areas[k],
                junction=(float(run[0, 0]), float(run[0, 1])),
                run=run,
                aligned=piece.aligned and walls[k] >= min_walls,
            )
        out.append(kept)
    return out


# How far (radians) a piece joining the chain may turn from the heading the chain's drift
# predicts for it. Joined at the point it turns about, a piece turned by a wrong match meets
# the chain's end as well as a right one; drift turns the pieces of a route steadily (0.1
# degree per metre, the worst the generated sets drift, is 2 degrees over a 20 m piece, and
# the trend takes that), so 5 degrees off the trend is a wrong match. Over the six drift
# sets, right pieces lie within 3.9 degrees of the trend, most within 1.5.
_MAX_TURN_RAD = math.radians(5.0)


def heading_trend(chain: Sequence[Piece], at: int) -> float:
    """The heading (radians) the chain's pieces (in route order along the growth, ``chain[-1]``
    the end it grows from; a piece stepped over leaves a gap in their indices) predict for the
    piece at route index ``at``: the end's, turned on by the chain's drift per route index
    (least squares over its last three pieces; none with fewer: two pieces' fits, each a
    degree or so off, give a slope that noisy)."""
    last = chain[-3:]
    end = last[-1]
    if len(last) < 3:
        return end.nav2_from_slam.theta
    x = np.array([p.index for p in last], float)
    y = np.unwrap([p.nav2_from_slam.theta for p in last])
    slope = float(np.polyfit(x, y, 1)[0])
    return end.nav2_from_slam.theta + slope * (at - end.index)


def grow_chain(
    pieces: Sequence[Piece],
    chain: set[int],
    fit: Callable[[int, Transform2D, int], Piece],
    agree_m: float,
    max_turn_rad: float = _MAX_TURN_RAD,
) -> tuple[list[Piece], set[int]]:
    """The chain of piece indices ``chain`` grown outwards along the route, and the pieces
    with those that joined it as they joined (aligned again, or their first fit).

    The pieces beyond the chain's ends were aligned from whatever piece came after them on the
    route, a wrong match among them too; the chain's end piece is the better start. Each piece
    beyond an end is aligned again from that end's transform (``fit(index, start, pivot)``,
    turned about the point of its run nearest the end: ``-1`` its run's end growing backwards,
    ``0`` its start growing forwards) and joins when it aligns, meets the end within
    ``agree_m`` and turns no more than ``max_turn_rad`` from the heading the chain's drift
    predicts for it (:func:`heading_trend`: turned about the point where it meets the end, a
    wrong match meets it too); it then becomes the end. Aligned again, a piece can take a
    wrong match the first alignment (from the route's later pieces) did not: when only its
    first fit passes those tests, it joins with that one. One piece that does not join is
    stepped over (a piece with too few walls, a stretch of clutter); the next is then measured
    against the end at the middle of the stepped-over run, not where it starts (a route's drift
    turns the two transforms apart over the run between them). Two in a row stop the growth.
    """
    out = list(pieces)
    chain = set(chain)
    for step in (-1, 1):
        end = min(chain) if step < 0 else max(chain)
        over: list[int] = []
        i = end + step
        while 0 <= i < len(out) and len(over) < 2:
            at = _measured_at([out[j] for j in over], out[max(i, end)])
            # The chain's pieces in growth order, its end last.
            trend = heading_trend([out[j] for j in sorted(chain, reverse=step < 0)], i)
            again = fit(i, out[end].nav2_from_slam, -1 if step < 0 else 0)
            # Aligned again from the end first, then its first fit.
            joined = next(
                (
                    p
                    for p in (again, pieces[i])
                    if _joins(p, out[end], at, trend, agree_m, max_turn_rad)
                ),
                None,
            )
            if joined is not None:
                out[i], end, over = joined, i, []
                chain.add(i)
            else:
                over.append(i)
            i += step
    return out, chain


def _measured_at(between: Sequence[Piece], later: Piece) -> FloatArray:
    """(1, 2) slam metres: where two pieces of a route are measured against each other, the
    middle pose of the runs of the pieces ``between`` them (drift turns two transforms apart
    over the run between them), or where the ``later`` one starts when those runs are empty."""
    runs = [p.run for p in between if len(p.run)]
    if not runs:
        return np.array([later.junction])
    run = np.concatenate(runs)
    return np.asarray(run[len(run) // 2][None], dtype=float)


def _meet(a: Piece, b: Piece, at: FloatArray, agree_m: float) -> bool:
    """Whether the transforms of pieces ``a`` and ``b`` put ``at`` (1, 2) within ``agree_m``
    of each other."""
    return float(apart(a.nav2_from_slam, b.nav2_from_slam, at)[0]) <= agree_m


def _joins(
    piece: Piece,
    end: Piece,
    at: FloatArray,
    trend: float,
    agree_m: float,
    max_turn_rad: float,
) -> bool:
    """Whether ``piece`` joins a chain that ends in ``end``: it aligned, the two transforms put
    ``at`` (1, 2) within ``agree_m`` of each other, and its heading lies within ``max_turn_rad``
    of ``trend``, the heading the chain predicts for it."""
    if not piece.aligned:
        return False
    gap = float(apart(piece.nav2_from_slam, end.nav2_from_slam, at)[0])
    turn = abs(wrap_angle(piece.nav2_from_slam.theta - trend))
    return gap <= agree_m and turn <= max_turn_rad


def apart(a: Transform2D, b: Transform2D, points: FloatArray) -> FloatArray:
    """How far apart ``a`` and ``b`` put each of ``points`` (N, 2), metres."""
    return np.asarray(np.hypot(*(a.apply(points) - b.apply(points)).T))


def _gap_across(pieces: Sequence[Piece], a: Piece, b: Piece) -> float:
    """How far apart the transforms of pieces ``a`` and ``b`` (later on the route) put the
    point where they are measured against each other (:func:`_measured_at`: the middle of the
    runs of ``pieces`` between them, else where ``b``'s route starts), metres."""
    at = _measured_at([q for q in pieces if a.index < q.index < b.index], b)
    return float(apart(a.nav2_from_slam, b.nav2_from_slam, at)[0])


def largest_chain(pieces: Sequence[Piece], agree_m: float) -> set[int]:
    """The indices of the largest (by total area) chain of aligned pieces (``Piece.aligned``),
    in route order, each within ``agree_m`` of the one before where they meet (pieces that did
    not align are skipped, not breaks: across them, two pieces are measured at the middle pose
    of the skipped pieces' runs, where drift over the route between has turned the two
    transforms apart the least, and where a wrong match turned about its own start does not
    meet its neighbour). A piece that found a wrong match jumps; drift does not: the pieces
    that agree with each other over most of the route are the right ones, whichever one the
    prior anchored.

    A chain may also step over an aligned piece, never two in a row: the pieces on either side
    of it agree at the middle pose of the runs between them (the stepped-over piece's and any
    that did not align). A piece a wrong match turned about one of its ends meets that
    neighbour and not the other, and would otherwise cut a right route in two. Stepping over
    only wins where it makes the chain heavier, so a route whose pieces all agree keeps every
    one of them."""
    aligned = [p for p in pieces if p.aligned]
    if not aligned:
        return set()
    # The heaviest path through the aligned pieces in route order: best[k], the area of the
    # best chain that ends at aligned[k], and the piece before it there.
    best: list[float] = []
    before: list[int] = []
    for k, piece in enumerate(aligned):
        best.append(piece.area_m2)
        before.append(-1)
        # From the aligned piece before it, or stepping over that one, when heavier.
        for j in (k - 1, k - 2):
            heavier = j >= 0 and best[j] + piece.area_m2 > best[k]
            if heavier and _gap_across(pieces, aligned[j], piece) <= agree_m:
                best[k], before[k] = best[j] + piece.area_m2, j
    k = int(np.argmax(best))
    chain: set[int] = set()
    while k >= 0:
        chain.add(aligned[k].index)
        k = before[k]
    return chain


def _corners(local: OccupancyMap, piece: Piece) -> FloatArray | None:
    """The slam-frame corners (4, 2) of the bounding box of ``piece``'s cells; None when it
    has none."""
    x, y, w, h = cv2.boundingRect(piece.mask.view(np.uint8))
    if w == 0:
        return None
    box = np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h]], float)
    return Grid.of_map(local).to_world(box)


def lands_within(local: OccupancyMap, pieces: Pieces, grid: Grid, margin_m: float) -> bool:
    """Whether every piece that was searched (one that scored at all, aligned or not: one may
    fail to align because its search ran off the view) lands on ``grid`` through its own
    transform with ``margin_m`` to spare on every side: the view it was searched on held it and
    the room around it. Over the corners of each piece's bounding box."""
    margin_px = margin_m / grid.resolution
    for piece in pieces.pieces:
        corners = _corners(local, piece) if piece.score > 0 else None
        if corners is None:
            continue
        px = grid.to_pixel(piece.nav2_from_slam.apply(corners))
        if (px.min(axis=0) < margin_px).any() or (
            px.max(axis=0) > np.array([grid.width, grid.height]) - margin_px
        ).any():
            return False
    return True


def departure(local: OccupancyMap, pieces: Pieces, transform: Transform2D) -> float:
    """How far, at most, a piece that aligned on its own (``aligned``, in the chain or left
    out of it) puts its own cells from where ``transform`` (one rigid fit of the whole
    local map) puts them, metres; 0 with no such piece. Over the corners of each piece's
    bounding box: the gap between two rigid transforms grows linearly across a region, so its
    largest is at a corner.

    A piece left out because it disagrees with its neighbour shows a bend as well as one in
    the chain: the route's last piece turned on by drift past what the chain's agreement
    allows. Should it be a wrong match instead, aligning in pieces only leaves it out."""
    worst = 0.0
    for piece in pieces.pieces:
        if not piece.aligned:
            continue
        corners = _corners(local, piece)
        if corners is not None:
            worst = max(worst, float(apart(piece.nav2_from_slam, transform, corners).max()))
    return worst


@dataclass(frozen=True)
class PlainSight:
    """When the robot's own run saw a difference plainly: its nearest pose within ``run_m`` of
    the difference's centre, a straight line of cells seen free from that pose to the
    difference's nearest cell, and no local wall within ``clear_m`` of any of its cells (a
    structure standing alone, seen gone with the floor all round). Then a pass whose run came
    more than ``ratio`` times as far from it explains nothing."""

    run_m: float
    ratio: float
    clear_m: float


def another_pass_explains(
    local: OccupancyMap,
    pieces: Pieces,
    xy: FloatArray,
    fits: Callable[[FloatArray, float], NDArray[np.bool_]],
    *,
    reach_m: float = 12.0,
    min_gap_m: float = 0.5,
    share: float = 0.8,
    open_there: Callable[[FloatArray], NDArray[np.bool_]] | None = None,
    near_ratio: float = math.inf,
    plain_sight: PlainSight | None = None,
) -> bool:
    """Whether a difference at nav2 points ``xy`` (N, 2) is a fold: seen on another pass.

    A route that comes back to a place after its heading drifted makes slam draw what it sees
    the second time where the first pass's map lies, a metre or more off. The cells belong to
    the piece of the first pass (the run nearest through free space), whose transform puts
    the second pass's wall in open floor. Here the cells are taken back to the slam frame
    through the trusted piece most of them belong to, then put through the transform of every
    other aligned piece (``aligned``, trusted or left out of the chain: a chain break leaves
    out pieces that are mostly right) whose run came within ``reach_m`` of them and that puts
    them ``min_gap_m`` or more from where the piece does: when ``share`` of them then fit the
    building (``fits(points, run_m)``, per nav2 point; ``run_m``: how near that pass's run
    came to them, metres, from its nearest pose to their centre in the slam frame, as the
    error of what it drew grows with the length of its rays), that pass saw them, and they
    are no change.

    A piece next on the route shares this one's junction, and two trusted neighbours meet there
    within the chain's agreement; it counts only where its run came nearer to the cells than
    the piece's own (never for a piece without a run): far from the junction a small error in
    either one's heading grows to a metre, and the transform of the run that saw the place
    from nearer is the better there (a 20 m lidar's piece draws a hall's far wall 15 m from
    its run; the next piece drove along that wall and lays it on the building, where the first
    lays it in the open).

    With ``open_there`` (per slam point: the local map open there), a pass does not explain
    them when ``share`` of the places its transform takes ``xy`` back to are open and its run
    came within ``reach_m`` of them: where that pass would have drawn what the building has at
    ``xy``, had it seen it standing, the map is open as well; two passes agree (a structure
    really gone, seen on both). Beyond its reach the place back is some other pass's floor,
    and says nothing of this one.

    ``near_ratio``: a pass whose run came farther than half ``reach_m`` from them explains
    them only when its run came no more than ``near_ratio`` times as far from them as the
    piece's own run (both from their centre, in the slam frame; ``inf``, the default, or a
    piece without a run: no such limit).

    ``plain_sight``: where the piece's own run saw them plainly (:class:`PlainSight`, asked
    in the slam frame), a pass whose run came more than its ``ratio`` times as far from them
    as that run explains nothing, however near. A structure standing alone lands on open
    floor through any transform that moves it its own width, so there the landing says
    nothing of a fold; what the robot saw from a pose beside it, looking at it across open
    floor, does: it saw the floor where the structure stood.
    """
    owned = _owner(local, pieces, xy)
    if owned is None:
        return False
    owner, slam = owned
    centre = slam.mean(axis=0, keepdims=True)
    limit_m = reach_m
    own_m = _run_distance_m(owner.run, centre) if len(owner.run) else math.inf
    if math.isfinite(own_m) and math.isfinite(near_ratio):
        limit_m = min(reach_m, max(reach_m / 2, near_ratio * own_m))
    if (
        plain_sight is not None
        and own_m <= plain_sight.run_m
        and _in_plain_sight(local, owner.run, slam, plain_sight.clear_m)
    ):
        limit_m = min(limit_m, plain_sight.ratio * own_m)
    for q in pieces.pieces:
        if not q.aligned or q.index == owner.index or len(q.run) < 2:
            continue
        q_m = _run_distance_m(q.run, centre)
        if q_m > limit_m or (abs(q.index - owner.index) == 1 and not q_m < own_m < math.inf):
            continue
        if float(apart(owner.nav2_from_slam, q.nav2_from_slam, centre)[0]) < min_gap_m:
            continue
        if float(np.mean(fits(q.nav2_from_slam.apply(slam), q_m))) < share:
            continue
        if open_there is not None:
            back = q.nav2_from_slam.inverse().apply(xy)
            near = _run_distance_m(q.run, back.mean(axis=0, keepdims=True)) <= reach_m
            if near and float(np.mean(open_there(back))) >= share:
                continue
        return True
    return False


def _in_plain_sight(local: OccupancyMap, run: FloatArray, slam: FloatArray, clear_m: float) -> bool:
    """Whether the pose of ``run`` (M, 2) nearest the centre of slam points ``slam`` (N, 2)
    saw them across open floor: every cell on the straight line from it to the nearest of
    them seen free in ``local`` (sampled every half cell), and no cell of ``local`` seen
    occupied within ``clear_m`` of any of them (worked out in the box around them)."""
    pose = run[int(np.argmin(np.hypot(*(run - slam.mean(axis=0)).T)))]
    target = slam[int(np.argmin(np.hypot(*(slam - pose).T)))]
    grid = Grid.of_map(local)
    line = densify(np.stack([pose, target]), local.resolution / 2)
    if not np.all(grid.sample(local.state, line, UNKNOWN) == FREE):
        return False
    px = np.rint(grid.to_pixel(slam)).astype(np.intp)
    rows, cols = px[:, 1], px[:, 0]
    h, w = local.state.shape
    on = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    if not on.any():
        return False
    rows, cols = rows[on], cols[on]
    k = max(1, math.ceil(clear_m / local.resolution))
    box = box_of_cells(rows, cols, k, local.state.shape)
    walls = local.state[box] == OCCUPIED
    if not walls.any():
        return True
    far = cv2.distanceTransform((~walls).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    far *= local.resolution
    return bool(np.all(far[rows - box[0].start, cols - box[1].start] > clear_m))


def _run_distance_m(run: FloatArray, point: FloatArray) -> float:
    """How near (metres) a run (M, 2) came to ``point`` (1, 2): its nearest pose's distance."""
    return float(np.hypot(*(run - point).T).min())


def _owner(local: OccupancyMap, pieces: Pieces, xy: FloatArray) -> tuple[Piece, FloatArray] | None:
    """The trusted piece most of nav2 points ``xy`` (N, 2) belong to (through its transform
    back into the slam frame, onto its cells), and those points in the slam frame; None when
    no trusted piece holds any of them."""
    grid = Grid.of_map(local)
    best: tuple[int, Piece, FloatArray] | None = None
    for p in pieces.trusted:
        at = p.nav2_from_slam.inverse().apply(xy)
        n = int(np.count_nonzero(grid.sample(p.mask, at, False)))
        if n and (best is None or n > best[0]):
            best = (n, p, at)
    return None if best is None else (best[1], best[2])


def left_out_pass_near(
    local: OccupancyMap,
    pieces: Pieces,
    xy: FloatArray,
    *,
    ratio: float = 2.0,
    reach_m: float = 12.0,
) -> bool:
    """Whether a piece left out of the comparison (not trusted: it did not align, or not in
    agreement with the chain) came on its run nearer to nav2 points ``xy`` (N, 2) than
    ``ratio`` times the run of the trusted piece they belong to, and no farther than
    ``reach_m``; distances from their centre, in the slam frame. A left-out neighbour on the
    route shares the piece's junction, so near that junction it always does. False when no
    trusted piece holds any of the points, or the one that does has no run.

    The local map there may be that pass's drawing, in the frame of a transform that could not
    be trusted: given to the trusted piece (the run nearest through free space), its open floor
    lands on the building's walls.
    """
    owned = _owner(local, pieces, xy)
    if owned is None:
        return False
    owner, slam = owned
    if len(owner.run) == 0:
        return False
    centre = slam.mean(axis=0, keepdims=True)
    own_m = _run_distance_m(owner.run, centre)
    for q in pieces.pieces:
        if q.trusted or len(q.run) < 2:
            continue
        q_m = _run_distance_m(q.run, centre)
        if q_m <= reach_m and q_m < ratio * own_m:
            return True
    return False


def compose(
    local: OccupancyMap,
    pieces: Pieces,
    grid: Grid,
    *,
    warp: Callable[[OccupancyMap, Transform2D], Landed | None] | None = None,
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """The trusted pieces on ``grid`` (nav2), each through its own transform, and the cells the
    untrusted ones land on (through theirs) that no trusted piece covers.

    ``warp(piece_map, nav2_from_slam)`` puts a trusted piece (its cells of the local map,
    cropped to them) onto ``grid``, for instance with its own drift correction: the box of
    ``grid`` it lands in and its states there (see :func:`mapserver.deform.warp_local_box`), or
    None; default: rigidly.

    Returns ``(state, left_out)``: (rows, cols) uint8 states (UNKNOWN outside the trusted
    pieces; where two pieces overlap, a wall in either is a wall) and (rows, cols) bool.
    """
    state = np.full(grid.shape, UNKNOWN, np.uint8)
    left_out = np.zeros(grid.shape, bool)
    disputed = np.zeros(grid.shape, bool)
    for piece in pieces.pieces:
        if not piece.mask.any():
            continue
        part = _sub_map(local, piece.mask)
        if piece.trusted and warp is not None:
            put = warp(part, piece.nav2_from_slam)
        else:
            put = warp_local_box(part, grid, piece.nav2_from_slam)
        # Only the box the piece lands in: a long route's pieces each cover a small part.
        if put is None:
            continue
        (r0, r1, c0, c1), landed = put
        window = (slice(r0, r1), slice(c0, c1))
        now = state[window]
        known = landed != UNKNOWN
        if piece.trusted:
            # Two pieces that saw one cell differently (a wall bent one way in one, another in
            # the other) give no evidence there: unknown, never a difference.
            conflict = known & (now != UNKNOWN) & (now != landed)
            take = known & (now == UNKNOWN)
            now[take] = landed[take]
            now[conflict] = UNKNOWN
            disputed[window] |= conflict
        else:
            left_out[window] |= known
    state[disputed] = UNKNOWN
    left_out &= state == UNKNOWN
    return state, left_out


def unfit_tiles(
    local_state: NDArray[np.uint8],
    global_walls: NDArray[np.bool_],
    *,
    resolution: float,
    tile_m: float = 6.0,
    reach_m: float = 0.5,
    max_share: float = 0.5,
    max_share_around: float = 0.8,
    min_wall_m: float = 6.0,
    tile_offset_px: tuple[int, int] = (0, 0),
) -> NDArray[np.bool_]:
    """The tiles of an aligned local map that the alignment does not put on the global map.

    One rigid fit (plus the drift warp) can score well over a local map bent beyond the warp's
    reach: the part that fits carries the score, the rest lands off the building and would be
    reported as changes. Each tile of ``tile_m`` (a lattice fixed by ``tile_offset_px``, as in
    :func:`mapserver.diff.misfit_tolerance`) with ``min_wall_m`` of local wall or more measures
    two shares: its local walls within ``reach_m`` of a global wall (the differences' largest
    misfit tolerance), and its global walls (where the local map is known) that the local map
    does not see through (free, no local wall within ``reach_m``). A tile is unfit when both are
    under ``max_share`` and, over the tile and its eight neighbours, the second is under
    ``max_share_around``: a new obstacle beside a removed wall can fail one tile, but a
    misaligned region runs global walls through space seen free all around it.

    ``local_state`` (uint8 states) and ``global_walls`` (bool) are (H, W) on one grid, ``[row,
    col]``. Returns (H, W) bool: the cells of unfit tiles (all false when every tile fits).
    """
    if resolution <= 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    h, w = local_state.shape
    unfit = np.zeros((h, w), bool)
    local_walls = local_state == OCCUPIED
    if not local_walls.any() or not global_walls.any():
        return unfit
    k = math.ceil(reach_m / resolution)
    # A square reach, not a disk: a statistic over metres of wall, and a square dilation is
    # separable (several times cheaper on the trusted path, where every bundle pays it).
    disk = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * k + 1, 2 * k + 1))
    near_global = cv2.dilate(global_walls.view(np.uint8), disk).view(bool)
    near_local = cv2.dilate(local_walls.view(np.uint8), disk).view(bool)
    seen = global_walls & (local_state != UNKNOWN)
    seen_through = seen & (local_state == FREE) & ~near_local
    tile = max(1, round(tile_m / resolution))
    # Pad to whole tiles of the lattice (and one empty tile around, for the neighbours).
    r_lo, c_lo = tile_offset_px[0] % tile + tile, tile_offset_px[1] % tile + tile
    n_i, n_j = -(-(h + r_lo) // tile) + 1, -(-(w + c_lo) // tile) + 1

    def per_tile(mask: NDArray[np.bool_]) -> NDArray[np.int64]:
        padded = np.zeros((n_i * tile, n_j * tile), bool)
        padded[r_lo : r_lo + h, c_lo : c_lo + w] = mask
        return np.asarray(padded.reshape(n_i, tile, n_j, tile).sum(axis=(1, 3)), np.int64)

    def around(counts: NDArray[np.int64]) -> NDArray[np.int64]:
        p = np.pad(counts, 1)
        out = np.zeros_like(counts)
        for di in (0, 1, 2):
            for dj in (0, 1, 2):
                out += p[di : di + n_i, dj : dj + n_j]
        return out

    walls, fitting = per_tile(local_walls), per_tile(local_walls & near_global)
    seen_n, through = per_tile(seen), per_tile(seen_through)
    bad = (
        (walls >= min_wall_m / resolution)
        & (fitting < max_share * walls)
        & (seen_n - through < max_share * seen_n)
        & (around(seen_n) - around(through) < max_share_around * around(seen_n))
    )
    for i, j in zip(*np.nonzero(bad), strict=True):
        r, c = i * tile - r_lo, j * tile - c_lo
        unfit[max(r, 0) : max(r + tile, 0), max(c, 0) : max(c + tile, 0)] = True
    return unfit


def carrier(pieces: Pieces, index: int) -> Transform2D | None:
    """The transform that carries piece ``index``'s run: its own when it is trusted, else
    that of the trusted piece nearest it along the route (the best the pieces know of it; of
    two as near, the later one, nearer where the robot reported its pose). None when no piece
    is trusted."""
    trusted = pieces.trusted
    return _nearest(trusted, index).nav2_from_slam if trusted else None


def _nearest(trusted: Sequence[Piece], index: int) -> Piece:
    return min(trusted, key=lambda p: (abs(p.index - index), -p.index))


def _carried_runs(pieces: Pieces) -> list[tuple[FloatArray, Transform2D]] | None:
    """Each piece's run with its :func:`carrier`, in route order; None when no piece is
    trusted."""
    trusted = pieces.trusted
    if not trusted:
        return None
    return [(p.run, _nearest(trusted, p.index).nav2_from_slam) for p in pieces.pieces]


def route_nav2(pieces: Pieces) -> FloatArray | None:
    """The robot's route (N, 2) in the nav2 frame, each piece's run carried by its
    :func:`carrier` (the runs share their junctions; each after the first drops its first
    point): where the robot drove on the building, where one rigid transform of a bent map
    draws it through walls. None when no piece is trusted."""
    carried = _carried_runs(pieces)
    if carried is None:
        return None
    return np.concatenate([t.apply(run[1:] if k else run) for k, (run, t) in enumerate(carried)])


def fit_rigid(pieces: Pieces) -> Transform2D | None:
    """The one rigid transform that best carries the robot's route onto the building (least
    squares over the route, a point every 0.1 m of path): what ``result.yaml`` reports as the
    alignment. Each piece's run is carried by its :func:`carrier`. None when no piece is
    trusted."""
    carried = _carried_runs(pieces)
    if carried is None:
        return None
    src = [along_route(run, 0.1) for run, _ in carried]
    xy = np.concatenate(src)
    if len(xy) < 3:
        return pieces.trusted[0].nav2_from_slam
    dst = np.concatenate([t.apply(p) for p, (_, t) in zip(src, carried, strict=True)])
    return fit_rigid_points(xy, dst)


__all__ = [
    "Piece",
    "Pieces",
    "align_pieces",
    "along_route",
    "another_pass_explains",
    "apart",
    "carrier",
    "compose",
    "departure",
    "fit_rigid",
    "grow_chain",
    "heading_trend",
    "label_cells",
    "lands_within",
    "largest_chain",
    "left_out_pass_near",
    "route_nav2",
    "route_pieces",
    "seen_reach_m",
    "unfit_tiles",
]
