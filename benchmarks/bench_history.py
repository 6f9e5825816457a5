"""Run the fleet map update over site histories and score the final maps (contract section 7).

A set holds one directory per history (or SET is one history directory)::

    SET/<history>/history.yaml           the truth: map name and true changes
    SET/<history>/reference/nav2_map.yaml  the building map, registered as version 1
    SET/<history>/bundles/<bundle_id>/   the bundles, over days, from several robots
    SET/<history>/truth/<bundle_id>.yaml   each bundle's section-4 truth

Usage::

    .venv/bin/python benchmarks/bench_history.py /work/shared/bench/public-history
    .venv/bin/python benchmarks/bench_history.py SET --out /tmp/hist1 --keep

For each history, in a fresh work directory: a configuration with the map update on
(``update: {mode: auto, confirm_sessions: 3, confirm_span_hours: 12}``), then
``mapserver maps add <map> reference/nav2_map.yaml`` and ONE ``mapserver process`` of all its
bundles (the command applies them in stamp order itself), timed. Then the final
``maps/<map>/current.yaml`` is scored against the reference (:mod:`mapserver.history_scoring`),
each bundle's ``result.yaml`` against its truth (section 4, as ``bench_public.py`` does), and
``maps/<map>/changes.yaml`` gives the versions published and the tracked changes' states.

It prints, per history, a row per true change and a summary line, then a TOTAL line; with
``--out DIR`` the same goes to ``DIR/bench_history.yaml``. It is a measurement: bundles that fail
are reported, not fatal. Exit code 0 when every history was scored, 1 when one could not be (the
map store is missing, ``maps add`` failed, no ``current.yaml``), 2 for a usage error.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

# benchmarks/ is on sys.path when a script in it runs: the section-4 half is bench_public's.
from bench_public import Case, Row, UsageError, find_cases, score_outbox

from mapserver.history_scoring import (
    FALSE_EDIT_MARGIN_M,
    ChangeScore,
    History,
    HistoryScore,
    HistoryTotals,
    polygon_mask,
    read_history,
    score_history,
    summarize_histories,
)
from mapserver.maps import OccupancyMap, load_map
from mapserver.scoring import Summary, summarize

log = logging.getLogger("bench_history")

CONFIRM_SESSIONS = 3
CONFIRM_SPAN_HOURS = 12
REFERENCE = Path("reference") / "nav2_map.yaml"
REPORT = "bench_history.yaml"


class SetupError(Exception):
    """The server could not run the history at all (the map store, ``maps add``, no final map)."""


@dataclass(frozen=True)
class Tracked:
    """One tracked change of ``changes.yaml``: what the benchmark reads of it."""

    id: Any
    kind: str
    state: str
    polygon_xy: Any


@dataclass
class HistoryRun:
    """Everything measured on one history."""

    name: str
    history_dir: Path
    history: History
    cases: list[Case]
    work: Path
    added: bool = False
    """Whether ``maps add`` succeeded."""
    seconds: float | None = None
    process_exit: int | None = None
    process_errors: list[str] = field(default_factory=list)
    error: str | None = None
    score: HistoryScore | None = None
    rows: list[Row] = field(default_factory=list)
    current_version: int | None = None
    tracked: list[Tracked] = field(default_factory=list)
    overlaps: dict[Any, list[Tracked]] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Running the server


def find_histories(set_dir: Path) -> list[Path]:
    """The history directories of a set, or the set itself when it is one history."""
    if (set_dir / "history.yaml").is_file():
        return [set_dir]
    found = sorted(p.parent for p in set_dir.glob("*/history.yaml"))
    if not found:
        raise UsageError(f"{set_dir}: no history (expected <history>/history.yaml)")
    return found


def _mapserver_command() -> Path:
    command = Path(sys.executable).parent / "mapserver"
    if not command.exists():
        raise UsageError(
            f"no 'mapserver' command beside {sys.executable} (is the package installed?)"
        )
    return command


def write_config(work: Path, *, mode: str) -> Path:
    """A configuration in ``work`` with the map update on; its folders made."""
    for name in ("inbox", "outbox", "archive", "failed"):
        (work / name).mkdir(parents=True)
    config = {
        "inbox": "./inbox",
        "outbox": "./outbox",
        "archive": "./archive",
        "failed": "./failed",
        "maps": "./maps",
        "update": {
            "mode": mode,
            "confirm_sessions": CONFIRM_SESSIONS,
            "confirm_span_hours": CONFIRM_SPAN_HOURS,
        },
    }
    path = work / "mapserver.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def _run(command: list[str], log_path: Path, timeout_s: float) -> subprocess.CompletedProcess[str]:
    """Run a command, its output appended to ``log_path`` after the command line."""
    try:
        done = subprocess.run(
            command, capture_output=True, text=True, timeout=timeout_s, check=False
        )
    except subprocess.TimeoutExpired:
        raise SetupError(f"timed out after {timeout_s:g} s: {shlex.join(command)}") from None
    with log_path.open("a", encoding="utf-8") as f:
        f.write(f"$ {shlex.join(command)}\n{done.stdout}{done.stderr}(exit {done.returncode})\n")
    return done


def _last_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = (done.stderr or done.stdout).strip().splitlines()
    return lines[-1] if lines else f"exit code {done.returncode}"


def run_history(run: HistoryRun, mapserver: str, *, mode: str, timeout_s: float) -> None:
    """``maps add`` then one ``mapserver process`` of every bundle, in ``run.work``.

    Raises :class:`SetupError` when ``maps add`` fails (nothing else can be measured then).
    """
    config = write_config(run.work, mode=mode)
    log_path = run.work / "commands.log"
    add = [mapserver, "maps", "add", run.history.map, str(run.history_dir / REFERENCE)]
    done = _run([*add, "--config", str(config)], log_path, timeout_s)
    if done.returncode != 0:
        # Exit 2 is argparse's: this mapserver has no `maps` command (no fleet map store).
        hint = "; has this mapserver the fleet map store?" if done.returncode == 2 else ""
        raise SetupError(
            f"`mapserver maps add` failed (exit {done.returncode}{hint}): {_last_line(done)}"
        )
    run.added = True
    bundles = [str(case.bundle_dir) for case in run.cases]
    command = [mapserver, "process", "--config", str(config), "--outbox", str(run.work / "outbox")]
    start = time.perf_counter()
    done = _run([*command, *bundles], log_path, timeout_s)
    run.seconds = time.perf_counter() - start
    run.process_exit = done.returncode
    # `process` exits 1 when some bundle failed: those are reported with the scores.
    run.process_errors = [
        line.removeprefix("mapserver: error: ")
        for line in done.stderr.splitlines()
        if line.startswith("mapserver: error: ")
    ]
    if done.returncode not in (0, 1):
        run.process_errors.append(f"mapserver process exited {done.returncode}: {_last_line(done)}")
    log.info("%s: processed %d bundles in %.1f s", run.name, len(bundles), run.seconds)


# --------------------------------------------------------------------------------------------
# Scoring


def read_changes(path: Path) -> tuple[int | None, list[Tracked]]:
    """``current_version`` and the tracked changes of ``changes.yaml`` (section 7)."""
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
        version = doc.get("current_version")
        changes = [
            Tracked(c.get("id"), str(c.get("kind")), str(c.get("state")), c.get("polygon"))
            for c in doc.get("changes") or []
        ]
    except (OSError, yaml.YAMLError, AttributeError, TypeError) as error:
        log.warning("%s: cannot read the tracked changes: %s", path, error)
        return None, []
    return (version if isinstance(version, int) else None), changes


def tracked_overlaps(
    reference: OccupancyMap, history: History, tracked: Sequence[Tracked]
) -> dict[Any, list[Tracked]]:
    """For each true change, the tracked changes with a cell within the false-edit margin of it."""
    masks = []
    for t in tracked:
        try:
            masks.append((t, polygon_mask(reference, t.polygon_xy)))
        except (ValueError, TypeError):
            log.warning("tracked change %s: unreadable polygon", t.id)
    out = {}
    for change in history.changes:
        near = polygon_mask(reference, change.polygon_xy, grow_m=FALSE_EDIT_MARGIN_M)
        out[change.id] = [t for t, mask in masks if (mask & near).any()]
    return out


def score_run(run: HistoryRun) -> None:
    """Score the final map, the per-bundle results and read the tracked changes of ``run``."""
    maps_dir = run.work / "maps" / run.history.map
    run.rows = score_outbox(run.cases, run.work / "outbox")
    run.current_version, run.tracked = read_changes(maps_dir / "changes.yaml")
    current = maps_dir / "current.yaml"
    if not current.is_file():
        raise SetupError(f"no final map {current} (the map update did not run?)")
    reference = load_map(run.history_dir / REFERENCE)
    try:
        run.score = score_history(
            reference,
            load_map(current),
            run.history,
            confirm_sessions=CONFIRM_SESSIONS,
            confirm_span_hours=CONFIRM_SPAN_HOURS,
        )
    except ValueError as error:
        raise SetupError(f"{current}: {error}") from None
    run.overlaps = tracked_overlaps(reference, run.history, run.tracked)


# --------------------------------------------------------------------------------------------
# The report


def _r(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def _update_ms(rows: Sequence[Row]) -> list[float]:
    return [row.timings_ms["update"] for row in rows if "update" in row.timings_ms]


def _stats_ms(values: Sequence[float]) -> dict[str, Any]:
    if not values:
        return {"n": 0, "median": None, "p90": None, "max": None}
    return {
        "n": len(values),
        "median": _r(np.median(values), 2),
        "p90": _r(np.percentile(values, 90), 2),
        "max": _r(max(values), 2),
    }


def _bundles(summary: Summary) -> dict[str, Any]:
    some = summary.n_bundles > 0
    return {
        "bundles": summary.n_bundles,
        "failures": summary.n_failures,
        "precision": _r(summary.precision) if some else None,
        "recall": _r(summary.recall) if some else None,
        "f1": _r(summary.f1) if some else None,
    }


def _change_doc(run: HistoryRun, c: ChangeScore) -> dict[str, Any]:
    truth = next(t for t in run.history.changes if t.id == c.id)
    return {
        "id": c.id,
        "kind": c.kind,
        "shape": truth.shape,
        "sessions": truth.sessions,
        "span_h": _r(truth.span_hours, 2),
        "role": c.role,
        "expected": c.expected,
        "held": c.held,
        "cells": c.cells,
        "of_cells": c.of_cells,
        "tracked": [{"id": t.id, "kind": t.kind, "state": t.state} for t in run.overlaps[c.id]],
    }


def history_doc(run: HistoryRun) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "name": run.name,
        "map": run.history.map,
        "error": run.error,
        "seconds": _r(run.seconds, 2),
        "process_exit": run.process_exit,
        "process_errors": run.process_errors,
    }
    if run.score is None:
        return doc
    s = run.score
    doc.update(
        {
            "changes": [_change_doc(run, c) for c in s.changes],
            "expected": s.n_expected,
            "expected_held": s.n_expected_held,
            "update_recall": _r(s.update_recall),
            "temporaries": s.n_temporaries,
            "temporaries_in_map": s.n_temporaries_in_map,
            "false_edit_cells": s.false_edit_cells,
            "false_edit_m2": _r(s.false_edit_m2),
            "current_version": run.current_version,
            "versions_published": None if run.current_version is None else run.current_version - 1,
            "tracked_by_state": dict(Counter(t.state for t in run.tracked).most_common()),
            "per_bundle": _bundles(summarize(row.score for row in run.rows)),
            "update_ms": _stats_ms(_update_ms(run.rows)),
            "bundles": [
                {
                    "bundle": row.case.bundle_id,
                    "status": row.status,
                    "reason": row.reason,
                    "precision": _r(row.score.precision),
                    "recall": _r(row.score.recall),
                    "f1": _r(row.score.f1),
                    "update_ms": row.timings_ms.get("update"),
                }
                for row in run.rows
            ],
        }
    )
    return doc


def report(runs: Sequence[HistoryRun], *, set_dir: Path, mode: str, command: str) -> dict[str, Any]:
    """The machine-readable summary (what ``--out`` writes)."""
    scored = [run for run in runs if run.score is not None]
    totals: HistoryTotals = summarize_histories(run.score for run in scored if run.score)
    rows = [row for run in scored for row in run.rows]
    versions = [run.current_version - 1 for run in scored if run.current_version is not None]
    return {
        "command": command,
        "set": str(set_dir),
        "mode": mode,
        "confirm_sessions": CONFIRM_SESSIONS,
        "confirm_span_hours": CONFIRM_SPAN_HOURS,
        "histories": [history_doc(run) for run in runs],
        "total": {
            "histories": len(runs),
            "scored": len(scored),
            "expected": totals.n_expected,
            "expected_held": totals.n_expected_held,
            "update_recall": _r(totals.update_recall) if scored else None,
            "temporaries": totals.n_temporaries,
            "temporaries_in_map": totals.n_temporaries_in_map,
            "false_edit_m2": _r(totals.false_edit_m2),
            "false_edit_m2_max": _r(totals.false_edit_m2_max),
            "versions_published": sum(versions) if versions else None,
            "per_bundle": _bundles(summarize(row.score for row in rows)),
            "update_ms": _stats_ms(_update_ms(rows)),
            "seconds": _r(sum(run.seconds or 0.0 for run in runs), 2),
        },
    }


def _fmt(value: Any, spec: str = "") -> str:
    return "n/a" if value is None else format(value, spec)


def _prf(b: dict[str, Any]) -> str:
    return "/".join(_fmt(b[k], ".3f") for k in ("precision", "recall", "f1"))


def _detail(c: dict[str, Any]) -> str:
    if c["kind"] == "removed":
        text = f"{c['cells']}/{c['of_cells']} erased cells no longer occupied"
    else:
        text = f"{c['cells']} cells turned occupied (of {c['of_cells']})"
    tracked = ", ".join(f"#{t['id']} {t['kind']} {t['state']}" for t in c["tracked"]) or "none"
    return f"{text}; tracked: {tracked}"


_EXPECTED = {"expected": "yes", "temporary": "temp", "unconfirmable": "no"}


def format_report(doc: dict[str, Any]) -> str:
    """The human-readable table of a :func:`report`."""
    lines = [f"$ {doc['command']}"]
    header = f"  {'id':>4} {'kind':<9} {'shape':<11} {'sess':>4} {'span_h':>6} {'expected':<8} {'held':<4}  detail"
    for h in doc["histories"]:
        lines.append(
            f"{h['name']} (map {h['map']}): process {_fmt(h['seconds'], '.1f')} s, "
            f"exit {_fmt(h['process_exit'])}"
        )
        if h["error"]:
            lines.append(f"  NOT SCORED: {h['error']}")
        lines += [f"  bundle failed: {reason}" for reason in h["process_errors"]]
        if "changes" not in h:
            continue
        lines += [header, "  " + "-" * (len(header) - 2)]
        for c in h["changes"]:
            lines.append(
                f"  {c['id']!s:>4} {c['kind']:<9} {_fmt(c['shape']):<11} {c['sessions']:>4} "
                f"{_fmt(c['span_h'], '6.1f'):>6} {_EXPECTED[c['role']]:<8} "
                f"{'yes' if c['held'] else 'no':<4}  {_detail(c)}"
            )
        b, u = h["per_bundle"], h["update_ms"]
        states = ", ".join(f"{k} {v}" for k, v in h["tracked_by_state"].items()) or "none"
        lines.append(
            f"  recall {h['expected_held']}/{h['expected']} = {h['update_recall']:.3f}  "
            f"temporaries in map {h['temporaries_in_map']}/{h['temporaries']}  "
            f"false edits {h['false_edit_m2']:.3f} m2 ({h['false_edit_cells']} cells)  "
            f"versions published {_fmt(h['versions_published'])}  tracked: {states}  "
            f"bundles P/R/F1 {_prf(b)} ({b['failures']} failed)  update ms median {_fmt(u['median'], '.1f')} "
            f"max {_fmt(u['max'], '.1f')}  {_fmt(h['seconds'], '.1f')} s"
        )
    t = doc["total"]
    b, u = t["per_bundle"], t["update_ms"]
    lines.append(
        f"TOTAL {t['scored']}/{t['histories']} histories scored: update recall "
        f"{t['expected_held']}/{t['expected']} = {_fmt(t['update_recall'], '.3f')}  "
        f"temporaries in map {t['temporaries_in_map']}/{t['temporaries']}  "
        f"false edits {t['false_edit_m2']:.3f} m2 (max {t['false_edit_m2_max']:.3f} per history)  "
        f"versions published {_fmt(t['versions_published'])}  "
        f"bundles P/R/F1 {_prf(b)} ({b['failures']}/{b['bundles']} failed)  update ms median/p90/max "
        f"{_fmt(u['median'], '.1f')}/{_fmt(u['p90'], '.1f')}/{_fmt(u['max'], '.1f')} "
        f"(n={u['n']})  {t['seconds']:.1f} s"
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The command


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bench_history.py", description=__doc__.split("\n\n")[0] if __doc__ else None
    )
    parser.add_argument("set_dir", type=Path, metavar="SET")
    parser.add_argument("--out", type=Path, default=None, help=f"write {REPORT} into this folder")
    parser.add_argument(
        "--keep", action="store_true", help="keep the work folders (configuration, maps, outbox)"
    )
    parser.add_argument(
        "--mode",
        choices=["auto"],
        default="auto",
        help="update mode (only auto: review would need every confirmed change approved)",
    )
    parser.add_argument(
        "--timeout", type=float, default=3600.0, help="seconds per mapserver command"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    command = shlex.join([sys.executable, sys.argv[0], *(sys.argv[1:] if argv is None else argv)])
    root = Path(tempfile.mkdtemp(prefix="bench-history-"))
    runs: list[HistoryRun] = []
    try:
        mapserver = str(_mapserver_command())
        for history_dir in find_histories(args.set_dir):
            try:
                history = read_history(history_dir / "history.yaml")
            except ValueError as error:
                raise UsageError(str(error)) from None
            cases = find_cases(history_dir)
            work = root / history_dir.name
            runs.append(HistoryRun(history_dir.name, history_dir, history, cases, work))
    except UsageError as error:
        sys.stderr.write(f"bench_history: error: {error}\n")
        shutil.rmtree(root, ignore_errors=True)
        return 2
    blocked = None
    for run in runs:
        if blocked is not None:
            run.error = blocked
            continue
        try:
            run_history(run, mapserver, mode=args.mode, timeout_s=args.timeout)
            score_run(run)
        except SetupError as error:
            run.error = str(error)
            if not run.added:  # it would fail on the others too
                blocked = f"not run: `mapserver maps add` failed on {run.name}"
    doc = report(runs, set_dir=args.set_dir, mode=args.mode, command=command)
    sys.stdout.write(format_report(doc) + "\n")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / REPORT).write_text(yaml.safe_dump(doc, sort_keys=False))
        sys.stdout.write(f"report: {args.out / REPORT}\n")
    failed = [run for run in runs if run.score is None]
    for run in failed:
        sys.stderr.write(f"bench_history: error: {run.name}: {run.error}\n")
    if args.keep:
        sys.stdout.write(f"work folders (configuration, commands.log, maps, outbox) in {root}\n")
    else:
        shutil.rmtree(root, ignore_errors=True)
        if failed:
            sys.stderr.write(
                "bench_history: --keep keeps the work folders and their commands.log\n"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
