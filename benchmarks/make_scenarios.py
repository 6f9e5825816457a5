"""Generate a benchmark SET of synthetic scenarios with known truth, laid out like the public set.

Each scenario is one simulated SLAM session (``mapserver.synth``) over a generated building or a
real map of ``/work/shared/maps``, stressed in one way (its *case*)::

    OUT_DIR/set.yaml
    OUT_DIR/<scenario>/scenario.yaml                 the sampled parameters and what came of them
    OUT_DIR/<scenario>/bundles/<scenario>-b000/      bundle.yaml, slam_map.*, the nav2 map files
    OUT_DIR/<scenario>/truth/<scenario>-b000.yaml    contract section 4 (never inside a bundle)
    OUT_DIR/<scenario>/reference/                    the global map, as the fleet has it

so that ``benchmarks/bench_public.py OUT_DIR`` runs and scores it. Usage::

    python benchmarks/make_scenarios.py /tmp/gen-set                       # 30 scenarios, 2 per case
    python benchmarks/make_scenarios.py /tmp/gen-set --count 60 --seed 7
    python benchmarks/make_scenarios.py /tmp/gen-set --cases airport,grey --count 6
    python benchmarks/make_scenarios.py /tmp/k --count 90 --override occupied_ratio=0.1

``--override`` sets a ``simulate_session`` option in every scenario after sampling (the same
scenarios under another simulator setting: a sensitivity study); ``--maps`` points at another
copy of the real maps.

Scenario ``i`` gets case ``cases[i % len(cases)]`` and its own seed from ``(--seed, i)``, so a seed
fixes every bundle and truth file byte for byte (whatever ``--jobs``), and a larger ``--count``
only appends scenarios. Cases:

==============  =============================================================================
moderate        like the public set: real warehouse maps, 20-45 m, no drift
long            80-120 m with strong SLAM drift (heading 0.03-0.08 deg/m, scale 0.2-0.6 %)
short           about 15 m
airport         generated terminal: big halls, a grid of IDENTICAL columns (repeated structure)
hospital        generated hospital ward: wide corridors, rows of similar rooms
office          generated office floor
mislocalized    the reported nav2 pose off by 0.5-3 m and 5-30 deg
scanner270      a 270-degree scanner (nothing seen behind the robot), various ranges
coarse          global map at 0.08-0.1 m (reduced from the true world), local 0.05 m
fine            global map at 0.02-0.03 m, local 0.05 m
localres        local map at 0.03 or 0.1 m, global 0.05 m
walkers         3-6 people walking past during the session
grey            grey anti-aliased walls: willow maps as they are, or a generated map redrawn grey
real            the other lidar maps of /work/shared/maps, as they are (their own image files)
combo           several at once: drift, walkers, a 270-degree scanner, a wrong prior
drifting        (only with --cases) 80-300 m, heading drift 0.05-0.1 deg/m, 1-4 walkers
wandering       (only with --cases) the same, the heading error a random walk of 0.03-0.1
                deg per square-root metre (how shared/bench/public-realism's sessions drift)
floorplan       (only with --cases) thin grey outlines (the RMF airport drawing, grey plans),
                the prior 5-30 deg and 0.5-3 m off
campus          (only with --cases) an outdoor campus mapped at 0.25 m (izs_campus)
==============  =============================================================================

How the global map relates to the simulated world:

- Generated buildings: the true world is the clean drawing; the global map is that drawing
  roughened like a SLAM-built map (ragged wall faces, speckles) and, for coarse and grey, reduced
  to its own resolution (the world is drawn at an integer fraction of it; a coarse cell with any
  wall in it is occupied, as a coarse SLAM map makes it). The sensor sees the true world, so the
  two maps never agree cell for cell, as with a real robot.
- Real maps: the bundle carries the original image and YAML (grey levels, 16-bit PNGs, odd
  thresholds, an origin yaw); the world the sensor sees is that map with its grey walls made solid
  (cells clearly darker than the map's unknown grey), so a grey wall is seen by the lidar.

Walkers are recorded in the truth as ``temporary`` changes (shape ``walker``): the area swept by
the person while the robot was scanning. ``synth.simulate_session`` does not return them, so they
are recomputed from a copy of its random generator (see :func:`_walker_changes`). A removed
structure counts as observed only when its area holds 5 local cells (see :func:`_seen_cells`).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from mapserver import synth
from mapserver.bundle import sha256_file
from mapserver.geometry import Pose2D, Transform2D, wrap_angle
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, load_map, save_map
from mapserver.scoring import alignment_error, observed_centroid_xy

MAPS_DIR = Path("/work/shared/maps")

# Real maps (short name -> YAML under MAPS_DIR). rmf_airport_terminal is a floor-plan drawing,
# not a lidar map: 1-pixel grey anti-aliased outlines at 0.082 m, pastel fills and grey label
# boxes; its world (see lidar_world) has the outlines as walls and the fills as floor. Not
# used: izs_campus (an outdoor map at 0.25 m, far from the indoor robots this product serves).
REAL_MAPS = {
    "rmf_airport_terminal": "rmf_airport_terminal/airport_terminal.yaml",
    "ipa_production_plant": "ipa_production_plant/map.yaml",
    "nav2_depot": "nav2_depot/depot.yaml",
    "aws_small_warehouse": "aws_small_warehouse/map.yaml",
    "nav2_warehouse": "nav2_warehouse/warehouse.yaml",
    "intel_lab": "intel_lab/intel_map.yaml",
    "ipa_lab_b": "ipa_lab_b/lab_b.yaml",
    "mit_stata_basement": "mit_stata_basement/stata_basement.yaml",
    "rmf_office_scan": "rmf_office_scan/office_scan.yaml",
    "tb3_world": "tb3_world/map.yaml",
    "willow_full": "willow_full/willow-full-0.05.yaml",
    "willow_2010": "willow_2010/willow-2010-02-18-0.10.yaml",
    "izs_campus": "izs_campus/map.yaml",
}

# In a real map, a grey cell this far (share of the way from the map's unknown grey to black) is a
# wall to the simulated lidar: willow_2010 draws most of its walls between its unknown grey and the
# occupied threshold. Lighter greys than that are smudges the beams pass through. Deliberately
# darker than the pipeline's own grey-wall rule (0.2 of the way in align.structure_mask), so that
# a wall the lidar sees is always one the global map shows.
_GREY_WALL_SHARE = 0.35
# Greys within this of the unknown grey are unknown (the beams stop there without a return).
_UNKNOWN_BAND = 3
_STAMP_BASE = "2026-11-2{day}T{hour:02d}:{minute:02d}:00Z"

Params = dict[str, Any]


# --------------------------------------------------------------------------------------------
# What a scenario is
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WorldSpec:
    """Where the true world and the global map come from.

    ``kind`` is ``office``, ``hospital``, ``airport`` (generated) or ``real`` (``name`` in
    :data:`REAL_MAPS`). ``world_res_m`` is the resolution the world is drawn at (generated only);
    ``global_res_m`` the global map's, an integer multiple of the world's (``None``: the same).
    ``grey`` redraws the global map's walls as anti-aliased grey lines of darkness ``ink``.
    """

    kind: str
    name: str = ""
    size_m: tuple[float, float] = (30.0, 30.0)
    world_res_m: float = 0.05
    global_res_m: float | None = None
    grey: bool = False
    ink: float = 1.0
    blur_px: float = 0.0
    roughen: bool = True
    floorplan: bool = False
    """A real map that is a floor-plan drawing: its world's walls are the drawn lines."""


