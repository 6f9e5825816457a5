"""DBSCAN (scikit-learn) over difference pixels -> obstacles in metres (nav2 frame).

scikit-learn is imported on first use, not with this module: with scipy it takes about 0.75 s,
most of a process's start-up, and the daemon's main process and ``check-config`` never cluster.
The daemon's worker processes import it once, when they start (forkserver preload).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.grid import Grid

IntArray = NDArray[np.intp]


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
    evidence: NDArray[np.bool_] | None = None,
    min_evidence: float = 0.5,
) -> list[Difference]:
    """Group the True pixels of ``mask`` (on ``grid``) into obstacles with DBSCAN.

    Pixels within ``eps_m`` of each other join one obstacle; clusters smaller than
    ``min_pixels`` or ``min_area_m2`` are dropped, and so is DBSCAN's noise. With ``evidence``
    (same shape as ``mask``), a cluster is kept only when at least the share ``min_evidence`` of
    its pixels are in it.
    """
    # The True pixels, row-major, found in their bounding box (a difference mask is sparse).
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    if w == 0:
        return []
    rows, cols = np.nonzero(mask[y : y + h, x : x + w])
    rows, cols = rows + y, cols + x
    xy = grid.to_world(np.stack([cols, rows], axis=1))
    labels = _dbscan()(eps=eps_m, min_samples=min_samples).fit_predict(xy)
    half = grid.resolution / 2.0
    out = []
    for label in np.unique(labels):
        if label < 0:
            continue
        members = labels == label
        pts = xy[members]
        area = len(pts) * grid.resolution**2
        if len(pts) < min_pixels or area < min_area_m2:
            continue
        if evidence is not None and evidence[rows[members], cols[members]].mean() < min_evidence:
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


def _dbscan() -> Any:
    """scikit-learn's DBSCAN class, imported on first use."""
    from sklearn.cluster import DBSCAN

    return DBSCAN


def sort_by_area(differences: list[Difference]) -> list[Difference]:
    """Largest first (the order of ``result.yaml``); ties by position for a stable order."""
    return sorted(differences, key=lambda d: (-d.area_m2, d.centroid))
