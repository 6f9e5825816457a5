"""Run the pipeline over a benchmark set and score the results against its truth (contract section 4).

A set is laid out as ``SET_DIR/<scenario>/bundles/<bundle_id>/`` with the truth at
``SET_DIR/<scenario>/truth/<bundle_id>.yaml`` (``SET_DIR`` may also be one scenario directory).
Usage::

    python benchmarks/bench_public.py /work/shared/bench/public                  # in-process
    python benchmarks/bench_public.py SET_DIR --out /tmp/run1 --config cfg.yaml
    python benchmarks/bench_public.py SET_DIR --cli          # via the installed `mapserver process`
    python benchmarks/bench_public.py SET_DIR --score-only OUTBOX --json   # score existing results

It prints one row per bundle and a total line (or, with ``--json``, one JSON document). It is a
measurement, not a test: the exit code is 0 whatever the scores, 2 only for a usage error (no
bundles, a bundle without its truth file, a bad configuration). A bundle that fails (an exception,
a result whose status is not ``ok``, no result) counts as a failure and the run goes on.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mapserver.bundle import read_manifest, safe_member
from mapserver.config import load_config
from mapserver.errors import MapserverError
from mapserver.maps import load_map
from mapserver.outbox import RESULT, write_result
from mapserver.pipeline import _DRIFTED_M, process_bundle
from mapserver.scoring import (
    RIGID_BEND_M,
    BundleScore,
    Summary,
    observed_centroid_xy,
    parse_result,
    parse_truth,
    score_bundle,
    summarize,
)

log = logging.getLogger("bench_public")


@dataclass(frozen=True)
class Case:
    """One bundle of the set and its truth file."""

    bundle_id: str
    bundle_dir: Path
    truth_path: Path
    kind: str = ""
    """The scenario's case (``scenario.yaml``'s ``case``, else the scenario folder's name)."""
    bend_m: float | None = None
    """How far the true local map bends from one rigid transform (metres; see
    :func:`_scenario_bend_m`), None when the scenario does not say."""


@dataclass(frozen=True)
class Run:
    """How running the pipeline on one bundle went."""

    ok: bool
    seconds: float
    reason: str | None = None
    stage: str | None = None


@dataclass(frozen=True)
class Row:
    """One bundle's line of the report."""

    case: Case
    score: BundleScore
    status: str
    seconds: float | None = None
    reason: str | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    trust: str = "-"
    """``trusted``, ``partly`` (a share of the local map compared), ``untrusted`` or ``-``."""
    aligned: str = "-"
    """How the local map was laid on the global map: see :func:`_alignment_class`."""


class UsageError(Exception):
    """The set or the options are wrong (exit code 2)."""


def find_cases(set_dir: Path) -> list[Case]:
    """Every bundle of a set (``<scenario>/bundles/<id>``) or of one scenario (``bundles/<id>``).

    Raises :class:`UsageError` when there is none, or when a bundle has no truth file.
    """
    bundle_dirs = sorted(set_dir.glob("*/bundles/*")) + sorted(set_dir.glob("bundles/*"))
    cases = []
    for bundle_dir in bundle_dirs:
        if not bundle_dir.is_dir() or bundle_dir.name.startswith("."):
            continue
        truth = bundle_dir.parent.parent / "truth" / f"{bundle_dir.name}.yaml"
        if not truth.is_file():
            raise UsageError(f"{truth}: no truth file for bundle {bundle_dir}")
        doc = _scenario_doc(bundle_dir)
        kind = _scenario_kind(doc, bundle_dir)
        cases.append(
            Case(bundle_dir.name, bundle_dir, truth, kind, _scenario_bend_m(doc, bundle_dir.name))
        )
    if not cases:
        raise UsageError(f"{set_dir}: no bundles (expected <scenario>/bundles/<bundle_id>/)")
    return cases


def _scenario_doc(bundle_dir: Path) -> dict[str, Any]:
    """The bundle's scenario's ``scenario.yaml`` (empty when it has none or it does not read)."""
    try:
        doc = yaml.safe_load((bundle_dir.parent.parent / "scenario.yaml").read_text())
    except (OSError, yaml.YAMLError):
        doc = None
    return doc if isinstance(doc, dict) else {}


