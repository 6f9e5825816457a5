"""The fast paths of the image stages give exactly what the plain computations give."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapserver import deform, roi
from mapserver import grid as grid_module
from mapserver.align import (
    GlobalView,
    NearestWall,
    _make_level,
    _search_level,
    consistency,
    structure_mask,
    thin_points,
)
from mapserver.diff import (
    _keep_far,
    _linear_quantiles,
    distance_to,
    drop_small,
    near,
    near_at,
    offset_distances,
    raw_differences,
    within,
)
from mapserver.geometry import Transform2D
from mapserver.grid import Grid, box_around, box_of_cells, landing_box, nonzero_cells, resample
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states
from mapserver.roi import _outline


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
    assert np.array_equal(within(walls, t), d <= t)  # the same, as one call
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


def _drift_node_by_node(walls_slam, nav2_from_slam, grid, nearest, *, tile_m, max_shift_m):  # type: ignore[no-untyped-def]
    """estimate_drift's per-node estimates as first written, one node at a time (before the
    smoothing): the reference for the vectorised version."""
    min_points, iterations = 40, 12
    spacing = tile_m / 2.0
    lo = walls_slam.min(axis=0) - spacing
    hi = walls_slam.max(axis=0) + spacing
    cols = max(2, math.ceil((hi[0] - lo[0]) / spacing) + 1)
    rows = max(2, math.ceil((hi[1] - lo[1]) / spacing) + 1)
    shifts = np.zeros((rows, cols, 2), np.float32)
    valid = np.zeros((rows, cols), bool)
    base = nav2_from_slam.apply(walls_slam)
    h, w = nearest.shape[:2]
    node_i = np.floor((walls_slam[:, 1] - lo[1]) / spacing + 0.5).astype(int)
    node_j = np.floor((walls_slam[:, 0] - lo[0]) / spacing + 0.5).astype(int)
    for i in range(rows):
        for j in range(cols):
            sel = (np.abs(node_i - i) <= 1) & (np.abs(node_j - j) <= 1)
            if sel.sum() < min_points:
                continue
            q0 = base[sel]
            shift = np.zeros(2)
            used = 0
            for k in range(iterations):
                limit = max_shift_m * (1.0 - 0.5 * k / max(iterations - 1, 1))
                q = q0 + shift
                px = np.rint(grid.to_pixel(q)).astype(np.int64)
                inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
                target = np.zeros_like(q)
                target[inside] = grid.to_world(nearest[px[inside, 1], px[inside, 0]])
                r = target - q
                d = np.sqrt((r**2).sum(axis=1))
                use = inside & (d <= limit)
                used = int(use.sum())
                if used < min_points // 2:
                    break
                shift = shift + r[use].mean(axis=0)
                if np.hypot(*shift) > max_shift_m:
                    shift *= max_shift_m / np.hypot(*shift)
            if used >= min_points // 2:
                shifts[i, j] = shift
                valid[i, j] = True
    return shifts, valid


@pytest.mark.parametrize("seed", range(3))
def test_vectorised_drift_estimate_is_the_node_by_node_one(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A room of walls, seen with a bend: the local walls are the global ones, shifted more
    # the further along x they lie.
    rng = np.random.default_rng(seed)
    grid = Grid(0.0, 0.0, 0.05, 600, 400)
    structure = np.zeros(grid.shape, bool)
    structure[40, 20:580] = structure[360, 20:580] = True
    structure[40:360, 20] = structure[40:360, 580] = True
    for _ in range(30):
        r, c = rng.integers(60, 340), rng.integers(40, 560)
        structure[r : r + 8, c : c + 8] = True
    rows, cols = np.nonzero(structure)
    walls = grid.to_world(np.stack([cols, rows], axis=1))
    walls = walls + np.stack([0.004 * walls[:, 0], 0.01 * walls[:, 0] - 0.1], axis=1)
    walls = walls[rng.random(len(walls)) < 0.8]
    nearest = NearestWall.of(structure)
    transform = Transform2D(0.01, -0.05, 0.08)

    captured = {}
    real_fill = deform._fill_missing

    def capture(values, valid):  # type: ignore[no-untyped-def]
        captured["shifts"], captured["valid"] = values.copy(), valid.copy()
        return real_fill(values, valid)

    monkeypatch.setattr(deform, "_fill_missing", capture)
    deform.estimate_drift(walls, transform, grid, nearest, tile_m=6.0, max_shift_m=0.8)
    shifts, valid = _drift_node_by_node(
        walls, transform, grid, nearest, tile_m=6.0, max_shift_m=0.8
    )
    assert valid.any() and not valid.all()
    assert np.array_equal(captured["valid"], valid)
    assert np.array_equal(captured["shifts"], shifts)


def _plain_differences(g, loc, roi, *, resolution, tolerance_m, removed_tolerance_m, walls):  # type: ignore[no-untyped-def]
    """raw_differences as first written: whole arrays, distance transforms."""
    g_occ, l_occ = g == OCCUPIED, loc == OCCUPIED
    added = (
        l_occ
        & (g == FREE)
        & roi
        & (distance_to(g_occ | walls | (g == UNKNOWN)) > tolerance_m / resolution)
    )
    removed = g_occ & (loc == FREE) & roi & (distance_to(l_occ) > removed_tolerance_m / resolution)
    return added, removed


def _states(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    return rng.choice(np.array([FREE, OCCUPIED, UNKNOWN], np.uint8), shape, p=[0.7, 0.2, 0.1])


@pytest.mark.parametrize("seed", range(8))
def test_raw_differences_on_the_roi_box_are_the_plain_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = (90, 130)
    g, loc = _states(rng, shape), _states(rng, shape)
    walls = rng.random(shape) < 0.02
    roi = np.zeros(shape, bool)
    r, c = rng.integers(0, 60), rng.integers(0, 100)
    roi[r : r + rng.integers(1, 40), c : c + rng.integers(1, 40)] = True
    if seed == 0:
        roi[:] = True
    for tol, removed_tol in [(0.15, 0.25), (0.1, 0.1), (0.0, 0.3)]:
        got = raw_differences(
            g,
            loc,
            roi,
            resolution=0.05,
            tolerance_m=tol,
            removed_tolerance_m=removed_tol,
            global_walls=walls,
        )
        added, removed = _plain_differences(
            g,
            loc,
            roi,
            resolution=0.05,
            tolerance_m=tol,
            removed_tolerance_m=removed_tol,
            walls=walls,
        )
        assert np.array_equal(got.added, added)
        assert np.array_equal(got.removed, removed)
    empty = raw_differences(g, loc, np.zeros(shape, bool), resolution=0.05, tolerance_m=0.1)
    assert not empty.added.any() and not empty.removed.any()


@pytest.mark.parametrize("density", [0.0, 0.002, 0.005, 0.05, 0.3])
@pytest.mark.parametrize("min_pixels", [1, 4, 9])
def test_drop_small_is_the_plain_one(density: float, min_pixels: int) -> None:
    mask = np.random.default_rng(7).random((120, 150)) < density
    mask[5:9, 5:20] = density > 0  # and one component that is never small
    before = mask.copy()
    if mask.any():
        _, labels, stats, _ = cv2.connectedComponentsWithStats(
            mask.astype(np.uint8), connectivity=8
        )
        keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
        keep[0] = False
        expected = keep[labels]
    else:
        expected = mask
    assert np.array_equal(drop_small(mask, min_pixels=min_pixels), expected)
    assert np.array_equal(mask, before)


def _warp_whole_grid(local, grid, transform, drift, s=8):  # type: ignore[no-untyped-def]
    """warp_local as first written: nodes over the whole grid."""
    n_cols, n_rows = math.ceil(grid.width / s) + 2, math.ceil(grid.height / s) + 2
    cc, rr = np.meshgrid(
        (np.arange(n_cols) + 0.5) * s - 0.5 - s, (np.arange(n_rows) + 0.5) * s - 0.5 - s
    )
    u, v = deform._source_coords(cc, rr, local, grid, transform, drift)
    size = (n_cols * s, n_rows * s)
    fu = cv2.resize(u.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    fv = cv2.resize(v.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    fu = np.ascontiguousarray(fu[s : s + grid.height, s : s + grid.width])
    fv = np.ascontiguousarray(fv[s : s + grid.height, s : s + grid.width])
    return cv2.remap(
        local.state, fu, fv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=UNKNOWN
    )


@pytest.mark.parametrize("seed", range(6))
def test_drift_warp_of_the_landing_box_is_the_whole_grid_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    state = _states(rng, (140, 170))
    state[:, : rng.integers(0, 60)] = UNKNOWN  # the known part is off-centre
    local = from_states(state, 0.05, (rng.uniform(-3, 3), rng.uniform(-3, 3), 0.0))
    grid = Grid(-12.3, -11.1, 0.05, 501, 467)
    transform = Transform2D(rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-2, 2))
    shifts = rng.normal(0.0, 0.3, (5, 6, 2)).astype(np.float32)
    drift = deform.DriftField(-4.0, -4.0, 3.0, shifts)
    got = deform.warp_local(local, grid, transform, drift)
    assert (got != UNKNOWN).any()
    assert np.array_equal(got, _warp_whole_grid(local, grid, transform, drift))


@pytest.mark.parametrize("seed", range(4))
def test_a_piece_warped_into_its_landing_box_is_the_whole_grid_warp_there(seed: int) -> None:
    """deform.warp_local_box (what each piece is warped with): every known cell of the whole
    grid's warp lies in the box; with drift the box holds exactly that warp's cells; rigidly,
    the same up to nearest-neighbour ties of the cropped lattices; None off the grid."""
    rng = np.random.default_rng(seed)
    state = _states(rng, (140, 170))
    state[:, : rng.integers(0, 60)] = UNKNOWN
    local = from_states(state, 0.05, (rng.uniform(-3, 3), rng.uniform(-3, 3), 0.0))
    grid = Grid(-12.3, -11.1, 0.05, 501, 467)
    transform = Transform2D(rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-2, 2))
    shifts = rng.normal(0.0, 0.3, (5, 6, 2)).astype(np.float32)
    drift = deform.DriftField(-4.0, -4.0, 3.0, shifts)
    for field in (drift, None):
        whole = deform.warp_local(local, grid, transform, field)
        landed = deform.warp_local_box(local, grid, transform, field)
        assert landed is not None
        (r0, r1, c0, c1), states = landed
        outside = whole.copy()
        outside[r0:r1, c0:c1] = UNKNOWN
        assert (whole != UNKNOWN).any() and not (outside != UNKNOWN).any()
        differ = np.count_nonzero(states != whole[r0:r1, c0:c1])
        assert differ == 0 if field is not None else differ <= 0.001 * states.size
    far = Transform2D(0.0, 500.0, 500.0)
    assert deform.warp_local_box(local, grid, far, None) is None
    assert deform.warp_local_box(local, grid, far, drift) is None


def _plain_consistency(local, transform, view, tolerance_m):  # type: ignore[no-untyped-def]
    """consistency() as first written: the whole view, a distance transform."""
    warped = resample(local.state, Grid.of_map(local), view.grid, transform)
    walls = view.structure & (warped != UNKNOWN)
    if not walls.any():
        return 0.0
    seen_free = walls & (warped == FREE)
    local_walls = warped == OCCUPIED
    if seen_free.any() and local_walls.any():
        seen_free &= distance_to(local_walls) * view.grid.resolution > tolerance_m
    return 1.0 - float(seen_free.sum()) / int(walls.sum())


@pytest.mark.parametrize("seed", range(6))
def test_consistency_on_the_local_box_is_the_plain_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    state = _states(rng, (90, 110))
    state[: rng.integers(0, 40)] = UNKNOWN
    local = from_states(state, 0.05, (0.0, 0.0, 0.0))
    grid = Grid(-3.0, -4.0, 0.05, 260, 240)
    structure = rng.random(grid.shape) < 0.1
    view = GlobalView(grid, np.full(grid.shape, FREE, np.uint8), structure)
    for _ in range(4):
        transform = Transform2D(rng.uniform(-3, 3), rng.uniform(-2, 4), rng.uniform(-2, 4))
        for tolerance_m in (0.1, 0.2):
            expected = _plain_consistency(local, transform, view, tolerance_m)
            assert consistency(local, transform, view, tolerance_m=tolerance_m) == expected


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("tolerance_m", [0.1, 0.15, 0.0])
def test_near_walls_is_the_thresholded_distance_field(seed: int, tolerance_m: float) -> None:
    grid = Grid(0.0, 0.0, 0.05, 130, 110)
    structure = _walls(seed, grid.shape, 0.01)
    view = GlobalView(grid, np.full(grid.shape, FREE, np.uint8), structure)
    # The distance field's float32 values in a float64 array, thresholded.
    expected = distance_to(structure).astype(np.float64) * grid.resolution <= tolerance_m
    assert np.array_equal(view.near_walls(tolerance_m), expected)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("distance_m", [0.15, 1.0])
def test_near_walls_at_points_is_the_whole_view_sampled(seed: int, distance_m: float) -> None:
    """Worked out in the box around the points, the same as the whole view's mask sampled
    there: points clustered in a corner, at the edges and off the grid."""
    rng = np.random.default_rng(seed)
    grid = Grid(-1.0, 2.0, 0.05, 130, 110)
    structure = _walls(seed, grid.shape, 0.01)
    view = GlobalView(grid, np.full(grid.shape, FREE, np.uint8), structure)
    corner = rng.uniform([-1.5, 1.5], [1.5, 4.0], (300, 2))  # a corner, part off the grid
    spread = rng.uniform([-1.2, 1.8], [5.7, 7.7], (300, 2))  # the whole grid and its edges
    for points in (corner, spread, corner[:0]):
        expected = grid.sample(view.near_walls(distance_m), points, False)
        assert np.array_equal(view.near_walls_at(points, distance_m), expected)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("radius_px", [1, 3, 6])
def test_near_at_points_is_the_whole_dilation_sampled(seed: int, radius_px: int) -> None:
    """The fold check's "within so far of a global wall" (an elliptic kernel, as
    ``cv2.getStructuringElement`` makes it), worked out around the points only: the same as
    the whole mask dilated and sampled, at the grid's edges and off it too."""
    rng = np.random.default_rng(seed)
    grid = Grid(-1.0, 2.0, 0.05, 130, 110)
    walls = _walls(seed, grid.shape, 0.01)
    size = 2 * radius_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    whole = cv2.dilate(walls.view(np.uint8), disk).view(bool)
    corner = rng.uniform([-1.5, 1.5], [1.5, 4.0], (300, 2))
    spread = rng.uniform([-1.2, 1.8], [5.7, 7.7], (300, 2))
    for points in (corner, spread, corner[:0]):
        expected = grid.sample(whole, points, False)
        assert np.array_equal(near_at(walls, disk.astype(bool), grid, points), expected)


