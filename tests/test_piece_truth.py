"""benchmarks/piece_truth.py: the true route of a drifting session, rebuilt from its slam
trajectory by running the simulator's drift model backwards."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from types import ModuleType

import numpy as np
import pytest
from bench_support import benchmark_module

from mapserver.geometry import Transform2D, fit_rigid
from mapserver.synth.session import _drifted


@pytest.fixture(scope="module")
def pt() -> Iterator[ModuleType]:
    with benchmark_module("piece_truth") as module:
        yield module


def square_route() -> np.ndarray:
    """A 60 m route round a 15 m square, poses 0.25 m apart (x, y, yaw), nav2 frame."""
    legs = []
    corners = [(0.0, 0.0), (15.0, 0.0), (15.0, 15.0), (0.0, 15.0), (0.0, 0.0)]
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        t = np.linspace(0.0, 1.0, 61)[:-1, None]
        yaw = math.atan2(y1 - y0, x1 - x0)
        xy = np.array([x0, y0]) + t * np.array([x1 - x0, y1 - y0])
        legs.append(np.column_stack([xy, np.full(len(xy), yaw)]))
    return np.concatenate(legs) + np.array([3.0, -2.0, 0.0])


def test_undrift_inverts_the_simulators_drift(pt: ModuleType) -> None:
    true = square_route()
    anchor = Transform2D(0.4, 3.0, -2.0)
    est = _drifted(true, anchor, math.radians(0.08), 1.004)
    back = pt.undrift(est, math.radians(0.08), 1.004)
    # Back in the frame the slam estimate started in, then onto nav2 through the anchor.
    np.testing.assert_allclose(anchor.apply(back[:, :2]), true[:, :2], atol=1e-9)
    # The drift is real: the estimate's end is metres from the truth's.
    assert np.hypot(*(anchor.apply(est[-1:, :2])[0] - true[-1, :2])) > 0.5


@pytest.mark.parametrize(("yaw_sign", "scale_sign"), [(1, 1), (1, -1), (-1, 1), (-1, -1)])
def test_true_route_picks_the_drifts_signs_from_the_prior(
    pt: ModuleType, yaw_sign: int, scale_sign: int
) -> None:
    true = square_route()
    anchor = Transform2D(-1.2, 3.0, -2.0)
    est = _drifted(true, anchor, yaw_sign * math.radians(0.08), 1.0 + scale_sign * 0.004)
    truth = fit_rigid(est[:, :2], true[:, :2])  # what a set's truth file holds
    prior = (true[-1, 0] + 0.03, true[-1, 1] - 0.04)  # AMCL noise
    route, miss = pt.true_route(est, truth, prior, 0.08, 0.004)
    np.testing.assert_allclose(route, true[:, :2], atol=1e-6)
    assert miss == pytest.approx(0.05, abs=1e-6)