@dataclass(frozen=True)
class Plan:
    """Everything sampled for one scenario before it is simulated."""

    index: int
    name: str
    case: str
    seed: int
    world: WorldSpec
    route_length_m: float
    n_added: int
    n_removed: int
    n_people: int
    mislocalize_m: float = 0.0
    mislocalize_deg: float = 0.0
    robot: str = "sim-01"
    session: Params = field(default_factory=dict)
    maps_dir: str = str(MAPS_DIR)


def _u(rng: np.random.Generator, lo: float, hi: float, digits: int = 4) -> float:
    return round(float(rng.uniform(lo, hi)), digits)


def _pick(rng: np.random.Generator, options: Sequence[Any]) -> Any:
    return options[int(rng.integers(len(options)))]


def _base_session(rng: np.random.Generator, *, drift: str = "mild") -> Params:
    """Sensor and SLAM noise every case starts from (public-set values), with some drift."""
    params: Params = {
        "fov_deg": 360.0,
        "angle_increment_deg": 0.5,
        "max_range_m": 12.0,
        "range_sigma_m": 0.02,
        "drop_rate": 0.01,
        "scan_every": 2,
        "slam_resolution": 0.05,
        "slam_xy_m": 0.02,
        "slam_yaw_deg": 0.3,
        "amcl_xy_m": 0.05,
        "amcl_yaw_deg": 1.0,
        "walkers": 0,
        "robot_speed_mps": 0.5,
    }
    # Heading drift always turns one way (the worst case for a bias): 0.03-0.08 deg/m bends a
    # 100 m map by 0.2-0.6 m against its best rigid fit, and doubles the walls of a revisit.
    if drift == "mild":
        params["drift_yaw_deg_per_m"] = _u(rng, 0.005, 0.03)
        params["drift_scale"] = _u(rng, 0.0005, 0.003, 5)
    elif drift == "strong":
        params["drift_yaw_deg_per_m"] = _u(rng, 0.03, 0.08)
        params["drift_scale"] = _u(rng, 0.002, 0.006, 5)
    elif drift == "severe":
        params["drift_yaw_deg_per_m"] = _u(rng, 0.05, 0.1)
        params["drift_scale"] = _u(rng, 0.002, 0.006, 5)
    elif drift == "walk":
        # The heading error a random walk of 0.03-0.1 deg per square-root metre: it wanders and
        # partly cancels, as in shared/bench/public-realism's long sessions.
        params["drift_yaw_deg_per_m"] = _u(rng, 0.03, 0.1)
        params["drift_scale"] = _u(rng, 0.002, 0.006, 5)
        params["drift_walk"] = True
    return params


def _changes(rng: np.random.Generator) -> tuple[int, int, int]:
    """Added, removed and standing-people changes to plant."""
    return int(rng.integers(2, 6)), int(rng.integers(1, 4)), int(rng.integers(0, 3))


WorldFn = Callable[[np.random.Generator], WorldSpec]
ChangesFn = Callable[[np.random.Generator], tuple[int, int, int]]


def gen(kind: str, **kw: Any) -> WorldFn:
    """A generated building of ``kind`` (office, hospital, airport), size drawn at random."""
    sizes = {"airport": ((110, 200), (60, 100)), "hospital": ((35, 70), (25, 45))}
    (w0, w1), (h0, h1) = sizes.get(kind, ((22, 50), (20, 40)))

    def world(rng: np.random.Generator) -> WorldSpec:
        return WorldSpec(kind, kind, (_u(rng, w0, w1, 1), _u(rng, h0, h1, 1)), **kw)

    return world


def real(name: str, **kw: Any) -> WorldFn:
    """A real map of :data:`REAL_MAPS`."""
    if name not in REAL_MAPS:
        raise ValueError(f"unknown real map {name!r}; know {', '.join(REAL_MAPS)}")
    return lambda rng: WorldSpec("real", name, roughen=False, **kw)