@pytest.mark.parametrize("seed", range(6))
def test_observed_roi_outline_on_the_box_is_the_whole_grid_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = Grid(-2.0, 3.0, 0.05, 160, 120)
    state = np.full(grid.shape, UNKNOWN, np.uint8)
    for _ in range(4):  # known blobs, some at the grid's edge, some with gaps to close
        r, c = rng.integers(-10, 110), rng.integers(-10, 150)
        state[max(r, 0) : r + rng.integers(3, 50), max(c, 0) : c + rng.integers(3, 50)] = FREE
    state[rng.random(grid.shape) < 0.05] = UNKNOWN
    known = state != UNKNOWN
    closed = cv2.morphologyEx(known.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    expected = _outline(closed.astype(bool), grid, simplify_m=0.25)
    got = roi.observed(state, grid)
    assert got.polygon == expected
    assert np.array_equal(got.mask, known)


def _cells_in_first_order(points: np.ndarray, size: float) -> dict[tuple[int, int], list[int]]:
    """The indices of the points in each cell, cells in the order of their first point."""
    cells: dict[tuple[int, int], list[int]] = {}
    for i, (x, y) in enumerate(points):
        cells.setdefault((math.floor(x / size), math.floor(y / size)), []).append(i)
    return cells


def test_thin_keeps_the_first_point_of_every_cell() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 3.0, (2000, 2))
    expected = [members[0] for members in _cells_in_first_order(points, 0.3).values()]
    assert np.array_equal(thin_points(points, 0.3), points[expected])
    assert len(thin_points(points[:0], 0.3)) == 0


