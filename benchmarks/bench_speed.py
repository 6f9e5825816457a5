"""Airport-scale speed and memory benchmark (issue 4): the pipeline against its targets.

It builds its own bundles (seeded, so every run sees the same data) with :mod:`mapserver.synth`:

* ``airport``: a 5000 x 3000 px airport terminal at 0.05 m (250 m x 150 m) and a 200 m session
  (a local map of about 1500 px on a side) with planted changes;
* ``scale-1000`` ... ``scale-8000``: ONE session recorded in a 1000 x 1000 px window of an
  8000 x 8000 px airport, bundled with square crops of 1000, 2000, 4000 and 8000 px around that
  window. The crops keep the big map's metric frame, so the local map, the poses, the
  trajectory and the truth are byte-identical across sizes; only the global map grows.

and prints, with PASS/FAIL against each target of issue 4 (2 cores):

1. per-stage wall time of :func:`~mapserver.pipeline.process_bundle` in this process (median of
   ``--runs``): the first call, calls with the decoded global map cache cleared before each
   (``GLOBAL_MAPS.clear()``: the global map is decoded every time) and calls with it warm;
2. the peak RSS (VmHWM) of a fresh interpreter that processes the airport bundle once;
3. the end-to-end wall time of ``mapserver process`` (interpreter start and imports included);
4. the scaling curve over the four global map sizes, with and without the global map's load;
5. a naive pipeline the prototype's way (full-canvas warp, DBSCAN over every difference pixel)
   on the same bundles, and the ratio. DBSCAN over millions of pixels would take minutes and
   gigabytes: it runs on the first ``--naive-pixel-cap`` difference pixels (a band of rows, so
   the density stays the same) and its time is extrapolated linearly, which UNDER-states the
   naive cost (its measured growth is slightly worse than linear); the output says when;
6. the backlog drain rate of the daemon (``mapserver run``) on ``--bundles`` airport bundles,
   against the workers times the single-bundle rate of the same bundles (the backlog cycles
   through four sessions, one harder than the others: the rate is the mean of their
   in-process times, map cached).

Usage::

    .venv/bin/python benchmarks/bench_speed.py                # the full run, about 2 minutes
    .venv/bin/python benchmarks/bench_speed.py --quick        # fewer runs and bundles, < 2 min
    .venv/bin/python benchmarks/bench_speed.py --out /tmp/bs  # keep (and reuse) the data there

Speed claims live here, not in timed tests. The exit code is 0 whatever the figures (2 for a
usage error): it measures, it does not judge a CI run.
"""

from __future__ import annotations

import argparse
import compileall
import gc
import hashlib
import json
import math
import os
import platform
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

import mapserver
from mapserver import synth
from mapserver.bundle import read_manifest
from mapserver.cluster import cluster_mask
from mapserver.config import Config
from mapserver.diff import drop_along_walls
from mapserver.grid import Grid, warp_matrix
from mapserver.maps import FREE, OCCUPIED, OccupancyMap, from_states, load_map
from mapserver.pipeline import GLOBAL_MAPS, process_bundle
from mapserver.scoring import observed_centroid_xy, parse_result, parse_truth, score_bundle

STAGES = ("load", "align", "warp", "roi", "diff", "cluster", "render")
RESOLUTION = 0.05
AIRPORT_PX = (5000, 3000)
SCALE_SIZES = (1000, 2000, 4000, 8000)
STAMP = "2026-11-21T10:15:00Z"
MIB = 1 << 20

# Targets of issue 4.
TARGET_IN_PROCESS_S = 0.3
TARGET_CLI_S = 1.0
TARGET_NAIVE_RATIO = 10.0
TARGET_RSS_FACTOR, TARGET_RSS_EXTRA_MIB = 3, 150
TARGET_SCALING = 2.0
TARGET_DRAIN = 0.8
# Target of issue 12: a 300 m session drifting one way, aligned in pieces, in-process.
TARGET_DRIFTING_S = 1.5

# A pathological difference (tens of thousands of dashes along walls): a stage's cost per dash
# at sixteen times the dashes (1,250 -> 20,000), against the cost at one time (linear: 1;
# session 55's code gave x1.9 for the wall filter and x2.9 for the clustering).
TARGET_PER_DASH_GROWTH = 1.5

# The data's recipe; a change here (or in the synth package) makes --out regenerate the data.
RECIPE: dict[str, Any] = {
    "version": 3,
    "airport": {"seed": 4242, "session_seed": 7, "route_m": 200.0, "changes": [4, 3, 2]},
    # The generated sets' `drifting` case at its harshest: heading drift 0.08 deg/m, one way.
    "drifting": {"session_seed": 21, "route_m": 300.0, "yaw_deg_per_m": 0.08, "scale": 0.004},
    "pool_session_seeds": [8, 9, 10],
    "scaling": {"seed": 11, "session_seed": 12, "window_px": 1000, "route_m": 120.0},
    "scaling_changes": [3, 2, 1],
}