def grey(kind: str) -> WorldFn:
    """A generated building whose global map (0.05 m) has grey anti-aliased walls."""

    def world(rng: np.random.Generator) -> WorldSpec:
        ink, blur = _u(rng, 0.55, 1.0, 3), _u(rng, 0.5, 1.0, 3)
        spec = gen(kind, world_res_m=0.025, global_res_m=0.05, grey=True, ink=ink, blur_px=blur)
        return spec(rng)

    return world


@dataclass(frozen=True)
class Case:
    """How to sample one case: scenario ``k`` of the case uses ``worlds[k % len(worlds)]``."""

    worlds: tuple[WorldFn, ...]
    route_m: tuple[float, float]
    drift: str = "mild"  # none | mild | strong | severe | walk, see _base_session
    session: Callable[[np.random.Generator, int], Params] | None = None  # extra session options
    changes: ChangesFn = _changes
    mislocalize: bool = False  # the prior off by 0.5-3 m and 5-30 degrees


def _walkers(lo: int, hi: int) -> Callable[[np.random.Generator, int], Params]:
    return lambda rng, k: {"walkers": int(rng.integers(lo, hi + 1))}


def _worlds(*names: str, **kw: Any) -> tuple[WorldFn, ...]:
    """World makers by name: a generated kind (office, hospital, airport) or a real map."""
    return tuple(real(n, **kw) if n in REAL_MAPS else gen(n, **kw) for n in names)


def _counts(added: tuple[int, int], removed: tuple[int, int], people: int) -> ChangesFn:
    """Changes drawn from inclusive ranges, with a fixed number of standing people."""
    return lambda rng: (
        int(rng.integers(added[0], added[1] + 1)),
        int(rng.integers(removed[0], removed[1] + 1)),
        people,
    )


def _fov270(rng: np.random.Generator, k: int) -> Params:
    return {
        "fov_deg": 270.0,
        "angle_increment_deg": float(_pick(rng, [0.25, 0.33, 0.5])),
        "max_range_m": float(_pick(rng, [8.0, 10.0, 15.0, 25.0])),
    }


CASES: dict[str, Case] = {
    "moderate": Case(
        _worlds("ipa_production_plant", "nav2_depot", "aws_small_warehouse"),
        (20, 45),
        drift="none",
        changes=_counts((2, 5), (1, 3), 1),
    ),
    "long": Case(
        _worlds("ipa_production_plant", "hospital", "mit_stata_basement", "airport")
        + _worlds("nav2_warehouse", "office"),
        (80, 120),
        drift="strong",
        session=_walkers(0, 2),
        changes=_counts((4, 7), (1, 3), 1),
    ),
    "short": Case(
        _worlds("office", "intel_lab", "tb3_world", "rmf_office_scan", "airport"),
        (13, 17),
        changes=_counts((1, 3), (0, 1), 0),
    ),
    "airport": Case(_worlds("airport"), (30, 65), session=_walkers(0, 1)),
    "hospital": Case(_worlds("hospital"), (30, 65), session=_walkers(0, 1)),
    "office": Case(_worlds("office"), (30, 65), session=_walkers(0, 1)),
    "mislocalized": Case(
        _worlds("office", "ipa_production_plant", "airport", "nav2_warehouse", "hospital")
        + _worlds("willow_full"),
        (25, 50),
        mislocalize=True,
    ),
    "scanner270": Case(
        _worlds("hospital", "nav2_warehouse", "airport", "ipa_production_plant", "office"),
        (25, 55),
        session=_fov270,
    ),
    "coarse": Case(
        _worlds("office", world_res_m=0.04, global_res_m=0.08)
        + _worlds("ipa_production_plant", "hospital", global_res_m=0.1)
        + _worlds("aws_small_warehouse", global_res_m=0.08)
        + _worlds("airport", "aws_small_warehouse", global_res_m=0.1),
        (25, 55),
    ),
    "fine": Case(
        _worlds("office", world_res_m=0.03)
        + _worlds("aws_small_warehouse")
        + _worlds("hospital", world_res_m=0.02)
        + _worlds("nav2_warehouse"),
        (25, 50),
    ),
    "localres": Case(
        _worlds("office", "ipa_production_plant", "airport", "hospital"),
        (25, 50),
        session=lambda rng, k: {"slam_resolution": (0.1, 0.03)[k % 2]},
    ),
    "walkers": Case(
        _worlds("hospital", "ipa_production_plant", "airport", "nav2_warehouse"),
        (30, 55),
        session=lambda rng, k: {
            "walkers": int(rng.integers(3, 7)),
            "robot_speed_mps": _u(rng, 0.3, 0.8, 2),
        },
    ),
    "grey": Case(
        (real("willow_full"), grey("office"), real("willow_2010"), grey("hospital")),
        (25, 50),
    ),
    "real": Case(
        _worlds("intel_lab", "ipa_lab_b", "mit_stata_basement", "rmf_office_scan", "nav2_depot")
        + _worlds("willow_full", "nav2_warehouse", "tb3_world", "willow_2010"),
        (20, 50),
        session=_walkers(0, 1),
    ),
    "combo": Case(
        _worlds("airport", "willow_full", "hospital", "ipa_production_plant"),
        (40, 100),
        drift="strong",
        session=lambda rng, k: {
            "walkers": int(rng.integers(1, 4)),
            "fov_deg": float(_pick(rng, [270.0, 360.0])),
        },
        changes=_counts((3, 6), (1, 3), 1),
        mislocalize=True,
    ),
    # Floor-plan maps (thin grey outlines) with the prior 5-30 degrees and 0.5-3 m off.
    "floorplan": Case(
        (real("rmf_airport_terminal", floorplan=True), grey("office"), grey("airport")),
        (30, 65),
        session=_walkers(0, 1),
        mislocalize=True,
    ),
    # Not in the default list (a set's seed keeps making the same scenarios): ask for it with
    # --cases. A campus mapped at 0.25 m (the coarsest map in ../shared/maps, outdoor, long
    # rays): objects of 0.3-2 m are a few of its cells.
    "campus": Case(_worlds("izs_campus"), (20, 60), session=_walkers(0, 1)),
    # Also only with --cases. A fleet's long sessions: 80-300 m, heading drift 0.05-0.1 deg/m,
    # people walking.
    "drifting": Case(
        _worlds("airport", "hospital", "ipa_production_plant", "willow_full", "office")
        + _worlds("mit_stata_basement"),
        (80, 300),
        drift="severe",
        session=_walkers(1, 4),
        changes=_counts((4, 8), (1, 3), 1),
    ),
    # Also only with --cases: the same long sessions, drifting the way the public-realism set's
    # do (the heading error a random walk, not a bias).
    "wandering": Case(
        _worlds("airport", "hospital", "ipa_production_plant", "willow_full", "office")
        + _worlds("mit_stata_basement", "nav2_warehouse"),
        (80, 300),
        drift="walk",
        session=_walkers(1, 4),
        changes=_counts((4, 8), (1, 3), 1),
    ),
}
# The cases asked for with --cases only: a set's seed keeps making the same scenarios.
OPT_IN_CASES = ("drifting", "floorplan", "wandering", "campus")
DEFAULT_CASES = tuple(c for c in CASES if c not in OPT_IN_CASES)


