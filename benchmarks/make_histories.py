"""Generate a benchmark SET of site histories with known truth, laid out like the public history set.

A history is one building (a generated office, hospital or airport, or a real map of
``/work/shared/maps``) and many simulated SLAM sessions over days by several robots, each working
in an area of the building, while the world changes: obstacles are added, structures removed,
walls put up and taken down again, carts parked for an afternoon, people standing about::

    OUT_DIR/set.yaml
    OUT_DIR/maps/<building>/<building>.yaml, .pgm     a generated building's reference map
    OUT_DIR/<history>/history.yaml                    contract section 7: every change of the site
    OUT_DIR/<history>/scenario.yaml                   the sampled parameters, one line per session
    OUT_DIR/<history>/bundles/<history>-s000/         bundle.yaml, slam_map.*, nav2_map.*
    OUT_DIR/<history>/truth/<history>-s000.yaml       contract section 4 (never inside a bundle)
    OUT_DIR/<history>/reference/nav2_map.yaml, .pgm   the map the fleet navigates on (version 1)

Every bundle carries the same reference map, byte for byte (the robots keep navigating on
version 1), so ``benchmarks/bench_public.py OUT_DIR`` scores the bundles one by one and a fleet-map
benchmark registers ``reference/`` as map ``site`` and feeds it the bundles in stamp order.
Usage::

    python benchmarks/make_histories.py /tmp/gen-history --count 8 --seed 11
    python benchmarks/make_histories.py /tmp/h --cases cart,reverted --count 4 --jobs 2
    python benchmarks/make_histories.py /tmp/big --cases airport-large --count 1

History ``i`` gets case ``cases[i % len(cases)]`` and its own seed from ``(--seed, i)``: a seed
fixes every byte (whatever ``--jobs``; no timings are written), and a larger ``--count`` only
appends histories. Cases (each samples everything else too: building, robots, areas, routes,
changes and their times):

=============  ===============================================================================
office         generated office floor, 14-18 sessions over 2.5-4.5 days, 2-4 robots
hospital       generated hospital ward
airport        generated terminal, a small one (60-110 x 40-70 m)
real           the lidar maps of /work/shared/maps (their thresholded states as the reference)
long           4-6 robots, 30-40 sessions over 5-7 days, 3-4 areas
reverted       walls / obstacles added then taken away again, structures removed then put back,
               each within a day
cart           a cart parked for two sessions of one afternoon, carts parked elsewhere, groups
               of people standing
drift          long routes (60-100 m) with strong SLAM drift, as make_scenarios' long case
walkers        3-6 people walking past during each session
airport-large  a 250 x 150 m terminal (5000 x 3000 cells, 15 MB a bundle): not in the default cases
=============  ===============================================================================

How a history is made:

1. The building: the world the lidar sees and the reference map, as in ``make_scenarios``
   (generated: the clean drawing and its roughened copy; real: the map with grey walls made solid,
   and the map's own thresholded states saved by map_saver's rules).
2. Areas: boxes of the building around points spread over its free space; a session drives a
   route inside its area (``scenario.yaml``'s ``area``); robots mostly keep to a home area.
3. The schedule: session stamps over the days, areas balanced, robots drawn.
4. The changes: ``synth.plant_changes`` plants a pool of candidates along a route of each area;
   the history's changes are drawn from the pools, each with its time window ``[from, until)``:
   permanent ones (most there before the first session, some appearing later, one sometimes
   appearing near the end: seen too rarely to be expected), reverted ones (gone within a day),
   carts and groups of people (temporary, a few hours at most).
5. Each session: the world at its stamp (the changes active then), a route planned in it, people
   standing near the route (in that bundle's truth only), then ``synth.simulate_session`` and the
   bundle. Walkers are in that bundle's truth only too (``make_scenarios``' walker changes).

A change is observed by a bundle by contract section 4's rule (``make_scenarios._seen_cells``);
``history.yaml`` counts those bundles (``sessions``, ``seen_from``, ``seen_until``) and lists, for
a removed change, the reference map's occupied cells it erased.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from mapserver import synth
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, load_map, save_map

try:
    import make_scenarios as scen
except ModuleNotFoundError:  # imported as a file (the tests): make_scenarios is beside it
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import make_scenarios as scen

Params = dict[str, Any]
WorldFn = Callable[[np.random.Generator], scen.WorldSpec]

T0 = datetime(2026, 11, 21, tzinfo=timezone.utc)  # minute 0 of every history
DAY_MIN = 24 * 60
CONFIRM_SESSIONS = 3  # contract section 7's defaults, for the "expected" count in the records
CONFIRM_SPAN_MIN = 12 * 60
_CLEARANCE_M = 0.4  # route clearance, as make_scenarios
_APART_M = 0.5  # changes keep this far apart (as plant_changes keeps its own)


# --------------------------------------------------------------------------------------------
# Cases and plans
# --------------------------------------------------------------------------------------------

Range = tuple[int, int]  # inclusive
FRange = tuple[float, float]

_SIZES = {"office": ((22, 50), (20, 40)), "hospital": ((35, 70), (25, 45))}
_SIZES["airport"] = ((60, 110), (40, 70))  # smaller than make_scenarios': many sessions each


def building(kind: str, size_m: tuple[FRange, FRange] | None = None) -> WorldFn:
    """A generated building of ``kind`` (office, hospital, airport), size drawn at random."""
    (w0, w1), (h0, h1) = size_m or _SIZES[kind]

    def world(rng: np.random.Generator) -> scen.WorldSpec:
        return scen.WorldSpec(kind, kind, (scen._u(rng, w0, w1, 1), scen._u(rng, h0, h1, 1)))

    return world


def _worlds(*names: str) -> tuple[WorldFn, ...]:
    return tuple(scen.real(n) if n in scen.REAL_MAPS else building(n) for n in names)


@dataclass(frozen=True)
class HistoryCase:
    """How to sample one case: history ``k`` of the case uses ``worlds[k % len(worlds)]``.

    Ranges are inclusive; counts of changes are what the history asks for (fewer when the
    building has no room for them near the areas' routes).
    """

    worlds: tuple[WorldFn, ...]
    sessions: Range = (14, 18)
    days: FRange = (2.5, 4.5)
    robots: Range = (2, 4)
    areas: Range = (2, 3)
    area_m: FRange = (18.0, 28.0)  # side of an area's box
    route_m: FRange = (25.0, 50.0)
    drift: str = "mild"  # see make_scenarios._base_session
    walkers: Range = (0, 1)  # people walking past, per session
    people: Range = (0, 1)  # people standing near the route, per session
    speed_mps: FRange = (0.5, 0.5)
    added: Range = (2, 4)  # permanent
    removed: Range = (1, 2)  # permanent
    reverted_added: Range = (0, 1)
    reverted_removed: Range = (0, 1)
    carts: Range = (0, 2)
    groups: Range = (0, 1)
    cart_pair: bool = False  # a cart parked for two sessions of one afternoon
    late: float = 0.6  # chance of a permanent change appearing near the end (seen too rarely)


CASES: dict[str, HistoryCase] = {
    "office": HistoryCase(_worlds("office"), area_m=(16.0, 24.0)),
    "hospital": HistoryCase(_worlds("hospital")),
    "airport": HistoryCase(_worlds("airport"), area_m=(24.0, 34.0)),
    "real": HistoryCase(
        _worlds("willow_full", "intel_lab", "mit_stata_basement", "ipa_lab_b", "nav2_depot")
        + _worlds("ipa_production_plant", "rmf_office_scan", "aws_small_warehouse")
        + _worlds("nav2_warehouse", "willow_2010"),
    ),
    "long": HistoryCase(
        _worlds("airport", "ipa_production_plant", "hospital", "willow_full"),
        sessions=(30, 40),
        days=(5.0, 7.0),
        robots=(4, 6),
        areas=(3, 4),
        added=(4, 7),
        removed=(2, 3),
        carts=(1, 3),
        groups=(0, 2),
    ),
    "reverted": HistoryCase(
        _worlds("willow_2010", "office", "nav2_warehouse", "hospital"),
        reverted_added=(1, 2),
        reverted_removed=(1, 1),
    ),
    "cart": HistoryCase(
        _worlds("hospital", "aws_small_warehouse", "office", "ipa_production_plant"),
        carts=(2, 3),
        groups=(1, 3),
        people=(0, 2),
        cart_pair=True,
    ),
    "drift": HistoryCase(
        _worlds("ipa_production_plant", "airport", "willow_full", "hospital"),
        route_m=(60.0, 100.0),
        area_m=(30.0, 40.0),
        drift="strong",
    ),
    "walkers": HistoryCase(
        _worlds("nav2_warehouse", "hospital", "airport", "office"),
        walkers=(3, 6),
        speed_mps=(0.3, 0.8),
    ),
    "airport-large": HistoryCase(
        (building("airport", ((250.0, 250.0), (150.0, 150.0))),),
        sessions=(16, 20),
        area_m=(24.0, 32.0),
    ),
}
DEFAULT_CASES = [c for c in CASES if c != "airport-large"]


@dataclass(frozen=True)
class Plan:
    """Everything sampled for one history before it is simulated (per-session values, such as
    each route's length, are drawn while simulating, from the history's seed)."""

    index: int
    name: str
    case: str
    seed: int
    world: scen.WorldSpec
    sessions: int
    days: float
    robots: int
    areas: int
    area_m: FRange
    route_m: FRange
    drift: str
    walkers: Range
    people: Range
    speed_mps: FRange
    added: int
    removed: int
    reverted_added: int
    reverted_removed: int
    carts: int
    groups: int
    cart_pair: bool
    late: bool
    maps_dir: str = str(scen.MAPS_DIR)


def _int(rng: np.random.Generator, r: Range) -> int:
    return int(rng.integers(r[0], r[1] + 1))


def make_plans(
    set_seed: int, count: int, cases: Sequence[str], maps_dir: Path = scen.MAPS_DIR
) -> list[Plan]:
    """Sample the plans of a set: history ``i`` is of case ``cases[i % len(cases)]``."""
    plans = []
    for i in range(count):
        name = cases[i % len(cases)]
        case, k = CASES[name], i // len(cases)
        seed = scen.scenario_seed(set_seed, i)
        rng = np.random.default_rng(seed)
        plans.append(
            Plan(
                index=i,
                name=f"hist-{i:02d}-{name}",
                case=name,
                seed=seed,
                world=case.worlds[k % len(case.worlds)](rng),
                sessions=_int(rng, case.sessions),
                days=scen._u(rng, *case.days, 3),
                robots=_int(rng, case.robots),
                areas=_int(rng, case.areas),
                area_m=case.area_m,
                route_m=case.route_m,
                drift=case.drift,
                walkers=case.walkers,
                people=case.people,
                speed_mps=case.speed_mps,
                added=_int(rng, case.added),
                removed=_int(rng, case.removed),
                reverted_added=_int(rng, case.reverted_added),
                reverted_removed=_int(rng, case.reverted_removed),
                carts=_int(rng, case.carts),
                groups=_int(rng, case.groups),
                cart_pair=case.cart_pair,
                late=bool(rng.random() < case.late),
                maps_dir=str(maps_dir),
            )
        )
    return plans


# --------------------------------------------------------------------------------------------
# The site: world, reference map, areas
# --------------------------------------------------------------------------------------------

Window = tuple[int, int, int, int]  # rows [r0, r1), cols [c0, c1) of the full map


@dataclass(frozen=True, eq=False)
class Site:
    """The building: what the lidar sees (before any change) and the map the fleet has."""

    world: OccupancyMap
    reference: OccupancyMap
    source: str  # where it came from, for the records
    map_name: str  # a real map's name, or ``<kind>-<6 digits>`` for a generated building
    generated: bool


def make_site(plan: Plan, rng: np.random.Generator, reference_dir: Path) -> Site:
    """The world and the reference map (trinary, origin yaw 0, the world's grid), the reference
    written into ``reference_dir`` as ``nav2_map.yaml`` and ``nav2_map.pgm``."""
    spec = plan.world
    reference_dir.mkdir(parents=True, exist_ok=True)
    if spec.kind == "real":
        path = Path(plan.maps_dir) / scen.REAL_MAPS[spec.name]
        original = scen._load_real(path)
        world = scen.lidar_world(original)
        save_map(reference_dir / "nav2_map.yaml", original.state, world.resolution, world.origin)
        source, name = str(path), spec.name
    else:
        world, global_map = scen.build_maps(spec, rng, maps_dir=Path(plan.maps_dir))
        global_map.write(reference_dir)  # the roughened drawing, saved by map_saver's rules
        source, name = "", f"{spec.kind}-{plan.seed % 1_000_000:06d}"
    reference = load_map(reference_dir / "nav2_map.yaml")
    if reference.state.shape != world.state.shape:
        raise ValueError(f"{name}: the reference map and the world differ in size")
    return Site(world, reference, source, name, spec.kind != "real")


def crop(m: OccupancyMap, state: NDArray[np.uint8], window: Window) -> OccupancyMap:
    """The window of ``state`` (a state array on ``m``'s grid) as a map in the same frame."""
    r0, r1, c0, c1 = window
    origin = (m.origin[0] + c0 * m.resolution, m.origin[1] + (m.height - r1) * m.resolution, 0.0)
    return from_states(state[r0:r1, c0:c1], m.resolution, origin)


def _window(m: OccupancyMap, centre_rc: tuple[float, float], half_m: float) -> Window:
    half = half_m / m.resolution
    r, c = centre_rc
    return (
        max(0, int(r - half)),
        min(m.height, int(r + half) + 1),
        max(0, int(c - half)),
        min(m.width, int(c + half) + 1),
    )


def _grow(window: Window, m: OccupancyMap, margin_m: float) -> Window:
    k = math.ceil(margin_m / m.resolution)
    r0, r1, c0, c1 = window
    return max(0, r0 - k), min(m.height, r1 + k), max(0, c0 - k), min(m.width, c1 + k)


def pick_areas(
    world: OccupancyMap, n: int, side_m: FRange, rng: np.random.Generator
) -> list[Window]:
    """``n`` boxes around points spread over the building's main free space (each the farthest
    of 64 random points from the earlier centres)."""
    free = (world.state == FREE).astype(np.uint8)
    roomy = cv2.distanceTransform(free, cv2.DIST_L2, 5) * world.resolution >= 2 * _CLEARANCE_M
    count, labels, stats, _ = cv2.connectedComponentsWithStats(
        roomy.astype(np.uint8), connectivity=8
    )
    if count < 2:
        raise ValueError("the building has no free space to drive in")
    main = np.flatnonzero(labels.reshape(-1) == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])))
    centres: list[tuple[int, int]] = []
    areas = []
    for _ in range(n):
        draws = np.array(
            [divmod(int(i), world.width) for i in main[rng.integers(main.size, size=64)]]
        )
        if centres:
            c = np.array(centres)
            gap = np.hypot(draws[:, None, 0] - c[None, :, 0], draws[:, None, 1] - c[None, :, 1])
            best = draws[int(np.argmax(gap.min(1)))]
        else:
            best = draws[0]
        centres.append((int(best[0]), int(best[1])))
        areas.append(_window(world, centres[-1], scen._u(rng, *side_m, 2) / 2))
    return areas


