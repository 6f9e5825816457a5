"""The simulator: planted truth in, local maps and files that agree with it out."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from mapserver import synth
from mapserver.bundle import check_bundle_files, read_manifest
from mapserver.errors import BundleIncomplete
from mapserver.geometry import Transform2D
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, load_map
from mapserver.synth.session import _drifted


@pytest.fixture(scope="module")
def office() -> OccupancyMap:
    return synth.make_office_map(width_m=26, height_m=18, rng=11)


@pytest.fixture(scope="module")
def airport() -> OccupancyMap:
    return synth.make_airport_map(width_px=1400, height_px=1300, rng=7)


@pytest.fixture(scope="module")
def scenario(office: OccupancyMap) -> synth.SyntheticBundle:
    """A clean session: no drift, no registration noise, no walkers."""
    return synth.make_scenario(
        office, seed=5, route_length_m=20, n_added=3, n_removed=2, n_people=1
    )


def local_cells_in_world(sc: synth.SyntheticBundle, state: int) -> tuple[np.ndarray, np.ndarray]:
    """World (row, col) of the local cells in ``state``, moved by the true transform."""
    m, world = sc.slam_map, sc.world
    rows, cols = np.nonzero(m.state == state)
    x, y = m.pixel_to_world(cols, rows)
    p = sc.nav2_from_slam.apply(np.stack([x, y], 1))
    c, r = world.world_to_pixel(p[:, 0], p[:, 1])
    r, c = np.round(r).astype(int), np.round(c).astype(int)
    inside = (r >= 0) & (r < world.height) & (c >= 0) & (c < world.width)
    return r[inside], c[inside]


def near(mask: np.ndarray, px: int) -> np.ndarray:
    k = 2 * px + 1
    return cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0


def polygon_mask(world: OccupancyMap, polygon: tuple[tuple[float, float], ...]) -> np.ndarray:
    xy = np.array(polygon)
    c, r = world.world_to_pixel(xy[:, 0], xy[:, 1])
    mask = np.zeros(world.state.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(np.stack([c, r], 1) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
    return mask > 0


def agreement(sc: synth.SyntheticBundle, tolerance_px: int) -> tuple[float, float]:
    """Shares of local occupied cells near true occupied cells and of local free cells on true
    free cells."""
    truth = sc.true_state
    r, c = local_cells_in_world(sc, OCCUPIED)
    occupied = float(near(truth == OCCUPIED, tolerance_px)[r, c].mean())
    r, c = local_cells_in_world(sc, FREE)
    free = float(near(truth == FREE, tolerance_px)[r, c].mean())
    return occupied, free


# ---------------------------------------------------------------------------------------------
# Route
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["office", "airport"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_route_stays_in_free_space(which: str, seed: int, request: pytest.FixtureRequest) -> None:
    world = request.getfixturevalue(which)
    route = synth.plan_route(world, length_m=25, rng=seed, clearance_m=0.4)
    xy = np.array([(p.x, p.y) for p in route])
    c, r = world.world_to_pixel(xy[:, 0], xy[:, 1])
    r, c = np.floor(r + 0.5).astype(int), np.floor(c + 0.5).astype(int)
    assert np.all(world.state[r, c] == FREE)
    clearance_px = cv2.distanceTransform(
        (world.state == FREE).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
    )
    assert clearance_px[r, c].min() * world.resolution >= 0.1
    steps = np.hypot(*np.diff(xy, axis=0).T)
    assert steps.max() <= 0.25 + 1e-6
    assert steps.sum() == pytest.approx(25, abs=0.3)
    heading = np.arctan2(np.diff(xy[:, 1]), np.diff(xy[:, 0]))
    yaw = np.array([p.yaw for p in route[:-1]])
    assert np.allclose(np.cos(heading - yaw), 1, atol=1e-6)


def test_route_depends_only_on_the_seed(office: OccupancyMap) -> None:
    assert synth.plan_route(office, length_m=15, rng=3) == synth.plan_route(
        office, length_m=15, rng=3
    )
    assert synth.plan_route(office, length_m=15, rng=3) != synth.plan_route(
        office, length_m=15, rng=4
    )


# ---------------------------------------------------------------------------------------------
# Planted changes
# ---------------------------------------------------------------------------------------------


def test_changes_are_planted_in_the_true_world_only(scenario: synth.SyntheticBundle) -> None:
    world, truth = scenario.world, scenario.true_state
    assert world.state is not truth
    kinds = [c.kind for c in scenario.changes]
    assert (
        kinds.count("added") == 3 and kinds.count("removed") == 2 and kinds.count("temporary") == 1
    )
    assert [c.id for c in scenario.changes] == list(range(1, len(kinds) + 1))
    for change in scenario.changes:
        inside = polygon_mask(world, change.polygon)
        if change.kind == "removed":
            erased = inside & (world.state == OCCUPIED) & (truth == FREE)
            assert erased.sum() >= 3
        else:
            assert np.mean(truth[inside] == OCCUPIED) > 0.5
            assert np.mean(world.state[inside] == FREE) > 0.95
    # Nothing changes outside the polygons.
    anywhere = np.zeros(world.state.shape, bool)
    for change in scenario.changes:
        anywhere |= near(polygon_mask(world, change.polygon), 2)
    assert np.array_equal(world.state[~anywhere], truth[~anywhere])


def test_changes_leave_the_route_clear(scenario: synth.SyntheticBundle) -> None:
    xy = np.array([(p.x, p.y) for p in scenario.route])
    for change in scenario.changes:
        if change.kind == "removed":
            continue
        poly = np.array(change.polygon, np.float32)
        gaps = [abs(cv2.pointPolygonTest(poly, (float(x), float(y)), True)) for x, y in xy]
        assert min(gaps) >= 0.4
        assert cv2.pointPolygonTest(poly, (float(xy[0, 0]), float(xy[0, 1])), False) < 0


# ---------------------------------------------------------------------------------------------
# The simulated local map
# ---------------------------------------------------------------------------------------------


def test_local_map_reprojects_onto_the_true_world(scenario: synth.SyntheticBundle) -> None:
    occupied, free = agreement(scenario, tolerance_px=1)
    assert occupied >= 0.97
    assert free >= 0.97
    assert np.count_nonzero(scenario.slam_map.state == OCCUPIED) > 500


def test_local_map_is_anchored_like_slam_toolbox(scenario: synth.SyntheticBundle) -> None:
    s = scenario.session
    first = scenario.route[0]
    assert s.trajectory[0].x == pytest.approx(0, abs=1e-9)
    assert s.trajectory[0].y == pytest.approx(0, abs=1e-9)
    assert s.trajectory[0].yaw == pytest.approx(0, abs=1e-9)
    assert s.nav2_from_slam_start == Transform2D(first.yaw, first.x, first.y)
    assert s.nav2_from_slam.theta == pytest.approx(first.yaw, abs=1e-9)
    m = scenario.slam_map
    assert m.origin[2] == 0.0
    assert m.resolution == 0.05
    # The origin lies on the grid (like slam_toolbox) and the map is cropped with a small margin.
    assert m.origin[0] / 0.05 == pytest.approx(round(m.origin[0] / 0.05), abs=1e-6)
    known = np.argwhere(m.state != UNKNOWN)
    assert known.min(0).tolist() == [5, 5]
    assert (np.array(m.state.shape) - 1 - known.max(0)).tolist() == [5, 5]


@pytest.mark.parametrize("kind", ["added", "temporary"])
def test_observed_obstacles_are_occupied_in_the_local_map(
    scenario: synth.SyntheticBundle, kind: str
) -> None:
    r, c = local_cells_in_world(scenario, OCCUPIED)
    changes = [ch for ch in scenario.changes if ch.kind == kind and ch.observed]
    assert changes
    for change in changes:
        on_it = near(polygon_mask(scenario.world, change.polygon), 1)[r, c].sum()
        assert on_it >= 5, change


def test_observed_removed_structures_are_free_in_the_local_map(
    scenario: synth.SyntheticBundle,
) -> None:
    r, c = local_cells_in_world(scenario, FREE)
    world, truth = scenario.world, scenario.true_state
    changes = [ch for ch in scenario.changes if ch.kind == "removed" and ch.observed]
    assert changes
    for change in changes:
        erased = polygon_mask(world, change.polygon) & (world.state == OCCUPIED) & (truth == FREE)
        assert erased[r, c].sum() >= 5, change


def test_observed_follows_the_seen_cells(scenario: synth.SyntheticBundle) -> None:
    for change in scenario.changes:
        assert change.observed == (scenario.session.seen_cells[change.id] >= 5)


@pytest.mark.parametrize(
    ("world_resolution", "slam_resolution", "fov_deg"),
    [(0.1, 0.05, 360.0), (0.05, 0.1, 270.0), (0.05, 0.05, 180.0)],
)
def test_other_sensors_and_resolutions(
    world_resolution: float, slam_resolution: float, fov_deg: float
) -> None:
    world = synth.make_office_map(width_m=22, height_m=14, resolution=world_resolution, rng=4)
    sc = synth.make_scenario(
        world,
        seed=4,
        route_length_m=15,
        fov_deg=fov_deg,
        slam_resolution=slam_resolution,
        max_range_m=8.0,
    )
    assert sc.slam_map.resolution == slam_resolution
    tolerance_px = max(1, round(slam_resolution / world_resolution))
    occupied, free = agreement(sc, tolerance_px=tolerance_px)
    assert occupied >= 0.95
    assert free >= 0.95


def test_drift_bends_the_far_end_and_the_truth_is_the_best_fit(airport: OccupancyMap) -> None:
    sc = synth.make_scenario(
        airport,
        seed=8,
        route_length_m=50,
        n_added=1,
        n_removed=0,
        n_people=0,
        drift_yaw_deg_per_m=0.05,
        drift_scale=0.003,
        slam_xy_m=0.01,
        slam_yaw_deg=0.1,
    )
    drift = sc.session.drift
    assert 0.03 <= drift.fit_max_residual_m <= 0.6
    assert drift.end_position_error_m > drift.fit_max_residual_m
    start, best = sc.session.nav2_from_slam_start, sc.nav2_from_slam
    assert abs(best.theta - start.theta) > 1e-3
    # Anchored at the start the far end is off; the best fit keeps the whole map close.
    occupied, _ = agreement(sc, tolerance_px=3)
    assert occupied >= 0.9


def test_a_random_walk_heading_drift_wanders_where_a_bias_keeps_turning() -> None:
    # 100 m east in 1 m steps, estimated from the slam frame's anchor at the start.
    true = np.stack([np.arange(101.0), np.zeros(101), np.zeros(101)], axis=1)
    anchor = Transform2D(0.0, 0.0, 0.0)
    rate = math.radians(0.1)
    bias = _drifted(true, anchor, rate, 1.0)
    assert bias[-1, 2] == pytest.approx(100 * rate)
    # Draws of +1 every 1 m step turn as the bias does (sqrt(1) = 1); alternating ones cancel.
    same = _drifted(true, anchor, rate, 1.0, np.ones(100))
    assert np.allclose(same, bias)
    back_and_forth = _drifted(true, anchor, rate, 1.0, np.tile([1.0, -1.0], 50))
    assert back_and_forth[-1, 2] == pytest.approx(0.0, abs=1e-12)
    # Sideways: the bias bends the route by metres, the wandering heading by centimetres.
    assert np.abs(back_and_forth[:, 1]).max() < 0.1
    assert np.abs(bias[:, 1]).max() > 5.0
    # Steps of 0.25 m: each turns by the rate times 0.5 (the square root of its length).
    fine = np.stack([np.arange(0.0, 1.01, 0.25), np.zeros(5), np.zeros(5)], axis=1)
    assert _drifted(fine, anchor, rate, 1.0, np.ones(4))[-1, 2] == pytest.approx(4 * 0.5 * rate)


def test_walkers_leave_only_a_few_occupied_cells(office: OccupancyMap) -> None:
    sc = synth.make_scenario(
        office, seed=21, route_length_m=20, n_added=0, n_removed=0, n_people=0, walkers=4
    )
    occupied, _ = agreement(sc, tolerance_px=1)
    assert occupied >= 0.9


def test_prior_pose_has_amcl_noise_or_a_mislocalisation(office: OccupancyMap) -> None:
    ok = synth.make_scenario(office, seed=9, route_length_m=12, amcl_xy_m=0.05, amcl_yaw_deg=1.0)
    bad = synth.make_scenario(office, seed=9, route_length_m=12, mislocalize=True)
    true_end = ok.route[-1]
    gap_ok = math.hypot(ok.pose_nav2.x - true_end.x, ok.pose_nav2.y - true_end.y)
    gap_bad = math.hypot(bad.pose_nav2.x - true_end.x, bad.pose_nav2.y - true_end.y)
    assert gap_ok < 0.3
    assert 0.2 < gap_bad < 2.5
    # Mislocalising changes the prior only, not the session.
    assert np.array_equal(ok.slam_map.state, bad.slam_map.state)


def test_same_seed_same_scenario(office: OccupancyMap) -> None:
    a = synth.make_scenario(office, seed=33, route_length_m=12, walkers=1)
    b = synth.make_scenario(office, seed=33, route_length_m=12, walkers=1)
    c = synth.make_scenario(office, seed=34, route_length_m=12, walkers=1)
    assert np.array_equal(a.slam_map.state, b.slam_map.state)
    assert a.slam_map.origin == b.slam_map.origin
    assert a.changes == b.changes and a.route == b.route
    assert a.nav2_from_slam == b.nav2_from_slam and a.pose_nav2 == b.pose_nav2
    assert a.route != c.route


def test_inputs_are_not_modified(office: OccupancyMap) -> None:
    before = office.state.copy()
    route = synth.plan_route(office, length_m=10, rng=1)
    truth, changes = synth.plant_changes(office, route, n_added=2, n_removed=2, n_people=1, rng=1)
    truth_before = truth.copy()
    synth.simulate_session(office, route, rng=1, true_state=truth, changes=changes)
    assert np.array_equal(office.state, before)
    assert np.array_equal(truth, truth_before)


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("fov_deg", 0),
        ("angle_increment_deg", -0.5),
        ("max_range_m", 0),
        ("drop_rate", 1.0),
        ("scan_every", 0),
        ("slam_resolution", 0),
        ("walkers", -1),
    ],
)
def test_bad_session_options_are_named(office: OccupancyMap, option: str, value: float) -> None:
    route = synth.plan_route(office, length_m=5, rng=1)
    with pytest.raises(ValueError, match=option):
        synth.simulate_session(office, route, rng=1, **{option: value})


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------


def test_bundle_files_verify_and_load(scenario: synth.SyntheticBundle, tmp_path) -> None:
    bundle = synth.write_scenario(
        scenario, tmp_path / "inbox", "sim-0001", robot="sim-01", stamp="2026-11-21T10:15:00Z"
    )
    files = check_bundle_files(bundle)
    manifest = files.manifest
    assert set(manifest.checksums or {}) == {
        "slam_map.yaml",
        "slam_map.pgm",
        "nav2_map.yaml",
        "nav2_map.pgm",
    }
    assert manifest.robot == "sim-01" and manifest.stamp == "2026-11-21T10:15:00Z"
    assert len(manifest.trajectory_poses()) >= 15
    assert sorted(p.name for p in bundle.iterdir()) == [
        "bundle.yaml",
        "nav2_map.pgm",
        "nav2_map.yaml",
        "slam_map.pgm",
        "slam_map.yaml",
    ]
    prior, truth = manifest.nav2_from_slam_prior(), scenario.nav2_from_slam
    assert abs(prior.theta - truth.theta) < math.radians(5)
    slam = load_map(files.slam_yaml)
    assert np.array_equal(slam.state, scenario.slam_map.state)
    assert slam.origin == pytest.approx(scenario.slam_map.origin, abs=1e-6)
    nav2 = load_map(bundle / "nav2_map.yaml")
    assert np.array_equal(nav2.state, scenario.world.state)  # the global map, without the changes
    # A changed file no longer matches its checksum.
    (bundle / "slam_map.pgm").write_bytes((bundle / "slam_map.pgm").read_bytes()[:-1] + b"\x00")
    with pytest.raises(BundleIncomplete, match="sha256"):
        check_bundle_files(bundle)
    assert read_manifest(bundle).slam_map == "slam_map.yaml"


def test_bundle_without_global_map(scenario: synth.SyntheticBundle, tmp_path) -> None:
    bundle = synth.write_scenario(
        scenario, tmp_path, "b1", include_nav2_map=False, stamp="2026-01-01T00:00:00Z"
    )
    files = check_bundle_files(bundle)
    assert files.manifest.nav2_map is None and files.nav2_yaml is None


def test_bad_bundle_id_is_refused(scenario: synth.SyntheticBundle, tmp_path) -> None:
    with pytest.raises(ValueError, match="bundle_id"):
        synth.write_scenario(scenario, tmp_path, "../escape")


def test_truth_yaml_follows_the_contract(scenario: synth.SyntheticBundle, tmp_path) -> None:
    path = synth.write_truth(
        tmp_path / "truth" / "sim-0001.yaml", scenario.nav2_from_slam, scenario.changes
    )
    doc = yaml.safe_load(path.read_text())
    assert set(doc) == {"format", "transform", "changes"}
    assert doc["format"] == 1
    assert set(doc["transform"]) == {"theta", "tx", "ty"}
    t = scenario.nav2_from_slam
    assert doc["transform"]["theta"] == pytest.approx(t.theta, abs=1e-6)
    assert doc["transform"]["tx"] == pytest.approx(t.tx, abs=1e-5)
    assert doc["transform"]["ty"] == pytest.approx(t.ty, abs=1e-5)
    assert len(doc["changes"]) == len(scenario.changes)
    for entry, change in zip(doc["changes"], scenario.changes, strict=True):
        assert set(entry) == {"id", "kind", "polygon", "observed"}
        assert entry["id"] == change.id and isinstance(entry["id"], int)
        assert entry["kind"] in {"added", "removed", "temporary"}
        assert isinstance(entry["observed"], bool)
        assert len(entry["polygon"]) >= 3
        assert all(len(p) == 2 and all(isinstance(v, float) for v in p) for p in entry["polygon"])


# ---------------------------------------------------------------------------------------------
# Generated buildings
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_airport_has_rows_of_identical_columns(seed: int) -> None:
    airport = synth.make_airport_map(width_px=1600, height_px=1200, resolution=0.05, rng=seed)
    assert airport.state.shape == (1200, 1600)
    n, _labels, stats, centroids = cv2.connectedComponentsWithStats(
        (airport.state == OCCUPIED).astype(np.uint8), connectivity=8
    )
    shapes: dict[tuple[int, int, int], list[int]] = {}
    for i in range(1, n):
        w, h, area = (
            stats[i, cv2.CC_STAT_WIDTH],
            stats[i, cv2.CC_STAT_HEIGHT],
            stats[i, cv2.CC_STAT_AREA],
        )
        if 0.4 <= w * 0.05 <= 1.0 and w == h:
            shapes.setdefault((int(w), int(h), int(area)), []).append(i)
    columns = max(shapes.values(), key=len)
    assert len(columns) >= 12
    # Long rows on a regular grid: in each row the same step between neighbours, to the pixel.
    centres = centroids[columns]
    rows = [np.sort(centres[centres[:, 1] == y, 0]) for y in np.unique(centres[:, 1])]
    rows = [xs for xs in rows if len(xs) >= 4]
    assert len(rows) >= 2
    steps = np.concatenate([np.diff(xs) for xs in rows])
    assert steps.max() - steps.min() < 1e-6


def test_airport_is_known_inside_and_unknown_outside() -> None:
    airport = synth.make_airport_map(
        width_px=900, height_px=1500, rng=5, origin=(-10.0, -20.0, 0.0)
    )
    assert airport.state.shape == (1500, 900)
    assert airport.origin == (-10.0, -20.0, 0.0)
    border = np.concatenate(
        [airport.state[0], airport.state[-1], airport.state[:, 0], airport.state[:, -1]]
    )
    assert np.all(border == UNKNOWN)
    assert np.mean(airport.state == FREE) > 0.4
    assert set(np.unique(airport.state)) == {FREE, OCCUPIED, UNKNOWN}


@pytest.mark.parametrize("style", ["office", "hospital"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_office_floor_is_one_connected_building(style: str, seed: int) -> None:
    floor = synth.make_office_map(width_m=30, height_m=22, style=style, rng=seed)
    assert floor.state.shape == (round(24 / 0.05), round(32 / 0.05))
    free = (floor.state == FREE).astype(np.uint8)
    _n, _labels, stats, _ = cv2.connectedComponentsWithStats(free, connectivity=4)
    areas = np.sort(stats[1:, cv2.CC_STAT_AREA])[::-1]
    # Rooms open onto the corridors: free space is one piece (a furniture nook may be cut off).
    assert areas[0] >= 0.97 * areas.sum()
    assert np.all(floor.state[0] == UNKNOWN)


def test_generated_maps_vary_with_the_seed() -> None:
    a = synth.make_office_map(rng=1)
    b = synth.make_office_map(rng=2)
    assert a.state.shape != b.state.shape or not np.array_equal(a.state, b.state)
    assert np.array_equal(synth.make_office_map(rng=1).state, a.state)


def test_roughen_map_only_grows_walls_a_little(office: OccupancyMap) -> None:
    before = office.state.copy()
    rough = synth.roughen_map(office, rng=3, edge_rate=0.2, speckles_per_100m2=2.0)
    assert np.array_equal(office.state, before)
    changed = rough.state != office.state
    assert 0 < changed.mean() < 0.02
    assert np.all(office.state[changed] == FREE) and np.all(rough.state[changed] == OCCUPIED)
    assert rough.origin == office.origin and rough.resolution == office.resolution
    sc = synth.make_scenario(rough, seed=2, route_length_m=12)
    assert sc.slam_map.state.size > 0


def _cast_in_child(queue, args):  # type: ignore[no-untyped-def]
    from mapserver.synth.session import _cast

    queue.put(_cast(*args))


@pytest.mark.parametrize("heading", [math.pi / 2, 3 * math.pi / 2, math.pi, 0.0])
def test_cast_terminates_for_a_beam_along_a_cell_boundary(heading: float) -> None:
    """A beam starting on a cell boundary, along it (cos(pi/2) is 6e-17, not 0), reaches its wall.

    make_scenarios.py --count 30 --seed 99 hung on gen-08-coarse: such a beam's exit time rounded
    below its own position and the distance jump then walked it backwards, for ever. Run in a
    child process so that a regression fails after a deadline instead of hanging the suite.
    """
    import multiprocessing

    size = 60
    code = np.zeros((size, size), np.int8)
    code[0, :] = code[-1, :] = code[:, 0] = code[:, -1] = 1  # walls all round
    dist = cv2.distanceTransform((code == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    u0 = np.array([30.0, 17.0]), np.array([30.0, 41.0])  # on cell boundaries in both axes
    du = np.full(2, math.cos(heading))
    dv = np.full(2, -math.sin(heading))
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_cast_in_child, args=(queue, (code, dist, *u0, du, dv, 100.0)))
    child.start()
    child.join(timeout=20)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail(f"_cast did not finish within 20 s for heading {heading:.4f} rad")
    t, kind, _, _ = queue.get(timeout=5)
    assert kind.tolist() == [1, 1]
    # The wall cell's far side: start 30 (u) or 17/41 (v) px from the boundary of cell 0 / 59.
    u, v = u0
    expected = {
        0.0: 59 - u,  # east: the wall cell [59, 60) is entered at u = 59
        math.pi: u - 1,  # west: leaves cell 1 at u = 1
        math.pi / 2: v - 1,  # north (v decreasing)
        3 * math.pi / 2: 59 - v,  # south (cos is -1.8e-16: the hung beam)
    }[heading]
    # The range is to the middle of the chord through the hit cell: half a pixel beyond its face.
    np.testing.assert_allclose(t, expected + 0.5, atol=1e-6)
