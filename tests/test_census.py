"""benchmarks/census.py: where the pipeline lost each missed change and what let each false
positive through, on generated bundles whose truth the tests edit (a change planted where
nothing changed, a real one taken out), and its verdicts against what the re-fit drops."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import yaml
from bench_support import benchmark_module, one_bundle_set

from mapserver import cluster as cluster_stage
from mapserver import piecewise, pipeline, synth
from mapserver import refit as refit_stage
from mapserver.cluster import Difference
from mapserver.config import load_config
from mapserver.diff import DiffMasks
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED, UNKNOWN
from mapserver.scoring import Change, parse_result, parse_truth

STAMP = "2026-11-27T10:00:00Z"


@pytest.fixture(scope="module")
def census() -> Iterator[ModuleType]:
    with benchmark_module("census") as module:
        yield module


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 20 m office session without drift (the re-fit does not run)."""
    office = synth.make_office_map(width_m=26, height_m=18, rng=11)
    scenario = synth.make_scenario(
        office, seed=5, route_length_m=20, n_added=3, n_removed=2, n_people=0
    )
    return one_bundle_set(tmp_path_factory.mktemp("clean"), scenario, STAMP)


@pytest.fixture
def edited(clean: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path, dict[str, Any], int]:
    """A copy of the clean set whose truth has the change nearest the first reported added
    difference taken out (that difference is now a false positive, its id returned) and an
    obstacle planted on the robot's own route (change 99: free floor in both maps)."""
    set_dir, outbox = clean
    copy = tmp_path / "set"
    shutil.copytree(set_dir, copy)
    truth_path = copy / "s1" / "truth" / "b1.yaml"
    truth = yaml.safe_load(truth_path.read_text())
    result = yaml.safe_load((outbox / "b1" / "result.yaml").read_text())
    first = next(d for d in result["differences"] if d["kind"] == "added")
    at = np.array([first["centroid"]["x"], first["centroid"]["y"]])
    taken = min(
        (c for c in truth["changes"] if c["kind"] == "added"),
        key=lambda c: np.hypot(*(np.mean(c["polygon"], axis=0) - at)),
    )
    pose = yaml.safe_load((copy / "s1" / "bundles" / "b1" / "bundle.yaml").read_text())["pose"]
    x, y = pose["nav2"]["x"], pose["nav2"]["y"]
    planted = {
        "id": 99,
        "kind": "added",
        "polygon": [[x - 0.2, y - 0.2], [x + 0.2, y - 0.2], [x + 0.2, y + 0.2], [x - 0.2, y + 0.2]],
        "observed": True,
    }
    truth["changes"] = [c for c in truth["changes"] if c is not taken] + [planted]
    truth_path.write_text(yaml.safe_dump(truth))
    return copy, outbox, truth, int(first["id"])


def _run(
    census: ModuleType, set_dir: Path, outbox: Path, every: bool, config: Path | None = None
) -> tuple[Any, list[str]]:
    """The census of bundle b1 (with the configuration file ``config``): its counts and
    lines."""
    case = census.find_cases(set_dir)[0]
    truth = parse_truth(yaml.safe_load(case.truth_path.read_text()))
    result_path = outbox / "b1" / "result.yaml"
    result = parse_result(yaml.safe_load(result_path.read_text())) if result_path.exists() else None
    counts = census.Census()
    lines = census.census_of_bundle(case, truth, result, load_config(config), counts, every=every)
    return counts, lines


def test_a_change_nothing_shows_is_lost_before_any_difference_and_an_unlisted_one_is_a_false_positive(
    census: ModuleType, edited: tuple[Path, Path, dict[str, Any], int]
) -> None:
    set_dir, outbox, _, fp_id = edited
    counts, lines = _run(census, set_dir, outbox, every=True)

    miss = next(line for line in lines if "MISS 99 added" in line)
    assert "raw 0, mask 0;" in miss and miss.endswith("-> no difference")
    assert counts.misses[("added", "no difference")] == 1
    fp = next(line for line in lines if line.startswith(f"  FP #{fp_id} added"))
    # The map did not drift: no re-fit check ran on it (the same difference in the re-run).
    assert fp.endswith("no re-fit (the map did not drift)")
    assert not any("MISMATCH" in line for line in lines)
    # Without a re-fit only the removed differences are judged, by the faint-strip check
    # alone (explain.faint), which keeps these.
    assert counts.judged and all(
        kind == "removed" and check == "reported" for kind, check, _ in counts.judged
    )


