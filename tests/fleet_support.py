"""Planted evidence for the fleet-map tests: a small building map, and observations of it made
by hand (what a robot saw, and which differences it found), so every test knows its truth."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.evidence import pack_tiles
from mapserver.fleet.lattice import Lattice, Window
from mapserver.fleet.observe import Found, Observation
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, save_map

T0 = datetime(2026, 11, 21, 8, 0, tzinfo=timezone.utc)
RES = 0.05


def stamp(hours: float) -> str:
    return (T0 + timedelta(hours=hours)).isoformat().replace("+00:00", "Z")


def building() -> NDArray[np.uint8]:
    """A 20 m x 12 m hall (400 x 240 cells at 0.05 m): walls around, a column at (5, 6) m,
    unknown outside."""
    state = np.full((240, 400), UNKNOWN, np.uint8)
    cv2.rectangle(state, (10, 10), (389, 229), FREE, -1)
    cv2.rectangle(state, (10, 10), (389, 229), OCCUPIED, 3)
    cv2.rectangle(state, (96, 116), (104, 124), OCCUPIED, -1)  # the column, rows 116..124
    return state


def write_building(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return save_map(folder / "hall.yaml", building(), RES, (0.0, 0.0, 0.0))


LATTICE = Lattice(400, 240, RES, 0.0, 0.0)

# A new wall across the hall at x = 12 m, from y = 3 m to y = 9 m (cols 239..241).
WALL = (slice(60, 181), slice(239, 242))
# A person standing at (15, 4) m.
PERSON = (slice(156, 164), slice(296, 304))
# The column: rows 116..124, cols 96..104.
COLUMN = (slice(116, 125), slice(96, 105))


def cells(region: tuple[slice, slice]) -> NDArray[np.int64]:
    mask = np.zeros((LATTICE.height, LATTICE.width), bool)
    mask[region] = True
    return np.flatnonzero(mask).astype(np.int64)


@dataclass
class Robot:
    """Makes observations of the hall as it is at some time: the world state is the
    building with ``added`` regions occupied and ``removed`` regions free."""

    name: str = "r1"
    counter: list[int] = field(default_factory=lambda: [0])

    def observe(
        self,
        hours: float,
        *,
        added: tuple[tuple[slice, slice], ...] = (),
        removed: tuple[tuple[slice, slice], ...] = (),
        found: tuple[tuple[str, tuple[slice, slice]], ...] = (),
        judged_version: int = 1,
        bundle_version: int = 1,
        map_name: str = "hall",
        bundle_id: str | None = None,
        view: tuple[slice, slice] = (slice(0, 240), slice(0, 400)),
    ) -> Observation:
        world = building()
        for r in added:
            world[r] = OCCUPIED
        for r in removed:
            world[r] = FREE
        seen = np.full(world.shape, UNKNOWN, np.uint8)
        seen[view] = world[view]
        self.counter[0] += 1
        bid = bundle_id or f"{self.name}-{self.counter[0]:03d}"
        rows = np.arange(240)[view[0]]
        cols = np.arange(400)[view[1]]
        window = Window(int(rows[0]), int(cols[0]), len(rows), len(cols))
        crop = seen[view]
        occupied, free = crop == OCCUPIED, crop == FREE
        return Observation(
            map_name=map_name,
            bundle_id=bid,
            fingerprint=hashlib.sha256(f"{bid}-{hours}".encode()).hexdigest(),
            robot=self.name,
            stamp=stamp(hours),
            bundle_version=bundle_version,
            judged_version=judged_version,
            window=window,
            occupied=occupied,
            free=free,
            found=tuple(Found(kind, cells(region)) for kind, region in found),
            result_cells=tuple((kind, cells(region)) for kind, region in found),
            tiles=pack_tiles(window, occupied, free),
        )
