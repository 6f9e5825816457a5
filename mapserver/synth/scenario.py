"""Scenarios: a route, planted changes and a simulated session in one bundle with its truth
(:class:`SyntheticBundle`, :func:`make_scenario`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapserver.geometry import Pose2D, Transform2D
from mapserver.maps import OccupancyMap
from mapserver.synth._common import Seed, _as_rng
from mapserver.synth.changes import Change, plant_changes
from mapserver.synth.route import plan_route
from mapserver.synth.session import Session, simulate_session


@dataclass(frozen=True, eq=False)
class SyntheticBundle:
    """Everything about one synthetic bundle, in memory.

    Attributes
    ----------
    world
        The global map as the fleet has it (without the changes): what ``nav2_map`` holds.
    true_state
        (H, W) uint8 [row, col]: the world during the session, in ``world``'s grid.
    route
        True nav2-frame robot poses, every ~0.25 m.
    changes
        The planted changes, ``observed`` set from the session.
    session
        The simulated session (local map, truth transform, prior poses, drift).
    trajectory
        SLAM-frame poses about every metre, for the manifest.
    """

    world: OccupancyMap
    true_state: NDArray[np.uint8]
    route: tuple[Pose2D, ...]
    changes: tuple[Change, ...]
    session: Session
    trajectory: tuple[Pose2D, ...]

    @property
    def slam_map(self) -> OccupancyMap:
        return self.session.slam_map

    @property
    def nav2_from_slam(self) -> Transform2D:
        """The true slam -> nav2 transform."""
        return self.session.nav2_from_slam

    @property
    def pose_nav2(self) -> Pose2D:
        """The prior nav2 pose the robot reports (noisy)."""
        return self.session.pose_nav2

    @property
    def pose_slam(self) -> Pose2D:
        return self.session.pose_slam


def make_scenario(
    world: OccupancyMap,
    *,
    seed: Seed,
    route_length_m: float = 20.0,
    n_added: int = 3,
    n_removed: int = 2,
    n_people: int = 1,
    clearance_m: float = 0.4,
    mislocalize: bool = False,
    min_seen_cells: int = 5,
    trajectory_spacing_m: float = 1.0,
    **session_options: Any,
) -> SyntheticBundle:
    """Plan a route, plant changes, simulate the session: one bundle with its truth.

    Parameters
    ----------
    world
        The global map (nav2 frame).
    seed
        Seed or Generator for every random step.
    route_length_m
        Route length, metres.
    n_added, n_removed, n_people
        Changes to plant (see :func:`plant_changes`).
    clearance_m
        Route clearance from non-free cells, metres.
    mislocalize
        Offset the reported nav2 pose by 0.5-2 m and 5-30 degrees (a failed localisation).
    min_seen_cells
        A change is ``observed`` when the local map shows at least this many cells of it.
    trajectory_spacing_m
        Spacing of the manifest trajectory, metres.
    **session_options
        Passed to :func:`simulate_session` (sensor, drift, walkers, AMCL noise ...).

    Returns
    -------
    SyntheticBundle
    """
    if mislocalize and ("mislocalize_m" in session_options or "mislocalize_deg" in session_options):
        raise ValueError(
            "give either mislocalize=True or mislocalize_m / mislocalize_deg, not both"
        )
    rng = _as_rng(seed)
    route = plan_route(world, length_m=route_length_m, rng=rng, clearance_m=clearance_m)
    truth, changes = plant_changes(
        world,
        route,
        n_added=n_added,
        n_removed=n_removed,
        n_people=n_people,
        rng=rng,
        clearance_m=clearance_m,
    )
    offset_m, offset_deg = rng.uniform(0.5, 2.0), rng.uniform(5.0, 30.0)
    if mislocalize:
        session_options = {
            **session_options,
            "mislocalize_m": offset_m,
            "mislocalize_deg": offset_deg,
        }
    session = simulate_session(
        world, route, rng=rng, true_state=truth, changes=changes, **session_options
    )
    return bundle_from_session(
        world,
        truth,
        route,
        changes,
        session,
        min_seen_cells=min_seen_cells,
        trajectory_spacing_m=trajectory_spacing_m,
    )


def bundle_from_session(
    world: OccupancyMap,
    true_state: NDArray[np.uint8],
    route: Sequence[Pose2D],
    changes: Sequence[Change],
    session: Session,
    *,
    min_seen_cells: int = 5,
    trajectory_spacing_m: float = 1.0,
) -> SyntheticBundle:
    """The bundle of a simulated session: a change counts as observed when the session saw at
    least ``min_seen_cells`` of its cells; the manifest's trajectory is thinned to a pose about
    every ``trajectory_spacing_m`` metres."""
    return SyntheticBundle(
        world=world,
        true_state=true_state,
        route=tuple(route),
        changes=tuple(
            replace(c, observed=session.seen_cells.get(c.id, 0) >= min_seen_cells) for c in changes
        ),
        session=session,
        trajectory=thin_trajectory(session.trajectory, trajectory_spacing_m),
    )


def thin_trajectory(poses: Sequence[Pose2D], spacing_m: float = 1.0) -> tuple[Pose2D, ...]:
    """A pose about every ``spacing_m`` metres travelled, and the last one."""
    xy = np.array([(p.x, p.y) for p in poses])
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    marks = np.floor(travelled / spacing_m + 1e-9)
    keep = np.flatnonzero(np.diff(marks, prepend=-1) > 0).tolist()
    if keep[-1] != len(xy) - 1:
        keep.append(len(xy) - 1)
    return tuple(poses[i] for i in keep)
