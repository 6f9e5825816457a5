"""Axis-aligned rasters in a metric frame, and resampling maps into them.

A :class:`Grid` is a raster laid over a frame (usually nav2): arrays on it are indexed
``[row, col]`` with row 0 at the top, and the centre of pixel ``(col c, row k)`` is
``x = x0 + (c + 0.5) r``, ``y = y0 + (height - k - 0.5) r`` (the ROS map convention).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapserver.geometry import Transform2D
from mapserver.maps import UNKNOWN, OccupancyMap

ScalarT = TypeVar("ScalarT", bound=np.generic)


@dataclass(frozen=True)
class Grid:
    """A raster of ``height`` x ``width`` pixels of side ``resolution`` metres whose lower-left
    corner is at ``(x0, y0)``."""

    x0: float
    y0: float
    resolution: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not self.resolution > 0:
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"grid must have at least one pixel, got {self.width}x{self.height}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @staticmethod
    def of_map(m: OccupancyMap) -> Grid:
        """The grid of a map's own pixels, in the map's frame."""
        return Grid(m.origin[0], m.origin[1], m.resolution, m.width, m.height)

    @staticmethod
    def covering(min_x: float, min_y: float, max_x: float, max_y: float, resolution: float) -> Grid:
        """The smallest grid of the given resolution that covers a box (metres)."""
        width = max(1, math.ceil((max_x - min_x) / resolution))
        height = max(1, math.ceil((max_y - min_y) / resolution))
        return Grid(min_x, min_y, resolution, width, height)

    def pixel_from_world(self) -> NDArray[np.float64]:
        """3x3 matrix taking world (x, y, 1) to pixel (col, row, 1)."""
        r = self.resolution
        return np.array(
            [
                [1.0 / r, 0.0, -self.x0 / r - 0.5],
                [0.0, -1.0 / r, self.height + self.y0 / r - 0.5],
                [0.0, 0.0, 1.0],
            ]
        )

    def world_from_pixel(self) -> NDArray[np.float64]:
        return np.asarray(np.linalg.inv(self.pixel_from_world()), dtype=np.float64)

    def to_pixel(self, xy: ArrayLike) -> NDArray[np.float64]:
        """(N, 2) world points -> (N, 2) fractional (col, row)."""
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        col = (p[:, 0] - self.x0) / self.resolution - 0.5
        row = self.height - (p[:, 1] - self.y0) / self.resolution - 0.5
        return np.stack([col, row], axis=1)

    def to_world(self, colrow: ArrayLike) -> NDArray[np.float64]:
        """(N, 2) (col, row) -> (N, 2) world points (integer values are pixel centres)."""
        p = np.asarray(colrow, dtype=float).reshape(-1, 2)
        x = self.x0 + (p[:, 0] + 0.5) * self.resolution
        y = self.y0 + (self.height - p[:, 1] - 0.5) * self.resolution
        return np.stack([x, y], axis=1)

    def sample(self, image: NDArray[ScalarT], xy: ArrayLike, fill: Any) -> NDArray[ScalarT]:
        """Nearest-pixel values of ``image`` (H, W) on this grid at world points ``xy`` (N, 2),
        ``fill`` where a point falls off the grid; (N,) of ``image``'s dtype."""
        px = np.rint(self.to_pixel(xy)).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < self.width)
        inside &= (px[:, 1] >= 0) & (px[:, 1] < self.height)
        out = np.full(len(px), fill, dtype=image.dtype)
        out[inside] = image[px[inside, 1], px[inside, 0]]
        return out

    def crop(self, box: tuple[int, int, int, int]) -> Grid:
        """The grid of the cells ``box`` = (row0, row1, col0, col1) of this one: the same
        cells in the same places, indexed from the box's corner."""
        r0, r1, c0, c1 = box
        r = self.resolution
        return Grid(self.x0 + c0 * r, self.y0 + (self.height - r1) * r, r, c1 - c0, r1 - r0)


def warp_matrix(src: Grid, dst: Grid, dst_from_src: Transform2D) -> NDArray[np.float64]:
    """2x3 matrix taking a ``dst`` pixel to the ``src`` pixel that lands on it (for
    ``cv2.warpAffine(..., flags=WARP_INVERSE_MAP)``)."""
    m = src.pixel_from_world() @ dst_from_src.inverse().matrix() @ dst.world_from_pixel()
    return m[:2]


