"""benchmarks/crops.py: the crops around each change and each difference not judged correct,
on a generated bundle whose truth the test edits (a change planted where nothing changed)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest
import yaml
from bench_support import benchmark_module, one_bundle_set

from mapserver import synth
from mapserver.config import load_config

STAMP = "2026-12-02T06:00:00Z"
HALF_M, SCALE = 1.0, 3


@pytest.fixture(scope="module")
def crops() -> Iterator[ModuleType]:
    with benchmark_module("crops") as module:
        yield module


@pytest.fixture(scope="module")
def planted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[dict], float]:
    """A one-bundle set of a 20 m office session and its outbox, the truth holding one more
    added change (99) on the robot's own pose, where nothing was put: a change no stage saw.
    Also the real changes, and the work grid's resolution."""
    office = synth.make_office_map(width_m=26, height_m=18, rng=11)
    scenario = synth.make_scenario(
        office, seed=5, route_length_m=20, n_added=3, n_removed=2, n_people=0
    )
    set_dir, outbox = one_bundle_set(tmp_path_factory.mktemp("crops"), scenario, STAMP)
    truth_path = set_dir / "s1" / "truth" / "b1.yaml"
    bundle = set_dir / "s1" / "bundles" / "b1"
    result = yaml.safe_load((outbox / "b1" / "result.yaml").read_text())
    truth = yaml.safe_load(truth_path.read_text())
    real = list(truth["changes"])
    pose = yaml.safe_load((bundle / "bundle.yaml").read_text())["pose"]["nav2"]
    x, y = pose["x"], pose["y"]
    square = [[x - 0.2, y - 0.2], [x + 0.2, y - 0.2], [x + 0.2, y + 0.2], [x - 0.2, y + 0.2]]
    truth["changes"].append({"id": 99, "kind": "added", "polygon": square, "observed": True})
    truth_path.write_text(yaml.safe_dump(truth))
    return set_dir, outbox, real, result["map"]["resolution"]


def test_each_change_gets_three_panels_named_by_what_became_of_it(
    crops: ModuleType, planted: tuple[Path, Path, list[dict], float], tmp_path: Path
) -> None:
    set_dir, outbox, real, resolution = planted
    out = tmp_path / "crops"
    argv = [str(set_dir), str(outbox), str(out), "b1", "--half", str(HALF_M)]
    assert crops.main([*argv, "--scale", str(SCALE)]) == 0

    names = sorted(p.name for p in out.glob("*.png"))
    assert "b1_change99_added_MISS.png" in names
    for change in real:
        assert any(n.startswith(f"b1_change{change['id']}_{change['kind']}_") for n in names)
    image = cv2.imread(str(out / "b1_change99_added_MISS.png"))
    side = 2 * round(HALF_M / resolution) * SCALE  # a square of half_m each way, scaled
    assert image.shape == (side, 3 * side + 2 * crops._GAP_PX, 3)
    # The robot stands on open floor: the global map's panel is free (white) at its centre,
    # where the planted change's outline (cyan, an added one) runs 0.2 m around it.
    centre = side // 2
    assert image[centre, centre].tolist() == [255, 255, 255]
    outline_px = round((0.2 / resolution) * SCALE)
    ring = image[centre - outline_px - SCALE : centre + outline_px + SCALE, :side]
    assert (ring == np.array(crops._OUTLINE["added"], np.uint8)).all(axis=2).any()


def test_the_masks_panel_paints_the_removed_mask_over_the_paled_local_map(
    crops: ModuleType,
) -> None:
    trace = crops.Trace()
    trace.local_state = np.array([[0, 100], [255, 0]], np.uint8)
    removed = np.array([[True, False], [False, False]])
    trace.masks = type("Masks", (), {"removed": removed, "added": np.zeros((2, 2), bool)})()
    panel = crops.masks_panel(trace)
    assert panel[0, 0].tolist() == list(crops._REMOVED)
    # Occupied paled to 100, unknown (160) to 180, free (255) to 227.
    assert panel[0, 1].tolist() == [100] * 3
    assert panel[1, 0].tolist() == [180] * 3
    assert panel[1, 1].tolist() == [227] * 3


def test_no_bundle_matching_is_an_error(
    crops: ModuleType, planted: tuple[Path, Path, list[dict], float], tmp_path: Path
) -> None:
    set_dir, outbox, _, _ = planted
    assert crops.main([str(set_dir), str(outbox), str(tmp_path / "c"), "nosuchbundle"]) == 1
    assert not list((tmp_path / "c").glob("*.png"))


def test_without_a_result_in_the_outbox_the_re_run_labels_the_crops(
    crops: ModuleType, planted: tuple[Path, Path, list[dict], float], tmp_path: Path
) -> None:
    set_dir, _, _, _ = planted
    empty = tmp_path / "no-outbox"
    empty.mkdir()
    case = crops.find_cases(set_dir)[0]
    lines = crops.crops_of_bundle(
        case, empty, load_config(None), tmp_path, half_m=HALF_M, scale=SCALE
    )
    assert lines[0] == "== b1" and not any("MISMATCH" in line for line in lines)
    assert (tmp_path / "b1_change99_added_MISS.png").is_file()


def test_an_untrusted_alignment_compares_nothing_and_writes_no_crop(
    crops: ModuleType, planted: tuple[Path, Path, list[dict], float], tmp_path: Path
) -> None:
    set_dir, outbox, _, _ = planted
    config = tmp_path / "untrusting.yaml"
    config.write_text(yaml.safe_dump({"pipeline": {"align": {"min_score": 1.0}}}))
    out = tmp_path / "crops"
    assert crops.main([str(set_dir), str(outbox), str(out), "--config", str(config)]) == 0
    assert not list(out.glob("*.png"))