def scenario_seed(set_seed: int, index: int) -> int:
    """The seed of scenario ``index`` of a set: independent of the other scenarios."""
    return int(np.random.SeedSequence([set_seed, index]).generate_state(1)[0])


def make_plans(
    set_seed: int,
    count: int,
    cases: Sequence[str],
    overrides: Params | None = None,
    maps_dir: Path = MAPS_DIR,
) -> list[Plan]:
    """Sample the plans of a set: scenario ``i`` is of case ``cases[i % len(cases)]``.

    ``overrides`` replace session options of every plan after sampling (a sensitivity study:
    the same scenarios with, say, ``occupied_ratio: 0.1``).
    """
    plans = []
    for i in range(count):
        name = cases[i % len(cases)]
        case, k = CASES[name], i // len(cases)
        seed = scenario_seed(set_seed, i)
        rng = np.random.default_rng(seed)
        world = case.worlds[k % len(case.worlds)](rng)
        route_m = _u(rng, *case.route_m, 2)
        n_added, n_removed, n_people = case.changes(rng)
        session = _base_session(rng, drift=case.drift)
        session.update(case.session(rng, k) if case.session else {})
        session.update(overrides or {})
        miss_m = _u(rng, 0.5, 3.0, 3) if case.mislocalize else 0.0
        miss_deg = _u(rng, 5.0, 30.0, 2) if case.mislocalize else 0.0
        robot = f"sim-{int(rng.integers(1, 5)):02d}"
        plans.append(
            Plan(
                index=i,
                name=f"gen-{i:02d}-{name}",
                case=name,
                seed=seed,
                world=world,
                route_length_m=route_m,
                n_added=n_added,
                n_removed=n_removed,
                n_people=n_people,
                mislocalize_m=miss_m,
                mislocalize_deg=miss_deg,
                robot=robot,
                session=session,
                maps_dir=str(maps_dir),
            )
        )
    return plans


# --------------------------------------------------------------------------------------------
# Worlds and global maps
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=4)
def _load_real(path: Path) -> OccupancyMap:
    return load_map(path)


def lidar_world(m: OccupancyMap) -> OccupancyMap:
    """The world a lidar sees in a real map: its states, with grey walls made solid.

    Among the cells the thresholds read as unknown, those well darker than the map's unknown grey
    (the commonest occupancy of its unknown cells) are walls, those lighter are free, and only
    the unknown grey itself stays unknown. Otherwise the simulated beams would stop at a grey
    wall (or a grey smudge) without a return.
    """
    state = m.state.copy()
    unknown = m.state == UNKNOWN
    if unknown.any():
        occ = m.occupancy.astype(int)
        plateau = int(np.bincount(occ[unknown], minlength=256).argmax())
        wall = plateau + _GREY_WALL_SHARE * (255 - plateau)
        state[unknown & (occ >= wall)] = OCCUPIED
        state[unknown & (occ < wall) & (np.abs(occ - plateau) > _UNKNOWN_BAND)] = FREE
    return from_states(state, m.resolution, (m.origin[0], m.origin[1], 0.0))


def floorplan_world(m: OccupancyMap, *, ink: float = 0.35, line_contrast: int = 30) -> OccupancyMap:
    """The world of a floor-plan drawing: every pixel drawn at least ``ink`` dark (label boxes,
    icons) or on a line ``line_contrast`` darker than what lies beside it (outlines; not the
    faintest, which the thresholds read as free: guide lines) is a wall, grown by a pixel all
    round, and the rest (paper, pastel fills) is floor. Its outlines are 1-pixel anti-aliased grey lines that the trinary
    thresholds read as unknown or free."""
    occ = m.occupancy
    # Dark areas (label boxes, icons) and every line drawn darker than what lies beside it.
    hat = cv2.morphologyEx(occ, cv2.MORPH_TOPHAT, np.ones((5, 5), np.uint8))
    lines = (hat >= line_contrast) & (m.state != FREE)  # not the faint ones read as free
    drawn = ((occ >= round(ink * 255)) | lines).astype(np.uint8)
    # A line drawn one pixel wide stands for a wall a few times as thick (0.25 m at 0.082 m).
    walls = cv2.dilate(drawn, np.ones((3, 3), np.uint8)) > 0
    state = np.where(walls, OCCUPIED, FREE).astype(np.uint8)
    return from_states(state, m.resolution, (m.origin[0], m.origin[1], 0.0))


