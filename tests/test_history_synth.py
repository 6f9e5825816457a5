"""benchmarks/make_histories.py: a tiny site history whose files agree with the truth it planted."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import yaml
from bench_support import benchmark_module

from mapserver.bundle import check_bundle_files, read_manifest
from mapserver.maps import OCCUPIED, load_map


@pytest.fixture(scope="module")
def mh() -> Iterator[ModuleType]:
    with benchmark_module("make_histories") as module:
        yield module


def tiny_plan(mh: ModuleType) -> Any:
    """Four sessions in one day on a small office, two of them by a parked cart."""
    (plan,) = mh.make_plans(5, 1, ["cart"])
    return replace(
        plan,
        world=mh.scen.WorldSpec("office", "office", (24.0, 18.0)),
        sessions=4,
        days=1.0,
        robots=2,
        areas=1,
        area_m=(16.0, 16.0),
        route_m=(15.0, 20.0),
        walkers=(1, 1),
        added=2,
        removed=1,
        reverted_added=0,
        reverted_removed=0,
        carts=0,
        groups=1,
    )


def make_set(mh: ModuleType, out_dir: Path) -> Path:
    mh.generate(out_dir, [tiny_plan(mh)], seed=5, cases=["cart"], jobs=1)
    return out_dir


@pytest.fixture(scope="module")
def history_set(mh: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_set(mh, tmp_path_factory.mktemp("a") / "set")


def load(path: Path) -> Any:
    return yaml.safe_load(path.read_text())


def parse_stamp(text: str) -> datetime:
    return datetime.strptime(text, "%Y-%m-%dT%H:%M:%SZ")


def test_layout_is_the_public_history_sets(history_set: Path) -> None:
    doc = load(history_set / "set.yaml")
    (entry,) = doc["scenarios"]
    history = history_set / entry["name"]
    assert (history_set / entry["map"]).is_file()
    assert (history / "reference" / "nav2_map.yaml").is_file()
    reference = (history / "reference" / "nav2_map.pgm").read_bytes()
    scenario = load(history / "scenario.yaml")
    ids = [s["id"] for s in scenario["sessions"]]
    assert ids == entry["bundles"] and len(ids) == 4
    stamps = [s["stamp"] for s in scenario["sessions"]]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    for bundle_id in ids:
        bundle = history / "bundles" / bundle_id
        check_bundle_files(bundle)
        assert read_manifest(bundle).robot.startswith("sim-")
        assert (bundle / "nav2_map.pgm").read_bytes() == reference
        assert load(bundle / "bundle.yaml")["nav2_map"] == "nav2_map.yaml"
        truth = load(history / "truth" / f"{bundle_id}.yaml")
        assert truth["format"] == 1 and set(truth["transform"]) == {"theta", "tx", "ty"}


def test_history_yaml_agrees_with_the_bundles_truth(history_set: Path) -> None:
    history = history_set / load(history_set / "set.yaml")["scenarios"][0]["name"]
    doc = load(history / "history.yaml")
    assert (doc["format"], doc["map"]) == (1, "site")
    sessions = load(history / "scenario.yaml")["sessions"]
    truths = {s["id"]: load(history / "truth" / f"{s['id']}.yaml") for s in sessions}
    kinds = {c["kind"] for c in doc["changes"]}
    assert {"added", "removed", "temporary"} <= kinds
    for change in doc["changes"]:
        start = parse_stamp(change["from"])
        end = None if change["until"] is None else parse_stamp(change["until"])
        active = [
            s
            for s in sessions
            if start <= parse_stamp(s["stamp"]) and (end is None or parse_stamp(s["stamp"]) < end)
        ]
        observed = []
        for s in sessions:
            listed = [c for c in truths[s["id"]]["changes"] if c["id"] == change["id"]]
            assert bool(listed) == (s in active), (change["id"], s["id"])
            if listed and listed[0]["observed"]:
                observed.append(s["stamp"])
        assert change["sessions"] == len(observed)
        assert change["seen_from"] == (observed[0] if observed else None)
        assert change["seen_until"] == (observed[-1] if observed else None)
    temporary = [c for c in doc["changes"] if c["kind"] == "temporary"]
    assert any(c["shape"] == "cart" and c["sessions"] > 0 for c in temporary)


def test_erase_holds_occupied_reference_cells(history_set: Path) -> None:
    history = history_set / load(history_set / "set.yaml")["scenarios"][0]["name"]
    reference = load_map(history / "reference" / "nav2_map.yaml")
    removed = [c for c in load(history / "history.yaml")["changes"] if c["kind"] == "removed"]
    assert removed
    for change in removed:
        erase = np.array(change["erase"])
        # At least 0.1 m2: a removal an operator would call one, not a speck.
        assert erase.size * reference.resolution**2 >= 0.1 and np.all(np.diff(erase) > 0)
        assert np.all(reference.state.reshape(-1)[erase] == OCCUPIED)


def test_a_seed_fixes_every_byte(mh: ModuleType, history_set: Path, tmp_path: Path) -> None:
    again = make_set(mh, tmp_path / "set")

    def digest(root: Path) -> dict[str, str]:
        return {
            str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file()
        }

    assert digest(again) == digest(history_set)