def _scenario_kind(doc: dict[str, Any], bundle_dir: Path) -> str:
    case = doc.get("case")
    return str(case) if case else bundle_dir.parent.parent.name


def _scenario_bend_m(doc: dict[str, Any], bundle_id: str) -> float | None:
    """How far (metres) the true local map of ``bundle_id`` bends from one rigid transform: the
    simulator's record of its drift (``bundles[].drift.fit_max_residual_m``: the largest
    distance of a route pose from where the best rigid fit of the SLAM poses onto the true
    ones puts it). 0 for a scenario simulated without drift (no record, and its ``params`` do
    not ask for drift: the public set); None when the scenario does not say."""
    for b in doc.get("bundles") or ():
        if isinstance(b, dict) and b.get("id") == bundle_id:
            drift = b.get("drift")
            if isinstance(drift, dict) and isinstance(
                drift.get("fit_max_residual_m"), (int, float)
            ):
                return float(drift["fit_max_residual_m"])
    params = doc.get("params")
    if not isinstance(params, dict) or not doc.get("bundles"):
        return None
    asks_drift = params.get("drift") or any(
        isinstance(v, (int, float)) and v != 0
        for k, v in params.items()
        if str(k).startswith("drift_")
    )
    return None if asks_drift else 0.0


def _trust(doc: Any) -> str:
    """How far a result's alignment was trusted (FORMATS.md section 8), ``-`` when it says not."""
    alignment = doc.get("alignment") if isinstance(doc, dict) else None
    if not isinstance(alignment, dict) or "trusted" not in alignment:
        return "-"
    if not alignment["trusted"]:
        return "untrusted"
    share = alignment.get("trusted_share")
    return "partly" if isinstance(share, (int, float)) and share < 0.999 else "trusted"


def _alignment_class(doc: Any) -> str:
    """How a result's local map was laid on the global map: ``pieces`` (compared in pieces),
    ``drifted`` (whole, with a drift correction of ``pipeline._DRIFTED_M`` or more), ``fits``
    (whole, less), ``untrusted`` (not compared), ``-`` when the result does not say. The
    drifted and pieced bundles are where the pipeline's drift checks run, and where most of
    what it misses lies."""
    alignment = doc.get("alignment") if isinstance(doc, dict) else None
    if not isinstance(alignment, dict) or "trusted" not in alignment:
        return "-"
    if not alignment["trusted"]:
        return "untrusted"
    # ``whole_score`` is written only for a map compared in pieces; ``+pieces`` in the method
    # says only that pieces were tried (a map compared whole may have some).
    if "whole_score" in alignment:
        return "pieces"
    drift_m = alignment.get("drift_m")
    return "drifted" if isinstance(drift_m, (int, float)) and drift_m >= _DRIFTED_M else "fits"


def run_in_process(cases: Sequence[Case], outbox: Path, config_path: Path | None) -> dict[str, Run]:
    """Process every bundle with :func:`process_bundle` and write its result to ``outbox``."""
    try:
        config = load_config(config_path)
    except MapserverError as error:
        raise UsageError(error.reason) from None
    runs = {}
    for case in cases:
        start = time.perf_counter()
        try:
            outcome = process_bundle(case.bundle_dir, config, bundle_id=case.bundle_id)
            write_result(outbox, outcome)
        except MapserverError as error:
            run = Run(False, time.perf_counter() - start, error.reason, error.stage)
        except Exception as error:  # a crash in one bundle must not end the measurement
            log.debug("%s: crashed", case.bundle_id, exc_info=True)
            reason = f"{type(error).__name__}: {error}".rstrip(": ")
            run = Run(False, time.perf_counter() - start, reason, "crash")
        else:
            run = Run(True, time.perf_counter() - start)
        log.info("%s: %s in %.2f s", case.bundle_id, "ok" if run.ok else run.reason, run.seconds)
        runs[case.bundle_id] = run
    return runs


