"""Scoring against ground truth (contract section 4), from hand-built truth and result documents."""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest
import yaml
from bench_support import benchmark_module

from mapserver.errors import ProcessingError
from mapserver.geometry import Transform2D
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, from_states, save_map
from mapserver.pipeline import Outcome
from mapserver.scoring import (
    alignment_error,
    matches,
    observed_centroid_xy,
    parse_result,
    parse_truth,
    point_in_polygon,
    point_polygon_distance_m,
    rect_intersects_polygon,
    score_bundle,
    summarize,
)

UNIT_SQUARE = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
# An L: the unit square's top-right quarter is missing (the notch).
L_SHAPE = [[0.0, 0.0], [1.0, 0.0], [1.0, 0.5], [0.5, 0.5], [0.5, 1.0], [0.0, 1.0]]


def square(cx: float, cy: float, half: float) -> list[list[float]]:
    return [
        [cx - half, cy - half],
        [cx + half, cy - half],
        [cx + half, cy + half],
        [cx - half, cy + half],
    ]


def change(id_: int, kind: str, polygon: list[list[float]], observed: bool = True) -> dict:
    return {"id": id_, "kind": kind, "polygon": polygon, "observed": observed}


def truth_doc(*changes: dict, transform: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict:
    theta, tx, ty = transform
    return {
        "format": 1,
        "transform": {"theta": theta, "tx": tx, "ty": ty},
        "changes": list(changes),
    }


def diff(kind: str, bbox: tuple[float, ...], centroid: tuple[float, float] | None = None) -> dict:
    min_x, min_y, max_x, max_y = bbox
    cx, cy = centroid or ((min_x + max_x) / 2, (min_y + max_y) / 2)
    return {
        "kind": kind,
        "centroid": {"x": cx, "y": cy},
        "bbox": {"min_x": min_x, "min_y": min_y, "max_x": max_x, "max_y": max_y},
    }


def result_doc(*diffs: dict, status: str = "ok", alignment: tuple | None = None) -> dict:
    doc: dict = {
        "format": 1,
        "status": status,
        "differences": [{"id": i + 1, **d} for i, d in enumerate(diffs)],
    }
    if alignment is not None:
        doc["alignment"] = dict(zip(("theta", "tx", "ty"), alignment, strict=True))
    return doc


def score(truth: dict, result: dict | None, **kwargs):
    return score_bundle(
        parse_truth(truth), None if result is None else parse_result(result), **kwargs
    )


# ---------------------------------------------------------------------------------------------
# Geometry


@pytest.mark.parametrize(
    ("point", "polygon", "inside"),
    [
        ((0.5, 0.5), UNIT_SQUARE, True),
        ((1.0, 0.5), UNIT_SQUARE, True),  # on an edge
        ((1.0, 1.0), UNIT_SQUARE, True),  # on a vertex
        ((1.0 + 1e-6, 0.5), UNIT_SQUARE, False),
        ((0.75, 0.75), L_SHAPE, False),  # in the notch
        ((0.25, 0.75), L_SHAPE, True),
        ((0.75, 0.5), L_SHAPE, True),  # on the notch's floor
        ((2.0, 0.0), UNIT_SQUARE, False),  # on the line of an edge, beyond it
    ],
)
def test_point_in_polygon(point, polygon, inside):
    assert point_in_polygon(point, polygon) is inside


@pytest.mark.parametrize(
    ("point", "polygon", "distance_m"),
    [
        ((0.5, 0.5), UNIT_SQUARE, 0.0),
        ((1.6, 0.5), UNIT_SQUARE, 0.6),
        ((1.3, 1.4), UNIT_SQUARE, 0.5),  # nearest to the corner (1, 1)
        ((0.75, 0.75), L_SHAPE, 0.25),
    ],
)
def test_point_polygon_distance(point, polygon, distance_m):
    assert point_polygon_distance_m(point, polygon) == pytest.approx(distance_m, abs=1e-12)


@pytest.mark.parametrize(
    ("bbox", "polygon", "intersects"),
    [
        ((0.5, 0.5, 2.0, 2.0), UNIT_SQUARE, True),  # overlap
        ((1.0, 0.2, 2.0, 0.4), UNIT_SQUARE, True),  # touching an edge exactly
        ((1.0, 1.0, 2.0, 2.0), UNIT_SQUARE, True),  # touching a corner exactly
        ((1.0 + 1e-9, 0.2, 2.0, 0.4), UNIT_SQUARE, False),
        ((0.4, 0.4, 0.6, 0.6), UNIT_SQUARE, True),  # rectangle inside the polygon
        ((-1.0, -1.0, 2.0, 2.0), UNIT_SQUARE, True),  # polygon inside the rectangle
        ((0.6, 0.6, 0.9, 0.9), L_SHAPE, False),  # inside the notch
        ((0.6, -0.5, 0.7, 2.0), L_SHAPE, True),  # crosses an edge, no vertex inside either
        ((3.0, 3.0, 4.0, 4.0), UNIT_SQUARE, False),
    ],
)
def test_rect_intersects_polygon(bbox, polygon, intersects):
    assert rect_intersects_polygon(bbox, polygon) is intersects


def test_geometry_agrees_with_opencv_on_random_cases():
    rng = np.random.default_rng(7)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 12))
    star = np.c_[np.cos(angles), np.sin(angles)] * rng.uniform(0.3, 1.0, (12, 1))
    contour = star.astype(np.float32).reshape(-1, 1, 2)
    for point in rng.uniform(-1.5, 1.5, (200, 2)):
        expected = max(
            0.0, -cv2.pointPolygonTest(contour, (float(point[0]), float(point[1])), True)
        )
        assert point_polygon_distance_m(point, star) == pytest.approx(expected, abs=1e-5)
    for _ in range(200):
        theta = rng.uniform(0, np.pi)
        rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
        box = (np.array(UNIT_SQUARE) - 0.5) * rng.uniform(0.2, 1.5, 2) @ rot.T + rng.uniform(
            -1, 1, 2
        )
        lo = rng.uniform(-1, 1, 2)
        bbox = (*lo, *(lo + rng.uniform(0.05, 1.0, 2)))
        rect = np.array(
            [[bbox[0], bbox[1]], [bbox[2], bbox[1]], [bbox[2], bbox[3]], [bbox[0], bbox[3]]]
        )
        area, _ = cv2.intersectConvexConvex(rect.astype(np.float32), box.astype(np.float32))
        assert rect_intersects_polygon(bbox, box) is (area > 0)