def test_thin_by_mean_keeps_each_cells_mean() -> None:
    rng = np.random.default_rng(4)
    points = rng.normal(0.0, 3.0, (2000, 2))
    cells = _cells_in_first_order(points, 0.3)
    expected = np.array([points[members].mean(axis=0) for members in cells.values()])
    assert np.allclose(thin_points(points, 0.3, mean=True), expected, rtol=0.0, atol=1e-12)
    assert len(thin_points(points[:0], 0.3, mean=True)) == 0


@pytest.mark.parametrize("seed", range(4))
def test_structure_mask_is_the_plain_rule(seed: int) -> None:
    rng = np.random.default_rng(seed)
    occupancy = rng.integers(0, 256, (70, 90), dtype=np.uint8)
    occupancy[rng.random(occupancy.shape) < 0.4] = 127 + seed * 20  # a grey plateau: unknown
    state = np.where(occupancy > 200, OCCUPIED, np.where(occupancy < 40, FREE, UNKNOWN))
    m = OccupancyMap(state.astype(np.uint8), occupancy, 0.05, (0.0, 0.0, 0.0))
    unknown = m.state == UNKNOWN
    level_grey = int(np.argmax(np.bincount(occupancy[unknown], minlength=256)))
    level = level_grey + 0.2 * (255 - level_grey)
    expected = (m.state == OCCUPIED) | (occupancy >= level)
    assert np.array_equal(structure_mask(m), expected)


