"""The only module that knows the order of the stages: load, align, pieces, warp, fit, roi, diff,
cluster, refit, render, observe.

``process_bundle`` turns a bundle directory into an :class:`Outcome` (the result document and the
encoded images) without writing anything; publishing it is :mod:`mapserver.outbox`'s job. Each
stage is a function of plain data (its inputs as arguments, its result returned);
``process_bundle`` runs them in order, each timed and named by ``_Stages``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import cache, cached_property, partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from mapserver import align as align_stage
from mapserver import cluster as cluster_stage
from mapserver import compare, deform, explain, piecewise, render, roi
from mapserver import diff as diff_stage
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
    FileNotThere,
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
from mapserver.grid import (
    Grid,
    RouteDistance,
    box_around,
    landing_box,
    resample,
    route_distance,
)
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
# How far a piece's search may move it from where it starts (piecewise.align_pieces's
# search_xy_m), metres.
_PIECE_SEARCH_M = 1.5

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
    """Times each stage, logs one line per stage with the bundle id, and tags errors with it.

    A stage that runs again (a bent map aligned in pieces after the whole map's fit: warp and
    fit twice) adds its time to the first run's. A stage run inside another (the pieces a long
    route is aligned in before the wide search, inside align) counts for itself only: its time
    is taken out of the enclosing stage's."""

    def __init__(self, bundle_id: str) -> None:
        self.bundle_id = bundle_id
        self._ms: dict[str, float] = {}
        self._open: list[str] = []  # the stages running, outermost first

    @property
    def timings_ms(self) -> dict[str, float]:
        """Milliseconds per stage, in the order the stages first ran, to 0.1 ms."""
        return {name: round(ms, 1) for name, ms in self._ms.items()}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        self._open.append(name)
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
            self._ms[name] = self._ms.get(name, 0.0) + ms
            log.info("%s: %s %.1f ms", self.bundle_id, name, ms)
            self._open.pop()
            if self._open:
                outer = self._open[-1]
                self._ms[outer] = self._ms.get(outer, 0.0) - ms
                if _stage_listener is not None:
                    _stage_listener(outer)  # back in the enclosing stage

    def run(self, name: str, fn: Callable[[], T]) -> T:
        with self.stage(name):
            return fn()


@dataclass(frozen=True)
class _Inputs:
    files: BundleFiles
    local: OccupancyMap
    global_map: OccupancyMap
    route_slam: np.ndarray | None  # the robot's route (N, 2), slam frame; None without one

    @cached_property
    def reach_m(self) -> float:
        """How far from its route the robot saw anything (``piecewise.seen_reach_m``, in the
        slam frame where map and route agree whatever the alignment): the length of its
        longest rays, a lower bound of its sensor's range; 0 without a route. Worked out on
        first use, once for the removal evidence and the fold check of both comparisons."""
        if self.route_slam is None:
            return 0.0
        return piecewise.seen_reach_m(self.local, self.route_slam)


def _load(bundle_dir: Path, config: Config, *, checksums_verified: bool) -> _Inputs:
    limits = config.limits
    try:
        files = check_bundle_files(
            bundle_dir, verify_checksums=not checksums_verified, limits=limits
        )
    except BundleIncomplete as error:
        # process runs on bundles said to be complete: a missing file is an error here.
        problem = f"{error.what} is missing" if isinstance(error, FileNotThere) else error.problem
        raise BundleError(problem, file=error.file) from None
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
    route = _route_slam(files)
    manifest = bundle_dir / MANIFEST
    slam, nav2 = files.manifest.pose.slam, files.manifest.pose.nav2
    _refuse_far_off(np.array([[slam.x, slam.y]]), "pose.slam", local, "slam", extent, manifest)
    if route is not None:
        _refuse_far_off(route, "trajectory", local, "slam", extent, manifest)
    _refuse_far_off(np.array([[nav2.x, nav2.y]]), "pose.nav2", global_map, "nav2", extent, manifest)
    return _Inputs(files, local, global_map, route)


def _refuse_far_off(
    points: np.ndarray, name: str, on: OccupancyMap, frame: str, margin_m: float, manifest: Path
) -> None:
    """Refuse a bundle whose ``points`` (N, 2) lie more than ``margin_m`` (the limit on a map's
    extent) outside the map they belong to: a pose in the wrong frame or a broken value, which
    would make every array sized by the route's length as long as that distance."""
    grid = Grid.of_map(on)
    lo = np.array([grid.x0, grid.y0])
    hi = lo + grid.resolution * np.array([grid.width, grid.height])
    off = np.maximum(np.maximum(lo - points, points - hi), 0.0).max(axis=1)
    far = np.flatnonzero(off > margin_m)
    if len(far) == 0:
        return
    i = int(far[0])
    what = name if len(points) == 1 else f"{name} pose {i}"
    which = "local" if frame == "slam" else "global"  # the map of that frame
    raise BundleError(
        f"{what} at ({points[i, 0]:g}, {points[i, 1]:g}) lies {off[i]:.0f} m outside the {which} "
        f"map (x {lo[0]:g}..{hi[0]:g}, y {lo[1]:g}..{hi[1]:g}), more than limits.max_map_extent_m "
        f"({margin_m:g} m): is it in the {frame} frame?",
        file=manifest,
    )