def test_the_command_prints_the_misses_and_the_summary_and_leaves_the_pipeline_as_it_was(
    census: ModuleType,
    edited: tuple[Path, Path, dict[str, Any], int],
    capsys: pytest.CaptureFixture[str],
) -> None:
    set_dir, outbox, _, fp_id = edited
    originals = {(m, n): getattr(m, n) for m, n in census.OBSERVED}
    assert census.main([str(set_dir), str(outbox)]) == 0
    out = capsys.readouterr().out
    assert "-> no difference" in out and f"FP #{fp_id} added" in out
    summary = out[out.index("== misses by the stage that lost them") :].splitlines()[1:]
    assert any(line.split() == ["added", "no", "difference", "1"] for line in summary)
    assert all(getattr(m, n) is f for (m, n), f in originals.items())


def test_a_bundle_that_fails_loses_its_changes_before_the_comparison(
    census: ModuleType, clean: tuple[Path, Path], tmp_path: Path
) -> None:
    set_dir, _ = clean
    copy = tmp_path / "set"
    shutil.copytree(set_dir, copy)
    (copy / "s1" / "bundles" / "b1" / "slam_map.pgm").write_bytes(b"P5\n")  # damaged
    empty = tmp_path / "outbox"  # bench_public writes no result for a failed bundle
    empty.mkdir()
    truth = parse_truth(yaml.safe_load((copy / "s1" / "truth" / "b1.yaml").read_text()))
    observed = [c for c in truth.changes if c.structural and c.observed]

    counts, lines = _run(census, copy, empty, every=False)

    assert lines[0].startswith("== b1: failed (")
    assert sum(counts.misses.values()) == len(observed) > 0
    assert set(stage for _, stage in counts.misses) == {"not compared"}


def test_an_untrusted_alignment_loses_its_changes_before_the_comparison(
    census: ModuleType, edited: tuple[Path, Path, dict[str, Any], int], tmp_path: Path
) -> None:
    # No alignment reaches a score of 1: nothing is compared, every miss is lost there, and
    # the re-run no longer reports what the outbox holds.
    set_dir, outbox, _, _ = edited
    config = tmp_path / "untrusting.yaml"
    config.write_text(yaml.safe_dump({"pipeline": {"align": {"min_score": 1.0}}}))
    counts, lines = _run(census, set_dir, outbox, every=False, config=config)
    assert lines[0].startswith("== b1: trusted False")
    assert any(line.startswith("  MISMATCH: the re-run reports 0 differences") for line in lines)
    assert counts.misses[("added", "not compared")] >= 1
    assert set(stage for _, stage in counts.misses) == {"not compared"}