def _mapserver_command() -> str:
    beside = Path(sys.executable).parent / "mapserver"
    found = str(beside) if beside.exists() else shutil.which("mapserver")
    if not found:
        raise UsageError("--cli: no 'mapserver' command found (is the package installed?)")
    return found


def run_cli(
    cases: Sequence[Case], outbox: Path, config_path: Path | None, *, timeout_s: float
) -> dict[str, Run]:
    """Process every bundle with ``mapserver process``, one subprocess per bundle (so ``seconds``
    includes the interpreter's start-up)."""
    command = [_mapserver_command(), "process", "--outbox", str(outbox)]
    if config_path is not None:
        command += ["--config", str(config_path)]
    runs = {}
    for case in cases:
        start = time.perf_counter()
        try:
            done = subprocess.run(
                [*command, str(case.bundle_dir)],
                capture_output=True,
                text=True,
                timeout=timeout_s,
                check=False,
            )
        except subprocess.TimeoutExpired:
            run = Run(False, time.perf_counter() - start, f"timed out after {timeout_s:g} s", "cli")
        else:
            seconds = time.perf_counter() - start
            if done.returncode == 0:
                run = Run(True, seconds)
            else:
                lines = (done.stderr or done.stdout).strip().splitlines()
                reason = lines[-1] if lines else f"exit code {done.returncode}"
                run = Run(False, seconds, reason, "cli")
        log.info("%s: %s in %.2f s", case.bundle_id, "ok" if run.ok else run.reason, run.seconds)
        runs[case.bundle_id] = run
    return runs


def local_map_centre(bundle_dir: Path) -> tuple[float, float] | None:
    """Centre (slam frame, metres) of the observed area of the bundle's ``slam_map``, or ``None``
    when the map cannot be read (then no alignment error is computed)."""
    try:
        manifest = read_manifest(bundle_dir)
        path = safe_member(bundle_dir, manifest.slam_map, what="slam_map", source=bundle_dir)
        return observed_centroid_xy(load_map(path))
    except (MapserverError, OSError, ValueError, KeyError, TypeError) as error:
        log.warning("%s: no alignment error: cannot read the local map: %s", bundle_dir, error)
        return None


def _load_yaml(path: Path) -> Any:
    return yaml.safe_load(path.read_text(encoding="utf-8"))


def score_outbox(
    cases: Sequence[Case], outbox: Path, runs: dict[str, Run] | None = None
) -> list[Row]:
    """Score ``outbox/<bundle_id>/result.yaml`` of every case against its truth.

    With ``runs`` (from a run just made), a bundle whose run failed is a failure even if an
    older result lies in the outbox; without it (``--score-only``), whatever is there is scored.
    """
    rows = []
    for case in cases:
        try:
            truth = parse_truth(_load_yaml(case.truth_path))
        except (OSError, yaml.YAMLError, ValueError) as error:
            raise UsageError(f"{case.truth_path}: {error}") from None
        run = runs.get(case.bundle_id) if runs is not None else None
        seconds = run.seconds if run is not None else None
        result_path = outbox / case.bundle_id / RESULT
        if run is not None and not run.ok:
            score = score_bundle(truth, None)
            rows.append(Row(case, score, f"failed:{run.stage}", seconds, run.reason))
            continue
        if not result_path.is_file():
            rows.append(Row(case, score_bundle(truth, None), "missing", seconds, "no result.yaml"))
            continue
        try:
            raw = _load_yaml(result_path)
            result = parse_result(raw)
        except (OSError, yaml.YAMLError, ValueError) as error:
            reason = f"{result_path}: {' '.join(str(error).split())}"
            rows.append(Row(case, score_bundle(truth, None), "invalid", seconds, reason))
            continue
        centre = local_map_centre(case.bundle_dir) if result.ok else None
        score = score_bundle(truth, result, centre_slam_xy=centre)
        rows.append(
            Row(
                case,
                score,
                result.status,
                seconds,
                timings_ms=dict(result.timings_ms),
                trust=_trust(raw),
                aligned=_alignment_class(raw),
            )
        )
    return rows