# ---------------------------------------------------------------------------------------------
# Matching rules


@pytest.mark.parametrize(
    ("difference", "expected"),
    [
        (diff("added", (0.1, 0.1, 0.9, 0.9)), True),
        (diff("added", (1.6, 0.2, 1.8, 0.8)), False),  # 0.6 m away: (a) fails
        (diff("added", (1.25, 0.4, 1.35, 0.6)), True),  # grown bbox touches the edge exactly
        (diff("added", (1.1, 0.4, 2.2, 0.6)), False),  # (a) holds, centroid 0.65 m away: (b) fails
        (diff("added", (1.1, 0.4, 2.2, 0.6), centroid=(1.45, 0.5)), True),  # centroid 0.45 m away
        (diff("added", (-10.0, -10.0, 10.0, 10.0)), False),  # one box over everything: (c) fails
    ],
)
def test_match_rules(difference, expected):
    truth = parse_truth(truth_doc(change(1, "added", UNIT_SQUARE)))
    (parsed,) = parse_result(result_doc(difference)).differences
    assert matches(parsed, truth.changes[0]) is expected


@pytest.mark.parametrize(("extra_m", "expected"), [(0.0, True), (1e-9, False)])
def test_diagonal_rule_is_inclusive(extra_m, expected):
    width = math.hypot(1.0, 1.0) + 1.0 + extra_m  # the unit square's diagonal + 1 m
    truth = parse_truth(truth_doc(change(1, "added", UNIT_SQUARE)))
    (parsed,) = parse_result(
        result_doc(diff("added", (0.5 - width / 2, 0.5, 0.5 + width / 2, 0.5)))
    ).differences
    assert matches(parsed, truth.changes[0]) is expected


# ---------------------------------------------------------------------------------------------
# Scoring one bundle