# --------------------------------------------------------------------------------------------
# Reporting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    """One target: what was measured and whether it meets the limit (None: not measured)."""

    name: str
    measured: str
    limit: str
    ok: bool | None


def say(text: str = "") -> None:
    print(text, flush=True)


def verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else ("PASS" if ok else "FAIL")


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def fmt_ms(seconds: float) -> str:
    return f"{seconds * 1000:8.1f}"


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Data:
    airport: Path
    airport_truth: Path
    pool: list[Path]
    scaling: dict[int, Path]
    scaling_truth: Path
    drifting: Path
    drifting_truth: Path


def _recipe_stamp() -> str:
    sources = sorted(Path(synth.__file__).parent.glob("*.py"))
    text = json.dumps(RECIPE, sort_keys=True) + "".join(p.read_text() for p in sources)
    return hashlib.sha256(text.encode()).hexdigest()


def _session(
    world: OccupancyMap, seed: int, route_m: float, changes: Sequence[int], **drift: Any
) -> Any:
    n_added, n_removed, n_people = changes
    return synth.make_scenario(
        world,
        seed=seed,
        route_length_m=route_m,
        n_added=n_added,
        n_removed=n_removed,
        n_people=n_people,
        **drift,
    )


def _session_in_window(
    big: OccupancyMap, r0: int, c0: int, size: int, seed: int, route_m: float
) -> synth.SyntheticBundle:
    """A session whose route and changes lie in the window ``[r0:r0+size, c0:c0+size]`` of
    ``big``, its lidar seeing the whole building (so that no map's edge is in the local map,
    except where the 1000^2 crop itself ends)."""
    rng = np.random.default_rng(seed)
    window = _crop(big, r0, c0, size)
    route = synth.plan_route(window, length_m=route_m, rng=rng)
    n_added, n_removed, n_people = RECIPE["scaling_changes"]
    truth, changes = synth.plant_changes(
        window, route, n_added=n_added, n_removed=n_removed, n_people=n_people, rng=rng
    )
    true_state = big.state.copy()
    true_state[r0 : r0 + size, c0 : c0 + size] = truth
    session = synth.simulate_session(big, route, rng=rng, true_state=true_state, changes=changes)
    return synth.bundle_from_session(big, true_state, route, changes, session)