# --------------------------------------------------------------------------------------------
# Changes: planted candidates, their cells, and the world at a time
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Planted:
    """A planted change and the cells of the world it changes (full map, [row, col])."""

    change: synth.Change
    row: int
    col: int
    mask: NDArray[np.bool_]

    def window(self) -> Window:
        return self.row, self.row + self.mask.shape[0], self.col, self.col + self.mask.shape[1]


@dataclass(frozen=True, eq=False)
class SiteChange:
    """A change of the site's history: the world holds it over minutes ``[start, end)``."""

    planted: Planted
    start: int
    end: int | None
    role: str
    erase: tuple[int, ...] = ()

    @property
    def change(self) -> synth.Change:
        return self.planted.change

    def active(self, minute: int) -> bool:
        return self.start <= minute and (self.end is None or minute < self.end)


def paint(
    state: NDArray[np.uint8],
    window: Window,
    planted: Sequence[Planted],
    *,
    value: int | None = None,
) -> None:
    """Apply changes to ``state``, the given window of the full map (in place): their cells
    become free (removed) or occupied (the others), or ``value`` when given."""
    r0, r1, c0, c1 = window
    for p in planted:
        pr0, pr1, pc0, pc1 = p.window()
        a0, a1, b0, b1 = max(r0, pr0), min(r1, pr1), max(c0, pc0), min(c1, pc1)
        if a0 >= a1 or b0 >= b1:
            continue
        sub = p.mask[a0 - pr0 : a1 - pr0, b0 - pc0 : b1 - pc0]
        v = value if value is not None else FREE if p.change.kind == "removed" else OCCUPIED
        state[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0][sub] = v