def _draw_world(spec: WorldSpec, rng: np.random.Generator) -> OccupancyMap:
    w, h = spec.size_m
    res = spec.world_res_m
    if spec.kind == "airport":
        size_px = (min(20000, round(w / res)), min(20000, round(h / res)))
        return synth.make_airport_map(
            width_px=size_px[0], height_px=size_px[1], resolution=res, rng=rng
        )
    return synth.make_office_map(width_m=w, height_m=h, resolution=res, style=spec.kind, rng=rng)


def block_reduce(state: NDArray[np.uint8], k: int) -> tuple[NDArray[np.float32], ...]:
    """Occupied and unknown fractions of ``k x k`` blocks of a state array ``[row, col]``.

    Whole blocks only, counted from the bottom-left corner, so that the map origin (the lower-left
    corner) stays where it is: extra rows are dropped at the top, extra columns at the right.
    """
    h, w = state.shape
    rows, cols = h // k, w // k
    s = state[h - rows * k :, : cols * k].reshape(rows, k, cols, k)
    occ = (s == OCCUPIED).mean(axis=(1, 3), dtype=np.float32)
    unk = (s == UNKNOWN).mean(axis=(1, 3), dtype=np.float32)
    return occ, unk


def grey_image(
    occ: NDArray[np.float32], unk: NDArray[np.float32], *, ink: float, blur_px: float
) -> NDArray[np.uint8]:
    """A map image with anti-aliased grey walls (map_saver greys elsewhere).

    Occupancy ``p = ink * occupied fraction + 0.196 * unknown fraction``, blurred (``blur_px``
    sigma, pixels): a wall of darkness ``ink`` < 0.65 reads as unknown with the usual thresholds,
    and every wall gets a grey halo.
    """
    p = ink * occ + (50.0 / 255.0) * unk
    if blur_px > 0:
        p = cv2.GaussianBlur(p, (0, 0), blur_px)
    v = np.clip(np.round(255.0 * (1.0 - p)), 0, 255).astype(np.uint8)
    v[v == 255] = 254  # map_saver's free grey
    return v


@dataclass(frozen=True, eq=False)
class GlobalMap:
    """The global map of a bundle: its size (for the record) and how to write its files."""

    width: int
    height: int
    resolution: float
    write: Callable[[Path], list[str]]  # writes the files into a directory, returns their names
    yaml_name: str
    source: str

    @staticmethod
    def of(
        m: OccupancyMap, write: Callable[[Path], list[str]], yaml_name: str, source: str
    ) -> GlobalMap:
        return GlobalMap(m.width, m.height, m.resolution, write, yaml_name, source)


def _trinary_writer(m: OccupancyMap) -> Callable[[Path], list[str]]:
    def write(directory: Path) -> list[str]:
        save_map(directory / "nav2_map.yaml", m.state, m.resolution, m.origin)
        return ["nav2_map.yaml", "nav2_map.pgm"]

    return write


