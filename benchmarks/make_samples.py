"""Regenerate the sample bundles shipped for `mapserver demo` (mapserver/data/samples/).

    .venv/bin/python benchmarks/make_samples.py [OUT_DIR]

Deterministic: the same seeds give the same bundles. The depot sample's global map is Nav2's
depot map (Apache-2.0, see tests/data/maps/SOURCES.md); the office one is generated.

The depot is patrolled three times over a day (depot-demo-01, -03, -04: the same route, other
robots, new sensor noise): its added and removed obstacles are still there each time, the person
of the first session is gone. Three sessions over 12 hours: the demo's fleet map publishes them.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from mapserver import synth
from mapserver.maps import OccupancyMap, load_map

ROOT = Path(__file__).resolve().parents[1]
DEPOT = ROOT / "tests" / "data" / "maps" / "nav2_depot" / "depot.yaml"


def main(out: Path) -> None:
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    depot = load_map(DEPOT)
    scenario = synth.make_scenario(
        depot, seed=20261121, route_length_m=28.0, n_added=3, n_removed=1, n_people=1
    )
    synth.write_scenario(
        scenario, out, "depot-demo-01", robot="demo-01", stamp="2026-11-21T10:15:00Z"
    )
    world = _without_people(scenario)
    lasting = tuple(c for c in scenario.changes if c.kind != "temporary")
    for seed, bundle_id, robot, stamp in (
        (31, "depot-demo-03", "demo-03", "2026-11-21T19:40:00Z"),
        (32, "depot-demo-04", "demo-01", "2026-11-22T08:05:00Z"),
    ):
        session = synth.simulate_session(
            scenario.world, scenario.route, rng=seed, true_state=world, changes=lasting
        )
        again = synth.bundle_from_session(scenario.world, world, scenario.route, lasting, session)
        synth.write_scenario(again, out, bundle_id, robot=robot, stamp=stamp)
    office = synth.make_office_map(rng=7)
    scenario = synth.make_scenario(
        office, seed=11, route_length_m=30.0, n_added=2, n_removed=1, n_people=1
    )
    synth.write_scenario(
        scenario, out, "office-demo-02", robot="demo-02", stamp="2026-11-21T11:40:00Z"
    )
    for d in sorted(out.iterdir()):
        print(d, sum(f.stat().st_size for f in d.iterdir()) // 1024, "KiB")


def _without_people(scenario: synth.SyntheticBundle) -> np.ndarray:
    """The session's true world with its people gone (their cells as in the global map)."""
    world: OccupancyMap = scenario.world
    state = scenario.true_state.copy()
    for change in scenario.changes:
        if change.kind != "temporary":
            continue
        cols, rows = world.world_to_pixel(*np.array(change.polygon).T)
        mask = np.zeros(state.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(np.stack([cols, rows], 1)).astype(np.int32)], 1)
        mask = cv2.dilate(mask, np.ones((5, 5), np.uint8)).astype(bool)
        state[mask] = world.state[mask]
    return state


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "mapserver" / "data" / "samples")