def test_box_on_added_change_is_a_true_positive():
    s = score(
        truth_doc(change(1, "added", UNIT_SQUARE)), result_doc(diff("added", (0.1, 0.1, 0.9, 0.9)))
    )
    assert (s.n_correct, s.n_false_positive, s.n_neutral, s.n_matched, s.n_observed) == (
        1,
        0,
        0,
        1,
        1,
    )
    assert (s.precision, s.recall, s.f1, s.kind_accuracy) == (1.0, 1.0, 1.0, 1.0)
    assert not s.failed
    assert s.differences[0].assigned_change_id == 1


def test_box_over_everything_is_a_false_positive():
    truth = truth_doc(change(1, "added", UNIT_SQUARE), change(2, "removed", square(3, 3, 0.5)))
    s = score(truth, result_doc(diff("added", (-5.0, -5.0, 5.0, 5.0), centroid=(0.5, 0.5))))
    assert (s.n_correct, s.n_false_positive, s.n_matched) == (0, 1, 0)
    assert (s.precision, s.recall, s.f1) == (0.0, 0.0, 0.0)
    assert s.unmatched_change_ids == (1, 2)


def test_person_only_match_is_neutral_and_left_out_of_precision():
    truth = truth_doc(change(1, "added", UNIT_SQUARE), change(2, "temporary", square(5, 5, 0.3)))
    s = score(
        truth, result_doc(diff("added", (0.1, 0.1, 0.9, 0.9)), diff("added", (4.8, 4.8, 5.2, 5.2)))
    )
    assert (s.n_correct, s.n_neutral, s.n_false_positive) == (1, 1, 0)
    assert s.precision == 1.0
    assert [d.label for d in s.differences] == ["correct", "neutral"]
    assert s.n_observed == 1  # a person is not a structural change


def test_match_on_person_and_structure_is_correct():
    truth = truth_doc(
        change(1, "temporary", square(0.2, 0.5, 0.2)), change(2, "added", square(0.8, 0.5, 0.2))
    )
    s = score(truth, result_doc(diff("added", (0.1, 0.3, 0.9, 0.7))))
    assert s.differences[0].label == "correct"
    assert s.differences[0].matched_change_ids == (1, 2)
    assert s.differences[0].assigned_change_id == 2


def test_unobserved_change_makes_a_difference_correct_but_is_not_in_recall():
    truth = truth_doc(
        change(1, "added", UNIT_SQUARE), change(2, "removed", square(5, 5, 0.5), observed=False)
    )
    s = score(truth, result_doc(diff("removed", (4.6, 4.6, 5.4, 5.4))))
    assert (s.n_correct, s.n_false_positive, s.n_observed, s.n_matched) == (1, 0, 1, 0)
    assert s.recall == 0.0


def test_fragments_are_counted_but_not_errors():
    long_wall = [[0.0, 0.0], [4.0, 0.0], [4.0, 0.4], [0.0, 0.4]]
    pieces = [diff("added", (x, 0.05, x + 0.8, 0.35)) for x in (0.1, 1.5, 3.0)]
    s = score(truth_doc(change(1, "added", long_wall)), result_doc(*pieces))
    assert (s.n_correct, s.n_false_positive, s.n_matched, s.n_fragments) == (3, 0, 1, 2)
    assert (s.precision, s.recall) == (1.0, 1.0)


def test_kind_mismatch_is_correct_but_lowers_kind_accuracy():
    truth = truth_doc(change(1, "added", UNIT_SQUARE), change(2, "removed", square(5, 5, 0.5)))
    s = score(
        truth,
        result_doc(diff("removed", (0.1, 0.1, 0.9, 0.9)), diff("removed", (4.6, 4.6, 5.4, 5.4))),
    )
    assert (s.n_correct, s.n_kind_correct, s.kind_accuracy) == (2, 1, 0.5)
    assert [d.kind_correct for d in s.differences] == [False, True]


def test_difference_on_two_changes_is_counted_on_the_one_of_its_kind():
    truth = truth_doc(
        change(1, "added", square(0.2, 0.5, 0.2)), change(2, "removed", square(0.8, 0.5, 0.2))
    )
    s = score(truth, result_doc(diff("removed", (0.1, 0.3, 0.9, 0.7))))
    assert s.differences[0].assigned_change_id == 2
    assert (s.n_kind_correct, s.n_matched, s.n_fragments) == (1, 2, 0)  # recall counts both


