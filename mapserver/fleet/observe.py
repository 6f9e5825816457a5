"""What one bundle contributes to the fleet map, computed in a worker: plain data for the main
process, which alone writes the store (:meth:`mapserver.fleet.store.FleetStore.apply`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.evidence import TileDelta
from mapserver.fleet.lattice import (
    IntArray,
    Lattice,
    Window,
    cells_of_grid_cells,
    states_on_lattice,
)

if TYPE_CHECKING:
    from mapserver.grid import Grid  # OpenCV: the workers have it, the main process need not


@dataclass(frozen=True)
class Found:
    """A difference against the map's current version: its kind and its cells (flat indices on
    the map's lattice)."""

    kind: str
    cells: IntArray


@dataclass(frozen=True)
class Observation:
    """One bundle's contribution to a stored map.

    ``occupied`` and ``free`` are (window.rows, window.cols) bool arrays on the map's lattice:
    what the aligned, drift-corrected local map observed. ``found`` are the differences against
    version ``judged_version`` (the current one when the worker looked); ``result_cells`` the
    kind and cells of each difference of the bundle's own ``result.yaml`` (against the version
    the robot navigated on, ``bundle_version``), in its order.
    """

    map_name: str
    bundle_id: str
    fingerprint: str
    robot: str
    stamp: str
    bundle_version: int
    judged_version: int
    window: Window
    occupied: NDArray[np.bool_]
    free: NDArray[np.bool_]
    found: tuple[Found, ...]
    result_cells: tuple[tuple[str, IntArray], ...]
    tiles: tuple[TileDelta, ...] = ()
    """``occupied`` and ``free`` packed per evidence tile (:func:`evidence.pack_tiles`)."""


def fingerprint(manifest_bytes: bytes, slam_image_sha256: str) -> str:
    """What makes a bundle the same bundle, whatever its folder's name: its manifest and its
    local map's image."""
    h = hashlib.sha256(manifest_bytes)
    h.update(slam_image_sha256.lower().encode("ascii"))
    return h.hexdigest()


def cells_of(rows_cols: NDArray[np.intp] | None, grid: Grid, lattice: Lattice) -> IntArray:
    """Flat lattice cells of (N, 2) ``(row, col)`` work-grid cells."""
    if rows_cols is None or len(rows_cols) == 0:
        return np.zeros(0, np.int64)
    return cells_of_grid_cells(rows_cols[:, 0], rows_cols[:, 1], grid, lattice)


def observed(
    local_state: NDArray[np.uint8], grid: Grid, lattice: Lattice
) -> tuple[Window, NDArray[np.bool_], NDArray[np.bool_]]:
    """The observed occupied and free cells of the lattice (an empty 1x1 window if none)."""
    seen = states_on_lattice(local_state, grid, lattice)
    if seen is None:
        empty = np.zeros((1, 1), bool)
        return Window(0, 0, 1, 1), empty, empty.copy()
    return seen
