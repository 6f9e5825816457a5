"""Regenerate the sample bundles shipped for `mapserver demo` (mapserver/data/samples/).

    .venv/bin/python benchmarks/make_samples.py [OUT_DIR]

Deterministic: the same seeds give the same bundles. The depot sample's global map is Nav2's
depot map (Apache-2.0, see tests/data/maps/SOURCES.md); the office one is generated.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from mapserver import synth
from mapserver.maps import load_map

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
    office = synth.make_office_map(rng=7)
    scenario = synth.make_scenario(
        office, seed=11, route_length_m=30.0, n_added=2, n_removed=1, n_people=1
    )
    synth.write_scenario(
        scenario, out, "office-demo-02", robot="demo-02", stamp="2026-11-21T11:40:00Z"
    )
    for d in sorted(out.iterdir()):
        print(d, sum(f.stat().st_size for f in d.iterdir()) // 1024, "KiB")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "mapserver" / "data" / "samples")
