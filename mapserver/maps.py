"""ROS map_server maps: read and write them as :class:`OccupancyMap`; pixel <-> metre conversions.

Arrays are indexed ``[row, col]``; row 0 is the TOP of the map (contract section 1). The centre of
pixel ``(col c, row k)`` in an image ``h`` rows tall is ``x = ox + (c + 0.5) r``,
``y = oy + (h - k - 0.5) r``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from mapserver.errors import MapFileError

# Cell states, as stored in OccupancyMap.state (uint8).
FREE = 0
OCCUPIED = 100
UNKNOWN = 255

# What map_saver writes for each state.
PGM_OCCUPIED, PGM_UNKNOWN, PGM_FREE = 0, 205, 254


@dataclass(frozen=True, eq=False)
class OccupancyMap:
    """An occupancy grid.

    Attributes
    ----------
    state
        (H, W) uint8, indexed [row, col], row 0 at the top: FREE, OCCUPIED or UNKNOWN.
    occupancy
        (H, W) uint8 occupancy probability ``p`` scaled to 0..255 (0 certainly free, 255 certainly
        occupied), for every cell including unknown ones. Alignment uses it to see walls that a
        map draws in grey, below ``occupied_thresh``.
    resolution
        Metres per pixel.
    origin
        ``(x, y, yaw)`` of the lower-left pixel's corner, metres and radians.
    """

    state: NDArray[np.uint8]
    occupancy: NDArray[np.uint8]
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: Path | None = None
    image: Path | None = None
    warnings: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if self.state.ndim != 2 or self.state.shape != self.occupancy.shape:
            raise ValueError(
                f"state and occupancy must be 2-D arrays of one shape, got "
                f"{self.state.shape} and {self.occupancy.shape}"
            )

    @property
    def height(self) -> int:
        return int(self.state.shape[0])

    @property
    def width(self) -> int:
        return int(self.state.shape[1])

    def pixel_to_world(self, col: ArrayLike, row: ArrayLike) -> tuple[NDArray[np.float64], ...]:
        """Metres (x, y) of pixel coordinates (col, row); integer values are pixel centres."""
        r = self.resolution
        x = self.origin[0] + (np.asarray(col, dtype=float) + 0.5) * r
        y = self.origin[1] + (self.height - np.asarray(row, dtype=float) - 0.5) * r
        return x, y

    def world_to_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], ...]:
        """Fractional pixel coordinates (col, row) of points (x, y) in metres."""
        r = self.resolution
        col = (np.asarray(x, dtype=float) - self.origin[0]) / r - 0.5
        row = self.height - (np.asarray(y, dtype=float) - self.origin[1]) / r - 0.5
        return col, row

    def extent(self) -> tuple[float, float, float, float]:
        """``(min_x, min_y, max_x, max_y)`` of the map's area in metres."""
        ox, oy = self.origin[0], self.origin[1]
        return (ox, oy, ox + self.width * self.resolution, oy + self.height * self.resolution)


def from_states(
    state: NDArray[np.uint8],
    resolution: float,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> OccupancyMap:
    """An :class:`OccupancyMap` from a state array (occupancy set to 0, 127 or 255)."""
    state = np.ascontiguousarray(state, dtype=np.uint8)
    occupancy = np.full(state.shape, 127, np.uint8)
    occupancy[state == FREE] = 0
    occupancy[state == OCCUPIED] = 255
    return OccupancyMap(state, occupancy, float(resolution), tuple(origin))  # type: ignore[arg-type]


def state_to_pgm(state: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """The map_saver grey values (0 / 205 / 254) of a state array."""
    out = np.full(state.shape, PGM_UNKNOWN, np.uint8)
    out[state == FREE] = PGM_FREE
    out[state == OCCUPIED] = PGM_OCCUPIED
    return out


def save_map(
    yaml_path: Path,
    state: NDArray[np.uint8],
    resolution: float,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    image_name: str | None = None,
) -> Path:
    """Write a map the way map_saver does: a P5 PGM (0 / 205 / 254) and its YAML. Returns the YAML."""
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    image_path = yaml_path.parent / image_name
    pixels = state_to_pgm(state)
    header = f"P5\n# CREATOR: mapserver {resolution:.3f} m/pix\n{pixels.shape[1]} {pixels.shape[0]}\n255\n"
    image_path.write_bytes(header.encode("ascii") + pixels.tobytes())
    document = {
        "image": image_name,
        "mode": "trinary",
        "resolution": float(resolution),
        "origin": [float(v) for v in origin],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    yaml_path.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))
    return yaml_path


def load_map(
    yaml_path: str | Path,
    *,
    max_pixels: int = 100_000_000,
    confine_to: Path | None = None,
) -> OccupancyMap:
    """Read a ROS map YAML and the image it names.

    Raises :class:`MapFileError` naming the file and the problem.
    """
    # Placeholder reader: PGM/PNG 8-bit grey, trinary only. Replaced by the full reader.
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise MapFileError(f"cannot read map YAML: {error}", file=yaml_path) from None
    image_path = yaml_path.parent / meta["image"]
    grey = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise MapFileError("cannot decode the image", file=image_path)
    p = (255.0 - grey) / 255.0
    state = np.full(grey.shape, UNKNOWN, np.uint8)
    state[p > float(meta["occupied_thresh"])] = OCCUPIED
    state[p < float(meta["free_thresh"])] = FREE
    occupancy = (255 - grey).astype(np.uint8)
    origin = tuple(float(v) for v in meta["origin"])
    return OccupancyMap(state, occupancy, float(meta["resolution"]), origin, yaml_path, image_path)  # type: ignore[arg-type]
