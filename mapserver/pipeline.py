"""The only module that knows the order of the stages: load, align, roi, diff, cluster, render.

``process_bundle`` turns a bundle directory into an :class:`Outcome` (the result document and the
encoded images) without writing anything; publishing it is :mod:`mapserver.outbox`'s job.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from mapserver import align as align_stage
from mapserver import cluster as cluster_stage
from mapserver import deform, piecewise, render, roi
from mapserver import diff as diff_stage
from mapserver import refit as refit_stage
from mapserver.bundle import (
    MANIFEST,
    BundleFiles,
    check_bundle_dir,
    check_bundle_files,
    is_valid_bundle_id,
    map_image_name,
    sha256_file,
)
from mapserver.config import Config
from mapserver.errors import (
    BundleError,
    BundleIncomplete,
    MapFileError,
    MapserverError,
    OutOfMemory,
    ProcessingError,
)
from mapserver.fleet import evidence as fleet_evidence
from mapserver.fleet import observe, store
from mapserver.fleet.model import MapLink
from mapserver.fleet.observe import Observation
from mapserver.geometry import Pose2D, Transform2D, fit_rigid
from mapserver.grid import Grid, landing_box, resample
from mapserver.mapcache import MapCache
from mapserver.maps import OCCUPIED, UNKNOWN, OccupancyMap, load_map
from mapserver.trust import trust_notice

log = logging.getLogger(__name__)
T = TypeVar("T")

# How far past the cells the local map lands on the differences look (wall tolerances, the
# misfit's reach, the removal evidence), metres.
_ANALYSIS_MARGIN_M = 1.0
# The alignment searches rotations within this first, and over search_theta_deg only when
# that finds no convincing fit.
_NARROW_SEARCH_DEG = 8.0

# Decoded global maps, kept across bundles in this process (a daemon worker serves many bundles
# of the same building). Three maps: the one in use, the one before it, and the fleet map's
# current version.
GLOBAL_MAPS = MapCache(capacity=3)


@dataclass(frozen=True)
class Outcome:
    """What processing one bundle produced.

    ``result`` is the ``result.yaml`` document (contract section 3); ``images`` maps file names
    (``overlay.png``, ``diff.png``) to PNG bytes.
    """

    bundle_id: str
    result: dict[str, Any]
    images: dict[str, bytes]
    observation: Observation | None = None
    """What the bundle contributes to its stored map (``maps:`` set and the map stored)."""


_stage_listener: Callable[[str], None] | None = None


def on_stage(listener: Callable[[str], None] | None) -> None:
    """Call ``listener(name)`` as each stage of :func:`process_bundle` begins, in this process
    (the daemon's workers tell the main process which stage a bundle is in). None: stop."""
    global _stage_listener
    _stage_listener = listener


class _Stages:
    """Times each stage, logs one line per stage with the bundle id, and tags errors with it."""

    def __init__(self, bundle_id: str) -> None:
        self.bundle_id = bundle_id
        self.timings_ms: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            if _stage_listener is not None:
                _stage_listener(name)
            yield
        except MapserverError as error:
            if error.stage == error.default_stage and name != "load":
                error.stage = name
            raise
        except MemoryError as error:
            detail = f" ({error})" if str(error) else ""
            raise OutOfMemory(
                f"{name}: out of memory{detail}; the maps may be too large for this server",
                stage=name,
            ) from None
        except Exception as error:
            # A bug or an input no check foresaw: name the stage, keep the traceback in the log,
            # and let the caller fail this bundle only.
            log.exception("%s: %s failed", self.bundle_id, name)
            raise ProcessingError(
                f"{name} failed unexpectedly ({type(error).__name__}: {error}); "
                "please report this bundle",
                stage=name,
            ) from error
        finally:
            ms = (time.perf_counter() - start) * 1000.0
            self.timings_ms[name] = round(ms, 1)
            log.info("%s: %s %.1f ms", self.bundle_id, name, ms)

    def run(self, name: str, fn: Callable[[], T]) -> T:
        with self.stage(name):
            return fn()


@dataclass(frozen=True)
class _Inputs:
    files: BundleFiles
    local: OccupancyMap
    global_map: OccupancyMap


def _load(bundle_dir: Path, config: Config, *, checksums_verified: bool) -> _Inputs:
    limits = config.limits
    try:
        files = check_bundle_files(
            bundle_dir, verify_checksums=not checksums_verified, limits=limits
        )
    except BundleIncomplete as error:
        # process runs on bundles said to be complete: a missing file is an error here.
        raise BundleError(error.problem, file=error.file) from None
    # The sanity limits on the maps are checked from the YAML and the image header: before
    # anything is decoded.
    resolutions, extent = limits.resolution_range_m, limits.max_map_extent_m
    local = load_map(
        files.slam_yaml,
        max_pixels=config.max_image_pixels,
        confine_to=bundle_dir,
        resolution_range_m=resolutions,
        max_extent_m=extent,
    )
    if files.nav2_yaml is not None and files.nav2_image is not None:
        rel = files.nav2_image.relative_to(bundle_dir).as_posix()
        global_map = GLOBAL_MAPS.load(
            files.nav2_yaml,
            files.nav2_image,
            max_pixels=config.max_image_pixels,
            confine_to=bundle_dir,
            image_sha256=(files.manifest.checksums or {}).get(rel),
            resolution_range_m=resolutions,
            max_extent_m=extent,
        )
    elif config.reference_map is not None:
        ref = config.reference_map
        try:
            ref_image = ref.parent / map_image_name(ref)
        except BundleError as error:
            raise MapFileError(error.problem, file=ref) from None
        global_map = GLOBAL_MAPS.load(
            ref,
            ref_image,
            max_pixels=config.max_image_pixels,
            resolution_range_m=resolutions,
            max_extent_m=extent,
        )
    else:
        raise BundleError(
            "the manifest names no nav2_map and no reference_map is configured",
            file=bundle_dir / "bundle.yaml",
        )
    if not (local.state != UNKNOWN).any():
        raise BundleError("the local map has no known cells", file=files.slam_image)
    return _Inputs(files, local, global_map)


def _route_nav2(files: BundleFiles, nav2_from_slam: Transform2D) -> np.ndarray | None:
    poses = files.manifest.trajectory_poses()
    if not poses:
        return None
    return nav2_from_slam.apply(np.array([[p.x, p.y] for p in poses]))


def _robot_nav2(files: BundleFiles, nav2_from_slam: Transform2D) -> Pose2D:
    slam = files.manifest.pose.slam.to_pose()
    x, y = nav2_from_slam.apply(np.array([slam.x, slam.y]))
    return Pose2D(float(x), float(y), slam.yaw + nav2_from_slam.theta)


def _align_in_pieces(
    files: BundleFiles,
    local: OccupancyMap,
    view: align_stage.GlobalView,
    alignment: align_stage.Alignment,
    config: Config,
    *,
    bent: bool = False,
) -> piecewise.Pieces | None:
    """The local map aligned in pieces along the route, when no rigid transform is trusted for
    the whole of it (or the trusted one leaves a region off the building: ``bent``) and the
    route is long enough for two pieces (else None)."""
    a = config.pipeline.align
    poses = files.manifest.trajectory_poses()
    if (alignment.trusted and not bent) or not a.pieces or not a.refine or len(poses) < 2:
        return None
    route = np.array([[p.x, p.y] for p in poses])
    if float(np.hypot(*np.diff(route, axis=0).T).sum()) < 1.5 * a.piece_m:
        return None
    # The prior is right where the robot was when it reported its pose (the route's end, where
    # the pieces start); the whole map's best rigid fit is a compromise over all of it.
    prior = files.manifest.nav2_from_slam_prior()
    return piecewise.align_pieces(
        local,
        view,
        route,
        prior,
        # A prior that is off (mislocalized) starts no piece well; the whole map's search, when
        # it refined the prior, may have found the building.
        also_from=alignment.nav2_from_slam if alignment.refined else None,
        piece_m=a.piece_m,
        min_score=a.min_score,
    )


def _estimate_drift(
    local: OccupancyMap,
    transform: Transform2D,
    view: align_stage.GlobalView,
    config: Config,
    *,
    reach_m: float,
) -> deform.DriftStack:
    """The slam drift left over by ``transform``: coarse to fine shift fields (README, warp)."""
    a = config.pipeline.align
    grid = view.grid
    # One wall point per two work cells: the shifts are averages over metres of wall.
    spacing = 2 * grid.resolution
    walls = align_stage.thin_points(align_stage.known_points(local, state=OCCUPIED), spacing)
    nearest = view.nearest_wall_near(transform.apply(walls), reach_m=reach_m)
    # Coarse to fine: large neighbourhoods take the bulk of the bend, small ones the rest.
    fields: list[deform.DriftField] = []
    for tile_m, max_shift_m in _drift_passes(
        a.deform_tile_m, a.deform_max_shift_m, a.deform_passes
    ):
        # A coarser pass averages over more wall: points as much sparser as its tiles are
        # larger do as well (the same number per tile), at a fraction of the cost.
        k = round(tile_m / a.deform_tile_m)
        pts = walls if k <= 1 else align_stage.thin_points(walls, spacing * k)
        fields.append(
            deform.estimate_drift(
                pts,
                transform,
                grid,
                nearest,
                tile_m=tile_m,
                max_shift_m=max_shift_m,
                initial=deform.DriftStack(tuple(fields)) if fields else None,
            )
        )
    return deform.DriftStack(tuple(fields))


def _make_roi(
    config: Config,
    files: BundleFiles,
    nav2_from_slam: Transform2D,
    route_xy: np.ndarray | None,
    local_state: np.ndarray,
    grid: Grid,
    warnings: list[str],
) -> roi.Roi:
    settings = config.pipeline.roi
    if settings.strategy == "box":
        region = roi.box(_robot_nav2(files, nav2_from_slam), grid, size_m=settings.box_size_m)
    elif settings.strategy == "heading":
        region = roi.heading(_robot_nav2(files, nav2_from_slam), grid, size_m=settings.box_size_m)
    elif settings.strategy == "trajectory" and route_xy is not None:
        region = roi.trajectory(route_xy, grid, radius_m=settings.trajectory_radius_m)
    else:
        if settings.strategy == "trajectory":
            warnings.append("roi 'trajectory' needs a trajectory in bundle.yaml; used 'observed'")
        return roi.observed(local_state, grid)
    # Unknown cells never differ anyway; intersecting keeps the mask honest for the images.
    return roi.Roi(region.strategy, region.mask & (local_state != UNKNOWN), region.polygon)


def _unfit(local_state: np.ndarray, view: align_stage.GlobalView, reach_m: float) -> np.ndarray:
    """The tiles of the aligned local map (on ``view``'s grid) whose walls do not lie on the
    global walls: beyond the differences' largest misfit tolerance, they would all be changes."""
    grid = view.grid
    return piecewise.unfit_tiles(
        local_state,
        view.structure,
        resolution=grid.resolution,
        reach_m=reach_m,
        # A lattice fixed in the nav2 frame, whatever part of the map the work grid covers.
        tile_offset_px=(
            -round((grid.y0 + grid.height * grid.resolution) / grid.resolution),
            round(grid.x0 / grid.resolution),
        ),
    )


def _drift_passes(tile_m: float, max_shift_m: float, passes: int) -> list[tuple[float, float]]:
    """(neighbourhood size, largest shift) of each drift pass, coarse to fine: every pass halves
    both, ending at ``tile_m``."""
    return [
        (tile_m * 2.0**k, max_shift_m / 2.0 ** (passes - 1 - k)) for k in reversed(range(passes))
    ]


def _difference_doc(index: int, d: cluster_stage.Difference) -> dict[str, Any]:
    return {
        "id": index,
        "kind": d.kind,
        "centroid": {"x": round(d.centroid[0], 3), "y": round(d.centroid[1], 3)},
        "bbox": {
            "min_x": round(d.bbox[0], 3),
            "min_y": round(d.bbox[1], 3),
            "max_x": round(d.bbox[2], 3),
            "max_y": round(d.bbox[3], 3),
        },
        "area_m2": round(d.area_m2, 4),
        "pixels": d.pixels,
    }


def _diff_masks(
    global_state: np.ndarray,
    structure: np.ndarray,
    local_state: np.ndarray,
    roi_mask: np.ndarray,
    grid: Grid,
    config: Config,
    local: OccupancyMap,
    global_map: OccupancyMap,
) -> tuple[diff_stage.DiffMasks, np.ndarray]:
    """The filtered added/removed masks of the local map against a global state (on ``grid``),
    and the removal evidence."""
    d = config.pipeline.diff
    tolerance_map = None
    if d.max_misfit_tolerance_m > d.tolerance_m:
        tolerance_map = diff_stage.misfit_tolerance(
            local_state,
            structure,  # the global walls: occupied cells and grey-drawn ones
            resolution=grid.resolution,
            base_m=d.tolerance_m,
            max_m=d.max_misfit_tolerance_m,
            tile_m=d.misfit_tile_m,
            # Tiles fixed in the nav2 frame (edges at multiples of the tile from its
            # origin), whatever part of the map the work grid covers.
            tile_offset_px=(
                -round((grid.y0 + grid.height * grid.resolution) / grid.resolution),
                round(grid.x0 / grid.resolution),
            ),
        )
    raw = diff_stage.raw_differences(
        global_state,
        local_state,
        roi_mask,
        resolution=grid.resolution,
        tolerance_m=d.tolerance_m,
        removed_tolerance_m=d.removed_tolerance_m,
        global_walls=structure,
        extra_tolerance_m=tolerance_map,
        end_tolerance_m=d.removed_end_tolerance_m,
    )
    min_px = max(1, round(d.min_local_cells * (local.resolution / grid.resolution) ** 2))
    filtered = diff_stage.filter_noise(raw, min_pixels=min_px)
    if d.along_wall_m > 0 and filtered.added.any():
        # The walls drawn (occupied and grey cells); not the edge of what is known, which no
        # robot saw displaced.
        walls = structure | (global_state == OCCUPIED)
        added = diff_stage.drop_along_walls(
            filtered.added, walls, resolution=grid.resolution, within_m=d.along_wall_m
        )
        filtered = diff_stage.DiffMasks(added, filtered.removed)
    evidence = diff_stage.removal_evidence(
        global_state,
        local_state,
        filtered.removed,
        resolution=grid.resolution,
        depth_m=max(d.removed_depth_m, 2 * max(local.resolution, global_map.resolution)),
        see_through_m=d.see_through_m,
        both_sides_m=d.both_sides_m,
    )
    return filtered, evidence


def _cluster_masks(
    masks: diff_stage.DiffMasks,
    removal_evidence: np.ndarray,
    grid: Grid,
    config: Config,
    local: OccupancyMap,
    *,
    drifted: bool = False,
) -> list[cluster_stage.Difference]:
    """The obstacles of the difference masks, largest first. ``drifted``: the session drifted
    (see ``_REFIT_DRIFT_M``), so the floor on their area is ``drifted_min_area_m2``."""
    d = config.pipeline.diff
    cell_m2 = local.resolution**2
    floor_m2 = max(d.min_area_m2, d.drifted_min_area_m2) if drifted else d.min_area_m2
    found = []
    for kind, mask, cells, evidence in (
        ("added", masks.added, d.min_local_cells, None),
        (
            "removed",
            masks.removed,
            max(d.min_local_cells, d.min_removed_cells),
            removal_evidence,
        ),
    ):
        min_area = max(floor_m2, cells * cell_m2)
        found += cluster_stage.cluster_mask(
            mask,
            grid,
            kind,
            eps_m=d.cluster_eps_m,
            min_samples=d.cluster_min_samples,
            min_area_m2=min_area,
            evidence=evidence,
            min_evidence=d.removed_evidence_share,
            engine=d.cluster_engine,
        )
    return cluster_stage.sort_by_area(found)


# The drift correction (metres) from which differences are checked by a local re-fit.
_REFIT_DRIFT_M = 0.2
# ... and from which the transform reported is the rigid fit of the warp (beyond the noise
# of the walls the drift is measured on).
_REPORT_WARP_M = 0.1


def _rigid_of_warp(
    local: OccupancyMap, transform: Transform2D, drift: deform.DriftStack
) -> Transform2D:
    """The rigid transform closest to ``transform`` plus the drift correction over the local
    walls (one point per 0.25 m): the slam map's best rigid fit to the building, where the
    alignment's own fit leans to the part whose walls carried it."""
    walls = align_stage.thin_points(align_stage.known_points(local, state=OCCUPIED), 0.25)
    if len(walls) < 3:
        return transform
    return fit_rigid(walls, transform.apply(walls) + drift.at(walls))


def _refit(
    differences: list[cluster_stage.Difference],
    view: align_stage.GlobalView,
    local_state: np.ndarray,
    added: np.ndarray,
    grid: Grid,
    config: Config,
) -> list[cluster_stage.Difference]:
    """The differences a small local re-fit of the walls around them does not explain, nor a
    move of the added cells around them onto a wall seen in place (a wall drawn twice)."""
    d = config.pipeline.diff
    global_walls = view.structure | (view.state == OCCUPIED)
    local_walls = local_state == OCCUPIED

    def explained(diff: cluster_stage.Difference) -> bool:
        assert diff.cells is not None
        if refit_stage.explained_by_refit(
            diff.cells,
            diff.kind,
            global_walls,
            local_walls,
            resolution=grid.resolution,
            tolerance_m=d.tolerance_m,
            removed_tolerance_m=d.removed_tolerance_m,
        ):
            return True
        return diff.kind == "added" and refit_stage.ghost_of_wall(
            diff.cells,
            added,
            global_walls,
            local_walls,
            resolution=grid.resolution,
            tolerance_m=d.tolerance_m,
        )

    return [diff for diff in differences if diff.cells is None or not explained(diff)]


def _map_link(
    maps_root: Path,
    files: BundleFiles,
    global_map: OccupancyMap,
    bundle_dir: Path,
    warnings: list[str],
) -> MapLink | None:
    """The stored map whose version is this bundle's global map (by its image's sha256), or
    None with a warning."""
    image = global_map.image
    if image is None:
        return None
    known = None
    if files.nav2_image is not None:
        known = (files.manifest.checksums or {}).get(
            files.nav2_image.relative_to(bundle_dir).as_posix()
        )
    digest = GLOBAL_MAPS.digest(image, known)
    link = store.lookup(maps_root, digest)
    if link is None:
        warnings.append(
            f"the global map {image.name} is no version of a stored map: this bundle changes "
            "no stored map (register the building map with 'mapserver maps add')"
        )
        return None
    if not link.lattice.matches(global_map):
        warnings.append(
            f"the global map's image is version {link.bundle_version} of map {link.name}, but "
            "its YAML gives another size, resolution or origin: this bundle changes no stored map"
        )
        return None
    return link


def process_bundle(
    bundle_dir: Path,
    config: Config,
    *,
    bundle_id: str | None = None,
    checksums_verified: bool = False,
) -> Outcome:
    """Process one complete bundle. Raises a :class:`~mapserver.errors.MapserverError` subclass
    for bad input (its ``stage`` says where it failed). Reads the inputs, never modifies them.

    ``checksums_verified``: the manifest's checksums were checked against these very files
    already (the daemon does when it takes a bundle), so they are not hashed again.
    """
    bundle_dir = Path(bundle_dir)
    check_bundle_dir(bundle_dir)
    bundle_id = bundle_id or bundle_dir.resolve().name
    if not is_valid_bundle_id(bundle_id):
        raise BundleError(
            f"invalid bundle id '{bundle_id}': use letters, digits, '.', '_' and '-', "
            "starting with a letter or digit, at most 128 characters",
            file=bundle_dir,
        )
    stages = _Stages(bundle_id)
    settings = config.pipeline
    inputs = stages.run(
        "load", lambda: _load(bundle_dir, config, checksums_verified=checksums_verified)
    )
    files, local, global_map = inputs.files, inputs.local, inputs.global_map
    warnings = list(global_map.warnings) + list(local.warnings)
    prior = files.manifest.nav2_from_slam_prior()
    # Around where the local map lands, the views keep room for the differences' reach and the
    # images' margin.
    margin_m = max(settings.render.margin_m, _ANALYSIS_MARGIN_M)
    # How far the drift estimate looks for a wall's counterpart: the views' nearest-wall
    # fields are built that wide from the start, for ICP and the drift estimate alike.
    drift_reach_m = 2 * settings.align.deform_max_shift_m + 0.5 if settings.align.deform else 0.0

    # The stored map this bundle's global map is a version of (maps: set), looked up once:
    # alignment reads a floor-plan drawing's walls from its version 1, the fleet update needs
    # it after.
    link_warnings: list[str] = []
    link = (
        _map_link(config.maps, files, global_map, bundle_dir, link_warnings)
        if config.maps is not None
        else None
    )
    drawing = None
    if link is not None and link.bundle_version > 1:
        drawing = GLOBAL_MAPS.load(
            link.first_yaml,
            link.first_yaml.parent / map_image_name(link.first_yaml),
            max_pixels=config.max_image_pixels,
        )

    def _align() -> tuple[align_stage.GlobalView, align_stage.Alignment]:
        robot = files.manifest.pose.slam.to_pose()
        pivot = (robot.x, robot.y)
        wide_rad = math.radians(settings.align.search_theta_deg)
        views: list[align_stage.GlobalView] = []

        def view_for(theta_rad: float) -> align_stage.GlobalView:
            views.append(
                align_stage.make_view(
                    global_map,
                    local,
                    prior,
                    search_xy_m=settings.align.search_xy_m,
                    search_theta_rad=theta_rad,
                    # Room for the images' margin around where the local map lands.
                    margin_m=margin_m,
                    pivot_slam=pivot,
                    wall_reach_m=drift_reach_m,
                    drawing=drawing,
                )
            )
            return views[-1]

        # The view for the narrow search first (most priors are within a few degrees): the
        # wide one, several times larger, is built only when the wide search runs.
        narrow = min(math.radians(_NARROW_SEARCH_DEG), wide_rad)
        result = align_stage.align(
            local,
            view_for(narrow),
            prior,
            narrow_theta_rad=narrow,
            widen=lambda: view_for(wide_rad),
            refine=settings.align.refine,
            search_xy_m=settings.align.search_xy_m,
            search_theta_rad=wide_rad,
            min_score=settings.align.min_score,
            min_gain=settings.align.min_gain,
            jump_m=settings.align.jump_m,
            pivot_slam=pivot,
        )
        return views[-1], result

    view, alignment = stages.run("align", _align)
    warnings += alignment.warnings
    transform = alignment.nav2_from_slam
    grid = view.grid
    search_view = view
    pieces = None
    if not alignment.trusted and settings.align.pieces:
        pieces = stages.run(
            "pieces", lambda: _align_in_pieces(files, local, search_view, alignment, config)
        )

    def _warp_pieces() -> tuple[align_stage.GlobalView, np.ndarray, np.ndarray]:
        assert pieces is not None
        grid = search_view.grid

        def warp_piece(part: OccupancyMap, t: Transform2D) -> np.ndarray:
            drift = None
            if settings.align.deform:
                drift = _estimate_drift(part, t, search_view, config, reach_m=drift_reach_m)
            return deform.warp_local(part, grid, t, drift)

        state, out = piecewise.compose(local, pieces, grid, warp=warp_piece)
        x, y, w, h = cv2.boundingRect(((state != UNKNOWN) | out).view(np.uint8))
        m = math.ceil(margin_m / grid.resolution)
        box = (
            max(y - m, 0),
            min(y + h + m, grid.height),
            max(x - m, 0),
            min(x + w + m, grid.width),
        )
        r0, r1, c0, c1 = box
        return search_view.cropped(box), state[r0:r1, c0:c1], out[r0:r1, c0:c1]

    warp_drift: list[deform.DriftStack] = []

    def _warp() -> tuple[align_stage.GlobalView, np.ndarray, float]:
        a = settings.align
        drift = None
        if a.deform and alignment.trusted:
            drift = _estimate_drift(local, transform, search_view, config, reach_m=drift_reach_m)
            warp_drift.append(drift)
        # From here on, only where the local map lands matters (with room for the tolerances and
        # the images' margin): the search view around it is several times larger.
        drift_m = drift.max_shift_m() if drift is not None else 0.0
        box = landing_box(
            local,
            search_view.grid,
            transform,
            margin_px=(drift_m + margin_m) / search_view.grid.resolution,
            step_px=deform.WARP_STEP_PX,  # the same warp as on the whole view
        )
        work = search_view.cropped(box) if box is not None else search_view
        return work, deform.warp_local(local, work.grid, transform, drift), drift_m

    def _fit() -> np.ndarray:
        return _unfit(local_state, view, settings.diff.max_misfit_tolerance_m)

    in_pieces = pieces is not None and bool(pieces.trusted)
    left_out: np.ndarray | None = None
    drift_m = 0.0
    if in_pieces:
        view, local_state, left_out = stages.run("warp", _warp_pieces)
    else:
        view, local_state, drift_m = stages.run("warp", _warp)
        if warp_drift and drift_m >= _REPORT_WARP_M:
            transform = _rigid_of_warp(local, transform, warp_drift[0])
    compared = alignment.trusted or in_pieces
    unfit = stages.run("fit", _fit) if compared and settings.align.fit_check else None
    if alignment.trusted and unfit is not None and unfit.any() and settings.align.pieces:
        # Trusted as a whole, yet a region lands off the building: a bend beyond the drift
        # correction. Aligned in pieces, each region fits on its own or is left out.
        pieces = stages.run(
            "pieces",
            lambda: _align_in_pieces(files, local, search_view, alignment, config, bent=True),
        )
        if pieces is not None and pieces.trusted:
            in_pieces = True
            view, local_state, left_out = stages.run("warp", _warp_pieces)
            drift_m = 0.0
            unfit = stages.run("fit", _fit)
    if pieces is not None and in_pieces:
        transform = piecewise.fit_rigid(local, pieces) or transform
        warnings[:] = [w for w in warnings if w not in alignment.warnings]
        warnings.append(
            f"the local map was aligned in {len(pieces.pieces)} pieces along the route, "
            f"{len(pieces.trusted)} trusted: {pieces.trusted_share:.0%} of the observed area "
            f"({pieces.trusted_area_m2:.0f} m2) compared, the rest left out"
        )
    route_xy = _route_nav2(files, transform)  # the trajectory ROI and the overlay draw it
    grid = view.grid
    kept = 1.0
    if unfit is not None and unfit.any():
        observed_m2 = float(np.count_nonzero(local_state != UNKNOWN)) * grid.resolution**2
        cut = unfit & (local_state != UNKNOWN)
        left_out = cut if left_out is None else left_out | cut
        local_state = np.where(unfit, UNKNOWN, local_state).astype(np.uint8)
        cut_m2 = float(np.count_nonzero(cut)) * grid.resolution**2
        kept = 1.0 - cut_m2 / observed_m2 if observed_m2 > 0 else 0.0
        compared = kept > 0.0
        warnings.append(
            f"{cut_m2:.0f} m2 of the local map ({1.0 - kept:.0%}) left out: its walls do not lie "
            "on the global map's walls after alignment (a bend beyond the drift correction)"
        )
    if drift_m > 0.1:
        log.info("%s: drift corrected, up to %.2f m", bundle_id, drift_m)
    region = stages.run(
        "roi", lambda: _make_roi(config, files, transform, route_xy, local_state, grid, warnings)
    )

    def _diff() -> tuple[diff_stage.DiffMasks, np.ndarray]:
        if not compared:
            empty = np.zeros(grid.shape, bool)
            return diff_stage.DiffMasks(empty, empty.copy()), empty.copy()
        return _diff_masks(
            view.state, view.structure, local_state, region.mask, grid, config, local, global_map
        )

    masks, removal_evidence = stages.run("diff", _diff)
    # After a drifting session (a drift correction of 0.2 m or more, or pieces), specks are
    # not reported, and a difference that a small local re-fit of the walls around it
    # explains is a wall seen twice.
    refit = compared and (drift_m >= _REFIT_DRIFT_M or in_pieces)
    differences = stages.run(
        "cluster",
        lambda: _cluster_masks(masks, removal_evidence, grid, config, local, drifted=refit),
    )
    if refit and differences:
        differences = stages.run(
            "refit", lambda: _refit(differences, view, local_state, masks.added, grid, config)
        )

    alignment_doc = {
        "theta": round(transform.theta, 6),
        "tx": round(transform.tx, 4),
        "ty": round(transform.ty, 4),
        "method": alignment.method,
        "refined": alignment.refined,
        "score": round(alignment.score, 3),
        "prior_score": round(alignment.prior_score, 3),
        # The largest slam-drift correction applied on top of the rigid transform, metres.
        "drift_m": round(drift_m, 3),
        "trusted": compared,
        "min_score": settings.align.min_score,
    }
    if pieces is not None:
        alignment_doc["method"] = f"{alignment.method}+pieces"
        alignment_doc["trusted_area_m2"] = round(pieces.trusted_area_m2 * kept, 1)
        alignment_doc["trusted_share"] = round(pieces.trusted_share * kept, 3)
        alignment_doc["pieces"] = len(pieces.pieces)
        alignment_doc["trusted_pieces"] = len(pieces.trusted)
        if in_pieces:
            # The score of what was compared: the trusted pieces', by area; the whole map's
            # rigid fit scored whole_score.
            alignment_doc["whole_score"] = alignment_doc["score"]
            weights = [p.area_m2 for p in pieces.trusted]
            scores = [p.score for p in pieces.trusted]
            alignment_doc["score"] = round(float(np.average(scores, weights=weights)), 3)
    if (kept < 1.0 or pieces is not None) and compared and not in_pieces:
        # Compared whole (no piece trusted, the whole map's fit was): what the fit check kept.
        local_m2 = float(np.count_nonzero(local.state != UNKNOWN)) * local.resolution**2
        alignment_doc["trusted_area_m2"] = round(local_m2 * kept, 1)
        alignment_doc["trusted_share"] = round(kept, 3)
    notice = trust_notice(alignment_doc)

    def _render() -> dict[str, bytes]:
        r = settings.render
        window = render.window_for(
            grid, region.mask, margin_m=r.margin_m, max_side_px=r.max_side_px
        )
        title = f"{bundle_id}  robot {files.manifest.robot}  {files.manifest.stamp}"
        over = render.overlay(
            grid,
            window,
            view.state,
            local_state,
            region.polygon,
            differences,
            route_xy=route_xy,
            title=title,
            banner=notice,
            left_out=left_out,
        )
        dimg = render.diff_image(grid, window, view.state, masks.added, masks.removed, differences)
        return {"overlay.png": render.encode_png(over), "diff.png": render.encode_png(dimg)}

    images = stages.run("render", _render)

    observation = None
    maps_root = config.maps
    if maps_root is not None:

        def _observe() -> Observation | None:
            warnings.extend(link_warnings)
            if link is None:
                return None
            if not compared:
                warnings.append(
                    f"map {link.name}: the alignment is not trusted; this bundle adds nothing "
                    "to the fleet map"
                )
                return None
            found = differences
            if link.current_version != link.bundle_version:
                # Judged against the version the fleet navigates on now, not the robot's copy.
                current = GLOBAL_MAPS.load(
                    link.current_yaml,
                    link.current_yaml.parent / map_image_name(link.current_yaml),
                    max_pixels=config.max_image_pixels,
                )
                state = resample(current.state, Grid.of_map(current), grid)
                own = view.state if view.raw_state is None else view.raw_state
                same = state == own
                structure = (view.structure & same) | (state == OCCUPIED)
                if view.raw_state is not None:
                    # The drawing's walls, where no published change has touched them.
                    state = np.where(same & (view.state == OCCUPIED), OCCUPIED, state)
                    state = state.astype(np.uint8)
                fleet_masks, removal_current = _diff_masks(
                    state, structure, local_state, region.mask, grid, config, local, global_map
                )
                found = _cluster_masks(
                    fleet_masks, removal_current, grid, config, local, drifted=refit
                )
                if refit and found:
                    found = _refit(found, view, local_state, fleet_masks.added, grid, config)
            lattice = link.lattice
            window, occupied, free = observe.observed(local_state, grid, lattice)
            slam_rel = files.slam_image.relative_to(bundle_dir).as_posix()
            slam_sha = (files.manifest.checksums or {}).get(slam_rel) or sha256_file(
                files.slam_image
            )
            return Observation(
                map_name=link.name,
                bundle_id=bundle_id,
                fingerprint=observe.fingerprint((bundle_dir / MANIFEST).read_bytes(), slam_sha),
                robot=files.manifest.robot,
                stamp=files.manifest.stamp,
                bundle_version=link.bundle_version,
                judged_version=link.current_version,
                window=window,
                occupied=occupied,
                free=free,
                found=tuple(
                    observe.Found(d.kind, observe.cells_of(d.cells, grid, lattice)) for d in found
                ),
                result_cells=tuple(
                    (d.kind, observe.cells_of(d.cells, grid, lattice)) for d in differences
                ),
                tiles=fleet_evidence.pack_tiles(window, occupied, free),
            )

        observation = stages.run("observe", _observe)

    image_name = global_map.image.name if global_map.image is not None else ""
    result: dict[str, Any] = {
        "format": 1,
        "bundle": bundle_id,
        "robot": files.manifest.robot,
        "stamp": files.manifest.stamp,
        "processed_at": datetime.now(timezone.utc)
        .isoformat(timespec="milliseconds")
        .replace("+00:00", "Z"),
        "status": "ok",
        "map": {
            "image": image_name,
            "resolution": global_map.resolution,
            "origin": [float(v) for v in global_map.origin],
            "width": global_map.width,
            "height": global_map.height,
        },
        "alignment": alignment_doc,
        "roi": {"strategy": region.strategy, "polygon": [list(p) for p in region.polygon]},
        "differences": [_difference_doc(i, d) for i, d in enumerate(differences, start=1)],
        "warnings": warnings,
        "timings_ms": dict(stages.timings_ms),
    }
    log.info(
        "%s: done, %d differences, alignment %s score %.2f, %.0f ms",
        bundle_id,
        len(differences),
        alignment.method,
        alignment.score,
        sum(stages.timings_ms.values()),
    )
    if observation is not None:
        result["map"]["name"] = observation.map_name
        result["map"]["version"] = observation.bundle_version
    return Outcome(bundle_id, result, images, observation)
