"""DBSCAN over difference pixels -> obstacles in metres (nav2 frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from sklearn.cluster import DBSCAN

from mapserver.grid import Grid


@dataclass(frozen=True)
class Difference:
    """One added or removed obstacle, in metres in the nav2 frame.

    ``bbox`` is ``(min_x, min_y, max_x, max_y)`` over the pixels' extents; ``pixels`` counts
    work-grid pixels and ``area_m2`` is their area.
    """

    kind: str
    centroid: tuple[float, float]
    bbox: tuple[float, float, float, float]
    area_m2: float
    pixels: int


def cluster_mask(
    mask: NDArray[np.bool_],
    grid: Grid,
    kind: str,
    *,
    eps_m: float,
    min_samples: int,
    min_pixels: int = 1,
    min_area_m2: float = 0.0,
) -> list[Difference]:
    """Group the True pixels of ``mask`` (on ``grid``) into obstacles with DBSCAN.

    Pixels closer than ``eps_m`` join one obstacle; clusters smaller than ``min_pixels`` or
    ``min_area_m2`` are dropped, and so is DBSCAN's noise.
    """
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return []
    xy = grid.to_world(np.stack([cols, rows], axis=1))
    labels = DBSCAN(eps=eps_m, min_samples=min_samples).fit_predict(xy)
    half = grid.resolution / 2.0
    out = []
    for label in np.unique(labels):
        if label < 0:
            continue
        pts = xy[labels == label]
        area = len(pts) * grid.resolution**2
        if len(pts) < min_pixels or area < min_area_m2:
            continue
        lo, hi = pts.min(axis=0) - half, pts.max(axis=0) + half
        c = pts.mean(axis=0)
        out.append(
            Difference(
                kind,
                (float(c[0]), float(c[1])),
                (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                float(area),
                len(pts),
            )
        )
    return out


def sort_by_area(differences: list[Difference]) -> list[Difference]:
    """Largest first (the order of ``result.yaml``); ties by position for a stable order."""
    return sorted(differences, key=lambda d: (-d.area_m2, d.centroid))