def test_no_differences_and_no_changes_conventions():
    empty = score(truth_doc(change(1, "added", UNIT_SQUARE)), result_doc())
    assert (empty.precision, empty.recall, empty.f1, empty.kind_accuracy) == (1.0, 0.0, 0.0, None)
    quiet = score(truth_doc(), result_doc(diff("added", (0.1, 0.1, 0.9, 0.9))))
    assert (quiet.precision, quiet.recall, quiet.f1) == (0.0, 1.0, 0.0)


@pytest.mark.parametrize("status", ["failed", "error", "missing"])
def test_failed_or_missing_result_leaves_every_change_unmatched(status):
    truth = truth_doc(change(1, "added", UNIT_SQUARE), change(2, "temporary", square(5, 5, 0.3)))
    result = (
        None
        if status == "missing"
        else result_doc(diff("added", (0.1, 0.1, 0.9, 0.9)), status=status)
    )
    s = score(truth, result, centre_slam_xy=(0.0, 0.0))
    assert s.failed and s.status == status
    assert (s.n_differences, s.n_observed, s.n_matched, s.recall) == (0, 1, 0, 0.0)
    assert s.unmatched_change_ids == (1,)
    assert s.alignment_error_m is None


def test_parsing_does_not_modify_the_documents():
    truth = truth_doc(change(1, "added", UNIT_SQUARE))
    result = result_doc(diff("added", (0.1, 0.1, 0.9, 0.9)), alignment=(0.1, 1.0, 2.0))
    before = copy.deepcopy((truth, result))
    score(truth, result, centre_slam_xy=(1.0, 1.0))
    assert (truth, result) == before


@pytest.mark.parametrize(
    ("truth", "result", "message"),
    [
        ({**truth_doc(), "format": 2}, result_doc(), "format"),
        (truth_doc(change(1, "moved", UNIT_SQUARE)), result_doc(), r"changes\[0\]\.kind"),
        (truth_doc(change(1, "added", UNIT_SQUARE[:2])), result_doc(), r"changes\[0\]\.polygon"),
        (truth_doc(change(1, "added", UNIT_SQUARE, observed="yes")), result_doc(), "observed"),
        ({"changes": []}, result_doc(), "transform"),
        (truth_doc(), result_doc(diff("added", (1.0, 0.0, 0.0, 1.0))), "min <= max"),
        (
            truth_doc(),
            result_doc(diff("temporary", (0.0, 0.0, 1.0, 1.0))),
            r"differences\[0\]\.kind",
        ),
        (truth_doc(), {"format": 1, "differences": []}, "status"),
    ],
)
def test_bad_documents_name_the_field(truth, result, message):
    with pytest.raises(ValueError, match=message):
        parse_truth(truth)
        parse_result(result)


# ---------------------------------------------------------------------------------------------
# Alignment error


def test_alignment_error_of_a_known_offset():
    true = Transform2D(0.3, 2.0, -1.0)
    shifted = Transform2D(0.3, 2.3, -1.4)
    assert alignment_error(shifted, true, (5.0, 7.0)) == pytest.approx((0.5, 0.0))


def test_rotation_about_the_observed_centre_gives_no_distance():
    true = Transform2D(0.3, 2.0, -1.0)
    centre = np.array([4.0, -3.0])
    # Rotate the nav2 image by 0.05 rad about the point where the centre lands.
    pivot = true.apply(centre)
    spin = Transform2D(0.05, *(pivot - Transform2D(0.05, 0.0, 0.0).apply(pivot)))
    error_m, error_rad = alignment_error(spin.compose(true), true, centre)
    assert error_m == pytest.approx(0.0, abs=1e-12)
    assert error_rad == pytest.approx(0.05)


def test_rotation_about_the_slam_origin_is_measured_at_the_centre():
    true = Transform2D(0.0, 0.0, 0.0)
    error_m, error_rad = alignment_error(Transform2D(0.02, 0.0, 0.0), true, (10.0, 0.0))
    assert error_m == pytest.approx(2 * 10.0 * math.sin(0.01))
    assert error_rad == pytest.approx(0.02)


def test_angle_error_wraps_around_pi():
    error_rad = alignment_error(Transform2D(3.1, 0, 0), Transform2D(-3.1, 0, 0), (0.0, 0.0))[1]
    assert error_rad == pytest.approx(2 * math.pi - 6.2)