@pytest.mark.parametrize(
    ("seed", "checks"), [(3, {"floor", "refit", "pass"}), (6, {"faces", "pass", "ghost"})]
)
def test_the_verdicts_recorded_drop_exactly_what_the_refit_drops(
    census: ModuleType,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    seed: int,
    checks: set[str],
) -> None:
    # A 70 m session drifting 0.1 degrees per metre one way: aligned in pieces and re-fitted,
    # the re-fit's checks deciding (each seed's named ones at least once).
    office = synth.make_office_map(width_m=30, height_m=20, rng=11)
    scenario = synth.make_scenario(
        office,
        seed=seed,
        route_length_m=70,
        n_added=4,
        n_removed=3,
        n_people=0,
        drift_yaw_deg_per_m=0.1,
        drift_scale=0.005,
    )
    bundle = synth.write_scenario(scenario, tmp_path, "b1", stamp=STAMP)
    judged: list[Any] = []
    kept_by_refit: list[Any] = []
    refit = pipeline._refit

    def recording_refit(differences: list[Any], *args: Any, **kwargs: Any) -> Any:
        kept = refit(differences, *args, **kwargs)
        judged.extend(differences)
        kept_by_refit.extend(kept)
        return kept

    monkeypatch.setattr(pipeline, "_refit", recording_refit)
    trace = census.Trace()
    with census.observing(trace):
        pipeline.process_bundle(bundle, load_config(None))

    # The raw masks recorded too, the filtered ones inside them.
    assert trace.raw is not None and trace.masks is not None and trace.masks.added.any()
    assert not (trace.masks.added & ~trace.raw.added).any()
    deciding = set()
    for difference in judged:
        verdicts = trace.of(difference)
        assert verdicts, "every difference the re-fit judged has its checks recorded"
        dropped = all(difference is not k for k in kept_by_refit)
        assert (census.decided(verdicts) != "reported") == dropped
        # The checks after the one that explained it were not asked.
        explained = [v.explained for v in verdicts]
        assert explained.count(True) <= 1 and (not any(explained) or explained[-1])
        deciding.add(census.decided(verdicts))
    # The left-out check is found on the cells' nav2 points (the pieces of these seeds leave
    # some out), and asked of removed differences only.
    asked = {(d.kind, v.check) for d in judged for v in trace.of(d)}
    assert ("removed", "left out") in asked and ("added", "left out") not in asked
    # Each of the seed's checks decided at least once (others may too: which check explains a
    # wall seen twice moves with the alignment's last millimetres).
    assert checks | {"reported"} <= deciding


def test_the_observers_record_each_checks_verdict_and_are_undone_whatever_happens(
    census: ModuleType,
) -> None:
    # A removed difference inside a block whose floor all round went unseen: the floor check
    # explains it (share 0 < the pipeline's threshold); no local wall lies round it to be seen
    # from behind, so the faces check does not.
    global_state = np.full((20, 20), FREE, np.uint8)
    global_state[8:12, 8:12] = OCCUPIED
    local_state = np.full((20, 20), UNKNOWN, np.uint8)
    local_state[9:11, 9:11] = FREE
    cells = np.argwhere(local_state == FREE)
    originals = {(m, n): getattr(m, n) for m, n in census.OBSERVED}
    trace = census.Trace()
    with pytest.raises(RuntimeError, match="stop"), census.observing(trace):
        share = refit_stage.floor_seen_share(cells, global_state, local_state, resolution=0.05)
        faces = refit_stage.faces_seen_from_behind(
            cells, global_state == OCCUPIED, local_state, resolution=0.05
        )
        band = refit_stage.band_in_structure(
            cells, global_state == OCCUPIED, local_state, resolution=0.05
        )
        raise RuntimeError("stop")
    assert share == 0.0 and faces.walls == 0
    verdicts = trace.verdicts[census._key(cells)]
    assert [(v.check, v.explained, v.shown) for v in verdicts] == [
        ("floor", True, "0.00"),
        ("faces", False, f"depth {faces.depth_m:.2f} m, walls 0, behind {faces.behind_share:.2f}"),
        # No local wall at its inner edge: not a face seen displaced.
        ("band", False, f"depth 0.10 m, length 0.10 m, inner {band.inner}, walled 0.00"),
    ]
    assert all(getattr(m, n) is f for (m, n), f in originals.items())


