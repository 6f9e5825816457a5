"""Synthetic bundles with known truth: generated buildings, planted changes, simulated SLAM sessions.

The simulator stands in for a robot and its fleet. It plans a route through a global map, changes
the true world along it (obstacles added, structures removed, people standing about), drives the
route with a 2-D lidar and a drifting SLAM pose estimate, and builds the local map slam_toolbox
would have saved. Unit tests, the demo data and the speed benchmarks use it.

Conventions (contract section 1): arrays are indexed ``[row, col]`` with row 0 at the top; metres
and radians; ``nav2_from_slam`` maps slam points to nav2 points, ``p_nav2 = R(theta) p_slam + t``.
A map's origin yaw is ignored, as Nav2 ignores it. Every random step takes ``rng``: a
``numpy.random.Generator`` or an int seed, so a seed fixes every output.

Inside, points are often handled in continuous pixel coordinates ``(u, v)`` of a map ``h`` rows
tall: ``u = (x - ox) / r`` and ``v = h - (y - oy) / r``, so that pixel ``(row k, col c)`` covers
``c <= u < c + 1`` and ``k <= v < k + 1``.
"""

from __future__ import annotations

from mapserver.synth._common import Seed as Seed
from mapserver.synth.buildings import make_airport_map, make_office_map, roughen_map
from mapserver.synth.changes import Change, plant_changes
from mapserver.synth.files import write_bundle, write_scenario, write_truth
from mapserver.synth.route import plan_route
from mapserver.synth.scenario import (
    SyntheticBundle,
    bundle_from_session,
    make_scenario,
    thin_trajectory,
)
from mapserver.synth.session import DriftReport, Session, Walker, simulate_session

__all__ = [
    "Change",
    "DriftReport",
    "Session",
    "SyntheticBundle",
    "Walker",
    "bundle_from_session",
    "make_airport_map",
    "make_office_map",
    "make_scenario",
    "plan_route",
    "plant_changes",
    "roughen_map",
    "simulate_session",
    "thin_trajectory",
    "write_bundle",
    "write_scenario",
    "write_truth",
]
