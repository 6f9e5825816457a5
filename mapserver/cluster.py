"""DBSCAN over difference pixels -> obstacles in metres (nav2 frame).

Two engines give the same labels. The points are pixel centres of one grid, so the default
``grid`` engine runs DBSCAN on the grid itself: neighbours are a fixed set of pixel offsets,
counted and joined with array lookups instead of a spatial index. ``scikit-learn`` runs
scikit-learn's DBSCAN on the pixel centres in metres; it is the reference the tests hold the grid
engine to, and importing it (with scipy) costs about 0.7 s and 95 MiB per process, more than
processing an airport-sized bundle does. The grid engine's labels are scikit-learn's: the same
clusters, numbered the same way, border points given to the same cluster. Only pixels exactly
``eps`` apart, which scikit-learn counts as neighbours or not depending on the floating-point
rounding of their coordinates, are always neighbours here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.diff import distance_to
from mapserver.grid import Grid, by_label, nonzero_cells

IntArray = NDArray[np.intp]
Engine = Literal["grid", "scikit-learn"]
ENGINES: tuple[Engine, ...] = ("grid", "scikit-learn")


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
    cells: NDArray[np.intp] | None = field(default=None, compare=False, repr=False)
    """(pixels, 2) ``(row, col)`` of its pixels on the grid it was found on."""


def cluster_mask(
    mask: NDArray[np.bool_],
    grid: Grid,
    kind: str,
    *,
    eps_m: float,
    min_samples: int,
    min_area_m2: float = 0.0,
    evidence: NDArray[np.bool_] | None = None,
    min_evidence: float = 0.5,
    min_evidence_m2: float = math.inf,
    whole: NDArray[np.bool_] | None = None,
    min_whole_share: float = 0.5,
    min_whole_area_m2: float = 0.0,
    engine: Engine = "grid",
) -> list[Difference]:
    """Group the True pixels of ``mask`` (on ``grid``) into obstacles with DBSCAN.

    Pixels within ``eps_m`` of each other join one obstacle; clusters smaller than
    ``min_area_m2`` are dropped, and so is DBSCAN's noise. With ``whole`` (same shape as
    ``mask``: the pixels of small things seen changed whole), a smaller cluster passes that
    floor when at least ``min_whole_share`` of its pixels are in it and it covers
    ``min_whole_area_m2`` (the evidence test below still applies). With ``evidence``
    (same shape as ``mask``), a cluster is kept only when at least the share ``min_evidence`` of
    its pixels are in it, or when those cover ``min_evidence_m2`` and the area floor or more
    however many do not, and reported as those and its pixels within ``eps_m`` of them (the
    area floor applies to the cluster before that).
    ``engine`` picks the DBSCAN implementation (the labels are the same).
    """
    rows, cols = nonzero_cells(mask)
    if len(rows) == 0:
        return []
    xy = grid.to_world(np.stack([cols, rows], axis=1))
    if engine == "scikit-learn":
        labels = _sklearn_dbscan()(eps=eps_m, min_samples=min_samples).fit_predict(xy)
    elif engine == "grid":
        offsets = neighbour_offsets(eps_m, grid.resolution)
        labels = dbscan_pixels(rows, cols, neighbours=offsets, min_samples=min_samples)
    else:
        raise ValueError(f"unknown DBSCAN engine {engine!r}; use one of {', '.join(ENGINES)}")
    half = grid.resolution / 2.0
    cell_m2 = grid.resolution**2
    # Kept for its evidence's area, that evidence alone passes the area floor too (on a coarse
    # grid a cell or two of evidence would otherwise keep any cluster).
    evidence_floor_m2 = max(min_evidence_m2, min_area_m2)
    out = []
    for label, members in by_label(labels):
        if label < 0:
            continue
        pts = xy[members]
        area = len(pts) * cell_m2
        if _short_of(area, min_area_m2) and not _whole_enough(
            whole, rows[members], cols[members], area, min_whole_share, min_whole_area_m2
        ):
            continue
        if evidence is not None:
            shown = evidence[rows[members], cols[members]]
            shown_m2 = np.count_nonzero(shown) * cell_m2
            if shown.mean() < min_evidence and _short_of(shown_m2, evidence_floor_m2):
                continue
            # Reported as its evidence and what lies within eps of it: a strip of a wall's face
            # that grazing rays eroded (no evidence) joins a removal it touches, and would
            # stretch its box along the wall; a fold's free band inside a block (no evidence)
            # joins a piece of the block really gone, and may outnumber it.
            # The area floor above judged the cluster as found; this shapes only the report.
            # With no evidence at all (a share of 0 asked for), it is reported whole.
            if shown.any():
                reach_px = eps_m / grid.resolution
                members = members[_near_evidence(rows[members], cols[members], shown, reach_px)]
                pts = xy[members]
                area = len(pts) * cell_m2
        lo, hi = pts.min(axis=0) - half, pts.max(axis=0) + half
        c = pts.mean(axis=0)
        out.append(
            Difference(
                kind,
                (float(c[0]), float(c[1])),
                (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                float(area),
                len(pts),
                np.stack([rows[members], cols[members]], axis=1),
            )
        )
    return out


def _whole_enough(
    whole: NDArray[np.bool_] | None,
    rows: IntArray,
    cols: IntArray,
    area_m2: float,
    min_share: float,
    floor_m2: float,
) -> bool:
    """Whether a cluster under the area floor (its pixels at ``rows``, ``cols``) is a small
    thing seen changed whole: ``min_share`` of its pixels in ``whole``, ``floor_m2`` covered."""
    return (
        whole is not None
        and not _short_of(area_m2, floor_m2)
        and int(np.count_nonzero(whole[rows, cols])) >= min_share * len(rows)
    )


def _short_of(area_m2: float, floor_m2: float) -> bool:
    """Whether an area of whole cells falls short of ``floor_m2``: a floor of whole cells (12
    at 0.05 m is 0.03 m2) keeps that many, whatever the rounding of the product."""
    return area_m2 < floor_m2 * (1 - 1e-9)


def _near_evidence(
    rows: IntArray, cols: IntArray, shown: NDArray[np.bool_], reach_px: float
) -> NDArray[np.bool_]:
    """Which of a cluster's pixels ``(rows, cols)`` lie within ``reach_px`` of one of them that
    ``shown`` holds (:func:`mapserver.diff.distance_to` on the cluster's own box)."""
    r0, c0 = int(rows.min()), int(cols.min())
    evidence = np.zeros((int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1), bool)
    evidence[rows[shown] - r0, cols[shown] - c0] = True
    return np.asarray(distance_to(evidence)[rows - r0, cols - c0] <= reach_px)


def _sklearn_dbscan() -> Any:
    """scikit-learn's DBSCAN class, imported on first use (never, with the grid engine)."""
    from sklearn.cluster import DBSCAN

    return DBSCAN


def neighbour_offsets(eps_m: float, resolution: float) -> IntArray:
    """(K, 2) ``(d_row, d_col)`` of the pixels whose centres lie within ``eps_m`` of a pixel's
    centre on a grid of ``resolution`` metres, itself included. A relative 1e-9 of slack makes
    pixels exactly ``eps_m`` apart neighbours, whatever the rounding."""
    if not (eps_m > 0 and resolution > 0):
        raise ValueError(f"eps_m and resolution must be > 0, got {eps_m} and {resolution}")
    k = int(eps_m / resolution * (1 + 1e-9))
    dr, dc = np.mgrid[-k : k + 1, -k : k + 1]
    inside = (dr**2 + dc**2) * resolution**2 <= eps_m**2 * (1 + 1e-9)
    return np.stack([dr[inside], dc[inside]], axis=1)


def dbscan_pixels(
    rows: IntArray, cols: IntArray, *, neighbours: IntArray, min_samples: int
) -> IntArray:
    """DBSCAN labels (-1 for noise) of pixels ``(rows, cols)`` given in row-major order.

    ``neighbours`` are the offsets within ``eps`` (:func:`neighbour_offsets`). A pixel with at
    least ``min_samples`` pixels among its neighbours (itself included) is a core pixel; core
    pixels within reach of each other form a cluster; a border pixel (not core, a core pixel
    within reach) joins the first cluster that reaches it. As in scikit-learn, clusters are
    numbered in the order of their first core pixel, and "first" is the lowest number.
    """
    n = len(rows)
    labels = np.full(n, -1, np.intp)
    if n == 0:
        return labels
    k = int(np.abs(neighbours).max())
    # Pixels on a padded box around them, so that every neighbour lookup is inside, with wide
    # empty bands squeezed out: scattered differences need a small box, not the whole view.
    r, c = _squeezed(rows, k), _squeezed(cols, k)
    shape = (int(r.max()) + k + 1, int(c.max()) + k + 1)
    present = np.zeros(shape, np.uint8)
    present[r, c] = 1
    count = np.zeros(n, np.int32)
    for dr, dc in neighbours:
        count += present[r + dr, c + dc]
    core = count >= min_samples
    if not core.any():
        return labels

    # Core pixels: first the components the grid's own connectivity already joins (neighbours
    # when within reach), then the joins across the remaining offsets.
    core_image = np.zeros(shape, np.uint8)
    core_image[r[core], c[core]] = 1
    within = {(int(a), int(b)) for a, b in neighbours}
    ring8 = {(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)} - {(0, 0)}
    ring4 = {(-1, 0), (1, 0), (0, -1), (0, 1)}
    connectivity = 8 if ring8 <= within else 4 if ring4 <= within else 0
    cr, cc = r[core], c[core]
    if connectivity:
        n_comp, components = cv2.connectedComponents(core_image, connectivity=connectivity)
        joined = ring8 if connectivity == 8 else ring4
    else:
        n_comp = int(core.sum()) + 1
        components = np.zeros(shape, np.int32)
        components[cr, cc] = np.arange(1, n_comp)
        joined = set()
    own = components[cr, cc]
    pairs = []
    for dr, dc in neighbours:
        if (dr, dc) <= (0, 0) or (int(dr), int(dc)) in joined:
            continue  # half the offsets are enough: the relation is symmetric
        other = components[cr + dr, cc + dc]
        across = (other > 0) & (other != own)
        pairs.append(np.stack([own[across], other[across]], axis=1))
    roots = _smallest_connected(
        n_comp, np.concatenate(pairs) if pairs else np.zeros((0, 2), np.intp)
    )
    cluster_of_core = roots[own]
    # Number the clusters by their first core pixel (the points are in row-major order).
    _, first = np.unique(cluster_of_core, return_index=True)
    number = np.zeros(n_comp, np.intp)
    number[cluster_of_core[np.sort(first)]] = np.arange(len(first))
    labels[core] = number[cluster_of_core]

    # Border pixels: the lowest-numbered cluster with a core pixel within reach.
    cluster_image = np.zeros(shape, np.int32)
    cluster_image[cr, cc] = labels[core] + 1
    border = np.flatnonzero(~core)
    if len(border):
        br, bc = r[border], c[border]
        none = np.iinfo(np.int32).max
        best = np.full(len(border), none, np.int32)
        for dr, dc in neighbours:
            near = cluster_image[br + dr, bc + dc]
            best = np.minimum(best, np.where(near > 0, near, none))
        reached = best < none
        labels[border[reached]] = best[reached] - 1
    return labels


def _squeezed(values: IntArray, k: int) -> IntArray:
    """``values`` moved to ``k`` and up, with every gap between them wider than ``2 k + 1``
    narrowed to that: values up to ``k`` apart keep their difference, values further apart stay
    further apart, and nothing else ever lands within ``k`` of a value."""
    distinct, index = np.unique(values, return_inverse=True)
    gaps = np.minimum(np.diff(distinct), 2 * k + 1)
    return np.asarray(np.concatenate([[0], np.cumsum(gaps)])[index] + k, dtype=np.intp)


def _smallest_connected(n: int, edges: NDArray[np.integer]) -> IntArray:
    """For nodes ``0..n-1`` joined by ``edges`` (E, 2): the smallest node of each one's
    connected part (the minimum label, spread along the edges with pointer jumping)."""
    label = np.arange(n)
    if len(edges) == 0:
        return label
    a, b = np.unique(edges, axis=0).T.astype(np.intp)
    while True:
        la, lb = label[a], label[b]
        if np.array_equal(la, lb):
            return label
        low = np.minimum(la, lb)
        # Hook each label onto the smaller one it meets, then shortcut the chains.
        np.minimum.at(label, la, low)
        np.minimum.at(label, lb, low)
        while True:
            jumped = label[label]
            if np.array_equal(jumped, label):
                break
            label = jumped


def sort_by_area(differences: list[Difference]) -> list[Difference]:
    """Largest first (the order of ``result.yaml``); ties by position for a stable order."""
    return sorted(differences, key=lambda d: (-d.area_m2, d.centroid))