def test_observed_centroid_of_known_cells():
    state = np.full((10, 8), UNKNOWN, np.uint8)
    state[2:4, 4:6] = FREE
    state[3, 5] = OCCUPIED
    local = from_states(state, 0.1, (1.0, 2.0, 0.0))
    # Mean column 4.5, mean row 2.5 of a 10-row map: x = 1 + 5 * 0.1, y = 2 + 7 * 0.1.
    assert observed_centroid_xy(local) == pytest.approx((1.5, 2.7))
    assert observed_centroid_xy(
        from_states(np.full((10, 8), UNKNOWN, np.uint8), 0.1, (1.0, 2.0, 0.0))
    ) == (pytest.approx((1.4, 2.5)))


def test_score_bundle_reports_alignment_error_at_the_centre():
    truth = truth_doc(change(1, "added", UNIT_SQUARE), transform=(0.5, 1.0, 1.0))
    s = score(truth, result_doc(alignment=(0.5, 1.0, 1.1)), centre_slam_xy=(3.0, 4.0))
    assert (s.alignment_error_m, s.alignment_error_rad) == pytest.approx((0.1, 0.0))
    assert score(truth, result_doc(alignment=(0.5, 1.0, 1.1))).alignment_error_m is None


# ---------------------------------------------------------------------------------------------
# Totals


def test_totals_are_micro_averages_over_counts():
    good = score(
        truth_doc(change(1, "added", UNIT_SQUARE)), result_doc(diff("added", (0.1, 0.1, 0.9, 0.9)))
    )
    far = [diff("added", (x, 9.0, x + 0.5, 9.5)) for x in (0.0, 2.0, 4.0)]
    truth = truth_doc(*(change(i, "removed", square(3 * i, -5, 0.4)) for i in range(1, 4)))
    bad = score(truth, result_doc(*far))
    total = summarize([good, bad, score(truth_doc(change(1, "added", UNIT_SQUARE)), None)])
    assert (total.n_bundles, total.n_failures, total.n_correct, total.n_false_positive) == (
        3,
        1,
        1,
        3,
    )
    assert (total.n_observed, total.n_matched) == (5, 1)
    assert (total.precision, total.recall) == (0.25, 0.2)
    assert total.f1 == pytest.approx(2 * 0.25 * 0.2 / 0.45)
    assert total.alignment_error_median_m is None


# ---------------------------------------------------------------------------------------------
# benchmarks/bench_public.py on a tiny generated set


@pytest.fixture(scope="module")
def bench() -> Iterator[ModuleType]:
    with benchmark_module("bench_public") as module:
        yield module


@pytest.fixture
def tiny_set(tmp_path: Path) -> Path:
    """Scenario ``s1`` with bundles b1 and b2; the local maps' observed area is centred on (2, 1)."""
    set_dir = tmp_path / "set"
    for bundle_id in ("b1", "b2"):
        bundle = set_dir / "s1" / "bundles" / bundle_id
        bundle.mkdir(parents=True)
        state = np.full((20, 40), UNKNOWN, np.uint8)
        state[5:15, 10:30] = FREE
        save_map(bundle / "slam_map.yaml", state, 0.1, (0.0, 0.0, 0.0))
        manifest = {
            "format": 1,
            "robot": "sim-01",
            "stamp": "2026-11-21T10:15:00Z",
            "slam_map": "slam_map.yaml",
            "pose": {"nav2": {"x": 0, "y": 0, "yaw": 0}, "slam": {"x": 0, "y": 0, "yaw": 0}},
        }
        (bundle / "bundle.yaml").write_text(yaml.safe_dump(manifest))
        truth = truth_doc(
            change(1, "added", UNIT_SQUARE), change(2, "temporary", square(5, 5, 0.3))
        )
        (set_dir / "s1" / "truth").mkdir(exist_ok=True)
        (set_dir / "s1" / "truth" / f"{bundle_id}.yaml").write_text(yaml.safe_dump(truth))
    return set_dir


B1_RESULT = result_doc(
    diff("added", (0.1, 0.1, 0.9, 0.9)),
    diff("added", (4.8, 4.8, 5.2, 5.2)),
    diff("removed", (8.0, 8.0, 8.5, 8.5)),
    alignment=(0.01, 0.0, 0.0),
)