def _route_slam(files: BundleFiles) -> np.ndarray | None:
    """The robot's route (N, 2), slam frame, or None when the bundle has none."""
    poses = files.manifest.trajectory_poses()
    if not poses:
        return None
    return np.array([[p.x, p.y] for p in poses])


def _robot_nav2(files: BundleFiles, nav2_from_slam: Transform2D) -> Pose2D:
    slam = files.manifest.pose.slam.to_pose()
    x, y = nav2_from_slam.apply(np.array([slam.x, slam.y]))
    return Pose2D(float(x), float(y), slam.yaw + nav2_from_slam.theta)


def _align_in_pieces(
    inputs: _Inputs,
    view: align_stage.GlobalView,
    also_from: Transform2D | None,
    config: Config,
    *,
    confirm_prior: bool = False,
) -> piecewise.Pieces | None:
    """The local map aligned in pieces along the route, when the route is long enough for two
    pieces (else None). The pieces start from the pose prior, and from ``also_from`` too (the
    whole map's fit, for a prior that is off).

    ``confirm_prior``: None too unless the last piece, aligned first, confirms the prior: it
    aligns on its own (``Piece.aligned``), and puts the robot within ``jump_m`` of where the
    prior does.
    """
    a = config.pipeline.align
    files, local, route = inputs.files, inputs.local, inputs.route_slam
    if not a.pieces or not a.refine or route is None or len(route) < 2:
        return None
    if float(np.hypot(*np.diff(route, axis=0).T).sum()) < 1.5 * a.piece_m:
        return None
    # The prior is right where the robot was when it reported its pose (the route's end, where
    # the pieces start); the whole map's best rigid fit is a compromise over all of it.
    prior = files.manifest.nav2_from_slam_prior()
    robot = files.manifest.pose.slam.to_pose()
    at_robot = np.array([[robot.x, robot.y]])

    def holds(last: piecewise.Piece) -> bool:
        apart = piecewise.apart(last.nav2_from_slam, prior, at_robot)
        return last.aligned and bool(apart[0] <= a.jump_m)

    return piecewise.align_pieces(
        local,
        view,
        route,
        prior,
        # A prior that is off (mislocalized) starts no piece well; the whole map's search (its
        # narrow search's best fit, before the wide search) may have found the building.
        also_from=also_from,
        piece_m=a.piece_m,
        min_score=a.min_score,
        search_xy_m=_PIECE_SEARCH_M,
        anchored=holds if confirm_prior else None,
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
    # One wall point per square of two work cells on a side, the mean of its wall points: the
    # shifts are averages over metres of wall.
    spacing = 2 * grid.resolution
    local_walls = align_stage.known_points(local, state=OCCUPIED)
    walls = align_stage.thin_points(local_walls, spacing, mean=True)
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


def _route_on_building(
    aligned: _Aligned, route_slam: np.ndarray | None
) -> tuple[Transform2D, np.ndarray | None]:
    """The transform that puts the robot where box and heading ROIs start, and the route
    (N, 2, nav2; None without one) the trajectory ROI and the overlay draw: aligned in
    pieces, each run carried by its own piece (a left-out one by its nearest trusted piece),
    the robot by the last one's carrier; else both by the one transform."""
    if aligned.in_pieces and aligned.pieces is not None:
        route_xy = piecewise.route_nav2(aligned.pieces)
        if route_xy is not None:
            last = aligned.pieces.pieces[-1].index
            return piecewise.carrier(aligned.pieces, last) or aligned.transform, route_xy
    route_xy = None if route_slam is None else aligned.transform.apply(route_slam)
    return aligned.transform, route_xy


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


def _route_on(grid: Grid, route_xy: np.ndarray | None) -> RouteDistance | None:
    """How far the cells of ``grid`` lie from the route ``route_xy`` ((N, 2) nav2; None
    without one): what the removal evidence of both comparisons measures from."""
    if route_xy is None:
        return None
    return route_distance(grid.to_pixel(route_xy), grid.shape, grid.resolution, nearest=True)


# A trusted whole-map fit sent to pieces by the fit check: the pieces must move some of their
# cells this far from it (metres; the pieces' own agreement tolerance) to show a bend. Any
# piece that aligned on its own counts, left out of the chain or not (session 11: gen99's
# `gen-01-long`, its last piece turned on 2 degrees past the chain's agreement and left out,
# showed no bend from the chain alone; the whole fit's warp left that end 1 m off, 2 false
# positives; over 9 sets precision up on gen99 0.973 -> 0.987, nothing else changed).
_BEND_M = 0.5
# The drift correction (metres) from which a session drifted (:func:`_drifted`): differences
# are checked by a local re-fit, specks are not reported and wall ends have a wider tolerance.
_DRIFTED_M = 0.2
# ... and from which the log says the drift was corrected.
_LOGGED_DRIFT_M = 0.1


# The route carries the reported transform when it spreads this far (metres, the largest
# distance of a point from their mean); a robot that barely moved says nothing of rotation.
_ROUTE_SPREAD_M = 2.0


def _rigid_of_warp(
    local: OccupancyMap,
    transform: Transform2D,
    drift: deform.DriftStack,
    route_slam: np.ndarray | None = None,
) -> Transform2D:
    """The rigid transform closest to ``transform`` plus the drift correction along the robot's
    route (``route_slam`` (N, 2), a point every 0.1 m of path; when it spreads
    ``_ROUTE_SPREAD_M`` or more), else over the local walls (one point per 0.25 m): the
    transform that best carries the route the robot drove onto the building, where the
    alignment's own fit leans to the part whose walls carried it."""
    points = None
    if route_slam is not None and len(route_slam) >= 2:
        points = piecewise.along_route(route_slam, 0.1)
    if points is None or np.hypot(*(points - points.mean(axis=0)).T).max() < _ROUTE_SPREAD_M:
        points = align_stage.thin_points(align_stage.known_points(local, state=OCCUPIED), 0.25)
    if len(points) < 3:
        return transform
    return fit_rigid(points, transform.apply(points) + drift.at(points))


def _refit(
    differences: list[cluster_stage.Difference],
    aligned: _Aligned,
    added: np.ndarray,
    config: Config,
    local: OccupancyMap,
    reach_m: Callable[[], float],
) -> list[cluster_stage.Difference]:
    """The re-fit stage (:func:`mapserver.explain.unexplained`) on the local map as compared:
    the differences that what drift drew in it does not explain."""
    # Pieces tried, but the map warped whole (they found no bend): compared whole.
    pieces = aligned.pieces if aligned.in_pieces else None
    return explain.unexplained(
        differences, aligned.view, aligned.local_state, pieces, added, config, local, reach_m
    )


def _map_link(
    maps_root: Path | None,
    files: BundleFiles,
    global_map: OccupancyMap,
    bundle_dir: Path,
    warnings: list[str],
) -> MapLink | None:
    """The stored map whose version is this bundle's global map (by its image's sha256), or
    None with a warning (None without one: no ``maps:`` configured, or a map with no image)."""
    image = global_map.image
    if maps_root is None or image is None:
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


def _bundle_id(bundle_dir: Path, given: str | None) -> str:
    """The bundle's id: ``given``, else the directory's name. Raises BundleError when it is not
    a valid one."""
    bundle_id = given or bundle_dir.resolve().name
    if not is_valid_bundle_id(bundle_id):
        raise BundleError(
            f"invalid bundle id '{bundle_id}': use letters, digits, '.', '_' and '-', "
            "starting with a letter or digit, at most 128 characters",
            file=bundle_dir,
        )
    return bundle_id


def _view_margin_m(config: Config) -> float:
    """The room, metres, the views keep around where the local map lands: for the differences'
    reach and the images' margin."""
    return max(config.pipeline.render.margin_m, _ANALYSIS_MARGIN_M)


def _drift_reach_m(config: Config) -> float:
    """How far, metres, the drift estimate looks for a wall's counterpart (0 without the drift
    correction): the views' nearest-wall fields are built that wide from the start, for ICP and
    the drift estimate alike."""
    a = config.pipeline.align
    return 2 * a.deform_max_shift_m + 0.5 if a.deform else 0.0


def _drawing(link: MapLink | None, config: Config) -> OccupancyMap | None:
    """The floor-plan drawing whose walls the alignment reads: version 1 of the stored map the
    bundle's global map is a later version of (None: no stored map, or it is version 1)."""
    if link is None or link.bundle_version <= 1:
        return None
    return GLOBAL_MAPS.load(
        link.first_yaml,
        link.first_yaml.parent / map_image_name(link.first_yaml),
        max_pixels=config.max_image_pixels,
    )


def _align(
    inputs: _Inputs, config: Config, drawing: OccupancyMap | None, stages: _Stages
) -> tuple[align_stage.GlobalView, align_stage.Alignment, piecewise.Pieces | None]:
    """The whole local map's rigid alignment (slam -> nav2), the view of the global map it was
    searched on (the wide search's when that ran; its grid is in the nav2 frame), and the
    pieces the map was aligned in when the narrow search found no trusted fit and they showed
    that the prior holds (else None).

    A long route whose whole map finds no fit in the narrow search is aligned in pieces before
    the wide search runs: when its last piece puts the robot where the prior does, the map is
    bent and the prior is right, and the wide search (a third of a long drifting route's time)
    has nothing to find. Else the pieces are left for after the wide search."""
    a = config.pipeline.align
    files, local = inputs.files, inputs.local
    prior = files.manifest.nav2_from_slam_prior()
    robot = files.manifest.pose.slam.to_pose()
    pivot = (robot.x, robot.y)
    wide_rad = math.radians(a.search_theta_deg)
    narrow = min(math.radians(_NARROW_SEARCH_DEG), wide_rad)
    built: dict[float, align_stage.GlobalView] = {}

    def view_for(theta_rad: float) -> align_stage.GlobalView:
        if theta_rad not in built:
            built[theta_rad] = align_stage.make_view(
                inputs.global_map,
                local,
                prior,
                search_xy_m=a.search_xy_m,
                search_theta_rad=theta_rad,
                # Room for the images' margin around where the local map lands.
                margin_m=_view_margin_m(config),
                pivot_slam=pivot,
                wall_reach_m=_drift_reach_m(config),
                drawing=drawing,
            )
        return built[theta_rad]

    pieces: list[piecewise.Pieces] = []

    def prior_confirmed(narrow_best: Transform2D) -> bool:
        def aligned_on(view: align_stage.GlobalView) -> piecewise.Pieces | None:
            return _align_in_pieces(inputs, view, narrow_best, config, confirm_prior=True)

        narrow_view = built[narrow]
        found = stages.run("pieces", partial(aligned_on, narrow_view))
        room = _view_margin_m(config) + _PIECE_SEARCH_M
        if found is not None and not piecewise.lands_within(local, found, narrow_view.grid, room):
            # A piece bent by drift landed near the narrow view's edge, where its search and
            # the room the differences need ran off the view: again on the wide view (the wide
            # search, if it ran after all, would search it too).
            log.info("%s: a piece landed near the narrow view's edge", stages.bundle_id)
            found = stages.run("pieces", partial(aligned_on, view_for(wide_rad)))
        if found is None:
            return False
        pieces.append(found)
        return True

    # The view for the narrow search first (most priors are within a few degrees): the
    # wide one, several times larger, is built only when the wide search (or a piece near the
    # narrow view's edge) needs it, and then it is the one the rest works on.
    result = align_stage.align(
        local,
        view_for(narrow),
        prior,
        narrow_theta_rad=narrow,
        widen=lambda: view_for(wide_rad),
        refine=a.refine,
        search_xy_m=a.search_xy_m,
        search_theta_rad=wide_rad,
        min_score=a.min_score,
        min_gain=a.min_gain,
        jump_m=a.jump_m,
        pivot_slam=pivot,
        prior_confirmed=prior_confirmed if a.pieces else None,
        edge_margin=a.edge_margin,  # the whole map only: never a piece's few walls
    )
    view = built.get(wide_rad, built[narrow])
    return view, result, pieces[0] if pieces and not result.trusted else None


@dataclass(frozen=True)
class _Warped:
    """The local map warped onto the global map: ``local_state`` on ``view.grid`` (nav2 frame),
    ``view`` the search view cropped to where the local map lands (with the views' margin).

    ``in_pieces``: through the trusted pieces' own transforms, ``left_out`` the cells the
    untrusted pieces land on (else None). ``drift``: the drift correction applied on top of the
    rigid transform (None: none, or in pieces), ``drift_m`` its largest shift, metres (in
    pieces: the largest of the pieces' own corrections).
    """

    view: align_stage.GlobalView
    local_state: np.ndarray
    left_out: np.ndarray | None
    in_pieces: bool
    drift: deform.DriftStack | None = None
    drift_m: float = 0.0


def _warp(
    local: OccupancyMap,
    search_view: align_stage.GlobalView,
    alignment: align_stage.Alignment,
    pieces: piecewise.Pieces | None,
    config: Config,
) -> _Warped:
    """The local map warped onto ``search_view``: in pieces when some piece is trusted, else
    through the whole map's transform."""
    if pieces is not None and pieces.trusted:
        return _warp_pieces(local, search_view, pieces, config)
    return _warp_whole(local, search_view, alignment, config)


def _warp_whole(
    local: OccupancyMap,
    search_view: align_stage.GlobalView,
    alignment: align_stage.Alignment,
    config: Config,
) -> _Warped:
    """The local map through the alignment's transform, plus the drift correction when the
    alignment is trusted (and ``deform`` on)."""
    a = config.pipeline.align
    transform = alignment.nav2_from_slam
    drift = None
    if a.deform and alignment.trusted:
        drift = _estimate_drift(
            local, transform, search_view, config, reach_m=_drift_reach_m(config)
        )
    # From here on, only where the local map lands matters (with room for the tolerances and
    # the images' margin): the search view around it is several times larger.
    drift_m = drift.max_shift_m() if drift is not None else 0.0
    box = landing_box(
        local,
        search_view.grid,
        transform,
        margin_px=(drift_m + _view_margin_m(config)) / search_view.grid.resolution,
        step_px=deform.WARP_STEP_PX,  # the same warp as on the whole view
    )
    work = search_view.cropped(box) if box is not None else search_view
    warped = deform.warp_local(local, work.grid, transform, drift)
    return _Warped(work, warped, None, in_pieces=False, drift=drift, drift_m=drift_m)


def _warp_pieces(
    local: OccupancyMap,
    search_view: align_stage.GlobalView,
    pieces: piecewise.Pieces,
    config: Config,
) -> _Warped:
    """The trusted pieces, each through its own transform (and drift correction), and the cells
    the untrusted ones land on; the view cropped to both with the views' margin."""
    grid = search_view.grid
    shifts: list[float] = []
    warp_piece = partial(_warp_piece, search_view, config, shifts)
    state, out = piecewise.compose(local, pieces, grid, warp=warp_piece)
    m = math.ceil(_view_margin_m(config) / grid.resolution)
    # Nothing composed at all: a corner of the view, as a box around no cell would be.
    corner = (slice(0, min(m, grid.height)), slice(0, min(m, grid.width)))
    window = box_around((state != UNKNOWN) | out, m) or corner
    rows, cols = window
    return _Warped(
        search_view.cropped((rows.start, rows.stop, cols.start, cols.stop)),
        state[window],
        out[window],
        in_pieces=True,
        drift_m=max(shifts, default=0.0),
    )


def _warp_piece(
    view: align_stage.GlobalView,
    config: Config,
    shifts: list[float],
    part: OccupancyMap,
    transform: Transform2D,
) -> deform.Landed | None:
    """One piece's states on ``view``'s grid, in the box it lands in: through ``transform``
    and its own drift correction (``deform`` on), whose largest shift (metres) is appended to
    ``shifts``."""
    drift = None
    if config.pipeline.align.deform:
        drift = _estimate_drift(part, transform, view, config, reach_m=_drift_reach_m(config))
        shifts.append(drift.max_shift_m())
    return deform.warp_local_box(part, view.grid, transform, drift)


def _reported_transform(
    local: OccupancyMap,
    alignment: align_stage.Alignment,
    warped: _Warped,
    route_slam: np.ndarray | None,
) -> Transform2D:
    """The slam -> nav2 transform to report for the local map warped whole: the rigid fit of
    the alignment's transform plus the drift correction (when there is one, however small),
    else the alignment's.

    Even a mild drift (a few centimetres) is measured better by the warp along the route than
    by the rigid fit, which leans to the part whose walls carried it (session 44, 177 bundles of
    seven sets: alignment error mean 0.0185 -> 0.0179 m, p90 0.0333 -> 0.0325 m; gen99 p90
    0.043 -> 0.035 m; public-realism mean 0.013 -> 0.010 m)."""
    transform = alignment.nav2_from_slam
    if warped.drift is not None:
        return _rigid_of_warp(local, transform, warped.drift, route_slam)
    return transform


@dataclass(frozen=True)
class _Aligned:
    """The local map as it is compared: ``local_state`` on ``view.grid`` (nav2 frame), the
    regions whose walls do not fit made unknown and added to ``left_out``.

    ``transform`` (slam -> nav2) is the one reported, ``drift_m`` the largest drift correction
    applied on top of it, metres. ``pieces``: the alignment in pieces, if one was tried;
    ``in_pieces``: it is what was warped. ``compared``: anything is compared; ``kept``: the
    share of the warped map's observed area the fit check kept. ``warnings``: what this adds to
    the result's warnings (in pieces, they stand for the whole map's alignment warnings).
    """

    view: align_stage.GlobalView
    local_state: np.ndarray
    transform: Transform2D
    drift_m: float
    pieces: piecewise.Pieces | None
    in_pieces: bool
    left_out: np.ndarray | None
    compared: bool
    kept: float
    warnings: tuple[str, ...]


def _aligned(
    local: OccupancyMap,
    alignment: align_stage.Alignment,
    pieces: piecewise.Pieces | None,
    warped: _Warped,
    transform: Transform2D,
    unfit: np.ndarray | None,
) -> _Aligned:
    """What of ``warped`` is compared, with which transform: ``unfit`` (on the warped view's
    grid, None: not checked) is left out; aligned in pieces, the pieces' rigid fit is
    reported."""
    warnings: list[str] = []
    if pieces is not None and warped.in_pieces:
        transform = piecewise.fit_rigid(pieces) or transform
        left = len(pieces.pieces) - len(pieces.trusted)
        warnings.append(
            f"the local map was aligned in {len(pieces.pieces)} pieces along the route (no one "
            f"transform fits all of it), {len(pieces.trusted)} trusted: "
            f"{pieces.trusted_share:.0%} of the observed area ({pieces.trusted_area_m2:.0f} m2) "
            + ("compared, the rest left out" if left else "compared")
        )
    local_state, left_out = warped.local_state, warped.left_out
    compared = alignment.trusted or warped.in_pieces
    kept = 1.0
    if unfit is not None and unfit.any():
        grid = warped.view.grid
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
    return _Aligned(
        view=warped.view,
        local_state=local_state,
        transform=transform,
        drift_m=warped.drift_m,
        pieces=pieces,
        in_pieces=warped.in_pieces,
        left_out=left_out,
        compared=compared,
        kept=kept,
        warnings=tuple(warnings),
    )


def _diff(
    aligned: _Aligned,
    roi_mask: np.ndarray,
    inputs: _Inputs,
    config: Config,
    route: Callable[[], RouteDistance | None],
    *,
    drifted: bool,
) -> tuple[diff_stage.DiffMasks, np.ndarray]:
    """The filtered added/removed masks of the aligned local map against the global map and the
    removal evidence, on ``aligned.view.grid`` (``route()``: the route's distance there,
    :func:`_route_on`; ``drifted``: :func:`_drifted`): all empty when nothing is compared."""
    view = aligned.view
    if not aligned.compared:
        empty = np.zeros(view.grid.shape, bool)
        return diff_stage.DiffMasks(empty, empty.copy()), empty.copy()
    return compare.masks(
        view.state,
        view.structure,
        aligned.local_state,
        roi_mask,
        view.grid,
        config,
        inputs.local,
        inputs.global_map,
        route,
        lambda: inputs.reach_m,
        drifted=drifted,
    )


def _drifted(aligned: _Aligned) -> bool:
    """Whether the session drifted: a drift correction of ``_DRIFTED_M`` or more, or
    aligned in pieces. Specks are not reported then, the wall ends' tolerance is wider, and a
    difference a small local re-fit of the walls around it explains is a wall seen twice."""
    return aligned.compared and (aligned.drift_m >= _DRIFTED_M or aligned.in_pieces)


def _alignment_doc(
    alignment: align_stage.Alignment, aligned: _Aligned, local: OccupancyMap, min_score: float
) -> dict[str, Any]:
    """The ``alignment`` section of ``result.yaml``: the transform reported (slam -> nav2,
    radians and metres), how it was found and how far it is trusted."""
    transform, pieces, kept = aligned.transform, aligned.pieces, aligned.kept
    doc: dict[str, Any] = {
        "theta": round(transform.theta, 6),
        "tx": round(transform.tx, 4),
        "ty": round(transform.ty, 4),
        "method": alignment.method,
        "refined": alignment.refined,
        "score": round(alignment.score, 3),
        "prior_score": round(alignment.prior_score, 3),
        # The largest slam-drift correction applied on top of the rigid transform, metres.
        "drift_m": round(aligned.drift_m, 3),
        "trusted": aligned.compared,
        "min_score": min_score,
    }
    if alignment.unchanged_score is not None and not aligned.in_pieces:
        # Trusted under min_score: on the structure that did not change (align.unchanged_score).
        doc["unchanged_score"] = round(alignment.unchanged_score, 3)
    if alignment.edges_score is not None and not aligned.in_pieces:
        # Trusted under min_score: with the edges of the known floor as walls (edge_margin).
        doc["edges_score"] = round(alignment.edges_score, 3)
    if pieces is not None:
        doc["method"] = f"{alignment.method}+pieces"
        doc["trusted_area_m2"] = round(pieces.trusted_area_m2 * kept, 1)
        doc["trusted_share"] = round(pieces.trusted_share * kept, 3)
        doc["pieces"] = len(pieces.pieces)
        doc["trusted_pieces"] = len(pieces.trusted)
        if aligned.in_pieces:
            # The score of what was compared: the trusted pieces', by area; the whole map's
            # rigid fit scored whole_score.
            doc["whole_score"] = doc["score"]
            weights = [p.area_m2 for p in pieces.trusted]
            scores = [p.score for p in pieces.trusted]
            doc["score"] = round(float(np.average(scores, weights=weights)), 3)
    if (kept < 1.0 or pieces is not None) and aligned.compared and not aligned.in_pieces:
        # Compared whole (no piece trusted, the whole map's fit was): what the fit check kept.
        local_m2 = float(np.count_nonzero(local.state != UNKNOWN)) * local.resolution**2
        doc["trusted_area_m2"] = round(local_m2 * kept, 1)
        doc["trusted_share"] = round(kept, 3)
    return doc


@dataclass(frozen=True)
class _Found:
    """What the comparison found, on the aligned view's grid (nav2 frame): ``region`` the ROI,
    ``masks`` the filtered added/removed cells, ``differences`` the ones reported (largest
    first). ``drifted``: the session drifted (:func:`_drifted`), so wall ends had the wider
    tolerance, specks were dropped and the differences checked by a local re-fit.
    ``route()``: the route's distance on that grid the removal evidence measured from
    (:func:`_route_on`, worked out on first use)."""

    region: roi.Roi
    masks: diff_stage.DiffMasks
    differences: list[cluster_stage.Difference]
    drifted: bool
    route: Callable[[], RouteDistance | None]


def _render(
    bundle_id: str,
    files: BundleFiles,
    aligned: _Aligned,
    found: _Found,
    route_xy: np.ndarray | None,
    banner: str | None,
    config: Config,
) -> dict[str, bytes]:
    """``overlay.png`` and ``diff.png``, PNG bytes: the window of ``aligned.view.grid`` around
    the ROI."""
    r = config.pipeline.render
    view = aligned.view
    region, masks, differences = found.region, found.masks, found.differences
    window = render.window_for(
        view.grid, region.mask, margin_m=r.margin_m, max_side_px=r.max_side_px
    )
    title = f"{bundle_id}  robot {files.manifest.robot}  {files.manifest.stamp}"
    over = render.overlay(
        view.grid,
        window,
        view.state,
        aligned.local_state,
        region.polygon,
        differences,
        route_xy=route_xy,
        title=title,
        banner=banner,
        left_out=aligned.left_out,
    )
    # PNG encoding takes as long as the painting, and OpenCV lets go of the GIL while it
    # encodes: the overlay is encoded while the difference image is painted and encoded.
    with ThreadPoolExecutor(max_workers=1) as encoder:
        over_png = encoder.submit(render.encode_png, over)
        dimg = render.diff_image(
            view.grid, window, view.state, masks.added, masks.removed, differences, banner=banner
        )
        diff_png = render.encode_png(dimg)
        return {"overlay.png": over_png.result(), "diff.png": diff_png}


def _observe(
    link: MapLink | None,
    bundle_dir: Path,
    bundle_id: str,
    inputs: _Inputs,
    aligned: _Aligned,
    found: _Found,
    config: Config,
) -> tuple[Observation | None, list[str]]:
    """What the bundle contributes to the stored map ``link`` names (None: nothing), and the
    warning that says why not."""
    if link is None:
        return None, []
    if not aligned.compared:
        return None, [
            f"map {link.name}: the alignment is not trusted; this bundle adds nothing "
            "to the fleet map"
        ]
    judged = found.differences
    if link.current_version != link.bundle_version:
        judged = _judged_on_current(link, inputs, aligned, found, config)
    observation = _observation(
        link, bundle_dir, bundle_id, inputs.files, aligned, judged, found.differences
    )
    return observation, []


def _judged_on_current(
    link: MapLink, inputs: _Inputs, aligned: _Aligned, found: _Found, config: Config
) -> list[cluster_stage.Difference]:
    """The differences of the aligned local map against the stored map's current version (on
    ``aligned.view.grid``), found as ``found``'s were against the bundle's own version."""
    view, local_state, grid = aligned.view, aligned.local_state, aligned.view.grid
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
    roi_mask, local, drifted = found.region.mask, inputs.local, found.drifted
    fleet_masks, removal_current = compare.masks(
        state,
        structure,
        local_state,
        roi_mask,
        grid,
        config,
        local,
        inputs.global_map,
        found.route,
        lambda: inputs.reach_m,
        drifted=drifted,
    )
    judged = compare.obstacles(
        fleet_masks,
        removal_current,
        grid,
        config,
        local,
        (state, local_state),
        current.resolution,
        drifted=drifted,
    )
    if drifted and judged:
        # The re-fit's checks read the bundle's own version of the map (the view), not the
        # current one: where a published change differs, a difference's explanation may lean
        # on what the robot's copy showed.
        judged = _refit(judged, aligned, fleet_masks.added, config, local, lambda: inputs.reach_m)
    return judged


def _observation(
    link: MapLink,
    bundle_dir: Path,
    bundle_id: str,
    files: BundleFiles,
    aligned: _Aligned,
    found: list[cluster_stage.Difference],
    differences: list[cluster_stage.Difference],
) -> Observation:
    """The observation of the stored map's cells the aligned local map makes: what it saw, the
    differences ``found`` against the current version and those ``result.yaml`` reports, on
    the stored map's lattice."""
    grid, lattice = aligned.view.grid, link.lattice
    window, occupied, free = observe.observed(aligned.local_state, grid, lattice)
    slam_rel = files.slam_image.relative_to(bundle_dir).as_posix()
    slam_sha = (files.manifest.checksums or {}).get(slam_rel) or sha256_file(files.slam_image)
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
        found=tuple(observe.Found(d.kind, observe.cells_of(d.cells, grid, lattice)) for d in found),
        result_cells=tuple((d.kind, observe.cells_of(d.cells, grid, lattice)) for d in differences),
        tiles=fleet_evidence.pack_tiles(window, occupied, free),
    )