def _grey_writer(
    pixels: NDArray[np.uint8], res: float, origin: tuple[float, float, float]
) -> Callable[[Path], list[str]]:
    def write(directory: Path) -> list[str]:
        header = f"P5\n# grey anti-aliased walls\n{pixels.shape[1]} {pixels.shape[0]}\n255\n"
        (directory / "nav2_map.pgm").write_bytes(header.encode("ascii") + pixels.tobytes())
        doc = {
            "image": "nav2_map.pgm",
            "mode": "trinary",
            "resolution": float(res),
            "origin": [float(v) for v in origin],
            "negate": 0,
            "occupied_thresh": 0.65,
            "free_thresh": 0.196,
        }
        (directory / "nav2_map.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        return ["nav2_map.yaml", "nav2_map.pgm"]

    return write


def _copy_writer(yaml_path: Path) -> Callable[[Path], list[str]]:
    """Copies a real map's YAML and image as they are (the YAML names an image beside it)."""
    image = yaml.safe_load(yaml_path.read_text())["image"]

    def write(directory: Path) -> list[str]:
        shutil.copyfile(yaml_path, directory / yaml_path.name)
        shutil.copyfile(yaml_path.parent / image, directory / image)
        return [yaml_path.name, image]

    return write


def build_maps(
    spec: WorldSpec, rng: np.random.Generator, *, maps_dir: Path = MAPS_DIR
) -> tuple[OccupancyMap, GlobalMap]:
    """The true world (what the sensor sees, before the planted changes) and the global map."""
    if spec.kind == "real":
        path = Path(maps_dir) / REAL_MAPS[spec.name]
        original = _load_real(path)
        world = floorplan_world(original) if spec.floorplan else lidar_world(original)
        if spec.global_res_m is None:
            return world, GlobalMap.of(original, _copy_writer(path), path.name, str(path))
        base = from_states(original.state, original.resolution, world.origin)
    else:
        world = _draw_world(spec, rng)
        base = world
        path = None
    if spec.roughen:
        base = synth.roughen_map(
            base, rng=rng, edge_rate=_u(rng, 0.05, 0.2), speckles_per_100m2=_u(rng, 0.2, 1.5)
        )
    source = str(path) if path is not None else f"(generated {spec.kind})"
    if spec.global_res_m is None:
        return world, GlobalMap.of(base, _trinary_writer(base), "nav2_map.yaml", source)
    k = round(spec.global_res_m / base.resolution)
    if k < 2 or abs(k * base.resolution - spec.global_res_m) > 1e-6:
        raise ValueError(
            f"global_res_m {spec.global_res_m} must be an integer multiple (>= 2) of the "
            f"world's resolution {base.resolution}"
        )
    occ, unk = block_reduce(base.state, k)
    res = spec.global_res_m
    if spec.grey:
        pixels = grey_image(occ, unk, ink=spec.ink, blur_px=spec.blur_px)
        h, w = pixels.shape
        writer = _grey_writer(pixels, res, base.origin)
        return world, GlobalMap(w, h, res, writer, "nav2_map.yaml", source)
    # A coarse SLAM map: a cell with any wall in it gets the hits, so it is occupied (a 2 cm wall
    # stays a wall at 10 cm); a cell mostly outside what was seen is unknown.
    state = np.full(occ.shape, FREE, np.uint8)
    state[unk > 0.5] = UNKNOWN
    state[occ > 0] = OCCUPIED
    g = from_states(state, res, base.origin)
    return world, GlobalMap.of(g, _trinary_writer(g), "nav2_map.yaml", source)


# --------------------------------------------------------------------------------------------
# Walkers in the truth
# --------------------------------------------------------------------------------------------


def _walker_changes(
    world: OccupancyMap,
    true_state: NDArray[np.uint8],
    session: synth.Session,
    first_id: int,
) -> list[tuple[synth.Change, int]]:
    """Temporary changes for the people who walked past while the robot scanned.

    Each of the session's walkers becomes the area its disc swept at the scan times when it was
    about (plus 5 cm); it is ``observed`` when at least 5 occupied local cells, mapped by the
    true transform, fall on that area more than 3 local cells from anything solid in the true
    world (nearer, they are the wall's own noise). Returns ``(change, seen_cells)`` pairs.
    """
    walkers = session.walkers
    if not walkers:
        return []
    t_scan = np.array(session.scan_times)

    local = session.slam_map
    rows, cols = np.nonzero(local.state == OCCUPIED)
    lx, ly = local.pixel_to_world(cols, rows)
    occ_nav2 = session.nav2_from_slam.apply(np.stack([lx, ly], 1))
    wc, wr = world.world_to_pixel(occ_nav2[:, 0], occ_nav2[:, 1])
    wc, wr = np.rint(wc).astype(int), np.rint(wr).astype(int)
    inside = (wc >= 0) & (wr >= 0) & (wc < world.width) & (wr < world.height)
    # Off the true walls by more than range noise and registration jitter (3 local cells).
    solid = (true_state != FREE).astype(np.uint8)
    clear_m = cv2.distanceTransform(1 - solid, cv2.DIST_L2, 5) * world.resolution
    world_free = np.zeros(len(wc), bool)
    world_free[inside] = clear_m[wr[inside], wc[inside]] > 3 * local.resolution

    out: list[tuple[synth.Change, int]] = []
    cell = 0.05
    for walker in walkers:
        active = (t_scan >= walker.t_start) & (t_scan <= walker.t_end)
        if not active.any():
            continue
        pts = walker.position(t_scan[active])
        pad = walker.radius_m + 0.05
        lo = pts.min(0) - pad - 2 * cell
        size = np.ceil((pts.max(0) + pad + 2 * cell - lo) / cell).astype(int) + 1
        mask = np.zeros((size[1], size[0]), np.uint8)
        px = np.rint((pts - lo) / cell).astype(np.int32)
        px[:, 1] = size[1] - 1 - px[:, 1]
        radius_px = max(1, round(pad / cell))
        if len(px) > 1:
            cv2.polylines(mask, [px.reshape(-1, 1, 2)], False, 1, 2 * radius_px + 1)
        for x, y in px[[0, -1]]:
            cv2.circle(mask, (int(x), int(y)), radius_px, 1, -1)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        contour = max(contours, key=cv2.contourArea)
        contour = cv2.approxPolyDP(contour, 0.6, True).reshape(-1, 2).astype(float)
        poly = np.stack(
            [lo[0] + contour[:, 0] * cell, lo[1] + (size[1] - 1 - contour[:, 1]) * cell], 1
        )
        # Cells on the swept area: the mask, looked up at the local occupied cells.
        q = np.rint((occ_nav2 - lo) / cell).astype(int)
        q[:, 1] = size[1] - 1 - q[:, 1]
        ok = (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < size[0]) & (q[:, 1] < size[1])
        on = np.zeros(len(q), bool)
        on[ok] = mask[q[ok, 1], q[ok, 0]] > 0
        seen = int(np.count_nonzero(on & world_free))
        polygon = tuple((round(float(x), 4), round(float(y), 4)) for x, y in poly)
        change = synth.Change(first_id + len(out), "temporary", "walker", polygon, seen >= 5)
        out.append((change, seen))
    return out


# --------------------------------------------------------------------------------------------
# One scenario
# --------------------------------------------------------------------------------------------


def _polygon_area_m2(polygon: Sequence[tuple[float, float]]) -> float:
    p = np.asarray(polygon, float)
    return 0.5 * abs(
        float(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1)))
    )


def _seen_cells(change: synth.Change, session: synth.Session) -> int:
    """What the local map shows of a change (contract section 4: 5 cells make it observed).

    ``synth`` counts the local cells that beams through a removed structure left free; with
    registration noise those scatter around it, so a speck of 4 cells can count 15. The count
    is capped at the number of local cells the structure covers: cells ON it.
    """
    seen = int(session.seen_cells.get(change.id, 0))
    if change.kind == "removed":
        cell_m2 = session.slam_map.resolution**2
        seen = min(seen, int(_polygon_area_m2(change.polygon) / cell_m2 + 1e-9))
    return seen


def _pose_doc(pose: Pose2D) -> dict[str, float]:
    return {"x": round(pose.x, 6), "y": round(pose.y, 6), "yaw": round(wrap_angle(pose.yaw), 6)}