def _whole_pixel_shift(matrix: NDArray[np.float64]) -> tuple[int, int] | None:
    """(d_col, d_row) when a 2x3 dst-to-src pixel matrix is a translation by whole pixels (a
    source pixel centre lands exactly on each destination pixel centre); else None."""
    if not np.allclose(matrix[:, :2], np.eye(2), rtol=0.0, atol=1e-9):
        return None
    shift = np.rint(matrix[:, 2])
    if not np.allclose(matrix[:, 2], shift, rtol=0.0, atol=1e-6):
        return None
    return int(shift[0]), int(shift[1])


def resample(
    image: NDArray[np.uint8],
    src: Grid,
    dst: Grid,
    dst_from_src: Transform2D | None = None,
    *,
    fill: int = UNKNOWN,
    interpolation: int = cv2.INTER_NEAREST,
) -> NDArray[np.uint8]:
    """Resample ``image`` (on ``src``) onto ``dst``; pixels from outside ``image`` get ``fill``.

    Returns a new (dst.height, dst.width) array; ``image`` is not modified.
    """
    transform = dst_from_src or Transform2D.identity()
    matrix = warp_matrix(src, dst, transform)
    shift = _whole_pixel_shift(matrix)
    if shift is not None:
        # The same lattice, moved by whole pixels: the warp is a copy of the overlap.
        dc, dr = shift
        copied = np.full((dst.height, dst.width), fill, np.uint8)
        r0, c0 = max(0, -dr), max(0, -dc)
        r1, c1 = min(dst.height, src.height - dr), min(dst.width, src.width - dc)
        if r1 > r0 and c1 > c0:
            copied[r0:r1, c0:c1] = image[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
        return copied
    out = cv2.warpAffine(
        image,
        matrix,
        (dst.width, dst.height),
        flags=interpolation | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=fill,
    )
    return np.asarray(out, dtype=np.uint8)


def landing_box(
    local: OccupancyMap,
    grid: Grid,
    dst_from_src: Transform2D,
    *,
    margin_px: float = 2.0,
    step_px: int = 1,
) -> tuple[int, int, int, int] | None:
    """``(row0, row1, col0, col1)`` of the cells of ``grid`` that the known cells of ``local``
    land on through ``dst_from_src``, with ``margin_px`` around them, starting on multiples of
    ``step_px`` (clipped to the grid); None if none.

    Every other cell of a warp samples an unknown cell or the outside: it stays unknown.
    """
    x, y, w, h = cv2.boundingRect((local.state != UNKNOWN).view(np.uint8))
    if w == 0:
        return None
    cols = np.array([x - 1.0, x + w, x - 1.0, x + w])
    rows = np.array([y - 1.0, y - 1.0, y + h, y + h])
    sx, sy = local.pixel_to_world(cols, rows)
    corners = grid.to_pixel(dst_from_src.apply(np.stack([sx, sy], axis=1)))
    c0, r0 = np.floor(corners.min(axis=0) - margin_px).astype(int)
    c1, r1 = np.ceil(corners.max(axis=0) + margin_px).astype(int) + 1
    c0, r0 = max(c0 - c0 % step_px, 0), max(r0 - r0 % step_px, 0)
    c1, r1 = min(c1, grid.width), min(r1, grid.height)
    if c1 <= c0 or r1 <= r0:
        return None
    return int(r0), int(r1), int(c0), int(c1)


def box_around(mask: NDArray[np.bool_], margin_px: int) -> tuple[slice, slice] | None:
    """The bounding box of ``mask``'s True cells grown by ``margin_px`` on every side, clipped
    to the array: ``(rows, cols)`` slices, None when no cell is True. The window a stage works
    in instead of the whole grid."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    if w == 0:
        return None
    return _grown((y, y + h, x, x + w), margin_px, mask.shape)


def box_of_cells(
    rows: NDArray[np.intp], cols: NDArray[np.intp], margin_px: int, shape: tuple[int, ...]
) -> tuple[slice, slice]:
    """:func:`box_around` for cells given by their (non-empty) ``rows`` and ``cols`` on an
    array of ``shape``: no pass over the whole array."""
    box = (int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1)
    return _grown(box, margin_px, shape)


def grown(box: tuple[slice, slice], margin_px: int, shape: tuple[int, ...]) -> tuple[slice, slice]:
    """``box`` ((rows, cols) slices) grown by ``margin_px`` on every side, clipped to an array
    of ``shape``."""
    rows, cols = box
    return _grown((rows.start, rows.stop, cols.start, cols.stop), margin_px, shape)


def _grown(
    box: tuple[int, int, int, int], margin_px: int, shape: tuple[int, ...]
) -> tuple[slice, slice]:
    r0, r1, c0, c1 = box
    return (
        slice(max(r0 - margin_px, 0), min(r1 + margin_px, shape[0])),
        slice(max(c0 - margin_px, 0), min(c1 + margin_px, shape[1])),
    )


def nonzero_cells(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``np.nonzero(mask)``: the rows and columns of the True cells in row-major order, found
    with ``cv2.findNonZero`` in their bounding box (several times faster on a sparse mask)."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    if w == 0:
        none = np.zeros(0, np.intp)
        return none, none.copy()
    found = cv2.findNonZero(mask[y : y + h, x : x + w].view(np.uint8))
    cells = found.reshape(-1, 2).astype(np.intp)
    return cells[:, 1] + y, cells[:, 0] + x


def by_label(labels: NDArray[np.integer[Any]]) -> Iterator[tuple[int, NDArray[np.intp]]]:
    """Each label of ``labels`` (N,), ascending, with the indices of its entries in their own
    order: sorted once, never a mask over all the entries per label (quadratic: tens of
    thousands of components or clusters on a badly drifted map of a large building)."""
    if not len(labels):
        return
    order = np.argsort(labels, kind="stable")
    ordered = labels[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    for members in np.split(order, starts[1:]):
        yield int(labels[members[0]]), members


def any_along(
    mask: NDArray[np.bool_],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    dr: ArrayLike,
    dc: ArrayLike,
    steps: int,
    norm: ArrayLike = 1.0,
) -> NDArray[np.bool_]:
    """(N,) bool: whether ``mask`` is True at one of the cells ``k * (dr, dc) / norm`` away
    from each cell (``rows``, ``cols``: (N,)), for k = 1..``steps``, rounded to the nearest
    cell; a cell off the array is not. ``dr``, ``dc``, ``norm``: scalars or (N,), one
    direction for every cell or one each (a unit one with ``norm`` 1)."""
    found = np.zeros(len(rows), bool)
    h, w = mask.shape
    for k in range(1, steps + 1):
        r = np.rint(rows + k * np.asarray(dr) / np.asarray(norm)).astype(np.intp)
        c = np.rint(cols + k * np.asarray(dc) / np.asarray(norm)).astype(np.intp)
        on = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        found[on] |= mask[r[on], c[on]]
    return found


def main_axis(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The centre of ``points`` ((N, 2), at least one) and the unit direction they spread most
    along (its sign, and for points spread evenly the direction itself, arbitrary)."""
    centre = points.mean(axis=0)
    return centre, np.linalg.svd(points - centre, full_matrices=False)[2][0]


def extent_along(
    points: NDArray[np.float64], centre: NDArray[np.float64], axis: NDArray[np.float64]
) -> float:
    """How far ``points`` ((N, 2), at least one) reach along ``axis`` (in their own units)."""
    along = (points - centre) @ axis
    return float(along.max() - along.min())


def square_to(axis: NDArray[np.float64]) -> NDArray[np.float64]:
    """The unit direction square to ``axis`` (row, col)."""
    return np.array([axis[1], -axis[0]])


def densify(polyline: NDArray[np.float64], step: float) -> NDArray[np.float64]:
    """The points of ``polyline`` (N, 2) and, on each leg, points at most ``step`` apart (in
    its own units): its vertices kept, its end exact."""
    if len(polyline) < 2:
        return polyline
    out = [polyline[:1]]
    for a, b in itertools.pairwise(polyline):
        k = max(1, math.ceil(float(np.hypot(*(b - a))) / step))
        t = np.arange(1, k + 1)[:, None] / k
        out.append(a + t * (b - a))
    return np.concatenate(out)


@dataclass(frozen=True)
class RouteDistance:
    """How far the cells of a grid lie from the robot's route, metres, on blocks of ``block``
    cells: a lower bound on the length of every ray that saw a cell. ``nearest`` (blocks'
    shape + (2,), optional): the (row, col) of the route's block nearest to each block, which
    gives the direction of the shortest rays that saw a cell (:meth:`toward`)."""

    blocks: NDArray[np.float32]
    block: int
    nearest: NDArray[np.float32] | None = None

    def of_box(self, box: tuple[slice, slice]) -> NDArray[np.float32]:
        """The distance of every cell of ``box`` ((rows, cols) slices of the grid)."""
        return np.asarray(self.blocks[self._blocks_of(box)])

    def beyond(self, box: tuple[slice, slice], metres: float) -> NDArray[np.bool_]:
        """Whether every cell of ``box`` lies farther than ``metres`` from the route (decided
        on the blocks, one byte a cell)."""
        return np.asarray((self.blocks > metres)[self._blocks_of(box)])

    def _blocks_of(self, box: tuple[slice, slice]) -> tuple[NDArray[Any], ...]:
        """The open-mesh index of the block of every cell of ``box``."""
        rows = np.arange(box[0].start, box[0].stop) // self.block
        cols = np.arange(box[1].start, box[1].stop) // self.block
        return np.ix_(rows, cols)

    def at(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.float32]:
        """(N,) float32: the distance of each cell (``rows``, ``cols``: (N,) of the grid)."""
        return np.asarray(self.blocks[rows // self.block, cols // self.block])

    def toward(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.float32] | None:
        """(N, 2) float32: the unit (row, col) vector from each cell (``rows``, ``cols``: (N,)
        of the grid) to the centre of the route's nearest block; None without ``nearest``. A
        cell at that centre points nowhere in particular: (1, 0)."""
        if self.nearest is None:
            return None
        near = self.nearest[rows // self.block, cols // self.block]
        half = np.float32(0.5 * self.block - 0.5)
        dr = near[:, 0] * np.float32(self.block) + half - rows.astype(np.float32)
        dc = near[:, 1] * np.float32(self.block) + half - cols.astype(np.float32)
        length = np.hypot(dr, dc)
        here = length == 0
        dr[here], length[here] = 1.0, 1.0
        return np.stack([dr / length, dc / length], axis=-1).astype(np.float32)

    def farthest(self, mask: NDArray[np.bool_]) -> float:
        """The largest distance of a True cell of ``mask`` (the grid's shape), metres, on its
        block (0 when none is True): how far from the route the map saw anything, given its
        known cells."""
        blocks = any_in_blocks(mask, self.block)
        if blocks.shape != self.blocks.shape:
            raise ValueError(f"a mask of {mask.shape} cells is not on this route's grid")
        return float(self.blocks[blocks].max()) if blocks.any() else 0.0


def route_distance(
    route_px: NDArray[np.float64],
    shape: tuple[int, ...],
    resolution: float,
    *,
    block_m: float = 0.25,
    nearest: bool = False,
) -> RouteDistance | None:
    """:class:`RouteDistance` on a grid of ``shape`` from the route ``route_px`` ((M, 2) pixel
    ``(col, row)`` points, joined by straight lines), on blocks of about ``block_m``; None for
    an empty route. A lower bound: a stretch of the route off the grid is taken at the grid's
    edge (nearer to every cell than it is), and the blocks' centres less half a block's
    diagonal. With ``nearest``, each block's nearest route block too (the directions of
    :meth:`RouteDistance.toward`; asked by the removal evidence, not by a reach)."""
    route = np.asarray(route_px, np.float64).reshape(-1, 2)
    if len(route) == 0:
        return None
    f = max(1, round(block_m / resolution))
    h, w = int(shape[0]), int(shape[1])
    # A point every pixel along the route (vertices far off the grid first brought within a
    # bound: the part beyond it only lies further off), then onto the grid's edge.
    points = densify(np.clip(route, -1e6, 1e6), 1.0)
    points = np.clip(points, [0.0, 0.0], [w - 1.0, h - 1.0])
    blocks = np.floor((points + 0.5) / f).astype(np.intp)
    off_route = np.ones((-(-h // f), -(-w // f)), np.uint8)
    off_route[blocks[:, 1], blocks[:, 0]] = 0
    block_m = f * resolution
    dist = cv2.distanceTransform(off_route, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * block_m
    dist = np.maximum(dist - block_m / math.sqrt(2), 0)
    if not nearest:
        return RouteDistance(np.asarray(dist, np.float32), f)
    # The route's block nearest to each block (the label of the zero pixel each one's
    # distance was measured to; a 5x5 mask, as labels need, not the precise distance above).
    _, labels = cv2.distanceTransformWithLabels(
        off_route, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    on_rows, on_cols = np.nonzero(off_route == 0)
    at = np.zeros((int(labels.max()) + 1, 2), np.float32)
    at[labels[on_rows, on_cols]] = np.stack([on_rows, on_cols], axis=1)
    return RouteDistance(np.asarray(dist, np.float32), f, at[labels])


def any_in_blocks(mask: NDArray[np.bool_], f: int) -> NDArray[np.bool_]:
    """(ceil(H / f), ceil(W / f)) bool: whether each block of f x f cells of ``mask`` (the last
    row and column of blocks padded with False) holds a True cell."""
    h, w = mask.shape
    hh, ww = -(-h // f), -(-w // f)
    padded = np.pad(mask, ((0, hh * f - h), (0, ww * f - w)))
    return np.asarray(padded.reshape(hh, f, ww, f).any(axis=(1, 3)))