def keepout(
    shape: tuple[int, int], window: Window, planted: Sequence[Planted], res: float
) -> NDArray[np.bool_]:
    """Cells of the window within ``_APART_M`` of the given changes."""
    cells = np.zeros(shape, np.uint8)
    paint(cells, window, planted, value=1)
    if not cells.any():
        return cells > 0
    k = 2 * round(_APART_M / res) + 1
    return cv2.dilate(cells, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def plant(
    world: OccupancyMap,
    state: NDArray[np.uint8],
    window: Window,
    route: Sequence[Any],
    rng: np.random.Generator,
    *,
    n_added: int,
    n_removed: int,
    n_people: int,
    avoid: Sequence[Planted] = (),
    distance_m: FRange = (1.0, 6.0),
) -> list[Planted]:
    """``synth.plant_changes`` in a window of the world as it is (``state``, full map), clear of
    ``avoid``; returns each change with its cells (ids as planted: renumber them)."""
    r0, r1, c0, c1 = window
    here = state[r0:r1, c0:c1].copy()
    here[keepout(here.shape, window, avoid, world.resolution)] = UNKNOWN
    site = from_states(here, world.resolution, crop(world, state, window).origin)
    truth, changes = synth.plant_changes(
        site,
        route,
        n_added=n_added,
        n_removed=n_removed,
        n_people=n_people,
        rng=rng,
        clearance_m=_CLEARANCE_M,
        distance_m=distance_m,
    )
    if not changes:
        return []
    # Each change's cells: the connected pieces of what changed, each given to the nearest
    # polygon (changes keep 0.5 m apart, so no piece is shared).
    n, labels = cv2.connectedComponents((truth != here).astype(np.uint8), connectivity=8)
    polys = [np.asarray(c.polygon, np.float32) for c in changes]
    owner = np.full(n, -1)
    for lab in range(1, n):
        rr, cc = np.nonzero(labels == lab)
        x, y = site.pixel_to_world(cc[0], rr[0])
        inside = [cv2.pointPolygonTest(p, (float(x), float(y)), True) for p in polys]
        owner[lab] = int(np.argmax(inside))
    out = []
    for i, change in enumerate(changes):
        mine = owner[labels] == i
        rows, cols = np.nonzero(mine)
        if rows.size == 0:
            continue
        a0, a1, b0, b1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        out.append(Planted(change, int(r0 + a0), int(c0 + b0), mine[a0:a1, b0:b1].copy()))
    return out


def erased_cells(site: Site, planted: Planted) -> tuple[int, ...]:
    """The reference map's occupied cells a removed change erases (flat ``row * width + col``):
    those of the structure and of the ragged face the map draws on it, not the rest of a wall."""
    r0, r1, c0, c1 = _grow(planted.window(), site.world, 2 * site.world.resolution)
    mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
    pr0, pr1, pc0, pc1 = planted.window()
    mask[pr0 - r0 : pr1 - r0, pc0 - c0 : pc1 - c0] = planted.mask
    near = cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0
    after_free = (mask > 0) | (site.world.state[r0:r1, c0:c1] != OCCUPIED)
    erase = near & after_free & (site.reference.state[r0:r1, c0:c1] == OCCUPIED)
    rows, cols = np.nonzero(erase)
    return tuple(int(i) for i in np.sort((rows + r0) * site.world.width + cols + c0))


def _removed_shape(site: Site, planted: Planted) -> str:
    """``structure`` when the whole thing went, ``wall_piece`` when the rest of it stands."""
    r0, r1, c0, c1 = _grow(planted.window(), site.world, site.world.resolution)
    mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
    pr0, pr1, pc0, pc1 = planted.window()
    mask[pr0 - r0 : pr1 - r0, pc0 - c0 : pc1 - c0] = planted.mask
    ring = (cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0) & (mask == 0)
    return "wall_piece" if (site.world.state[r0:r1, c0:c1][ring] == OCCUPIED).any() else "structure"


# --------------------------------------------------------------------------------------------
# The schedule
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Slot:
    """One session to simulate: when (minutes from T0), where and by which robot."""

    minute: int
    area: int
    robot: str
    pair: bool = False  # one of the cart case's two afternoon sessions


def stamp(minute: int) -> str:
    return (T0 + timedelta(minutes=int(minute))).strftime("%Y-%m-%dT%H:%M:%SZ")


def make_schedule(plan: Plan, rng: np.random.Generator) -> tuple[list[Slot], int | None]:
    """Session slots in time order (distinct stamps at least 2 minutes apart) and the cart
    pair's area (``None`` without a pair)."""
    span = round(plan.days * DAY_MIN)
    start = int(rng.integers(6 * 60, 20 * 60))
    n_pair = 2 if plan.cart_pair and plan.sessions >= 3 else 0
    minutes = [start, *(start + rng.integers(1, span + 1, plan.sessions - 1 - n_pair))]
    tags = [False] * len(minutes)
    pair_area = None
    if n_pair:
        days = [
            d
            for d in range(math.ceil(plan.days) + 2)
            if start <= d * DAY_MIN + 13 * 60 and d * DAY_MIN + 17 * 60 <= start + span
        ]
        day = days[int(rng.integers(len(days)))] if days else start // DAY_MIN
        t1 = day * DAY_MIN + 13 * 60 + int(rng.integers(0, 90))
        minutes += [t1, t1 + int(rng.integers(60, 150))]
        tags += [True, True]
        pair_area = int(rng.integers(plan.areas))
    order = sorted(range(len(minutes)), key=lambda i: (int(minutes[i]), tags[i]))
    areas = list(rng.permutation(np.resize(np.arange(plan.areas), len(minutes) - n_pair)))
    robots = [f"sim-{k + 1:02d}" for k in range(plan.robots)]
    slots: list[Slot] = []
    last = -10
    for i in order:
        minute = max(int(minutes[i]), last + 2)
        last = minute
        area = pair_area if tags[i] and pair_area is not None else int(areas.pop())
        home = [r for k, r in enumerate(robots) if k % plan.areas == area]
        pool = home if home and rng.random() < 0.75 else robots
        slots.append(Slot(minute, area, pool[int(rng.integers(len(pool)))], tags[i]))
    return slots, pair_area


# --------------------------------------------------------------------------------------------
# The history's changes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Role:
    """A change the history asks for: what it is, in which area."""

    what: str  # added | removed | reverted-added | reverted-removed | cart | cart-pair | group
    area: int

    @property
    def kind(self) -> str:
        return {"group": "temporary", "removed": "removed", "reverted-removed": "removed"}.get(
            self.what, "added"
        )


def make_roles(plan: Plan, pair_area: int | None, rng: np.random.Generator) -> list[Role]:
    counts = [
        ("added", plan.added),
        ("removed", plan.removed),
        ("reverted-added", plan.reverted_added),
        ("reverted-removed", plan.reverted_removed),
        ("cart", plan.carts),
        ("group", plan.groups),
    ]
    whats = [what for what, n in counts for _ in range(n)]
    areas = rng.permutation(np.resize(rng.permutation(plan.areas), len(whats)))
    roles = [Role(w, int(a)) for w, a in zip(whats, areas, strict=True)]
    if pair_area is not None:
        roles.append(Role("cart-pair", pair_area))
    return roles


def _windowed(slots: Sequence[Slot], area: int, lo: int, hi: int) -> list[int]:
    return [s.minute for s in slots if s.area == area and lo <= s.minute <= hi]


def time_window(
    role: Role, slots: Sequence[Slot], rng: np.random.Generator, *, late: bool
) -> tuple[int, int | None]:
    """``[from, until)`` in minutes for a change of ``role`` (``until`` None: to the end)."""
    first, last = slots[0].minute, slots[-1].minute
    span = max(1, last - first)
    if role.what in ("added", "removed"):
        if late:  # appears near the end: seen too rarely to be confirmed
            return int(rng.integers(last - max(60, span // 5), last - 30)), None
        if rng.random() < 0.6:
            return first - DAY_MIN, None  # there before the first session
        return first + int(rng.integers(0, max(1, span // 2))), None
    if role.what == "cart-pair":
        a, b = [s.minute for s in slots if s.pair][:2]
        return a - int(rng.integers(10, 45)), b + int(rng.integers(10, 45))
    # The others start a little before a session of their area, so that some are seen.
    if role.what.startswith("reverted"):
        anchors = _windowed(slots, role.area, first, last - 8 * 60) or [first]
        start = anchors[int(rng.integers(len(anchors)))] - int(rng.integers(15, 120))
        return start, max(start + 30, min(start + int(rng.integers(3 * 60, 16 * 60)), last - 1))
    anchors = _windowed(slots, role.area, first, last) or [s.minute for s in slots]
    anchor = anchors[int(rng.integers(len(anchors)))]
    if role.what == "cart":
        start = anchor - int(rng.integers(5, 90))
        return start, start + int(rng.integers(30, 6 * 60))
    start = anchor - int(rng.integers(2, 20))  # a group of people talking
    return start, anchor + int(rng.integers(5, 40))


_MIN_REMOVED_M2 = 0.1

_PREFER: dict[str, tuple[str, ...]] = {
    "reverted-added": ("wall",),
    "cart": ("box",),
    "cart-pair": ("box",),
    "group": ("group", "person"),
}


def _candidate(role: Role, pool: Sequence[Planted], site: Site) -> Planted | None:
    """The pool's first candidate for a role: of its kind, of a shape it wants (a cart must be
    a box; a reverted obstacle had better be a wall), a removed one erasing >= 0.1 m2 of the
    map (a 0.3 m column; the public histories' smallest removal erases 0.28 m2, and a few cells
    are a speck no operator would call a change). The pickier roles choose first
    (``_PICKY``)."""
    fits = [p for p in pool if p.change.kind == role.kind]
    if role.kind == "removed":
        cell_m2 = site.reference.resolution**2
        fits = [p for p in fits if len(erased_cells(site, p)) * cell_m2 >= _MIN_REMOVED_M2]
    prefer = _PREFER.get(role.what, ())
    best = [p for p in fits if p.change.shape in prefer]
    if best or role.what.startswith("cart"):
        return best[0] if best else None
    return fits[0] if fits else None


_PICKY = ("cart-pair", "cart", "reverted-added", "group")


def make_changes(
    plan: Plan,
    site: Site,
    areas: Sequence[Window],
    slots: Sequence[Slot],
    roles: Sequence[Role],
    rng: np.random.Generator,
) -> list[SiteChange]:
    """Plant pools of candidates along routes of each area (up to 4, until every role of the
    area has one), give each role a candidate and its time window. Ids 1, 2, ... in order of
    ``from``; roles the building has no room for are left out."""
    world = site.world
    permanent = [i for i, r in enumerate(roles) if r.what in ("added", "removed")]
    late_role = permanent[int(rng.integers(len(permanent)))] if plan.late and permanent else None
    chosen: list[tuple[Role, Planted, int, int | None]] = []
    everything: list[Planted] = []
    for area, window in enumerate(areas):
        pending = [(i, r) for i, r in enumerate(roles) if r.area == area]
        pending.sort(key=lambda ir: _PICKY.index(ir[1].what) if ir[1].what in _PICKY else 9)
        for _ in range(4):
            if not pending:
                break
            try:
                route = synth.plan_route(
                    crop(world, world.state, window),
                    length_m=1.5 * plan.route_m[1],
                    rng=rng,
                    clearance_m=_CLEARANCE_M,
                )
            except ValueError:
                continue
            kinds = [r.kind for _, r in pending]
            pool = plant(
                world,
                world.state,
                window,
                route,
                rng,
                avoid=everything,
                distance_m=(1.0, 5.0),
                n_added=kinds.count("added") + 3,
                n_removed=kinds.count("removed") + 1,
                n_people=kinds.count("temporary") + 1,
            )
            everything += pool
            left = []
            for i, role in pending:
                pick = _candidate(role, pool, site)
                if pick is None:
                    left.append((i, role))
                    continue
                pool.remove(pick)
                start, end = time_window(role, slots, rng, late=i == late_role)
                chosen.append((role, pick, start, end))
            pending = left
    chosen.sort(key=lambda c: (c[2], c[1].change.kind, c[0].what))
    out = []
    for new_id, (role, p, start, end) in enumerate(chosen, 1):
        change = p.change
        shape = change.shape
        if role.what.startswith("cart"):
            shape = "cart"
        elif change.kind == "removed":
            shape = _removed_shape(site, p)
        kind = "temporary" if role.what.startswith("cart") else change.kind
        planted = replace(p, change=replace(change, id=new_id, kind=kind, shape=shape))
        erase = erased_cells(site, p) if kind == "removed" else ()
        out.append(SiteChange(planted, start, end, role.what, erase))
    return out


# --------------------------------------------------------------------------------------------
# Sessions
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SessionRecord:
    """What a simulated session showed, for history.yaml and scenario.yaml."""

    bundle_id: str
    slot: Slot
    route_m: float
    active: tuple[int, ...]
    observed: tuple[int, ...]
    params: Params


def _session_params(plan: Plan, rng: np.random.Generator) -> Params:
    params = scen._base_session(rng, drift=plan.drift)
    params["walkers"] = _int(rng, plan.walkers)
    params["robot_speed_mps"] = scen._u(rng, *plan.speed_mps, 2)
    return params


def _plan_route(
    world: OccupancyMap,
    state: NDArray[np.uint8],
    windows: Sequence[Window],
    length_m: float,
    rng: np.random.Generator,
) -> list[Any]:
    """A route in the first window that has room for one (the whole map last)."""
    for window in [*windows, (0, world.height, 0, world.width)]:
        try:
            return synth.plan_route(
                crop(world, state, window), length_m=length_m, rng=rng, clearance_m=_CLEARANCE_M
            )
        except ValueError:
            continue
    raise ValueError("no room for a route anywhere in the building")


def simulate(
    plan: Plan,
    site: Site,
    areas: Sequence[Window],
    changes: Sequence[SiteChange],
    slot: Slot,
    index: int,
    first_id: int,
    history_dir: Path,
) -> tuple[SessionRecord, int]:
    """Simulate one session and write its bundle and truth. Returns its record and the next
    free change id (the session's people and walkers take ids from ``first_id`` on)."""
    rng = np.random.default_rng([plan.seed, 1, index])
    world = site.world
    params = _session_params(plan, rng)
    length_m = scen._u(rng, *plan.route_m, 2)
    active = [c for c in changes if c.active(slot.minute)]

    # The world at the stamp, in a window around the area wide enough for every beam.
    area = areas[slot.area]
    sim_window = _grow(area, world, params["max_range_m"] + 2.0)
    r0, r1, c0, c1 = sim_window
    state = world.state[r0:r1, c0:c1].copy()
    paint(state, sim_window, [c.planted for c in active])
    here = crop(world, world.state, sim_window)
    windows = [(area[0] - r0, area[1] - r0, area[2] - c0, area[3] - c0)]
    pair_cart = next((c for c in active if slot.pair and c.role == "cart-pair"), None)
    if pair_cart is not None:  # the robot works near the parked cart
        pr0, pr1, pc0, pc1 = pair_cart.planted.window()
        near = _window(world, ((pr0 + pr1) / 2, (pc0 + pc1) / 2), 8.0)
        a0, a1, b0, b1 = area
        focus = (max(near[0], a0), min(near[1], a1), max(near[2], b0), min(near[3], b1))
        if focus[0] < focus[1] and focus[2] < focus[3]:
            windows.insert(0, (focus[0] - r0, focus[1] - r0, focus[2] - c0, focus[3] - c0))
    route = _plan_route(here, state, windows, length_m, rng)

    # People standing near the route: this bundle's truth only.
    people = plant(
        here,
        state,
        (0, r1 - r0, 0, c1 - c0),
        route,
        rng,
        avoid=[_shift(c.planted, -r0, -c0) for c in active],
        distance_m=(0.8, 4.0),
        n_added=0,
        n_removed=0,
        n_people=_int(rng, plan.people),
    )
    people = [replace(p, change=replace(p.change, id=first_id + k)) for k, p in enumerate(people)]
    paint(state, (0, r1 - r0, 0, c1 - c0), people)
    next_id = first_id + len(people)

    planted = [c.change for c in active] + [p.change for p in people]
    session = synth.simulate_session(
        here, route, rng=rng, true_state=state, changes=planted, **params
    )
    walkers = scen._walker_changes(here, state, session, next_id)
    next_id += len(walkers)
    truth = [replace(c, observed=scen._seen_cells(c, session) >= 5) for c in planted]
    truth += [c for c, _ in walkers]

    bundle_id = f"{plan.name}-s{index:03d}"
    reference = history_dir / "reference"
    scen.write_bundle(
        history_dir / "bundles" / bundle_id,
        slam_map=session.slam_map,
        global_map=scen.GlobalMap.of(
            site.reference, _copy_reference(reference), "nav2_map.yaml", str(reference)
        ),
        pose_nav2=session.pose_nav2,
        pose_slam=session.pose_slam,
        trajectory=list(synth.thin_trajectory(session.trajectory)),
        robot=slot.robot,
        stamp=stamp(slot.minute),
    )
    synth.write_truth(
        history_dir / "truth" / f"{bundle_id}.yaml",
        session.nav2_from_slam,
        sorted(truth, key=lambda c: c.id),
    )
    xy = np.array([(p.x, p.y) for p in route])
    record = SessionRecord(
        bundle_id,
        slot,
        round(float(np.hypot(*np.diff(xy, axis=0).T).sum()), 2),
        tuple(c.change.id for c in active),
        tuple(c.id for c in truth if c.observed),
        params,
    )
    return record, next_id


def _shift(p: Planted, dr: int, dc: int) -> Planted:
    return replace(p, row=p.row + dr, col=p.col + dc)


def _copy_reference(reference: Path) -> Callable[[Path], list[str]]:
    """Copies the reference map's files: every bundle's global map is byte-identical to it."""

    def write(directory: Path) -> list[str]:
        names = ["nav2_map.yaml", "nav2_map.pgm"]
        for name in names:
            shutil.copyfile(reference / name, directory / name)
        return names

    return write


# --------------------------------------------------------------------------------------------
# One history
# --------------------------------------------------------------------------------------------


def expected(entry: Params) -> bool:
    """Contract section 7: a permanent change still there at the end, seen in at least
    confirm_sessions sessions spread over at least confirm_span_hours (the defaults)."""
    if (
        entry["kind"] == "temporary"
        or entry["until"] is not None
        or entry["sessions"] < CONFIRM_SESSIONS
    ):
        return False
    first = datetime.strptime(entry["seen_from"], "%Y-%m-%dT%H:%M:%SZ")
    last = datetime.strptime(entry["seen_until"], "%Y-%m-%dT%H:%M:%SZ")
    return (last - first) >= timedelta(minutes=CONFIRM_SPAN_MIN)


def _dump(path: Path, doc: Any) -> None:
    path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100))


def build_history(plan: Plan, out_dir: Path) -> Params:
    """Simulate one history and write it under ``out_dir/<name>``. Returns its set.yaml entry
    (and, under ``"seconds"``, how long it took: printed, never written)."""
    t_start = time.perf_counter()
    rng = np.random.default_rng(plan.seed)
    history_dir = out_dir / plan.name
    site = make_site(plan, rng, history_dir / "reference")
    ref = site.reference
    if site.generated:
        maps = out_dir / "maps" / site.map_name
        maps.mkdir(parents=True, exist_ok=True)
        save_map(maps / f"{site.map_name}.yaml", ref.state, ref.resolution, ref.origin)
        base_map = f"../maps/{site.map_name}/{site.map_name}.yaml"
        set_map = f"maps/{site.map_name}/{site.map_name}.yaml"
    else:
        base_map = set_map = site.source

    areas = pick_areas(site.world, plan.areas, plan.area_m, rng)
    slots, pair_area = make_schedule(plan, rng)
    roles = make_roles(plan, pair_area, rng)
    changes = make_changes(plan, site, areas, slots, roles, rng)

    records = []
    next_id = len(changes) + 1
    for index, slot in enumerate(slots):
        record, next_id = simulate(plan, site, areas, changes, slot, index, next_id, history_dir)
        records.append(record)

    entries = []
    for c in changes:
        seen = [r for r in records if c.change.id in r.observed]
        entry: Params = {
            "id": c.change.id,
            "kind": c.change.kind,
            "shape": c.change.shape,
            "polygon": [list(p) for p in c.change.polygon],
            "from": stamp(c.start),
            "until": None if c.end is None else stamp(c.end),
            "sessions": len(seen),
            "seen_from": stamp(seen[0].slot.minute) if seen else None,
            "seen_until": stamp(seen[-1].slot.minute) if seen else None,
        }
        if c.change.kind == "removed":
            entry["erase"] = list(c.erase)
        entries.append(entry)
    _dump(history_dir / "history.yaml", {"format": 1, "map": "site", "changes": entries})

    kinds = {k: sum(e["kind"] == k for e in entries) for k in ("added", "removed", "temporary")}
    params = scen._plain(
        {
            "history": True,
            "sessions": len(slots),
            "days": round((slots[-1].minute - slots[0].minute) / DAY_MIN, 3),
            "robots": len({s.robot for s in slots}),
            "areas": plan.areas,
            "route_length": list(plan.route_m),
            "drift": plan.drift,
            "walkers": list(plan.walkers),
            "changes": len(entries),
            **kinds,
            "reverted": sum(e["kind"] != "temporary" and e["until"] is not None for e in entries),
            "carts": sum(e["shape"] == "cart" for e in entries),
            "people_groups": sum(e["shape"] in ("group", "person") for e in entries),
            "expected": sum(expected(e) for e in entries),
        }
    )
    doc = {
        "format": 1,
        "name": plan.name,
        "case": plan.case,
        "seed": plan.seed,
        "base_map": base_map,
        "params": params,
        "sessions": [
            {
                "id": r.bundle_id,
                "stamp": stamp(r.slot.minute),
                "robot": r.slot.robot,
                "area": r.slot.area,
                "route_m": r.route_m,
                "walkers": r.params["walkers"],
                "active": list(r.active),
                "observed": list(r.observed),
            }
            for r in records
        ],
    }
    _dump(history_dir / "scenario.yaml", scen._plain(doc))
    return {
        "name": plan.name,
        "case": plan.case,
        "map": set_map,
        "map_name": site.map_name,
        "seed": plan.seed,
        "params": params,
        "bundles": [r.bundle_id for r in records],
        "seconds": round(time.perf_counter() - t_start, 1),
    }


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _build_one(args: tuple[Plan, Path]) -> Params:
    return build_history(*args)


def generate(
    out_dir: Path, plans: Sequence[Plan], *, seed: int, cases: Sequence[str], jobs: int
) -> list[Params]:
    """Write the histories of ``plans`` (see :func:`make_plans`) and ``set.yaml`` into
    ``out_dir``; returns the set entries (with the seconds each took, which set.yaml leaves out)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = scen.build_all(_build_one, [(plan, out_dir) for plan in plans], jobs)
    scen.write_set(
        out_dir, seed, cases, [{k: v for k, v in e.items() if k != "seconds"} for e in entries]
    )
    return entries


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="make_histories.py", description=__doc__.split("\n\n")[0] if __doc__ else None
    )
    parser.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    parser.add_argument("--count", type=int, default=len(DEFAULT_CASES), help="number of histories")
    parser.add_argument("--seed", type=int, default=20261124, help="seed of the set")
    parser.add_argument(
        "--cases", default=",".join(DEFAULT_CASES), help=f"comma-separated, of: {', '.join(CASES)}"
    )
    parser.add_argument(
        "--jobs", type=int, default=min(4, os.cpu_count() or 1), help="worker processes"
    )
    parser.add_argument(
        "--force", action="store_true", help="write into a non-empty OUT_DIR (replacing histories)"
    )
    parser.add_argument(
        "--maps", type=Path, default=scen.MAPS_DIR, help=f"the real maps (default {scen.MAPS_DIR})"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cases = scen.checked_cases(parser, args, list(CASES))
    plans = make_plans(args.seed, args.count, cases, args.maps)
    scen.prepare_out(parser, args, plans)
    start = time.perf_counter()
    entries = generate(args.out_dir, plans, seed=args.seed, cases=cases, jobs=args.jobs)
    for e in entries:
        p = e["params"]
        sys.stdout.write(
            f"{e['name']:<22} {e['map_name']:<22} {p['sessions']:3d} sessions {p['robots']} robots "
            f"{p['days']:5.2f} d  added {p['added']} removed {p['removed']} temporary "
            f"{p['temporary']}  expected {p['expected']}  {e['seconds']:6.1f} s\n"
        )
    sys.stdout.write(
        f"{len(entries)} histories in {args.out_dir} ({time.perf_counter() - start:.1f} s)\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