@pytest.mark.parametrize("seed", range(4))
def test_nearest_wall_on_a_box_is_the_full_field_inside_it(seed: int) -> None:
    from mapserver.align import NearestWall

    rng = np.random.default_rng(seed)
    structure = rng.random((120, 150)) < 0.01
    full = NearestWall.of(structure)
    boxed = NearestWall.of(structure, (20, 30, 90, 120))
    rows, cols = np.mgrid[0:120, 0:150]
    rows, cols = rows.ravel(), cols.ravel()
    got, want = boxed[rows, cols], full[rows, cols]
    inside = (rows >= 20) & (rows < 90) & (cols >= 30) & (cols < 120)
    # Inside the box, far enough from its edge that no nearer wall can lie outside it.
    d_edge = np.minimum.reduce([rows - 20, 89 - rows, cols - 30, 119 - cols])
    d_wall = np.hypot(*(want - np.stack([cols, rows], 1)).T)
    sure = inside & (d_wall < d_edge)
    assert np.array_equal(got[sure], want[sure])
    assert (got[~inside] >= 1e9).all()
    # In metres (what ICP and the drift estimate read), points given by cell centres: the
    # same walls' centres, and as far as no wall off the box (two cells off it too).
    grid = grid_module.Grid(1.0, -2.0, 0.05, 150, 120)
    centres = grid.to_world(np.stack([cols, rows], 1).astype(float))
    x, y = boxed.nearest_xy(centres[:, 0], centres[:, 1], grid)
    assert np.allclose(np.stack([x, y], 1)[inside], grid.to_world(got[inside]))
    assert (x[~inside] >= 1e9).all() and (y[~inside] >= 1e9).all()
    far_x, _ = boxed.nearest_xy(np.array([0.0, 1.0 + 7.6]), np.array([-2.0, 4.1]), grid)
    assert (far_x >= 1e9).all()