def _scaling_window(big: OccupancyMap, size: int) -> tuple[int, int]:
    """(row, col) of a ``size`` px square window inside the hall: mostly free space with as
    much structure as such windows have, nearest the map's centre among the best."""
    state = big.state
    h, w = state.shape
    best: tuple[float, float, int, int] | None = None
    for r in range(0, h - size + 1, size // 4):
        for c in range(0, w - size + 1, size // 4):
            window = state[r : r + size, c : c + size]
            free = float(np.mean(window == FREE))
            if free < 0.7:
                continue
            occupied = round(float(np.mean(window == OCCUPIED)), 3)
            off_centre = abs(r + size / 2 - h / 2) + abs(c + size / 2 - w / 2)
            key = (-occupied, off_centre, r, c)
            if best is None or key < best:
                best = key
    if best is None:
        raise RuntimeError("no mostly-free window in the generated airport")
    return best[2], best[3]


def _crop(big: OccupancyMap, r0: int, c0: int, size: int) -> OccupancyMap:
    """A square crop that keeps the big map's metric frame (its origin moves with the crop)."""
    ox = big.origin[0] + c0 * big.resolution
    oy = big.origin[1] + (big.height - r0 - size) * big.resolution
    state = big.state[r0 : r0 + size, c0 : c0 + size]
    return from_states(state, big.resolution, (round(ox, 6), round(oy, 6), 0.0))


def build_data(root: Path) -> Data:
    """Generate (or reuse, when the recipe is unchanged) every bundle of the benchmark."""
    stamp = _recipe_stamp()
    marker = root / "recipe.sha256"
    airport = root / "airport" / "bundles" / "airport"
    pool_dirs = [
        root / "airport" / "bundles" / f"airport-s{s}" for s in RECIPE["pool_session_seeds"]
    ]
    scaling = {s: root / "scaling" / "bundles" / f"scale-{s}" for s in SCALE_SIZES}
    data = Data(
        airport=airport,
        airport_truth=root / "airport" / "truth" / "airport.yaml",
        pool=[airport, *pool_dirs],
        scaling=scaling,
        scaling_truth=root / "scaling" / "truth" / "scale.yaml",
        drifting=root / "drifting" / "bundles" / "drifting",
        drifting_truth=root / "drifting" / "truth" / "drifting.yaml",
    )
    if marker.is_file() and marker.read_text().strip() == stamp:
        say(f"data: reusing {root}")
        return data
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    start = time.perf_counter()
    a = RECIPE["airport"]
    world = synth.make_airport_map(
        width_px=AIRPORT_PX[0], height_px=AIRPORT_PX[1], resolution=RESOLUTION, rng=a["seed"]
    )
    scenario = _session(world, a["session_seed"], a["route_m"], a["changes"])
    synth.write_scenario(
        scenario, airport.parent, airport.name, truth_path=data.airport_truth, stamp=STAMP
    )
    for seed, directory in zip(RECIPE["pool_session_seeds"], pool_dirs, strict=True):
        extra = _session(world, seed, a["route_m"], a["changes"])
        synth.write_scenario(extra, directory.parent, directory.name, stamp=STAMP)
    d = RECIPE["drifting"]
    drifting = _session(
        world,
        d["session_seed"],
        d["route_m"],
        a["changes"],
        drift_yaw_deg_per_m=d["yaw_deg_per_m"],
        drift_scale=d["scale"],
    )
    synth.write_scenario(
        drifting,
        data.drifting.parent,
        data.drifting.name,
        truth_path=data.drifting_truth,
        stamp=STAMP,
    )

    s = RECIPE["scaling"]
    big_px = SCALE_SIZES[-1]
    big = synth.make_airport_map(
        width_px=big_px, height_px=big_px, resolution=RESOLUTION, rng=s["seed"]
    )
    size = s["window_px"]
    r0, c0 = _scaling_window(big, size)
    session = _session_in_window(big, r0, c0, size, s["session_seed"], s["route_m"])
    synth.write_truth(data.scaling_truth, session.nav2_from_slam, session.changes)
    for px in SCALE_SIZES:
        # A crop centred on the window, moved inside the big map: it always holds the window.
        cr = int(np.clip(r0 + size // 2 - px // 2, 0, big_px - px))
        cc = int(np.clip(c0 + size // 2 - px // 2, 0, big_px - px))
        synth.write_bundle(
            scaling[px].parent,
            scaling[px].name,
            slam_map=session.slam_map,
            nav2_map=_crop(big, cr, cc, px),
            pose_nav2=session.pose_nav2,
            pose_slam=session.pose_slam,
            trajectory=session.trajectory,
            stamp=STAMP,
        )
    marker.write_text(stamp + "\n")
    say(f"data: generated in {time.perf_counter() - start:.1f} s under {root}")
    return data


def describe_bundle(bundle: Path) -> str:
    manifest = read_manifest(bundle)
    local = load_map(bundle / manifest.slam_map)
    assert manifest.nav2_map is not None
    nav2 = load_map(bundle / manifest.nav2_map)
    return (
        f"global {nav2.width}x{nav2.height} px, local {local.width}x{local.height} px, "
        f"{len(manifest.trajectory or [])} trajectory poses"
    )


# --------------------------------------------------------------------------------------------
# In-process runs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Runs:
    """Stage timings (ms) and wall time (s) of repeated calls on one bundle."""

    rows: list[dict[str, float]]
    walls: list[float]
    cpus: list[float]
    """CPU seconds of this process (all threads) per call: less sensitive than wall time to
    other work on the machine, and above it when OpenCV runs threads in parallel."""
    result: dict[str, Any]

    def stage(self, name: str) -> float:
        """Median of a stage, seconds."""
        return median([r.get(name, 0.0) for r in self.rows]) / 1000.0

    @property
    def wall(self) -> float:
        return median(self.walls)

    @property
    def wall_without_load(self) -> float:
        return median([w - r["load"] / 1000.0 for w, r in zip(self.walls, self.rows, strict=True)])


def run_in_process(bundle: Path, config: Config, *, runs: int, clear_cache: bool) -> Runs:
    rows, walls, cpus = [], [], []
    result: dict[str, Any] = {}
    for _ in range(runs):
        if clear_cache:
            GLOBAL_MAPS.clear()
        gc.collect()
        start, cpu = time.perf_counter(), time.process_time()
        outcome = process_bundle(bundle, config)
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
        rows.append(dict(outcome.result["timings_ms"]))
        result = outcome.result
    return Runs(rows, walls, cpus, result)


def score(result: dict[str, Any], truth_path: Path, bundle: Path) -> str:
    truth = parse_truth(yaml.safe_load(truth_path.read_text()))
    local = load_map(bundle / read_manifest(bundle).slam_map)
    s = score_bundle(truth, parse_result(result), centre_slam_xy=observed_centroid_xy(local))
    err = "-" if s.alignment_error_m is None else f"{s.alignment_error_m:.3f} m"
    return (
        f"{s.n_differences} differences: {s.n_correct} correct, {s.n_neutral} neutral, "
        f"{s.n_false_positive} false; changes found {s.n_matched}/{s.n_observed}; "
        f"precision {s.precision:.2f} recall {s.recall:.2f} F1 {s.f1:.2f}; alignment error {err}"
    )


def print_stage_table(columns: list[tuple[str, Runs]]) -> None:
    say(f"  {'stage (ms)':<12}" + "".join(f"{title:>16}" for title, _ in columns))
    for name in STAGES:
        say(f"  {name:<12}" + "".join(f"{fmt_ms(r.stage(name)):>16}" for _, r in columns))
    say(f"  {'wall':<12}" + "".join(f"{fmt_ms(r.wall):>16}" for _, r in columns))
    say(f"  {'cpu':<12}" + "".join(f"{fmt_ms(median(r.cpus)):>16}" for _, r in columns))


# --------------------------------------------------------------------------------------------
# Subprocesses: peak RSS, `mapserver process`, start-up
# --------------------------------------------------------------------------------------------

RSS_CHILD = """
import json, sys
from pathlib import Path
def status():
    out = {}
    for line in open("/proc/self/status"):
        key, _, value = line.partition(":")
        if key in ("VmHWM", "VmRSS"):
            out[key] = int(value.split()[0]) * 1024
    return out
from mapserver.config import Config
from mapserver.pipeline import process_bundle
after_import = status()
outcome = process_bundle(Path(sys.argv[1]), Config())
after = status()
print(json.dumps({"import_rss": after_import["VmRSS"], "import_hwm": after_import["VmHWM"],
                  "hwm": after["VmHWM"], "rss": after["VmRSS"]}))
"""


def peak_rss(bundle: Path) -> dict[str, int]:
    done = subprocess.run(
        [sys.executable, "-c", RSS_CHILD, str(bundle)],
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def mapserver_command() -> str:
    beside = Path(sys.executable).parent / "mapserver"
    found = str(beside) if beside.exists() else shutil.which("mapserver")
    if not found:
        raise SystemExit("no 'mapserver' command found (is the package installed?)")
    return found


def byte_compiled() -> str:
    """Compile mapserver's modules to bytecode, as any installed package has them, and say so.

    An editable install writes ``__pycache__`` on the first run, and ``pip install .`` at install
    time. With ``PYTHONDONTWRITEBYTECODE`` set (as on some build machines) neither happens, and
    every run would compile the package's source again (about 0.15 s), which is not what a user
    of the command waits for."""
    package = Path(mapserver.__file__).parent
    compileall.compile_dir(package, quiet=1)
    unset = "unset" if os.environ.get("PYTHONDONTWRITEBYTECODE") is None else "set"
    return f"bytecode compiled under {package} (PYTHONDONTWRITEBYTECODE is {unset} here)"


def time_command(command: list[str], runs: int) -> list[float]:
    walls = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(command, capture_output=True, check=True, timeout=300)
        walls.append(time.perf_counter() - start)
    return walls


# --------------------------------------------------------------------------------------------
# The naive pipeline (the prototype's way)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NaiveRun:
    seconds: float
    """Measured, plus the extrapolated rest of DBSCAN when the pixel cap cut it short."""
    measured_seconds: float
    stages: dict[str, float]
    pixels: int
    clustered: int
    boxes: int

    @property
    def extrapolated(self) -> bool:
        return self.clustered < self.pixels


def naive_process(
    bundle: Path, *, eps_m: float, min_samples: int, pixel_cap: int, threshold: int = 50
) -> NaiveRun:
    """The prototype: binarize both maps with unknown as obstacle, warp the local map with the
    pose prior onto a canvas the size of the WHOLE global map, absdiff, blur, threshold,
    dilate, DBSCAN over every difference pixel, one box per cluster."""
    from sklearn.cluster import DBSCAN

    stages: dict[str, float] = {}
    t = time.perf_counter()
    manifest = read_manifest(bundle)
    assert manifest.nav2_map is not None
    local = load_map(bundle / manifest.slam_map)
    global_map = load_map(bundle / manifest.nav2_map)
    prior = manifest.nav2_from_slam_prior()
    stages["load"] = time.perf_counter() - t

    t = time.perf_counter()
    local_bin = np.where(local.state == FREE, 0, 255).astype(np.uint8)
    global_bin = np.where(global_map.state == FREE, 0, 255).astype(np.uint8)
    matrix = warp_matrix(Grid.of_map(local), Grid.of_map(global_map), prior)
    canvas = cv2.warpAffine(
        local_bin,
        matrix,
        (global_map.width, global_map.height),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
    )
    stages["warp"] = time.perf_counter() - t

    t = time.perf_counter()
    diff = cv2.GaussianBlur(cv2.absdiff(canvas, global_bin), (5, 5), 0)
    _, mask = cv2.threshold(diff, threshold, 255, cv2.THRESH_BINARY)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    rows, cols = np.nonzero(mask)
    stages["diff"] = time.perf_counter() - t

    t = time.perf_counter()
    n = len(rows)
    take = min(n, pixel_cap)
    # Raster order: the first pixels are a band of rows, with the density of the whole.
    xy = np.stack([cols[:take], rows[:take]], axis=1).astype(np.float64) * global_map.resolution
    labels = DBSCAN(eps=eps_m, min_samples=min_samples).fit_predict(xy) if take else np.array([])
    boxes = []
    for label in np.unique(labels):
        if label >= 0:
            pts = xy[labels == label]
            boxes.append((*pts.min(axis=0), *pts.max(axis=0)))
    measured = time.perf_counter() - t
    stages["cluster"] = measured * (n / take) if take else 0.0
    total_measured = sum(stages.values()) - stages["cluster"] + measured
    return NaiveRun(sum(stages.values()), total_measured, stages, n, take, len(boxes))


# --------------------------------------------------------------------------------------------
# The daemon
# --------------------------------------------------------------------------------------------


def time_dashes(size: int) -> tuple[int, float, float]:
    """Two stages on a ``size`` x ``size`` grid of rooms 5 m square whose every wall has a
    dotted copy 0.15 m in front of it (dashes 0.2 m long every 0.4 m, each a component: a
    drifted map of a large building, seen displaced all along): the diff's wall filter
    (:func:`mapserver.diff.drop_along_walls`, with the local map) and the clustering of the
    dashes (:func:`mapserver.cluster.cluster_mask`, each dash a cluster). Returns the dashes
    and the seconds of each (best of 3)."""
    walls = np.zeros((size, size), bool)
    walls[::100, :] = True
    walls[:, ::100] = True
    added = np.zeros((size, size), bool)
    for c0 in range(0, size, 8):
        added[3::100, c0 : c0 + 4] = True
    local = np.where(walls, OCCUPIED, FREE).astype(np.uint8)
    grid = Grid(0.0, 0.0, RESOLUTION, size, size)
    n = cv2.connectedComponents(added.view(np.uint8))[0] - 1

    def best(run: Callable[[], object]) -> float:
        seconds = math.inf
        for _ in range(3):
            start = time.perf_counter()
            run()
            seconds = min(seconds, time.perf_counter() - start)
        return seconds

    walls_s = best(
        lambda: drop_along_walls(
            added, walls, resolution=RESOLUTION, within_m=0.35, local_state=local
        )
    )
    cluster_s = best(lambda: cluster_mask(added, grid, "added", eps_m=0.1, min_samples=1))
    return n, walls_s, cluster_s


def daemon_available() -> bool:
    try:
        done = subprocess.run(
            [mapserver_command(), "run", "--help"], capture_output=True, timeout=60, check=False
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _stage_bundle(source: Path, target: Path) -> None:
    """A copy of a bundle; its big global map image is hard-linked (same bytes, no disk)."""
    target.mkdir(parents=True)
    for f in source.iterdir():
        if f.suffix == ".pgm" and f.stat().st_size > MIB:
            os.link(f, target / f.name)
        else:
            shutil.copy2(f, target / f.name)


def _wait_until(check: Callable[[], bool], deadline: float, poll_s: float = 0.02) -> bool:
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(poll_s)
    return check()


@dataclass(frozen=True)
class DrainRun:
    results: int
    failed: int
    seconds: float
    startup_seconds: float
    note: str = ""


def drain_backlog(pool: Sequence[Path], n: int, work: Path, workers: int) -> DrainRun:
    """Drop ``n`` bundles into an inbox, start ``mapserver run`` on it and time the drain:
    from the daemon's ``ready`` line to the last ``result.yaml``."""
    if work.exists():
        shutil.rmtree(work)
    dirs = {k: work / k for k in ("inbox", "outbox", "archive", "failed")}
    for d in dirs.values():
        d.mkdir(parents=True)
    staging = work / "staging"
    ids = [f"backlog-{i:03d}" for i in range(n)]
    for i, bundle_id in enumerate(ids):
        _stage_bundle(pool[i % len(pool)], staging / bundle_id)
    for bundle_id in ids:  # a backlog: everything is in the inbox before the daemon starts
        (staging / bundle_id).rename(dirs["inbox"] / bundle_id)
    config = {
        **{k: str(v) for k, v in dirs.items()},
        "settle_seconds": 0.2,
        "rescan_seconds": 5.0,
        "workers": workers,
        "log_level": "INFO",
    }
    config_path = work / "config.yaml"
    config_path.write_text(yaml.safe_dump(config))
    log_path = work / "daemon.log"
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    started = time.monotonic()
    with log_path.open("w") as log_file:
        daemon = subprocess.Popen(
            [mapserver_command(), "run", "--config", str(config_path)],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            env=env,
        )
        try:

            def ready() -> bool:
                return "ready:" in log_path.read_text(errors="replace")

            if not _wait_until(ready, started + 120, poll_s=0.01):
                return DrainRun(0, 0, math.nan, math.nan, "never became ready")
            t_ready = time.monotonic()

            def done_count() -> tuple[int, int]:
                # A result folder appears whole (renamed in, result.yaml written last): count
                # the names, one directory read, not a stat per bundle (this loop shares the
                # cores with the daemon it measures).
                with os.scandir(dirs["outbox"]) as entries:
                    results = sum(1 for e in entries if not e.name.startswith("."))
                return results, sum(1 for _ in dirs["failed"].iterdir())

            finished = _wait_until(lambda: sum(done_count()) >= n, t_ready + 60 + 10 * n, 0.05)
            t_done = time.monotonic()
            results, failed = done_count()
            note = "" if finished else "timed out"
        finally:
            daemon.send_signal(signal.SIGTERM)
            try:
                daemon.wait(timeout=120)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
    return DrainRun(results, failed, t_done - t_ready, t_ready - started, note)


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer runs and bundles (< 2 min)")
    parser.add_argument("--out", type=Path, help="keep the data and daemon folders here")
    parser.add_argument("--runs", type=int, help="runs per in-process median (default 5)")
    parser.add_argument("--bundles", type=int, help="daemon backlog size (default 100; quick 20)")
    parser.add_argument("--naive-pixel-cap", type=int, help="DBSCAN pixel cap of the naive run")
    parser.add_argument("--skip-daemon", action="store_true")
    args = parser.parse_args(argv)
    quick = args.quick
    runs = args.runs or 5
    scale_runs = args.runs or (3 if quick else 5)
    n_bundles = args.bundles or (20 if quick else 100)
    cap = args.naive_pixel_cap or (200_000 if quick else 1_000_000)
    if runs < 1 or n_bundles < 1 or cap < 1:
        parser.error("--runs, --bundles and --naive-pixel-cap must be >= 1")
    cores = os.cpu_count() or 1

    say("command: " + shlex.join([sys.executable, *sys.argv]))
    say(
        f"host: {platform.node()}, {cores} cores, Python {platform.python_version()}, "
        f"numpy {np.__version__}, OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)"
    )
    say(
        f"date: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, load average "
        + " ".join(f"{v:.2f}" for v in os.getloadavg())
        + " (other work on the machine skews every figure)"
    )
    started = time.perf_counter()
    temp = None
    if args.out is None:
        temp = tempfile.mkdtemp(prefix="bench-speed-")
        out = Path(temp)
    else:
        out = args.out.resolve()
    checks: list[Check] = []
    try:
        data = build_data(out / "data")
        say(f"airport bundle: {describe_bundle(data.airport)}")
        say(f"scaling bundles: {describe_bundle(data.scaling[SCALE_SIZES[0]])} ... 8000x8000 px")
        config = Config()

        # 1. In-process, per stage.
        say()
        say(f"== 1. in-process, airport bundle (median of {runs} runs)")
        GLOBAL_MAPS.clear()
        first = run_in_process(data.airport, config, runs=1, clear_cache=True)
        uncached = run_in_process(data.airport, config, runs=runs, clear_cache=True)
        cached = run_in_process(data.airport, config, runs=runs, clear_cache=False)
        # As a daemon worker runs it (one OpenCV thread): the daemon's context, not a target.
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        one_thread = run_in_process(data.airport, config, runs=runs, clear_cache=False)
        cv2.setNumThreads(threads)
        print_stage_table(
            [
                ("first call", first),
                ("map decoded", uncached),
                ("map cached", cached),
                ("cached, 1 thr.", one_thread),
            ]
        )
        say(
            f"  global map load: {uncached.stage('load') * 1000:.1f} ms decoded each time, "
            f"{cached.stage('load') * 1000:.1f} ms from the cache "
            "(manifest, checksums and local map included in both)"
        )
        say(f"  accuracy: {score(cached.result, data.airport_truth, data.airport)}")
        checks.append(
            Check(
                "in-process, airport bundle, map cached",
                f"{cached.wall:.3f} s",
                f"<= {TARGET_IN_PROCESS_S} s",
                cached.wall <= TARGET_IN_PROCESS_S,
            )
        )
        checks.append(
            Check(
                "in-process, airport bundle, map decoded",
                f"{uncached.wall:.3f} s",
                f"<= {TARGET_IN_PROCESS_S} s",
                uncached.wall <= TARGET_IN_PROCESS_S,
            )
        )

        # 1b. A long session drifting one way: the pieces' path (issue 12).
        say()
        d = RECIPE["drifting"]
        say(
            f"== 1b. in-process, a {d['route_m']:.0f} m session in the same airport, heading drift "
            f"{d['yaw_deg_per_m']} deg/m one way (median of {runs} runs, map cached)"
        )
        say(f"  bundle: {describe_bundle(data.drifting)}")
        drift_runs = run_in_process(data.drifting, config, runs=runs, clear_cache=False)
        a = drift_runs.result["alignment"]
        stages = " ".join(
            f"{name}={drift_runs.stage(name) * 1000:.0f}"
            for name in drift_runs.result["timings_ms"]
        )
        say(f"  wall {drift_runs.wall:.3f} s; stage medians (ms): {stages}")
        say(
            f"  alignment {a['method']}, {a.get('trusted_pieces', '-')}/{a.get('pieces', '-')} "
            f"pieces trusted, drift corrected up to {a['drift_m']:.2f} m"
        )
        say(f"  accuracy: {score(drift_runs.result, data.drifting_truth, data.drifting)}")
        checks.append(
            Check(
                f"in-process, {d['route_m']:.0f} m drifting session",
                f"{drift_runs.wall:.3f} s",
                f"<= {TARGET_DRIFTING_S} s",
                drift_runs.wall <= TARGET_DRIFTING_S,
            )
        )

        # 1c. Two stages on a pathological difference (session 56: quadratic before).
        say()
        say(
            "== 1c. the diff's wall filter and the clustering on dashes along every wall (best of 3)"
        )
        per_dash: dict[str, list[float]] = {"wall filter": [], "clustering": []}
        for size in (1000, 4000):
            n, walls_s, cluster_s = time_dashes(size)
            per_dash["wall filter"].append(walls_s / n)
            per_dash["clustering"].append(cluster_s / n)
            say(
                f"  {size}^2 px, {n} dashes: wall filter {walls_s:.2f} s "
                f"({walls_s / n * 1e6:.0f} us each), clustering {cluster_s:.2f} s "
                f"({cluster_s / n * 1e6:.0f} us each)"
            )
        for name, (at_1x, at_16x) in per_dash.items():
            checks.append(
                Check(
                    f"{name}, cost per dash at 16x the dashes",
                    f"x{at_16x / at_1x:.2f}",
                    f"<= x{TARGET_PER_DASH_GROWTH}",
                    at_16x / at_1x <= TARGET_PER_DASH_GROWTH,
                )
            )

        # 2. Peak RSS in a fresh interpreter.
        say()
        say("== 2. peak RSS, one airport bundle in a fresh interpreter")
        rss = peak_rss(data.airport)
        airport_pixels = AIRPORT_PX[0] * AIRPORT_PX[1]  # one byte each
        limit = TARGET_RSS_FACTOR * airport_pixels / MIB + TARGET_RSS_EXTRA_MIB
        say(
            f"  after imports {rss['import_rss'] / MIB:.0f} MiB; peak (VmHWM) "
            f"{rss['hwm'] / MIB:.0f} MiB; limit 3 x {airport_pixels / MIB:.1f} MiB "
            f"+ 150 MiB = {limit:.0f} MiB"
        )
        checks.append(
            Check(
                "peak RSS, airport bundle",
                f"{rss['hwm'] / MIB:.0f} MiB",
                f"<= {limit:.0f} MiB",
                rss["hwm"] / MIB <= limit,
            )
        )

        # 3. `mapserver process`, start-up included.
        say()
        say("== 3. `mapserver process` on the airport bundle (wall, median of 5)")
        cli = mapserver_command()
        say(f"  {byte_compiled()}")
        cli_config = out / "cli-config.yaml"
        cli_config.write_text(yaml.safe_dump({"log_level": "WARNING"}))
        startup = median(time_command([cli, "--help"], 5))
        walls = time_command(
            [
                cli,
                "process",
                "--config",
                str(cli_config),
                "--outbox",
                str(out / "cli-outbox"),
                str(data.airport),
            ],
            5,
        )
        say(f"  start-up alone (`mapserver --help`): {startup:.3f} s")
        say(f"  runs: {', '.join(f'{w:.3f}' for w in walls)} s -> median {median(walls):.3f} s")
        checks.append(
            Check(
                "`mapserver process`, airport bundle",
                f"{median(walls):.3f} s",
                f"<= {TARGET_CLI_S} s",
                median(walls) <= TARGET_CLI_S,
            )
        )

        # 4. Scaling over the global map's size, the same local map.
        say()
        say(
            f"== 4. scaling: the same session, global maps of 1000^2 .. 8000^2 px "
            f"(median of {scale_runs} runs)"
        )
        say(
            f"  {'global px':<10}{'decoded':>10}{'cached':>10}{'w/o load':>10}"
            f"{'load dec.':>11}{'load cached':>13}   accuracy"
        )
        curve: dict[int, tuple[Runs, Runs]] = {}
        for px in SCALE_SIZES:
            bundle = data.scaling[px]
            GLOBAL_MAPS.clear()
            dec = run_in_process(bundle, config, runs=scale_runs, clear_cache=True)
            hot = run_in_process(bundle, config, runs=scale_runs, clear_cache=False)
            curve[px] = (dec, hot)
            accuracy = score(hot.result, data.scaling_truth, bundle)
            brief = ";".join(accuracy.split(";")[2:]).strip()
            say(
                f"  {px:<10}{fmt_ms(dec.wall):>10}{fmt_ms(hot.wall):>10}"
                f"{fmt_ms(hot.wall_without_load):>10}{fmt_ms(dec.stage('load')):>11}"
                f"{fmt_ms(hot.stage('load')):>13}   {brief}"
            )
        small, large = curve[SCALE_SIZES[0]][1], curve[SCALE_SIZES[-1]][1]
        growth = large.wall_without_load / small.wall_without_load
        growth_cached = large.wall / small.wall
        dec_small, dec_large = curve[SCALE_SIZES[0]][0], curve[SCALE_SIZES[-1]][0]
        say(
            f"  growth 1000^2 -> 8000^2: {growth:.2f}x without the load, {growth_cached:.2f}x "
            f"with the load from the cache, {dec_large.wall / dec_small.wall:.2f}x decoding it "
            "every time"
        )
        say(
            f"  loading the 8000^2 global map once per bundle costs "
            f"{dec_large.stage('load') * 1000:.0f} ms decoded, "
            f"{large.stage('load') * 1000:.0f} ms from the cache (the 1000^2 one "
            f"{dec_small.stage('load') * 1000:.0f} / {small.stage('load') * 1000:.0f} ms)"
        )
        checks.append(
            Check(
                "scaling 1000^2 -> 8000^2, w/o load",
                f"{growth:.2f}x",
                f"<= {TARGET_SCALING:.0f}x",
                growth <= TARGET_SCALING,
            )
        )
        checks.append(
            Check(
                "scaling 1000^2 -> 8000^2, cached load",
                f"{growth_cached:.2f}x",
                f"<= {TARGET_SCALING:.0f}x",
                growth_cached <= TARGET_SCALING,
            )
        )

        # 5. The naive pipeline on the same bundles.
        say()
        say(
            f"== 5. naive pipeline (full-canvas warp, DBSCAN over every difference pixel, "
            f"capped at {cap:,} pixels and extrapolated linearly beyond)"
        )
        d = config.pipeline.diff
        naive_targets = [("airport", data.airport, uncached)]
        if not quick:
            naive_targets += [(f"scale-{px}", data.scaling[px], curve[px][0]) for px in SCALE_SIZES]
        say(
            f"  {'bundle':<12}{'naive s':>10}{'measured s':>12}{'diff px':>12}{'boxes':>7}"
            f"{'ours s':>9}{'ratio':>8}   naive stages (s)"
        )
        for name, bundle, ours in naive_targets:
            gc.collect()
            naive = naive_process(
                bundle, eps_m=d.cluster_eps_m, min_samples=d.cluster_min_samples, pixel_cap=cap
            )
            ratio = naive.seconds / ours.wall
            stages = " ".join(f"{k}={v:.2f}" for k, v in naive.stages.items())
            mark = "*" if naive.extrapolated else " "
            say(
                f"  {name:<12}{naive.seconds:>9.2f}{mark}{naive.measured_seconds:>12.2f}"
                f"{naive.pixels:>12,}{naive.boxes:>7}{ours.wall:>9.3f}{ratio:>7.1f}x   {stages}"
            )
            if name == "airport":
                checks.append(
                    Check(
                        "naive / ours, airport bundle",
                        f"{ratio:.1f}x" + (" (extrapolated)" if naive.extrapolated else ""),
                        f">= {TARGET_NAIVE_RATIO:.0f}x",
                        ratio >= TARGET_NAIVE_RATIO,
                    )
                )
        say("  * DBSCAN extrapolated from the capped pixels; ours = map decoded every time")

        # 6. The daemon's backlog.
        say()
        workers = cores
        say(f"== 6. daemon: a backlog of {n_bundles} airport bundles, {workers} workers")
        # The backlog cycles through the pool's sessions, some harder than others: the
        # single-bundle rate is the pool's, one of each processed in-process (map cached).
        pool_walls = {
            b.name: run_in_process(b, config, runs=runs, clear_cache=False).wall for b in data.pool
        }
        pool_wall = statistics.fmean(pool_walls.values())
        rate = 1.0 / pool_wall
        needed = TARGET_DRAIN * workers * rate
        say(
            "  in-process, map cached (median of each): "
            + ", ".join(f"{name} {wall:.3f} s" for name, wall in pool_walls.items())
            + f"; mean {pool_wall:.3f} s"
        )
        if args.skip_daemon:
            say("  daemon: skipped (--skip-daemon)")
            checks.append(Check("daemon backlog drain", "skipped", f">= {needed:.2f}/s", None))
        elif not daemon_available():
            say("  daemon: not available (`mapserver run --help` fails)")
            checks.append(Check("daemon backlog drain", "not available", "", None))
        else:
            drain = drain_backlog(data.pool, n_bundles, out / "daemon", workers)
            got = drain.results / drain.seconds if drain.seconds > 0 else 0.0
            say(
                f"  {drain.results} results, {drain.failed} failed in {drain.seconds:.1f} s after "
                f"`ready` (start-up to ready {drain.startup_seconds:.1f} s) {drain.note}"
            )
            say(
                f"  drain rate {got:.2f} bundles/s; single-bundle rate of the pool {rate:.2f}/s; "
                f"target 0.8 x {workers} x {rate:.2f} = {needed:.2f}/s"
            )
            worker_share = one_thread.wall / cached.wall  # one OpenCV thread, as a worker has
            say(
                f"  (a worker has one OpenCV thread: in-process so, the airport bundle takes "
                f"{worker_share:.2f}x as long; the drain is "
                f"{got * worker_share / (workers * rate):.2f} x workers x that rate)"
            )
            checks.append(
                Check(
                    "daemon backlog drain",
                    f"{got:.2f}/s ({got / (workers * rate):.2f} x workers x single)",
                    f">= {needed:.2f}/s",
                    drain.failed == 0 and drain.results == n_bundles and got >= needed,
                )
            )
            shutil.rmtree(out / "daemon", ignore_errors=True)
    finally:
        if temp is not None:
            shutil.rmtree(temp, ignore_errors=True)

    say()
    say("== targets (issues 4 and 12)")
    width = max(len(c.name) for c in checks)
    for c in checks:
        say(f"  {c.name:<{width}}  {c.measured:>26}  {c.limit:>14}  {verdict(c.ok)}")
    say(
        f"benchmark wall time {time.perf_counter() - started:.0f} s, load average "
        + " ".join(f"{v:.2f}" for v in os.getloadavg())
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
