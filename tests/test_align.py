"""Alignment recovers a planted transform from a disturbed prior, and says when it cannot."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from worlds import (
    HALL_CENTRE,
    HALL_GONE,
    HALL_TRUTH,
    changed_hall,
    colonnade,
    cut_local,
    office,
    offset,
)

from mapserver.align import (
    UNCHANGED_MARGIN,
    NearestWall,
    align,
    icp,
    icp_many,
    known_points,
    make_view,
    structure_mask,
    thin_points,
    unchanged_score,
)
from mapserver.geometry import Transform2D, fit_rigid, wrap_angle
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states

TRUE = Transform2D(0.7, 5.0, -3.0)
CENTRE = (12.0, 6.0)


def _errors(
    found: Transform2D, truth: Transform2D, at_nav2: tuple[float, float]
) -> tuple[float, float]:
    p = truth.inverse().apply(np.array(at_nav2))
    d = float(np.linalg.norm(found.apply(p) - truth.apply(p)))
    return d, abs(math.degrees(wrap_angle(found.theta - truth.theta)))


def _run(world: OccupancyMap, local: OccupancyMap, prior: Transform2D, **kw: float):
    view = make_view(world, local, prior, search_xy_m=2.5)
    return align(local, view, prior, **kw)


@pytest.mark.parametrize(
    ("dx", "dy", "dtheta_deg"),
    [(0.0, 0.0, 0.0), (0.4, -0.3, 4.0), (-0.5, 0.2, -5.0), (1.6, -1.2, 25.0)],
)
def test_recovers_planted_transform(dx: float, dy: float, dtheta_deg: float) -> None:
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    prior = offset(TRUE, dx, dy, dtheta_deg, CENTRE)
    result = _run(world, cut.local, prior)
    d, a = _errors(result.nav2_from_slam, TRUE, CENTRE)
    assert result.trusted
    assert d < 0.03, f"position error {d:.3f} m"
    assert a < 0.3, f"angle error {a:.2f} deg"
    assert result.score > 0.9
    if dx or dy or dtheta_deg:
        assert result.refined and result.method.startswith("pose+")
        assert result.score > result.prior_score


@pytest.mark.parametrize(("global_res", "local_res"), [(0.1, 0.05), (0.02, 0.05), (0.05, 0.03)])
def test_different_resolutions(global_res: float, local_res: float) -> None:
    world = office(seed=5, resolution=global_res)
    cut = cut_local(
        world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE, resolution=local_res
    )
    prior = offset(TRUE, 0.3, 0.3, 3.0, CENTRE)
    result = _run(world, cut.local, prior)
    d, a = _errors(result.nav2_from_slam, TRUE, CENTRE)
    assert d < max(0.04, global_res / 2), f"position error {d:.3f} m"
    assert a < 0.4


def _hall(gone: list[tuple[float, float]]) -> tuple[OccupancyMap, OccupancyMap]:
    world, cut = changed_hall(gone)
    return world, cut.local


def test_a_hall_with_more_change_than_building_is_trusted_on_what_did_not_change() -> None:
    """The right transform scores under min_score over all walls (new objects off every drawn
    wall, columns seen gone), yet every column still standing fits: trusted, and it says why."""
    world, local = _hall(HALL_GONE)
    result = _run(world, local, offset(HALL_TRUTH, 0.1, -0.1, 1.0, HALL_CENTRE))
    d, a = _errors(result.nav2_from_slam, HALL_TRUTH, HALL_CENTRE)
    assert d < 0.03 and a < 0.3
    assert result.score < 0.6 and result.trusted
    assert result.unchanged_score is not None
    assert result.unchanged_score >= 0.6 + UNCHANGED_MARGIN
    assert any("aligned on the structure that did not change" in w for w in result.warnings)
    # A stricter minimum raises that bar too: at 0.8, 1.05 is out of reach.
    strict = _run(world, local, offset(HALL_TRUTH, 0.1, -0.1, 1.0, HALL_CENTRE), min_score=0.8)
    assert not strict.trusted and strict.unchanged_score is None


@pytest.mark.parametrize(("dx", "dy", "dtheta_deg"), [(0.3, 0.0, 0.0), (0.0, 0.6, 2.0)])
def test_a_wrong_transform_is_not_trusted_on_what_did_not_change(
    dx: float, dy: float, dtheta_deg: float
) -> None:
    """Off by decimetres, the local walls lie beside the columns and the columns run partly
    through seen floor: both still count."""
    world, local = _hall(HALL_GONE)
    wrong = offset(HALL_TRUTH, dx, dy, dtheta_deg, HALL_CENTRE)
    result = _run(world, local, wrong, refine=False)
    assert not result.trusted and result.unchanged_score is None
    view = make_view(world, local, wrong, search_xy_m=2.5)
    walls = known_points(local, state=OCCUPIED)
    assert unchanged_score(local, walls, wrong, view, tolerance_m=0.1) < 0.65


def test_no_more_than_a_share_of_the_building_may_be_gone() -> None:
    """Half the columns seen gone is no longer a hall that changed a little: not excused (two
    of six are)."""
    half = [(28.0, 13.5), (34.0, 19.5), (34.0, 13.5)]
    world, local = _hall(half)
    view = make_view(world, local, HALL_TRUTH, search_xy_m=2.5)
    walls = known_points(local, state=OCCUPIED)
    near = view.grid.sample(view.near_walls(1.0), HALL_TRUTH.apply(walls), False)
    assert near.mean() > 0.3  # enough walls near a column: the share of gone ones decides
    assert unchanged_score(local, walls, HALL_TRUTH, view, tolerance_m=0.1) == 0.0
    _, local = _hall(HALL_GONE)
    walls = known_points(local, state=OCCUPIED)
    assert unchanged_score(local, walls, HALL_TRUTH, view, tolerance_m=0.1) > 0.95


def test_repeated_columns_do_not_pull_away_from_a_good_prior() -> None:
    """Rows of identical columns 4 m apart: a prior 0.6 m off must not lock onto the next column."""
    world = colonnade(spacing_m=4.0)
    truth = Transform2D(-0.3, 20.0, 8.0)
    centre = (30.0, 16.0)
    cut = cut_local(world, centre_xy=centre, radius_m=6.0, nav2_from_slam=truth)
    prior = offset(truth, 0.6, -0.4, 3.0, centre)
    result = _run(world, cut.local, prior)
    d, _ = _errors(result.nav2_from_slam, truth, centre)
    assert d < 0.05


def test_mislocalised_beyond_search_is_reported_not_trusted() -> None:
    """A prior far outside the search window: low score, a warning, and no trust."""
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    prior = offset(TRUE, 6.0, 5.0, 90.0, CENTRE)
    result = _run(world, cut.local, prior)
    assert not result.trusted
    assert result.score < 0.6
    assert any("could not align" in w for w in result.warnings)


def _floor_ends_at_walls(world: OccupancyMap, keep_every: int) -> OccupancyMap:
    """``world`` as a map that ends its floor at a wall without drawing it dark: its wall
    cells unknown, but for one 3 x 3 block in ``keep_every`` (willow-2010 draws a few)."""
    state = world.state.copy()
    rows, cols = np.nonzero(state == OCCUPIED)
    undrawn = ((rows // 3 + cols // 3) % keep_every) != 0
    state[rows[undrawn], cols[undrawn]] = UNKNOWN
    return from_states(state, world.resolution, world.origin)


def test_walls_drawn_as_the_end_of_the_known_floor_trust_a_right_alignment_near_the_bar() -> None:
    """One wall block in 8 drawn: the right transform scores 0.57 on the drawn walls, and
    over 0.6 with the edges of the known floor taken as walls; trusted, saying so, only within
    ``edge_margin`` of the bar. One in 10: 0.49, under the margin, not trusted. A transform
    0.3 m off is not trusted, whatever the margin."""
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)

    def run(keep_every: int, prior: Transform2D, margin: float):
        sparse = _floor_ends_at_walls(world, keep_every)
        view = make_view(sparse, cut.local, prior, search_xy_m=2.5)
        return align(cut.local, view, prior, refine=False, edge_margin=margin)

    plain = run(8, TRUE, 0.0)
    assert 0.5 < plain.score < 0.6 and not plain.trusted
    edges = run(8, TRUE, 0.1)
    assert edges.trusted and edges.score == plain.score
    assert edges.edges_score is not None and edges.edges_score >= 0.6
    assert plain.edges_score is None and edges.unchanged_score is None
    assert any("edges of what the global map knows" in w for w in edges.warnings)
    assert not run(10, TRUE, 0.1).trusted
    off = offset(TRUE, 0.3, 0.0, 0.0, CENTRE)
    assert not run(8, off, 1.0).trusted


def test_refine_off_keeps_the_prior() -> None:
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    prior = offset(TRUE, 0.2, 0.0, 1.0, CENTRE)
    result = _run(world, cut.local, prior, refine=False)
    assert result.nav2_from_slam == prior
    assert result.method == "pose" and not result.refined


def test_grey_antialiased_walls_still_align() -> None:
    """A drawing whose walls are grey anti-aliased lines (unknown by the trinary rule)."""
    world = office(seed=7)
    grey = np.where(world.state == OCCUPIED, 150, np.where(world.state == FREE, 254, 205)).astype(
        np.uint8
    )
    grey = cv2.GaussianBlur(grey, (3, 3), 0)
    p = (255 - grey.astype(float)) / 255
    state = np.full(grey.shape, UNKNOWN, np.uint8)
    state[p > 0.65] = OCCUPIED
    state[p < 0.196] = FREE
    drawn = OccupancyMap(state, (p * 255).astype(np.uint8), world.resolution, world.origin)
    assert (drawn.state == OCCUPIED).sum() < 0.01 * (world.state == OCCUPIED).sum()
    assert structure_mask(drawn).sum() > 0.5 * (world.state == OCCUPIED).sum()
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    prior = offset(TRUE, 0.4, -0.3, 4.0, CENTRE)
    result = _run(drawn, cut.local, prior)
    d, a = _errors(result.nav2_from_slam, TRUE, CENTRE)
    assert result.trusted and d < 0.05 and a < 0.5


def test_inputs_are_not_modified() -> None:
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=6.0, nav2_from_slam=TRUE)
    before_g, before_l = world.state.copy(), cut.local.state.copy()
    _run(world, cut.local, offset(TRUE, 0.3, 0.0, 2.0, CENTRE))
    assert np.array_equal(world.state, before_g) and np.array_equal(cut.local.state, before_l)


def test_mislocalised_robot_far_from_the_map_centre() -> None:
    """AMCL off by 1.5 m and 25 degrees at the robot's pose, 7 m from the map's centre: the
    error is a rotation about the robot, which a search about the centroid would not cover."""
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    robot_nav2 = (CENTRE[0] + 6.0, CENTRE[1] - 3.5)
    prior = offset(TRUE, 1.2, -0.9, 25.0, robot_nav2)
    robot_slam = TRUE.inverse().apply(np.array(robot_nav2))
    pivot = (float(robot_slam[0]), float(robot_slam[1]))
    view = make_view(world, cut.local, prior, search_xy_m=2.5, pivot_slam=pivot)
    result = align(cut.local, view, prior, pivot_slam=pivot)
    d, a = _errors(result.nav2_from_slam, TRUE, CENTRE)
    assert result.trusted and d < 0.03 and a < 0.3


@pytest.mark.parametrize("dtheta_deg", [3.0, 25.0])
def test_the_wide_view_is_built_only_when_the_narrow_search_fails(dtheta_deg: float) -> None:
    """The search starts on a view that covers only the narrow rotations; a prior 25 degrees
    off needs the wide search, which asks for the wide view once; 3 degrees off never does."""
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    prior = offset(TRUE, 0.8, -0.6, dtheta_deg, CENTRE)
    narrow = math.radians(8.0)
    asked: list[float] = []

    def widen():  # type: ignore[no-untyped-def]
        asked.append(1.0)
        return make_view(
            world, cut.local, prior, search_xy_m=2.5, search_theta_rad=math.radians(35)
        )

    view = make_view(world, cut.local, prior, search_xy_m=2.5, search_theta_rad=narrow)
    result = align(cut.local, view, prior, narrow_theta_rad=narrow, widen=widen)
    d, a = _errors(result.nav2_from_slam, TRUE, CENTRE)
    assert result.trusted and d < 0.03 and a < 0.3
    assert len(asked) == (1 if dtheta_deg > 8 else 0)


def _icp_one(
    points: np.ndarray,
    start: Transform2D,
    grid: Grid,
    nearest: NearestWall,
    *,
    max_distance_m: float,
    iterations: int = 30,
) -> Transform2D:
    """Point-to-point ICP from one start, written plainly: the pairs within the shrinking limit
    and their least-squares rigid fit (:func:`mapserver.geometry.fit_rigid`)."""
    t = start
    for k in range(iterations):
        limit = max_distance_m * (1.0 - 0.66 * k / (iterations - 1))
        q = t.apply(points)
        wx, wy = nearest.nearest_xy(q[:, 0], q[:, 1], grid)
        use = (wx - q[:, 0]) ** 2 + (wy - q[:, 1]) ** 2 <= limit**2
        if use.sum() < 10:
            break
        new = fit_rigid(points[use], np.stack([wx[use], wy[use]], axis=1))
        step = math.hypot(new.tx - t.tx, new.ty - t.ty)
        t = new
        if step < 1e-4 and k > 5:
            break
    return t


def test_wall_points_thinned_by_their_mean_keep_the_walls_middle() -> None:
    """Walls two cells thick, thinned to one point per two cells: the means lie on the walls'
    middle line, the first point of each block (in row-major order) half a cell up and left of
    it, the offset an ICP on them once carried into the transform."""
    state = np.full((60, 80), FREE, np.uint8)
    state[10:12, 4:76] = OCCUPIED  # along x
    state[14:58, 40:42] = OCCUPIED  # along y
    local = from_states(state, 0.05, (1.0, 2.0, 0.0))
    walls = known_points(local, state=OCCUPIED)
    wall_y = float(local.pixel_to_world(np.array([0.0]), np.array([10.5]))[1][0])  # rows 10-11
    wall_x = float(local.pixel_to_world(np.array([40.5]), np.array([0.0]))[0][0])  # cols 40-41
    by_mean = thin_points(walls, 0.1, mean=True)
    assert len(by_mean) == len(walls) // 4
    along_x = by_mean[:, 1] > 4.35  # the wall along x lies at y = 4.45, the other below 4.3
    np.testing.assert_allclose(by_mean[along_x, 1], wall_y, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(by_mean[~along_x, 0], wall_x, rtol=0.0, atol=1e-9)
    first = thin_points(walls, 0.1)
    np.testing.assert_allclose(
        first.mean(axis=0) - walls.mean(axis=0), [-0.025, 0.025], rtol=0.0, atol=1e-9
    )


def test_alignment_has_no_bias_in_the_local_maps_frame() -> None:
    """Over many planted transforms the error averages out: no offset along the local map's
    own axes (the raster's rows and columns). Thinning that kept each block's first point moved
    the local map down and to the right on average (per-axis median 3.8 mm here)."""
    world = office(seed=3)
    gaps = []
    for k in range(24):
        truth = Transform2D(0.2 + 0.37 * k, 5.0 + 0.013 * k, -3.0 + 0.029 * k)
        cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=truth)
        found = _run(world, cut.local, offset(truth, 0.1, -0.1, 1.0, CENTRE)).nav2_from_slam
        at = truth.inverse().apply(np.array(CENTRE))
        gaps.append(Transform2D(-truth.theta, 0.0, 0.0).apply(found.apply(at) - truth.apply(at)))
    assert max(float(np.hypot(*g)) for g in gaps) < 0.05
    median_gap = np.median(gaps, axis=0)
    assert float(np.hypot(*median_gap)) < 0.002, f"median offset {median_gap} m (slam axes)"


def test_icp_polishes_each_start_on_its_own() -> None:
    """Starts polished together land where each lands alone (a plain one-start ICP): near
    offsets converge on the truth, and a start too far to find any wall within reach keeps its
    transform."""
    world = office(seed=3)
    cut = cut_local(world, centre_xy=CENTRE, radius_m=8.0, nav2_from_slam=TRUE)
    near_a = offset(TRUE, 0.12, -0.08, 1.0, CENTRE)
    near_b = offset(TRUE, -0.1, 0.1, -1.5, CENTRE)
    lost = offset(TRUE, 40.0, 40.0, 0.0, CENTRE)
    view = make_view(world, cut.local, TRUE, search_xy_m=2.5)
    walls = thin_points(known_points(cut.local, state=OCCUPIED), 2 * view.grid.resolution)
    starts = [near_a, lost, near_b]
    nearest = view.nearest_wall_near(np.concatenate([t.apply(walls) for t in starts]), reach_m=0.8)
    together = icp_many(walls, starts, view.grid, nearest, max_distance_m=0.3)
    alone = [_icp_one(walls, t, view.grid, nearest, max_distance_m=0.3) for t in starts]
    assert icp(walls, near_a, view.grid, nearest, max_distance_m=0.3) == together[0]
    for a, b in zip(together, alone, strict=True):
        assert (a.theta, a.tx, a.ty) == pytest.approx((b.theta, b.tx, b.ty), abs=1e-9)
    for found in (together[0], together[2]):
        d, angle = _errors(found, TRUE, CENTRE)
        assert d < 0.05, f"position error {d:.3f} m"
        assert angle < 0.3, f"angle error {angle:.2f} deg"
    assert together[1] == lost