def write_bundle(
    directory: Path,
    *,
    slam_map: OccupancyMap,
    global_map: GlobalMap,
    pose_nav2: Pose2D,
    pose_slam: Pose2D,
    trajectory: Sequence[Pose2D],
    robot: str,
    stamp: str,
) -> None:
    """A bundle directory (contract section 2), the manifest written last."""
    directory.mkdir(parents=True, exist_ok=True)
    save_map(directory / "slam_map.yaml", slam_map.state, slam_map.resolution, slam_map.origin)
    files = ["slam_map.yaml", "slam_map.pgm", *global_map.write(directory)]
    manifest = {
        "format": 1,
        "robot": robot,
        "stamp": stamp,
        "slam_map": "slam_map.yaml",
        "nav2_map": global_map.yaml_name,
        "pose": {"nav2": _pose_doc(pose_nav2), "slam": _pose_doc(pose_slam)},
        "trajectory": [_pose_doc(p) for p in trajectory],
        "checksums": {name: sha256_file(directory / name) for name in files},
    }
    text = yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None, width=100)
    (directory / "bundle.yaml").write_text(text)


def _plain(value: Any) -> Any:
    """YAML-friendly copy: tuples to lists, numpy scalars to Python, floats rounded."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return round(value, 6)
    return value


def plan_params(plan: Plan) -> Params:
    """The sampled parameters of a plan, for ``scenario.yaml`` and ``set.yaml``."""
    w = plan.world
    world: Params = {"kind": w.kind}
    if w.kind == "real":
        world["map"] = w.name
    else:
        world["size_m"] = list(w.size_m)
        world["world_resolution"] = w.world_res_m
    if w.global_res_m is not None:
        world["global_resolution"] = w.global_res_m
    if w.grey:
        world.update(grey=True, ink=w.ink, blur_px=w.blur_px)
    params: Params = {
        "bundles": 1,
        "world": world,
        "route_length": plan.route_length_m,
        "added": plan.n_added,
        "removed": plan.n_removed,
        "people_groups": plan.n_people,
        "robot": plan.robot,
        **plan.session,
    }
    if plan.mislocalize_m or plan.mislocalize_deg:
        params["mislocalize_m"] = plan.mislocalize_m
        params["mislocalize_deg"] = plan.mislocalize_deg
    plain: dict[str, Any] = _plain(params)
    return plain


def build_scenario(plan: Plan, out_dir: Path) -> Params:
    """Simulate one scenario and write it under ``out_dir/<name>``. Returns its set.yaml entry."""
    start = time.perf_counter()
    rng = np.random.default_rng(plan.seed)
    world, global_map = build_maps(plan.world, rng, maps_dir=Path(plan.maps_dir))
    route = synth.plan_route(world, length_m=plan.route_length_m, rng=rng, clearance_m=0.4)
    true_state, changes = synth.plant_changes(
        world,
        route,
        n_added=plan.n_added,
        n_removed=plan.n_removed,
        n_people=plan.n_people,
        rng=rng,
        clearance_m=0.4,
    )
    session = synth.simulate_session(
        world,
        route,
        rng=rng,
        true_state=true_state,
        changes=changes,
        mislocalize_m=plan.mislocalize_m,
        mislocalize_deg=plan.mislocalize_deg,
        **plan.session,
    )
    seen = {c.id: _seen_cells(c, session) for c in changes}
    changes = tuple(replace(c, observed=seen[c.id] >= 5) for c in changes)
    walkers = _walker_changes(world, true_state, session, len(changes) + 1)
    for change, cells in walkers:
        seen[change.id] = cells
    all_changes = changes + tuple(c for c, _ in walkers)

    bundle_id = f"{plan.name}-b000"
    scenario_dir = out_dir / plan.name
    stamp = _STAMP_BASE.format(
        day=1 + plan.index // 288 % 9, hour=plan.index // 12 % 24, minute=plan.index % 12 * 5
    )
    write_bundle(
        scenario_dir / "bundles" / bundle_id,
        slam_map=session.slam_map,
        global_map=global_map,
        pose_nav2=session.pose_nav2,
        pose_slam=session.pose_slam,
        trajectory=list(synth.thin_trajectory(session.trajectory)),
        robot=plan.robot,
        stamp=stamp,
    )
    synth.write_truth(
        scenario_dir / "truth" / f"{bundle_id}.yaml", session.nav2_from_slam, all_changes
    )
    reference = scenario_dir / "reference"
    reference.mkdir(exist_ok=True)
    global_map.write(reference)

    d = session.drift
    prior = Transform2D.from_poses(session.pose_nav2, session.pose_slam)
    truth = session.nav2_from_slam
    centre = observed_centroid_xy(session.slam_map)
    prior_error_m, prior_error_rad = alignment_error(prior, truth, centre)
    xy = np.array([(p.x, p.y) for p in route])
    bundle_doc = {
        "id": bundle_id,
        "route_m": round(float(np.hypot(*np.diff(xy, axis=0).T).sum()), 2),
        "poses": len(route),
        "local_map_px": [session.slam_map.width, session.slam_map.height],
        "local_resolution": session.slam_map.resolution,
        "global_map_px": [global_map.width, global_map.height],
        "global_resolution": global_map.resolution,
        "prior_error": {
            "at_centre_m": round(prior_error_m, 4),
            "deg": round(math.degrees(prior_error_rad), 3),
        },
        "drift": {
            "scale_factor": round(d.scale_factor, 6),
            "end_yaw_error_deg": round(d.end_yaw_error_deg, 3),
            "end_position_error_m": round(d.end_position_error_m, 4),
            "fit_max_residual_m": round(d.fit_max_residual_m, 4),
            "fit_rms_residual_m": round(d.fit_rms_residual_m, 4),
            "fit_end_residual_m": round(d.fit_end_residual_m, 4),
        },
        "changes": [
            {
                "id": c.id,
                "kind": c.kind,
                "shape": c.shape,
                "polygon": [list(p) for p in c.polygon],
                "observed": c.observed,
                "seen_cells": int(seen.get(c.id, 0)),
            }
            for c in all_changes
        ],
    }
    params = plan_params(plan)
    doc = {
        "format": 1,
        "name": plan.name,
        "case": plan.case,
        "seed": plan.seed,
        "base_map": global_map.source,
        "params": params,
        "bundles": [_plain(bundle_doc)],
    }
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    (scenario_dir / "scenario.yaml").write_text(text)
    return {
        "name": plan.name,
        "case": plan.case,
        "map": global_map.source,
        "map_name": plan.world.name if plan.world.kind == "real" else plan.world.kind,
        "seed": plan.seed,
        "params": params,
        "bundles": [bundle_id],
        "seconds": round(time.perf_counter() - start, 1),
    }


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _build_one(args: tuple[Plan, Path]) -> Params:
    return build_scenario(*args)


def generate(
    out_dir: Path,
    *,
    count: int,
    seed: int,
    cases: Sequence[str],
    jobs: int,
    overrides: Params | None = None,
    maps_dir: Path = MAPS_DIR,
) -> list[Params]:
    """Write a set of ``count`` scenarios into ``out_dir``; returns the ``set.yaml`` entries."""
    plans = make_plans(seed, count, cases, overrides, maps_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = build_all(_build_one, [(plan, out_dir) for plan in plans], jobs)
    extra = {"overrides": _plain(overrides)} if overrides else {}
    write_set(out_dir, seed, cases, entries, **extra)
    return entries


def build_all(build: Callable[[Any], Params], work: Sequence[Any], jobs: int) -> list[Params]:
    """``build`` of each item of ``work``, in order, in ``jobs`` processes (or in this one)."""
    if jobs > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            return list(pool.map(build, work))
    return [build(w) for w in work]


def write_set(
    out_dir: Path, seed: int, cases: Sequence[str], entries: Sequence[Params], **extra: Any
) -> None:
    """``out_dir/set.yaml``: the set's name, seed and cases, ``extra``, and ``entries``."""
    doc: Params = {"format": 1, "set": out_dir.name, "seed": seed, "cases": list(cases), **extra}
    doc["scenarios"] = list(entries)
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    (out_dir / "set.yaml").write_text(text)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="make_scenarios.py", description=__doc__.split("\n\n")[0] if __doc__ else None
    )
    parser.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    parser.add_argument(
        "--count", type=int, default=2 * len(DEFAULT_CASES), help="number of scenarios"
    )
    parser.add_argument("--seed", type=int, default=20261121, help="seed of the set")
    parser.add_argument(
        "--cases",
        default=",".join(DEFAULT_CASES),
        help=f"comma-separated, of: {', '.join(CASES)} (default: all but {', '.join(OPT_IN_CASES)})",
    )
    parser.add_argument(
        "--jobs", type=int, default=min(4, os.cpu_count() or 1), help="worker processes"
    )
    parser.add_argument(
        "--force", action="store_true", help="write into a non-empty OUT_DIR (replacing scenarios)"
    )
    parser.add_argument(
        "--maps", type=Path, default=MAPS_DIR, help=f"the real maps (default {MAPS_DIR})"
    )
    parser.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="set a simulate_session option in every scenario (repeatable), "
        "e.g. occupied_ratio=0.1 or slam_yaw_deg=0.1",
    )
    return parser