def test_a_removal_a_left_out_piece_explains_is_judged_by_that_check_in_the_refits_order(
    census: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The left-out check is given the difference's cells as nav2 points, not the cells: its
    # verdict is found from them, after the checks asked before it (session 27: the census
    # called such a miss "reported", a cluster that survived, though the re-fit dropped it).
    grid = Grid(-1.0, 2.0, 0.05, 40, 40)
    cells = np.array([[3, 4], [3, 5], [4, 4]])
    difference = _difference("removed", cells)
    monkeypatch.setattr(piecewise, "left_out_pass_near", lambda *args, **kwargs: True)
    trace = census.Trace(grid=grid)
    with census.observing(trace):
        xy = grid.to_world(cells[:, ::-1].astype(float))
        assert piecewise.left_out_pass_near(None, None, xy, ratio=2.0, reach_m=12.0)
        refit_stage.floor_seen_share(
            cells,
            np.full((40, 40), OCCUPIED, np.uint8),
            np.full((40, 40), FREE, np.uint8),
            resolution=0.05,
        )

    verdicts = trace.of(difference)
    assert [(v.check, v.explained) for v in verdicts] == [("floor", False), ("left out", True)]
    assert census.decided(verdicts) == "left out"


def _difference(kind: str, cells: np.ndarray) -> Difference:
    return Difference(kind, (0.6, 0.6), (0.5, 0.5, 0.7, 0.7), 0.01 * len(cells), len(cells), cells)


@pytest.mark.parametrize(
    "stage",
    ["not compared", "no difference", "diff filters", "clusters", "judged", "reported"],
)
def test_each_miss_is_put_at_the_stage_that_lost_it(census: ModuleType, stage: str) -> None:
    grid = Grid(0.0, 0.0, 0.05, 40, 40)  # 2 m x 2 m
    change = Change(7, "removed", np.array([[0.5, 0.5], [0.7, 0.5], [0.7, 0.7], [0.5, 0.7]]), True)
    box, in_box, _ = census.polygon_cells(grid, change, 0)
    inside = np.zeros(grid.shape, bool)
    inside[box] = in_box
    cells = np.argwhere(inside)
    none = np.zeros(grid.shape, bool)
    order = census.STAGES
    trace = census.Trace(
        compared=stage != "not compared",
        grid=grid,
        raw=DiffMasks(none, inside if order.index(stage) > 1 else none),
        masks=DiffMasks(none, inside if order.index(stage) > 2 else none),
        evidence=inside,
    )
    if order.index(stage) > 3:
        kept = _difference("removed", cells)
        trace.clusters.append(kept)
        trace.kept.append(kept)
        trace.verdicts[census._key(cells)] = [
            census.Verdict("floor", stage == "judged", "0.50"),
            *([census.Verdict("faces", False, "no walls")] if stage == "reported" else []),
        ]

    found, line = census.miss_line(change, trace)

    assert found == stage and line.endswith(f"-> {stage}")
    assert line.startswith("MISS 7 removed at (0.60,0.60) 0.20x0.20 m")
    if stage != "not compared":
        assert f"raw {int(order.index(stage) > 1) * len(cells)}," in line


def test_a_miss_says_how_much_of_it_the_local_map_saw_and_how_much_was_left_out(
    census: ModuleType,
) -> None:
    grid = Grid(0.0, 0.0, 0.05, 40, 40)
    change = Change(7, "removed", np.array([[0.5, 0.5], [0.7, 0.5], [0.7, 0.7], [0.5, 0.7]]), True)
    box, inside, _ = census.polygon_cells(grid, change, 0)
    none = np.zeros(grid.shape, bool)
    rows = np.flatnonzero(inside.any(axis=1)) + box[0].start
    assert rows.tolist() == [26, 27, 28, 29, 30] and inside.sum() == 20  # 4 cells a row
    # Its first two rows seen; the third left out (unknown in the map compared, as the
    # pipeline leaves it).
    local_state = np.full(grid.shape, UNKNOWN, np.uint8)
    local_state[:28, :] = FREE
    left_out = np.zeros(grid.shape, bool)
    left_out[28, :] = True
    trace = census.Trace(
        compared=True,
        grid=grid,
        raw=DiffMasks(none, none),
        masks=DiffMasks(none, none),
        local_state=local_state,
        left_out=left_out,
    )

    stage, line = census.miss_line(change, trace)

    assert stage == "no difference"
    assert "polygon 20 cells (seen 8, left out 4), raw 0," in line


def test_the_fleets_own_comparison_is_not_recorded(
    census: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    # With a map store, the pipeline compares again against the stored map's current version
    # (pipeline._judged_on_current), with the same clustering and checks: not the bundle's
    # own comparison, so the census records nothing of it.
    grid = Grid(0.0, 0.0, 0.05, 20, 20)
    mask = np.zeros(grid.shape, bool)
    mask[5:9, 5:9] = True

    def clusters() -> list[Difference]:
        return cluster_stage.cluster_mask(mask, grid, "added", eps_m=0.3, min_samples=3)

    monkeypatch.setattr(pipeline, "_judged_on_current", lambda *args, **kwargs: clusters())
    trace = census.Trace()
    with census.observing(trace):
        on_current = pipeline._judged_on_current()
        assert not trace.kept and not trace.paused
        own = clusters()
    assert len(on_current) == len(own) == 1 and trace.kept == own


def test_the_counts_written_as_json_add_up_over_sets_as_the_census_counts_them(
    census: ModuleType,
    edited: tuple[Path, Path, dict[str, Any], int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--counts`` writes what the summary prints; two sets' documents added up count every
    miss twice (what ``run_sets.py census`` pools)."""
    set_dir, outbox, _, _ = edited
    counts_path = tmp_path / "counts.json"
    assert census.main([str(set_dir), str(outbox), "--counts", str(counts_path)]) == 0
    capsys.readouterr()
    doc = json.loads(counts_path.read_text())
    assert ["added", "no difference", 1] in doc["misses"]
    pooled = census.Census()
    pooled.add_doc(doc)
    pooled.add_doc(doc)
    assert pooled.misses[("added", "no difference")] == 2
    assert sum(pooled.misses.values()) == 2 * sum(n for *_, n in doc["misses"])
    assert pooled.to_doc()["misses"] == [[*key, 2 * n] for *key, n in doc["misses"]]


def test_run_sets_census_runs_the_census_on_each_set_and_pools_its_counts(
    edited: tuple[Path, Path, dict[str, Any], int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``run_sets.py census``'s own path for one set: census.py in a subprocess on the set and
    the run's outbox of it, its lines kept beside the run and its counts returned."""
    set_dir, outbox, _, fp_id = edited
    run_dir = tmp_path / "run"
    shutil.copytree(outbox, run_dir / "one")
    with benchmark_module("run_sets") as rs:
        line, counts = rs._census_one(
            rs.BenchSet("one", "tuning", (), set_dir), run_dir, None, False
        )
    assert line == f"one          misses: 1 added, 0 removed  ({run_dir / 'census' / 'one.txt'})"
    assert counts == json.loads((run_dir / "census" / "one.json").read_text())
    assert ["added", "no difference", 1] in counts["misses"]
    # Not among the run's documents: compare reads every JSON document there as a set's.
    assert [p.name for p in run_dir.glob("*.json")] == []
    text = (run_dir / "census" / "one.txt").read_text()
    assert "MISS 99 added" in text and f"FP #{fp_id} added" in text


def test_the_judged_differences_written_as_json_lines_are_the_ones_the_census_counts(
    census: ModuleType,
    edited: tuple[Path, Path, dict[str, Any], int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--judged`` (every bundle and judged difference, without ``--all`` given) writes one
    JSON line per judged difference: its label and deciding check as the counts have them,
    and the values each check measured."""
    set_dir, outbox, _, _ = edited
    judged_path, counts_path = tmp_path / "judged.jsonl", tmp_path / "counts.json"
    argv = [str(set_dir), str(outbox), "--judged", str(judged_path), "--counts", str(counts_path)]
    assert census.main(argv) == 0
    capsys.readouterr()
    records = [json.loads(line) for line in judged_path.read_text().splitlines()]
    counted = json.loads(counts_path.read_text())["judged"]
    assert records and len(records) == sum(n for *_, n in counted)
    tally: dict[tuple[str, str, str], int] = {}
    for r in records:
        key = (r["kind"], r["decided"], r["label"])
        tally[key] = tally.get(key, 0) + 1
    assert sorted([*k, n] for k, n in tally.items()) == sorted(counted)
    for r in records:
        assert r["set"] == set_dir.name and r["bundle"] == "b1" and r["pixels"] > 0
        assert r["label"] in {"correct", "neutral", "false_positive"}
        # No drift: removed ones asked the faint-strip check only, which kept them.
        assert r["kind"] == "removed" and list(r["checks"]) == ["faint"]
        faint = r["checks"]["faint"]
        assert faint["explained"] is False and r["decided"] == "reported"
        assert faint["spread_m"] >= 0.0 and faint["faces"] >= faint["drawn"] >= 0
        assert faint["drawn_share"] == pytest.approx(
            faint["drawn"] / faint["faces"] if faint["faces"] else 1.0
        )


def test_every_cluster_is_written_with_whether_the_floors_kept_it_and_its_label(
    census: ModuleType,
    edited: tuple[Path, Path, dict[str, Any], int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--clusters`` writes every cluster the cluster stage made, before its floors: the kept
    ones are what the bundle reported (no drift: no re-fit, and the faint check kept them), the
    difference whose change was taken out of the truth is labelled a false positive, and a
    removed one carries its cells in the removal evidence."""
    set_dir, outbox, _, fp_id = edited
    clusters_path = tmp_path / "clusters.jsonl"
    assert census.main([str(set_dir), str(outbox), "--clusters", str(clusters_path)]) == 0
    capsys.readouterr()
    records = [json.loads(line) for line in clusters_path.read_text().splitlines()]
    result = yaml.safe_load((outbox / "b1" / "result.yaml").read_text())
    reported = sorted(
        (d["kind"], round(d["centroid"]["x"], 2), round(d["centroid"]["y"], 2))
        for d in result["differences"]
    )
    kept = sorted(
        (r["kind"], round(r["centroid"][0], 2), round(r["centroid"][1], 2))
        for r in records
        if r["kept"]
    )
    assert kept == reported and len(records) >= len(reported)
    fp = next(d for d in result["differences"] if d["id"] == fp_id)
    at = (fp["centroid"]["x"], fp["centroid"]["y"])
    (same,) = [r for r in records if np.hypot(*np.subtract(r["centroid"], at)) < 0.01]
    assert same["label"] == "false_positive" and same["kind"] == "added" and same["kept"]
    removed = [r for r in records if r["kind"] == "removed"]
    assert removed
    for r in records:
        assert r["set"] == set_dir.name and r["bundle"] == "b1" and r["pixels"] > 0
        assert r["label"] in {"correct", "neutral", "false_positive"}
        assert ("evidence_px" in r) == (r["kind"] == "removed")
    for r in removed:
        assert 0 <= r["evidence_px"] <= r["pixels"]
        assert r["evidence_share"] == pytest.approx(r["evidence_px"] / r["pixels"], abs=1e-4)


def test_a_checks_value_is_written_as_its_numbers(census: ModuleType) -> None:
    assert census.as_data(refit_stage.Faces(walls=10, seen_behind=7, depth_m=0.3)) == {
        "walls": 10,
        "seen_behind": 7,
        "depth_m": 0.3,
        "behind_share": pytest.approx(0.7),
    }
    strip = refit_stage.Strip(spread_m=0.02, along_m=0.3, faces=40, drawn=10)
    assert census.as_data(strip) == {
        "spread_m": 0.02,
        "along_m": 0.3,
        "faces": 40,
        "drawn": 10,
        "drawn_share": 0.25,
    }
    band = refit_stage.Band(depth_m=0.2, length_m=1.0, inner=10, walled=8)
    assert census.as_data(band)["walled_share"] == pytest.approx(0.8)
    assert json.loads(json.dumps(census.as_data(band))) == census.as_data(band)
    with pytest.raises(TypeError):
        census.as_data("a text")
    assert census.as_data(np.float32(0.5)) == {"value": 0.5}
    assert census.as_data(np.bool_(True)) == {"value": True}
    assert census.as_data(False) == {"value": False}
    assert census.as_data(3) == {"value": 3}


def test_run_sets_census_with_all_keeps_each_sets_judged_differences(
    edited: tuple[Path, Path, dict[str, Any], int], tmp_path: Path
) -> None:
    set_dir, outbox, _, _ = edited
    run_dir = tmp_path / "run"
    shutil.copytree(outbox, run_dir / "one")
    with benchmark_module("run_sets") as rs:
        _, counts = rs._census_one(rs.BenchSet("one", "tuning", (), set_dir), run_dir, None, True)
    assert counts is not None
    lines = (run_dir / "census" / "one.judged.jsonl").read_text().splitlines()
    assert len(lines) == sum(n for *_, n in counts["judged"]) > 0
    assert {json.loads(line)["set"] for line in lines} == {set_dir.name}
    clusters = (run_dir / "census" / "one.clusters.jsonl").read_text().splitlines()
    assert len(clusters) >= len(lines) and all(
        json.loads(c)["set"] == set_dir.name for c in clusters
    )