def test_bench_scores_an_existing_outbox(bench, tiny_set, tmp_path, capsys):
    outbox = tmp_path / "outbox"
    (outbox / "b1").mkdir(parents=True)
    (outbox / "b1" / "result.yaml").write_text(
        yaml.safe_dump({**B1_RESULT, "timings_ms": {"load": 4.0}})
    )
    assert bench.main([str(tiny_set), "--score-only", str(outbox), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    b1, b2 = doc["bundles"]
    assert (b1["status"], b1["correct"], b1["neutral"], b1["false_positive"]) == ("ok", 1, 1, 1)
    assert b1["alignment_error_m"] == pytest.approx(0.01 * math.hypot(2.0, 1.0), rel=1e-3)
    assert (b2["status"], b2["matched"], b2["observed"]) == ("missing", 0, 1)
    total = doc["total"]
    assert (total["failures"], total["precision"], total["recall"]) == (1, 0.5, 0.5)
    assert total["stage_median_ms"] == {"load": 4.0}
    assert bench.main([str(tiny_set), "--score-only", str(outbox)]) == 0
    assert "TOTAL 2 bundles, 1 failures" in capsys.readouterr().out


WHOLE = {"trusted": True, "method": "pose+correlative+icp", "drift_m": 0.05}


@pytest.mark.parametrize(
    ("alignment", "expected"),
    [
        (WHOLE, "fits"),
        ({**WHOLE, "drift_m": 0.25}, "drifted"),
        # Compared in pieces (whole_score is written only then), whatever the drift.
        ({**WHOLE, "method": "pose+correlative+icp+pieces", "whole_score": 0.5}, "pieces"),
        ({**WHOLE, "method": "p+pieces", "whole_score": 0.5, "drift_m": 0.3}, "pieces"),
        # Pieces tried, none trusted: compared whole.
        ({**WHOLE, "method": "pose+correlative+icp+pieces", "trusted_pieces": 0}, "fits"),
        ({**WHOLE, "trusted": False, "whole_score": 0.5}, "untrusted"),
        ({"theta": 0.0, "tx": 0.0, "ty": 0.0}, "-"),
    ],
)
def test_bench_tells_how_a_bundle_was_aligned(bench, alignment, expected):
    assert bench._alignment_class({"alignment": alignment}) == expected


def test_bench_totals_bundles_by_how_they_were_aligned(bench, tiny_set, tmp_path, capsys):
    """b1 aligned in pieces (its one change found, one false positive), b2 whole with a drift
    correction under the drifted threshold (its change missed): each counted under its own;
    a bundle whose result is missing under none."""
    outbox = tmp_path / "outbox"
    pieces = {**WHOLE, "method": "pose+correlative+icp+pieces", "whole_score": 0.5}
    results = {
        "b1": {**B1_RESULT, "alignment": {**B1_RESULT["alignment"], **pieces}},
        "b2": result_doc(alignment=(0.0, 0.0, 0.0)),
    }
    results["b2"]["alignment"].update(WHOLE)
    for bundle_id, doc in results.items():
        (outbox / bundle_id).mkdir(parents=True)
        (outbox / bundle_id / "result.yaml").write_text(yaml.safe_dump(doc))
    assert bench.main([str(tiny_set), "--score-only", str(outbox), "--json"]) == 0
    alignments = json.loads(capsys.readouterr().out)["alignments"]
    assert list(alignments) == ["fits", "pieces"]  # in the order the map fits less
    assert (alignments["pieces"]["matched"], alignments["pieces"]["false_positive"]) == (1, 1)
    assert (alignments["fits"]["matched"], alignments["fits"]["observed"]) == (0, 1)
    assert bench.main([str(tiny_set), "--score-only", str(outbox)]) == 0
    text = capsys.readouterr().out
    block = text[text.index("per alignment") :].splitlines()[1:]
    assert [line.split()[:2] for line in block] == [["fits", "1"], ["pieces", "1"]]
    (outbox / "b2" / "result.yaml").unlink()
    assert bench.main([str(tiny_set), "--score-only", str(outbox), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["total"]["failures"] == 1
    assert list(doc["alignments"]) == ["pieces"]


@pytest.mark.parametrize(
    ("doc", "expected"),
    [
        # The simulator's record of the bundle's drift: its largest residual from a rigid fit.
        ({"bundles": [{"id": "b1", "drift": {"fit_max_residual_m": 0.07}}]}, 0.07),
        # Another bundle's record says nothing of this one's; drift asked for: it bends.
        (
            {"params": {"drift": True}, "bundles": [{"id": "b2", "drift": {}}, {"id": "b1"}]},
            None,
        ),
        ({"params": {"drift_yaw_deg_per_m": 0.02}, "bundles": [{"id": "b1"}]}, None),
        # Simulated without drift (the public set's scenarios): rigid.
        ({"params": {"drift_yaw_deg_per_m": 0.0, "fov": 360}, "bundles": [{"id": "b1"}]}, 0.0),
        # No scenario file, or one of another layout: it does not say.
        ({}, None),
        ({"params": {"fov": 360}}, None),
    ],
)
def test_bench_reads_how_far_the_true_map_bends(bench, doc, expected):
    assert bench._scenario_bend_m(doc, "b1") == expected


def test_bench_totals_bundles_by_how_far_their_true_map_bends(bench, tiny_set, tmp_path, capsys):
    """b1's true map bends 0.2 m (its change found), b2's 0.01 m (its change missed): each
    counted under its own, rigid first, with the alignment error of each."""
    doc = {
        "case": "gen",
        "params": {"drift_yaw_deg_per_m": 0.02},
        "bundles": [
            {"id": "b1", "drift": {"fit_max_residual_m": 0.2}},
            {"id": "b2", "drift": {"fit_max_residual_m": 0.01}},
        ],
    }
    (tiny_set / "s1" / "scenario.yaml").write_text(yaml.safe_dump(doc))
    outbox = tmp_path / "outbox"
    for bundle_id, result in (("b1", B1_RESULT), ("b2", result_doc(alignment=(0.0, 0.0, 0.0)))):
        (outbox / bundle_id).mkdir(parents=True)
        (outbox / bundle_id / "result.yaml").write_text(yaml.safe_dump(result))
    assert bench.main([str(tiny_set), "--score-only", str(outbox), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [b["bend_m"] for b in out["bundles"]] == [0.2, 0.01]
    bends = out["bends"]
    assert list(bends) == ["rigid", "bent"]
    assert (bends["bent"]["matched"], bends["rigid"]["matched"]) == (1, 0)
    assert bends["rigid"]["alignment_error_p90_m"] == pytest.approx(0.0)
    assert bends["bent"]["alignment_error_p90_m"] == pytest.approx(0.01 * math.hypot(2, 1), 1e-3)
    assert bench.main([str(tiny_set), "--score-only", str(outbox)]) == 0
    text = capsys.readouterr().out
    block = text[text.index("per true bend") :].splitlines()[1:]
    assert [line.split()[:2] for line in block] == [["rigid", "1"], ["bent", "1"]]


def test_bench_run_survives_failing_bundles(bench, tiny_set, tmp_path, capsys, monkeypatch):
    def fake_process(bundle_dir, config, *, bundle_id=None):
        if bundle_id == "b2":
            raise NotImplementedError
        return Outcome(bundle_id, {"bundle": bundle_id, **B1_RESULT}, {"overlay.png": b"png"})

    monkeypatch.setattr(bench, "process_bundle", fake_process)
    outbox = tmp_path / "outbox"
    assert bench.main([str(tiny_set), "--out", str(outbox), "--json"]) == 0
    b1, b2 = json.loads(capsys.readouterr().out)["bundles"]
    assert (b1["status"], b1["correct"]) == ("ok", 1)
    assert (outbox / "b1" / "overlay.png").read_bytes() == b"png"
    assert (b2["status"], b2["reason"]) == ("failed:crash", "NotImplementedError")

    def refusing_process(bundle_dir, config, *, bundle_id=None):
        raise ProcessingError("maps do not overlap", stage="align")

    monkeypatch.setattr(bench, "process_bundle", refusing_process)
    # b1's result from the run before must not be scored for this run.
    assert bench.main([str(tiny_set), "--out", str(outbox), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["bundles"]
    assert [(r["status"], r["reason"]) for r in rows] == [
        ("failed:align", "maps do not overlap")
    ] * 2


def test_bench_refuses_a_set_without_truth(bench, tiny_set, capsys):
    (tiny_set / "s1" / "truth" / "b2.yaml").unlink()
    assert bench.main([str(tiny_set), "--score-only", str(tiny_set)]) == 2
    assert "b2.yaml: no truth file" in capsys.readouterr().err