@pytest.mark.parametrize("seed", range(4))
def test_the_drift_warp_on_a_crop_at_the_warp_step_is_the_whole_grid_ones_part(seed: int) -> None:
    # The pipeline warps onto the part of the view the local map lands on: cut at multiples of
    # the warp's node step, it must give the cells the whole view's warp gives there.
    rng = np.random.default_rng(seed)
    local = from_states(_states(rng, (120, 150)), 0.05, (rng.uniform(-3, 3), -2.0, 0.0))
    global_state = _states(rng, (467, 501))
    view = GlobalView(Grid(-12.3, -11.1, 0.05, 501, 467), global_state, global_state == OCCUPIED)
    transform = Transform2D(rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-2, 2))
    drift = deform.DriftField(-4.0, -4.0, 3.0, rng.normal(0, 0.3, (5, 6, 2)).astype(np.float32))
    margin_px = drift.max_shift_m() / 0.05 + 2
    box = landing_box(local, view.grid, transform, margin_px=margin_px, step_px=deform.WARP_STEP_PX)
    assert box is not None
    r0, r1, c0, c1 = box
    assert r0 % deform.WARP_STEP_PX == 0 and c0 % deform.WARP_STEP_PX == 0
    part = view.cropped(box)
    assert np.array_equal(part.state, global_state[r0:r1, c0:c1])
    # The same cell is at the same place in the nav2 frame.
    assert part.grid.to_world([[0, 0]]) == pytest.approx(view.grid.to_world([[c0, r0]]))
    whole = deform.warp_local(local, view.grid, transform, drift)
    assert np.array_equal(
        deform.warp_local(local, part.grid, transform, drift),
        whole[box[0] : box[1], box[2] : box[3]],
    )
    # Nothing lands outside the box.
    outside = whole.copy()
    outside[r0:r1, c0:c1] = UNKNOWN
    assert (outside == UNKNOWN).all()


