"""What the simulator's modules share: the ``rng`` argument, argument checks, and the pixel
geometry of map windows (continuous pixel coordinates, polygon rasterisation)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

Seed = int | np.random.Generator
_SHIFT = 4  # sub-pixel bits for cv2 drawing
_ONE = 1 << _SHIFT


def _as_rng(rng: Seed) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, int | np.integer) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise TypeError(f"rng must be a numpy Generator or an int seed, got {type(rng).__name__}")


def _positive(name: str, value: float) -> None:
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be > 0, got {value}")


def _fill_uv(
    mask: NDArray[np.uint8], polys_uv: Sequence[NDArray[np.float64]], value: int = 1
) -> None:
    """Fill polygons given in continuous pixel coordinates of ``mask`` (pixel centres at +0.5)."""
    pts = [np.round((np.asarray(p, float) - 0.5) * _ONE).astype(np.int32) for p in polys_uv]
    cv2.fillPoly(mask, pts, value, cv2.LINE_8, _SHIFT)


@dataclass(frozen=True, eq=False)
class _Frame:
    """Pixel geometry of a window ``[row0:row0+h, col0:col0+w]`` of a map ``world_h`` rows tall."""

    resolution: float
    origin: tuple[float, float, float]
    world_h: int
    row0: int = 0
    col0: int = 0

    def uv(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Window pixel coordinates (u, v) of nav2 points (..., 2)."""
        xy = np.asarray(xy, float)
        u = (xy[..., 0] - self.origin[0]) / self.resolution - self.col0
        v = self.world_h - (xy[..., 1] - self.origin[1]) / self.resolution - self.row0
        return np.stack([u, v], -1)

    def xy(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        uv = np.asarray(uv, float)
        x = self.origin[0] + (uv[..., 0] + self.col0) * self.resolution
        y = self.origin[1] + (self.world_h - uv[..., 1] - self.row0) * self.resolution
        return np.stack([x, y], -1)


def _footprint(
    frame: _Frame, shape: tuple[int, int], polys_xy: Sequence[NDArray[np.float64]]
) -> tuple[int, int, NDArray[np.bool_]] | None:
    """Pixels of polygons (nav2 metres) in a window: ``(row, col, mask)`` of their bounding box,
    or None when they leave the window."""
    uvs = [frame.uv(p) for p in polys_xy]
    allp = np.concatenate(uvs)
    u0, v0 = np.floor(allp.min(0)).astype(int) - 1
    u1, v1 = np.ceil(allp.max(0)).astype(int) + 1
    if u0 < 0 or v0 < 0 or u1 > shape[1] or v1 > shape[0]:
        return None
    mask = np.zeros((v1 - v0, u1 - u0), np.uint8)
    _fill_uv(mask, [p - (u0, v0) for p in uvs])
    if not mask.any():
        return None
    return int(v0), int(u0), mask.astype(bool)
