"""benchmarks/census.py: where the pipeline lost each missed change, what let each false
positive through, on a generated bundle whose truth the test edits (a change planted where
nothing changed, a real one taken out)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import yaml
from bench_support import benchmark_module

from mapserver import pipeline, synth
from mapserver import refit as refit_stage
from mapserver.config import load_config
from mapserver.maps import FREE, OCCUPIED, UNKNOWN


@pytest.fixture(scope="module")
def census() -> Iterator[ModuleType]:
    with benchmark_module("census") as module:
        yield module


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    """A one-bundle set, the pipeline's result for it in an outbox, and its truth document."""
    root = tmp_path_factory.mktemp("census")
    office = synth.make_office_map(width_m=26, height_m=18, rng=11)
    scenario = synth.make_scenario(
        office, seed=5, route_length_m=20, n_added=3, n_removed=2, n_people=0
    )
    set_dir = root / "set"
    truth_path = set_dir / "s1" / "truth" / "b1.yaml"
    truth_path.parent.mkdir(parents=True)
    bundle = synth.write_scenario(
        scenario,
        set_dir / "s1" / "bundles",
        "b1",
        truth_path=truth_path,
        stamp="2026-11-27T10:00:00Z",
    )
    outcome = pipeline.process_bundle(bundle, load_config(None))
    outbox = root / "outbox"
    (outbox / "b1").mkdir(parents=True)
    (outbox / "b1" / "result.yaml").write_text(yaml.safe_dump(outcome.result))
    return set_dir, outbox, yaml.safe_load(truth_path.read_text())


def test_a_change_nothing_shows_is_lost_at_the_mask_and_an_unlisted_one_is_a_false_positive(
    census: ModuleType, run: tuple[Path, Path, dict], capsys: pytest.CaptureFixture[str]
) -> None:
    set_dir, outbox, truth = run
    result = yaml.safe_load((outbox / "b1" / "result.yaml").read_text())
    found = [d for d in result["differences"] if d["kind"] == "added"]
    assert found, "the session reports its planted obstacles"
    # The truth edited: the first added change taken out (what was reported there is now a
    # false positive), and an obstacle planted on the robot's own route (free floor in both
    # maps: nothing in the difference mask there).
    first = min(
        (c for c in truth["changes"] if c["kind"] == "added"),
        key=lambda c: np.hypot(
            *(
                np.mean(c["polygon"], axis=0)
                - [found[0]["centroid"]["x"], found[0]["centroid"]["y"]]
            )
        ),
    )
    manifest = yaml.safe_load((set_dir / "s1" / "bundles" / "b1" / "bundle.yaml").read_text())
    x, y = manifest["pose"]["nav2"]["x"], manifest["pose"]["nav2"]["y"]
    planted = {
        "id": 99,
        "kind": "added",
        "polygon": [[x - 0.2, y - 0.2], [x + 0.2, y - 0.2], [x + 0.2, y + 0.2], [x - 0.2, y + 0.2]],
        "observed": True,
    }
    edited = {**truth, "changes": [c for c in truth["changes"] if c is not first] + [planted]}
    (set_dir / "s1" / "truth" / "b1.yaml").write_text(yaml.safe_dump(edited))
    originals = {(m, n): getattr(m, n) for m, n in census.OBSERVED}

    assert census.main([str(set_dir), str(outbox), "--all"]) == 0

    out = capsys.readouterr().out
    miss = next(line for line in out.splitlines() if "MISS 99 added" in line)
    assert "mask 0;" in miss and miss.endswith("-> no mask")
    assert f"FP #{found[0]['id']} added" in out
    summary = out[out.index("== misses by the stage") :].splitlines()
    assert summary[1:] == ["  added    no mask           1"]
    # The pipeline is left as it was.
    assert all(getattr(m, n) is f for (m, n), f in originals.items())


def test_the_observers_record_each_checks_verdict_on_the_cells_it_judged(
    census: ModuleType,
) -> None:
    # A removed difference inside a block whose floor all round went unseen: the floor check
    # explains it (share 0 < the pipeline's threshold); the faces check sees no wall round it.
    global_state = np.full((20, 20), FREE, np.uint8)
    global_state[8:12, 8:12] = OCCUPIED
    local_state = np.full((20, 20), UNKNOWN, np.uint8)
    local_state[9:11, 9:11] = FREE
    cells = np.argwhere(local_state == FREE)
    trace = census.Trace()
    before = refit_stage.floor_seen_share
    with census.observing(trace):
        share = refit_stage.floor_seen_share(cells, global_state, local_state, resolution=0.05)
        faces = refit_stage.faces_seen_from_behind(
            cells, global_state == OCCUPIED, local_state, resolution=0.05
        )
    assert share == 0.0
    verdicts = trace.verdicts[census._key(cells)]
    assert [(v.check, v.explained) for v in verdicts] == [
        ("floor", True),
        ("faces", pipeline._folded(faces, 0.05)),
    ]
    assert verdicts[0].value == "0.00"
    assert refit_stage.floor_seen_share is before  # undone on exit