@pytest.mark.parametrize("factor", [2, 5, 10])
def test_a_search_level_max_pools_the_walls_onto_cells_in_the_same_place(factor: int) -> None:
    structure = _walls(factor, (203, 157), 0.002)  # sizes that are no multiple of the factor
    view = GlobalView(Grid(-3.7, 8.2, 0.05, 157, 203), np.zeros((203, 157), np.uint8), structure)
    level = _make_level(view, factor, pad=3)
    assert level.grid.resolution == pytest.approx(0.05 * factor)
    pooled = level.field[3:-3, 3:-3] == 1.0  # a wall cell has likelihood 1
    # The plain max-pool: blocks of factor x factor cells from the top-left corner.
    h, w = -(-203 // factor) * factor, -(-157 // factor) * factor
    padded = np.zeros((h, w), bool)
    padded[:203, :157] = structure
    assert np.array_equal(
        pooled, padded.reshape(h // factor, factor, w // factor, factor).any((1, 3))
    )
    # Every wall lies inside the level cell that holds it.
    rows, cols = np.nonzero(structure)
    xy = view.grid.to_world(np.stack([cols, rows], 1))
    cell = np.floor(level.grid.to_pixel(xy) + 0.5).astype(int)
    assert np.array_equal(cell[:, 0], cols // factor) and np.array_equal(cell[:, 1], rows // factor)


@pytest.mark.parametrize("seed", range(8))
def test_resampling_onto_the_same_lattice_is_the_warp(seed: int) -> None:
    # A grid whose cells coincide with the source's (moved by whole cells, overlapping it
    # partly, wholly or not at all) gets a copy of the overlap: what warpAffine gives.
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (53, 71)).astype(np.uint8)
    src = Grid(-1.3, 2.1, 0.05, 71, 53)
    dc, dr = (int(v) for v in rng.integers(-90, 90, 2))
    w, h = (int(v) for v in rng.integers(1, 120, 2))
    dst = Grid(src.x0 + dc * 0.05, src.y0 + dr * 0.05, 0.05, w, h)
    matrix = grid_module.warp_matrix(src, dst, Transform2D.identity())
    assert grid_module._whole_pixel_shift(matrix) is not None
    expected = cv2.warpAffine(
        image,
        matrix,
        (w, h),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=7,
    )
    assert np.array_equal(resample(image, src, dst, fill=7), expected)
    # Off the lattice by a fraction of a cell, or turned: a real warp.
    shifted = Grid(dst.x0 + 0.02, dst.y0, 0.05, w, h)
    assert (
        grid_module._whole_pixel_shift(
            grid_module.warp_matrix(src, shifted, Transform2D.identity())
        )
        is None
    )
    turned = grid_module.warp_matrix(src, dst, Transform2D(0.01, 0.0, 0.0))
    assert grid_module._whole_pixel_shift(turned) is None


@pytest.mark.parametrize("q", [0.25, 0.5, 0.8, 0.9])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_tile_quantile_is_numpys(q: float, dtype: type) -> None:
    rng = np.random.default_rng(int(q * 100))
    for _ in range(300):
        n = int(rng.integers(1, 400))
        values = (rng.random(n) * rng.choice([0.5, 10.0])).astype(dtype)
        if rng.random() < 0.3:  # ties, as distances on a grid have
            values = (np.round(values * 20) / 20).astype(dtype)
        # As misfit_tolerance counts them: per distinct value, cumulated.
        levels, level_of = np.unique(values, return_inverse=True)
        cum = np.cumsum(np.bincount(level_of.ravel(), minlength=len(levels)))[None, :]
        got = _linear_quantiles(levels, cum, np.array([n]), q)
        assert got.shape == (1,) and float(got[0]) == float(np.quantile(values, q))


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("density", [0.0005, 0.01, 0.3])
def test_keeping_cells_far_from_walls_is_the_thresholded_distance(
    seed: int, density: float
) -> None:
    rng = np.random.default_rng(seed + 1000)  # not _walls' own draws
    walls = _walls(seed, (200, 260), 0.002)
    cells = rng.random((200, 260)) < density  # few cells: the offsets; many: the transform
    resolution = float(rng.choice([0.05, 0.025]))
    limit = (0.15 + rng.choice([0.0, 0.05, 0.1, 0.35], size=(200, 260))).astype(np.float32)
    expected = cells & (distance_to(walls) * resolution > limit)
    got = cells.copy()
    _keep_far(got, walls, limit, resolution)
    assert np.array_equal(got, expected)


def _plain_search_level(level, points, centre, target, thetas, shift_px):  # type: ignore[no-untyped-def]
    """_search_level as first written: cv2.matchTemplate at every rotation."""
    grid, field, pad = level.grid, level.field, level.pad
    out = []
    for theta in thetas:
        c, s = math.cos(theta), math.sin(theta)
        q = (points - centre) @ np.array([[c, s], [-s, c]]) + target
        px = np.rint(grid.to_pixel(q)).astype(np.int64) + pad
        cmin, rmin = np.maximum(px.min(axis=0), shift_px)
        cmax = min(px[:, 0].max(), field.shape[1] - 1 - shift_px)
        rmax = min(px[:, 1].max(), field.shape[0] - 1 - shift_px)
        keep = (px[:, 0] >= cmin) & (px[:, 0] <= cmax) & (px[:, 1] >= rmin) & (px[:, 1] <= rmax)
        template = np.zeros((rmax - rmin + 1, cmax - cmin + 1), np.float32)
        template[px[keep, 1] - rmin, px[keep, 0] - cmin] = 1.0
        region = field[rmin - shift_px : rmax + shift_px + 1, cmin - shift_px : cmax + shift_px + 1]
        response = cv2.matchTemplate(region, template, cv2.TM_CCORR) / len(points)
        _, best, _, (j, i) = cv2.minMaxLoc(response)
        out.append(
            (
                best,
                theta,
                target[0] + (j - shift_px) * grid.resolution,
                target[1] - (i - shift_px) * grid.resolution,
            )
        )
    return out


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("shift_px", [2, 6])  # a fine level's gathers, a coarse one's template
def test_the_correlative_search_scores_are_the_template_matchs(seed: int, shift_px: int) -> None:
    rng = np.random.default_rng(seed)
    structure = _walls(seed, (240, 260), 0.003)
    view = GlobalView(Grid(-3.0, -4.0, 0.1, 260, 240), np.zeros((240, 260), np.uint8), structure)
    level = _make_level(view, 2, pad=shift_px + 4)
    rows, cols = np.nonzero(structure[40:200, 50:210])
    points = view.grid.to_world(np.stack([cols + 50, rows + 40], 1))[:: int(rng.integers(1, 4))]
    centre = points.mean(axis=0)
    target = centre + rng.normal(0.0, 0.3, 2)
    thetas = rng.normal(0.0, 0.05, 5)
    got = _search_level(level, points, centre, target, thetas, shift_px)
    expected = _plain_search_level(level, points, centre, target, thetas, shift_px)
    for g, e in zip(got, expected, strict=True):
        assert g[0] == pytest.approx(e[0], abs=1e-5)
        assert g[1:] == pytest.approx(e[1:], abs=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_raw_differences_with_the_misfit_tolerance_on_the_roi_box_are_the_plain_ones(
    seed: int,
) -> None:
    # The box around the ROI must reach as far as the widest tolerance, the extra included: a
    # wall just past the box but within the widened tolerance still explains a local wall.
    rng = np.random.default_rng(seed + 100)
    shape = (90, 130)
    g, loc = _states(rng, shape), _states(rng, shape)
    walls = rng.random(shape) < 0.01
    roi = np.zeros(shape, bool)
    r, c = rng.integers(10, 60), rng.integers(10, 100)
    roi[r : r + rng.integers(1, 20), c : c + rng.integers(1, 20)] = True
    extra = rng.choice(np.array([0.0, 0.1, 0.35], np.float32), shape)
    got = raw_differences(
        g,
        loc,
        roi,
        resolution=0.05,
        tolerance_m=0.15,
        removed_tolerance_m=0.25,
        global_walls=walls,
        extra_tolerance_m=extra,
    )
    g_walls = (g == OCCUPIED) | walls | (g == UNKNOWN)
    l_occ = loc == OCCUPIED
    added = l_occ & (g == FREE) & roi & (distance_to(g_walls) * 0.05 > 0.15 + extra)
    removed = (g == OCCUPIED) & (loc == FREE) & roi & (distance_to(l_occ) * 0.05 > 0.25 + extra)
    assert np.array_equal(got.added, added)
    assert np.array_equal(got.removed, removed)


def test_a_global_wall_just_past_the_roi_box_still_explains_a_local_wall() -> None:
    shape = (60, 60)
    g = np.full(shape, FREE, np.uint8)
    loc = np.full(shape, FREE, np.uint8)
    roi = np.zeros(shape, bool)
    roi[20:40, 20:30] = True
    loc[30, 29] = OCCUPIED  # on the ROI's edge
    g[30, 37] = OCCUPIED  # 0.4 m away: beyond 0.15 m, within 0.15 + 0.35 m
    extra = np.full(shape, 0.35, np.float32)
    got = raw_differences(g, loc, roi, resolution=0.05, tolerance_m=0.15, extra_tolerance_m=extra)
    assert not got.added[30, 29]
    assert raw_differences(g, loc, roi, resolution=0.05, tolerance_m=0.15).added[30, 29]


@pytest.mark.parametrize("density", [0.0, 0.001, 0.05, 0.6])
def test_nonzero_cells_are_numpys(density: float) -> None:
    rng = np.random.default_rng(int(density * 1000))
    mask = rng.random((70, 90)) < density
    for m in (mask, mask[5:60, 7:80], mask[::2, ::3]):  # views too, strided ones
        rows, cols = nonzero_cells(m)
        expected_rows, expected_cols = np.nonzero(m)
        assert np.array_equal(rows, expected_rows) and np.array_equal(cols, expected_cols)
        assert rows.dtype == np.intp and cols.dtype == np.intp


def test_box_around_is_the_bounding_box_grown_and_clipped() -> None:
    mask = np.zeros((20, 30), bool)
    assert box_around(mask, 3) is None
    mask[5:8, 10:12] = True
    assert box_around(mask, 2) == (slice(3, 10), slice(8, 14))
    mask[0, 29] = True  # at the corner: the growth is clipped to the array
    assert box_around(mask, 4) == (slice(0, 12), slice(6, 30))


@pytest.mark.parametrize("seed", range(5))
def test_box_of_cells_is_box_around_their_mask(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mask = rng.random((40, 60)) > 0.995
    mask[rng.integers(40), rng.integers(60)] = True
    rows, cols = np.nonzero(mask)
    for margin in (0, 3, 50):
        assert box_of_cells(rows, cols, margin, mask.shape) == box_around(mask, margin)