def stage_medians_ms(rows: Sequence[Row]) -> dict[str, float]:
    """Median of each ``timings_ms`` stage over the bundles that report it, in first-seen order."""
    samples: dict[str, list[float]] = {}
    for row in rows:
        for stage, value in row.timings_ms.items():
            samples.setdefault(stage, []).append(value)
    return {stage: float(np.median(values)) for stage, values in samples.items()}


def _ratio(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


def _deg(value_rad: float | None) -> float | None:
    return None if value_rad is None else math.degrees(value_rad)


def report(rows: Sequence[Row], *, set_dir: Path, outbox: Path, mode: str) -> dict[str, Any]:
    """The machine-readable summary (what ``--json`` prints)."""
    total: Summary = summarize(row.score for row in rows)
    seconds = [row.seconds for row in rows if row.seconds is not None]
    bundles = []
    for row in rows:
        s = row.score
        bundles.append(
            {
                "bundle": row.case.bundle_id,
                "kind": row.case.kind,
                "bend_m": row.case.bend_m,
                "trust": row.trust,
                "status": row.status,
                "reason": row.reason,
                "differences": s.n_differences,
                "correct": s.n_correct,
                "false_positive": s.n_false_positive,
                "neutral": s.n_neutral,
                "observed": s.n_observed,
                "matched": s.n_matched,
                "fragments": s.n_fragments,
                "precision": _ratio(s.precision),
                "recall": _ratio(s.recall),
                "f1": _ratio(s.f1),
                "kind_accuracy": _ratio(s.kind_accuracy),
                "alignment_error_m": s.alignment_error_m,
                "alignment_error_deg": _deg(s.alignment_error_rad),
                "seconds": row.seconds,
                "timings_ms": row.timings_ms,
                "unmatched_changes": list(s.unmatched_change_ids),
                "labels": [
                    {
                        "id": d.difference_id,
                        "kind": d.kind,
                        "label": d.label,
                        "changes": list(d.matched_change_ids),
                        "assigned": d.assigned_change_id,
                        "kind_correct": d.kind_correct,
                    }
                    for d in s.differences
                ],
            }
        )
    return {
        "set": str(set_dir),
        "outbox": str(outbox),
        "mode": mode,
        "bundles": bundles,
        "total": {
            "bundles": total.n_bundles,
            "failures": total.n_failures,
            "differences": total.n_differences,
            "correct": total.n_correct,
            "false_positive": total.n_false_positive,
            "neutral": total.n_neutral,
            "observed": total.n_observed,
            "matched": total.n_matched,
            "fragments": total.n_fragments,
            "precision": _ratio(total.precision),
            "recall": _ratio(total.recall),
            "f1": _ratio(total.f1),
            "kind_accuracy": _ratio(total.kind_accuracy),
            "alignment_error_median_m": total.alignment_error_median_m,
            "alignment_error_p90_m": total.alignment_error_p90_m,
            "alignment_error_median_deg": _deg(total.alignment_error_median_rad),
            "alignment_error_p90_deg": _deg(total.alignment_error_p90_rad),
            "seconds_median": float(np.median(seconds)) if seconds else None,
            "seconds_total": float(sum(seconds)) if seconds else None,
            "stage_median_ms": stage_medians_ms(rows),
        },
        "kinds": kind_totals(rows),
        "alignments": alignment_totals(rows),
        "bends": bend_totals(rows),
    }


def kind_totals(rows: Sequence[Row]) -> dict[str, dict[str, Any]]:
    """The totals of each kind of scenario (its case), in first-seen order."""
    return _group_totals(rows, lambda row: row.case.kind)


# The order of the alignment totals: as the local map fits the global map less.
_ALIGNED_ORDER = ("fits", "drifted", "pieces", "untrusted", "-")


def alignment_totals(rows: Sequence[Row]) -> dict[str, dict[str, Any]]:
    """The totals of the bundles of each way of alignment (:func:`_alignment_class`), failed
    ones left out (their result does not say), in the order of ``_ALIGNED_ORDER``."""
    totals = _group_totals([r for r in rows if r.status == "ok"], lambda row: row.aligned)
    return {key: totals[key] for key in _ALIGNED_ORDER if key in totals}


def _bend_class(row: Row) -> str:
    """``rigid`` (the true map bends under ``RIGID_BEND_M``), ``bent`` (more), ``-`` (the
    scenario does not say)."""
    if row.case.bend_m is None:
        return "-"
    return "rigid" if row.case.bend_m < RIGID_BEND_M else "bent"


def bend_totals(rows: Sequence[Row]) -> dict[str, dict[str, Any]]:
    """The totals of the bundles whose true map is rigid, bent (:func:`_bend_class`) or does
    not say, in that order, failed ones included (a failure is scored as one)."""
    totals = _group_totals(rows, _bend_class)
    return {key: totals[key] for key in ("rigid", "bent", "-") if key in totals}


def _group_totals(rows: Sequence[Row], key: Callable[[Row], str]) -> dict[str, dict[str, Any]]:
    """The totals of the rows of each ``key``, in first-seen order."""
    groups: dict[str, list[Row]] = {}
    for row in rows:
        groups.setdefault(key(row), []).append(row)
    out = {}
    for name, group in groups.items():
        t = summarize(r.score for r in group)
        out[name] = {
            "bundles": t.n_bundles,
            "failures": t.n_failures,
            "untrusted": sum(r.trust == "untrusted" for r in group),
            "partly": sum(r.trust == "partly" for r in group),
            "correct": t.n_correct,
            "false_positive": t.n_false_positive,
            "observed": t.n_observed,
            "matched": t.n_matched,
            "precision": _ratio(t.precision),
            "recall": _ratio(t.recall),
            "f1": _ratio(t.f1),
            "kind_accuracy": _ratio(t.kind_accuracy),
            "alignment_error_p90_m": t.alignment_error_p90_m,
        }
    return out


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def format_report(doc: dict[str, Any]) -> str:
    """The human-readable table of a :func:`report`."""
    header = (
        f"{'bundle':<24} {'diffs':>5} {'TP':>4} {'FP':>4} {'neut':>4} {'obs':>4} {'match':>5} "
        f"{'frag':>4} {'P':>5} {'R':>5} {'F1':>5} {'kind':>5} {'align_m':>7} {'deg':>5} "
        f"{'sec':>6} {'trust':>9}  status"
    )
    lines = [header, "-" * len(header)]
    for b in doc["bundles"]:
        status = b["status"] if b["reason"] is None else f"{b['status']}: {b['reason']}"
        lines.append(
            f"{b['bundle']:<24} {b['differences']:>5} {b['correct']:>4} {b['false_positive']:>4} "
            f"{b['neutral']:>4} {b['observed']:>4} {b['matched']:>5} {b['fragments']:>4} "
            f"{b['precision']:>5.2f} {b['recall']:>5.2f} {b['f1']:>5.2f} "
            f"{_fmt(b['kind_accuracy'], '5.2f'):>5} {_fmt(b['alignment_error_m'], '7.3f'):>7} "
            f"{_fmt(b['alignment_error_deg'], '5.2f'):>5} {_fmt(b['seconds'], '6.2f'):>6} "
            f"{b['trust']:>9}  {status}"
        )
    t = doc["total"]
    stages = " ".join(f"{k}={v:.1f}" for k, v in t["stage_median_ms"].items()) or "-"
    lines += [
        "-" * len(header),
        f"TOTAL {t['bundles']} bundles, {t['failures']} failures: "
        f"precision {t['precision']:.3f}  recall {t['recall']:.3f}  F1 {t['f1']:.3f}  "
        f"kind accuracy {_fmt(t['kind_accuracy'], '.3f')}  "
        f"({t['correct']} correct, {t['false_positive']} FP, {t['neutral']} neutral, "
        f"{t['matched']}/{t['observed']} changes found, {t['fragments']} fragments)",
        f"alignment error median {_fmt(t['alignment_error_median_m'], '.3f')} m / "
        f"{_fmt(t['alignment_error_median_deg'], '.2f')} deg, "
        f"p90 {_fmt(t['alignment_error_p90_m'], '.3f')} m / "
        f"{_fmt(t['alignment_error_p90_deg'], '.2f')} deg",
        f"seconds median {_fmt(t['seconds_median'], '.2f')}, total "
        f"{_fmt(t['seconds_total'], '.1f')}; stage medians (ms): {stages}",
        f"results in {doc['outbox']} ({doc['mode']})",
    ]
    kinds = doc.get("kinds", {})
    if len(kinds) > 1:
        lines.append("per kind:")
        for kind, k in kinds.items():
            lines.append(
                _group_line(kind, k, f"kind {_fmt(k['kind_accuracy'], '.3f')}  ")
                + f"{k['matched']}/{k['observed']} found, {k['false_positive']} FP, "
                f"{k['untrusted']} untrusted, {k['partly']} partly, {k['failures']} failed"
            )
    alignments = doc.get("alignments", {})
    if len(alignments) > 1:
        lines.append(
            f"per alignment (fits: whole, drift correction under {_DRIFTED_M} m; drifted: "
            "whole, more; pieces: in pieces):"
        )
        for name, k in alignments.items():
            lines.append(
                _group_line(name, k) + f"{k['matched']}/{k['observed']} found, "
                f"{k['observed'] - k['matched']} missed, {k['false_positive']} FP"
            )
    bends = doc.get("bends", {})
    if set(bends) - {"-"}:  # some scenario says how far its true map bends
        lines.append(
            f"per true bend (rigid: the true local map within {RIGID_BEND_M} m of one rigid "
            "transform, a session without drift; bent: more; -: the scenario does not say):"
        )
        for name, k in bends.items():
            lines.append(
                _group_line(name, k) + f"{k['matched']}/{k['observed']} found, "
                f"{k['false_positive']} FP"
            )
    return "\n".join(lines)


def _group_line(name: str, k: dict[str, Any], middle: str = "") -> str:
    """The start of a group's line of totals (:func:`_group_totals`): its name, bundles,
    precision, recall, F1, then ``middle``, then the alignment error's p90."""
    return (
        f"  {name:<14} {k['bundles']:>3} bundles  P {_fmt(k['precision'], '.3f')}  "
        f"R {_fmt(k['recall'], '.3f')}  F1 {_fmt(k['f1'], '.3f')}  {middle}"
        f"align p90 {_fmt(k['alignment_error_p90_m'], '.3f')} m  "
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bench_public.py", description=__doc__.split("\n\n")[0] if __doc__ else None
    )
    parser.add_argument("set_dir", type=Path, metavar="SET_DIR")
    parser.add_argument("--out", type=Path, default=None, help="outbox (default: a new temp dir)")
    parser.add_argument("--config", type=Path, default=None, help="mapserver configuration file")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--cli", action="store_true", help="run `mapserver process` per bundle")
    mode.add_argument(
        "--score-only",
        type=Path,
        default=None,
        metavar="OUTBOX",
        help="do not run anything; score the results already in OUTBOX",
    )
    parser.add_argument("--timeout", type=float, default=600.0, help="--cli: seconds per bundle")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead")
    parser.add_argument("-v", "--verbose", action="store_true", help="log each bundle to stderr")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        cases = find_cases(args.set_dir)
        if args.score_only is not None:
            outbox, mode, runs = args.score_only, "score-only", None
        else:
            outbox = args.out or Path(tempfile.mkdtemp(prefix="bench-public-"))
            outbox.mkdir(parents=True, exist_ok=True)
            if args.cli:
                mode = "cli"
                runs = run_cli(cases, outbox, args.config, timeout_s=args.timeout)
            else:
                mode = "in-process"
                runs = run_in_process(cases, outbox, args.config)
        doc = report(
            score_outbox(cases, outbox, runs), set_dir=args.set_dir, outbox=outbox, mode=mode
        )
    except UsageError as error:
        sys.stderr.write(f"bench_public: error: {error}\n")
        return 2
    sys.stdout.write(json.dumps(doc, indent=2) + "\n" if args.json else format_report(doc) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
