"""The fast paths of the image stages give exactly what the plain computations give."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapserver.align import NearestWall
from mapserver.diff import distance_to, near, offset_distances


def _walls(seed: int, shape: tuple[int, int], density: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < density
    canvas = mask.astype(np.uint8)
    for _ in range(4):  # and some lines, as walls are
        a, b = rng.integers(0, min(shape), (2, 2))
        cv2.line(canvas, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, 1)
    return canvas.astype(bool)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("density", [0.001, 0.02, 0.3])
@pytest.mark.parametrize(
    ("tolerance_m", "resolution"),
    [(0.1, 0.05), (0.15, 0.05), (0.25, 0.05), (0.17, 0.03), (0.0, 0.05)],
)
def test_near_is_the_thresholded_distance(
    seed: int, density: float, tolerance_m: float, resolution: float
) -> None:
    walls = _walls(seed, (97 + seed * 13, 150), density)
    before = walls.copy()
    d = distance_to(walls)
    t = tolerance_m / resolution
    reach = offset_distances(t)
    # Both ways the stages write the test: in pixels, and in metres.
    assert np.array_equal(~near(walls, ~(reach > t)), d > t)
    assert np.array_equal(
        ~near(walls, ~(reach * resolution > tolerance_m)), d * resolution > tolerance_m
    )
    assert np.array_equal(walls, before)


def test_offset_distances_hold_every_offset_within_reach() -> None:
    reach = offset_distances(4.3)
    assert reach.shape == (13, 13)
    assert reach[6, 6] == 0
    # The border of the square is beyond the reach: nothing within it was cut off.
    border = np.concatenate([reach[0], reach[-1], reach[:, 0], reach[:, -1]])
    assert border.min() > 4.3
    assert not reach.flags.writeable


@pytest.mark.parametrize("seed", range(4))
def test_nearest_wall_lookup_is_the_dense_field(seed: int) -> None:
    structure = _walls(seed, (120, 90), 0.01)
    free = np.where(structure, 0, 255).astype(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(
        free, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    rows, cols = np.nonzero(structure)
    table = np.zeros((len(rows) + 1, 2))
    table[1:, 0], table[1:, 1] = cols, rows
    dense = table[labels]  # (H, W, 2), what the field used to be

    field = NearestWall.of(structure)
    assert field.shape == dense.shape
    rr, cc = np.mgrid[: structure.shape[0], : structure.shape[1]]
    got = field[rr.ravel(), cc.ravel()]
    assert np.array_equal(got, dense.reshape(-1, 2))
    # The cells it names are walls, at the distance the transform measured.
    named = got.astype(int)
    assert structure[named[:, 1], named[:, 0]].all()
    gap = np.hypot(named[:, 0] - cc.ravel(), named[:, 1] - rr.ravel())
    assert np.allclose(gap, dist.ravel(), atol=0.1 * gap.max() + 0.1)