def _result_doc(
    bundle_id: str,
    inputs: _Inputs,
    alignment_doc: dict[str, Any],
    found: _Found,
    warnings: list[str],
    timings_ms: dict[str, float],
    link: MapLink | None,
    *,
    observed: Observation | None,
) -> dict[str, Any]:
    """The ``result.yaml`` document (contract section 3), stamped with the time now. On a
    stored map (``link``), its name and the version the robot navigated on (FORMATS.md section
    7); the current version too when the bundle adds nothing to the map (``observed`` None: its
    alignment not trusted), else the store's update gives it, which may publish one."""
    files, global_map = inputs.files, inputs.global_map
    region, differences = found.region, found.differences
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
        "timings_ms": dict(timings_ms),
    }
    if link is not None:
        result["map"].update(name=link.name, version=link.bundle_version)
        if observed is None:
            result["map"]["current_version"] = link.current_version
    return result


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
    bundle_id = _bundle_id(bundle_dir, bundle_id)
    stages = _Stages(bundle_id)
    settings = config.pipeline
    inputs = stages.run(
        "load", partial(_load, bundle_dir, config, checksums_verified=checksums_verified)
    )
    files, local = inputs.files, inputs.local
    warnings = list(inputs.global_map.warnings) + list(local.warnings)
    # The stored map this bundle's global map is a version of (maps: set), looked up once:
    # alignment reads a floor-plan drawing's walls from its version 1, the fleet update needs
    # it after.
    link_warnings: list[str] = []
    link = _map_link(config.maps, files, inputs.global_map, bundle_dir, link_warnings)
    drawing = _drawing(link, config)

    search_view, alignment, pieces = stages.run(
        "align", partial(_align, inputs, config, drawing, stages)
    )
    warnings += alignment.warnings
    # The pieces, when they are wanted below, start from the whole map's fit too.
    whole_fit = alignment.nav2_from_slam if alignment.refined else None
    in_pieces = partial(_align_in_pieces, inputs, search_view, whole_fit, config)
    if pieces is None and not alignment.trusted and settings.align.pieces:
        pieces = stages.run("pieces", in_pieces)
    warped = stages.run("warp", partial(_warp, local, search_view, alignment, pieces, config))
    transform = _reported_transform(local, alignment, warped, inputs.route_slam)
    misfit_m = settings.diff.max_misfit_tolerance_m
    unfit = None
    # Every bundle with fit_check; else only a drifting one (a kink beyond the warp leaves a
    # large drift correction too): a clean session pays nothing for it.
    drifting = warped.drift_m >= settings.align.fit_check_drift_m
    if (alignment.trusted or warped.in_pieces) and (settings.align.fit_check or drifting):
        unfit = stages.run("fit", partial(_unfit, warped.local_state, warped.view, misfit_m))
    off_building = unfit is not None and bool(unfit.any())
    if alignment.trusted and settings.align.pieces and (off_building or drifting):
        # Trusted as a whole, yet a region lands off the building, or the warp had to bend the
        # map by decimetres: maybe a bend beyond the drift correction (a 5-6 degree kink leaves
        # no tile off the building, the warp takes most of it, and still walls land doubled).
        # Aligned in pieces, each region fits on its own or is left out, if they find a bend.
        pieces = stages.run("pieces", in_pieces)
        if (
            pieces is not None
            and pieces.trusted
            and piecewise.departure(local, pieces, alignment.nav2_from_slam) >= _BEND_M
        ):
            warped = stages.run("warp", partial(_warp_pieces, local, search_view, pieces, config))
            unfit = stages.run("fit", partial(_unfit, warped.local_state, warped.view, misfit_m))
        elif pieces is not None and (pieces.trusted or not off_building):
            # The pieces found no bend: what sits off the building is changes (new obstacles in
            # a sparse hall, a column gone), compared like the rest; the whole map's fit stands.
            pieces, unfit = None, None
    aligned = _aligned(local, alignment, pieces, warped, transform, unfit)
    if aligned.in_pieces:
        # The pieces' warning stands for the whole map's alignment warnings.
        warnings = [w for w in warnings if w not in alignment.warnings]
    warnings += aligned.warnings
    if aligned.drift_m >= _LOGGED_DRIFT_M:
        log.info("%s: drift corrected, up to %.2f m", bundle_id, aligned.drift_m)
    grid, local_state = aligned.view.grid, aligned.local_state
    robot_from, route_xy = _route_on_building(aligned, inputs.route_slam)
    region = stages.run(
        "roi",
        partial(_make_roi, config, files, robot_from, route_xy, local_state, grid, warnings),
    )
    # Worked out once when either comparison has removed cells to judge.
    route = cache(partial(_route_on, grid, route_xy))
    drifted = _drifted(aligned)
    masks, evidence = stages.run(
        "diff", partial(_diff, aligned, region.mask, inputs, config, route, drifted=drifted)
    )
    differences = stages.run(
        "cluster",
        partial(
            compare.obstacles,
            masks,
            evidence,
            grid,
            config,
            local,
            (aligned.view.state, local_state),
            inputs.global_map.resolution,
            drifted=drifted,
        ),
    )
    if drifted and differences:
        differences = stages.run(
            "refit",
            partial(
                _refit, differences, aligned, masks.added, config, local, lambda: inputs.reach_m
            ),
        )
    found = _Found(region, masks, differences, drifted, route)

    alignment_doc = _alignment_doc(alignment, aligned, local, settings.align.min_score)
    notice = trust_notice(alignment_doc)
    images = stages.run(
        "render", partial(_render, bundle_id, files, aligned, found, route_xy, notice, config)
    )
    observation = None
    if config.maps is not None:
        contribution = partial(
            _observe, link, bundle_dir, bundle_id, inputs, aligned, found, config
        )
        observation, observe_warnings = stages.run("observe", contribution)
        warnings += link_warnings + observe_warnings

    timings = stages.timings_ms
    result = _result_doc(
        bundle_id, inputs, alignment_doc, found, warnings, timings, link, observed=observation
    )
    log.info(
        "%s: done, %d differences, alignment %s score %.2f, %.0f ms",
        bundle_id,
        len(differences),
        alignment.method,
        alignment.score,
        sum(stages.timings_ms.values()),
    )
    return Outcome(bundle_id, result, images, observation)
