"""The cells of a stored map: flat indices, windows, and moving work-grid cells onto them.

A stored map's cells are numbered ``row * width + col`` (row 0 the image's top row), as in the
contract's ``erase`` lists. Every version of a map shares its lattice (size, resolution, origin).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mapserver.maps import FREE, OCCUPIED, OccupancyMap

if TYPE_CHECKING:
    # Only for types: mapserver.grid imports OpenCV, and the daemon's main process, which
    # applies bundles to the store, starts without it.
    from mapserver.grid import Grid

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Lattice:
    """The cell lattice of a stored map: ``height`` x ``width`` cells of ``resolution`` metres,
    lower-left corner at ``(x0, y0)`` (the map's origin, its yaw ignored as in Nav2)."""

    width: int
    height: int
    resolution: float
    x0: float
    y0: float

    @staticmethod
    def of_map(m: OccupancyMap) -> Lattice:
        return Lattice(m.width, m.height, m.resolution, m.origin[0], m.origin[1])

    def matches(self, m: OccupancyMap, *, tol: float = 1e-6) -> bool:
        """Whether ``m`` lies on this lattice (same size, resolution and origin)."""
        return (
            m.width == self.width
            and m.height == self.height
            and math.isclose(m.resolution, self.resolution, rel_tol=1e-9, abs_tol=1e-12)
            and abs(m.origin[0] - self.x0) <= tol
            and abs(m.origin[1] - self.y0) <= tol
        )

    def cells_of_points(self, xy: NDArray[np.float64]) -> tuple[IntArray, IntArray]:
        """(rows, cols) of the cells holding (N, 2) points in metres (may be off the map)."""
        col = np.floor((xy[:, 0] - self.x0) / self.resolution).astype(np.int64)
        row = self.height - 1 - np.floor((xy[:, 1] - self.y0) / self.resolution).astype(np.int64)
        return row, col

    def flat(self, rows: IntArray, cols: IntArray) -> IntArray:
        """Flat indices of the cells on the map (cells off the map dropped), sorted, unique."""
        inside = (rows >= 0) & (rows < self.height) & (cols >= 0) & (cols < self.width)
        return np.unique(rows[inside] * self.width + cols[inside])

    def unflat(self, cells: IntArray) -> tuple[IntArray, IntArray]:
        """(rows, cols) of flat indices."""
        cells = np.asarray(cells, dtype=np.int64)
        return cells // self.width, cells % self.width

    def centres(self, cells: IntArray) -> NDArray[np.float64]:
        """(N, 2) metres of the cells' centres."""
        rows, cols = self.unflat(cells)
        x = self.x0 + (cols + 0.5) * self.resolution
        y = self.y0 + (self.height - rows - 0.5) * self.resolution
        return np.stack([x, y], axis=1)

    def outline(self, cells: IntArray) -> list[list[float]]:
        """A polygon around the cells (metres, nav2 frame): the convex hull of their corners,
        counter-clockwise. Empty for no cells."""
        if len(cells) == 0:
            return []
        import cv2

        h = self.resolution / 2.0
        c = self.centres(cells)
        corners = np.concatenate([c + np.array([dx, dy]) for dx in (-h, h) for dy in (-h, h)])
        hull = cv2.convexHull(corners.astype(np.float32)).reshape(-1, 2)
        return [[round(float(x), 3), round(float(y), 3)] for x, y in hull[::-1]]


@dataclass(frozen=True)
class Window:
    """A rectangle of a lattice's cells: rows ``row0 .. row0 + rows``, cols ``col0 .. col0 + cols``."""

    row0: int
    col0: int
    rows: int
    cols: int

    def flat(self, lattice: Lattice) -> IntArray:
        """Flat lattice indices of every cell of the window, as a (rows, cols) array."""
        r = np.arange(self.row0, self.row0 + self.rows, dtype=np.int64)[:, None]
        c = np.arange(self.col0, self.col0 + self.cols, dtype=np.int64)[None, :]
        return r * lattice.width + c

    def local(
        self, lattice: Lattice, cells: IntArray
    ) -> tuple[IntArray, IntArray, NDArray[np.bool_]]:
        """(rows, cols) of flat lattice cells relative to the window, and which lie inside it."""
        rows, cols = lattice.unflat(cells)
        rows, cols = rows - self.row0, cols - self.col0
        inside = (rows >= 0) & (rows < self.rows) & (cols >= 0) & (cols < self.cols)
        return rows, cols, inside


def states_on_lattice(
    state: NDArray[np.uint8], grid: Grid, lattice: Lattice
) -> tuple[Window, NDArray[np.bool_], NDArray[np.bool_]] | None:
    """What a state raster on ``grid`` says about the lattice's cells.

    Every known cell of ``state`` votes for the lattice cell its centre falls in. A lattice
    cell is *occupied* when any of its votes is occupied (walls are thin: a finer local map's
    wall is one cell of a coarser lattice), *free* when it has free votes and no occupied one.

    Returns ``(window, occupied, free)``, two (window.rows, window.cols) bool arrays, or None
    when no known cell falls on the map.
    """
    known = state != 255
    rows, cols = np.nonzero(known)
    if len(rows) == 0:
        return None
    xy = grid.to_world(np.stack([cols, rows], axis=1))
    lr, lc = lattice.cells_of_points(xy)
    inside = (lr >= 0) & (lr < lattice.height) & (lc >= 0) & (lc < lattice.width)
    if not inside.any():
        return None
    lr, lc = lr[inside], lc[inside]
    values = state[rows[inside], cols[inside]]
    r0, c0 = int(lr.min()), int(lc.min())
    window = Window(r0, c0, int(lr.max()) - r0 + 1, int(lc.max()) - c0 + 1)
    idx = (lr - r0) * window.cols + (lc - c0)
    size = window.rows * window.cols
    occ = np.bincount(idx[values == OCCUPIED], minlength=size) > 0
    free = np.bincount(idx[values == FREE], minlength=size) > 0
    occupied = occ.reshape(window.rows, window.cols)
    return window, occupied, free.reshape(window.rows, window.cols) & ~occupied


def cells_of_grid_cells(rows: IntArray, cols: IntArray, grid: Grid, lattice: Lattice) -> IntArray:
    """Flat lattice indices of the lattice cells that work-grid cells ``(rows, cols)`` fall in."""
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    xy = grid.to_world(np.stack([cols, rows], axis=1))
    return lattice.flat(*lattice.cells_of_points(xy))