def _parse_overrides(items: Sequence[str], parser: argparse.ArgumentParser) -> Params:
    known = set(_base_session(np.random.default_rng(0))) | {"occupied_ratio", "margin_m"}
    out: Params = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in known:
            parser.error(f"--override {item!r}: expected KEY=VALUE with KEY in {sorted(known)}")
        out[key] = yaml.safe_load(value)
    return out


def checked_cases(
    parser: argparse.ArgumentParser, args: argparse.Namespace, known: Collection[str]
) -> list[str]:
    """``--cases`` as a list, once ``--cases``, ``--count`` and the output folder are checked
    (``parser.error`` otherwise): shared by this script and ``make_histories.py``."""
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in known]
    if unknown or not cases:
        parser.error(
            f"--cases: unknown {', '.join(unknown) or '(none given)'}; know {', '.join(known)}"
        )
    if args.count < 1:
        parser.error(f"--count must be >= 1, got {args.count}")
    if args.out_dir.exists() and any(args.out_dir.iterdir()) and not args.force:
        parser.error(f"{args.out_dir} is not empty (use --force to write into it)")
    return cases


def prepare_out(
    parser: argparse.ArgumentParser, args: argparse.Namespace, plans: Sequence[Any]
) -> None:
    """Check that the real maps the plans use are under ``--maps`` (``parser.error``
    otherwise), and with ``--force`` clear the plans' folders."""
    missing = sorted(
        {str(args.maps / REAL_MAPS[p.world.name]) for p in plans if p.world.kind == "real"}
        - {str(args.maps / y) for y in REAL_MAPS.values() if (args.maps / y).is_file()}
    )
    if missing:
        parser.error(f"--maps: missing {', '.join(missing)}")
    if args.force:
        for plan in plans:
            shutil.rmtree(args.out_dir / plan.name, ignore_errors=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cases = checked_cases(parser, args, CASES)
    overrides = _parse_overrides(args.override, parser)
    plans = make_plans(args.seed, args.count, cases, overrides, args.maps)
    prepare_out(parser, args, plans)
    start = time.perf_counter()
    entries = generate(
        args.out_dir,
        count=args.count,
        seed=args.seed,
        cases=cases,
        jobs=args.jobs,
        overrides=overrides,
        maps_dir=args.maps,
    )
    for e in entries:
        sys.stdout.write(f"{e['name']:<26} {e['map_name']:<22} {e['seconds']:6.1f} s\n")
    sys.stdout.write(
        f"{len(entries)} scenarios in {args.out_dir} ({time.perf_counter() - start:.1f} s)\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
