"""Where the pipeline lost each missed change, and what let each false positive through: a
census of a ``bench_public.py`` run (issue 12's instrument).

Every bundle of SET whose result in OUTBOX misses a change or reports a false positive (every
bundle, with ``--all``) is processed again with observers on the pipeline's stages. For each
missed change it prints the cells of its polygon (grown by two cells) that the difference mask
of its kind holds, the removal evidence among them, the clusters made there (``clusters``:
before the area and evidence filters; ``kept``: after) and, for the kept ones, what each of the
re-fit's checks decided. Each miss gets the stage that lost it:

* ``not compared``: the bundle was not compared (untrusted, failed);
* ``no mask``: no cell of the change in the difference mask (unseen, or within a tolerance);
* ``filtered``: in the mask, but every cluster there too small or without evidence;
* ``judged``: a kept cluster that a re-fit check explained away (``floor``, ``faces``,
  ``refit``, ``pass``, ``ghost``: see ``pipeline._refit``);
* ``reported``: a difference was reported there, yet it does not match the change (its box
  too large, its kind wrong...).

For each false positive it prints the checks it passed. With ``--all``, every difference the
re-fit judged is listed with its label (contract section 4: ``correct``, ``neutral``,
``false_positive``) and the check that decided it, and a table counts them by check and label:
the census behind the thresholds in ``pipeline.py``.

Usage::

    .venv/bin/python benchmarks/bench_public.py SET --out /tmp/run
    .venv/bin/python benchmarks/census.py SET /tmp/run [BUNDLE_SUBSTRING ...] [--all]

The observers wrap module-level functions of the pipeline (``OBSERVED``); a test runs this
script on a bundle, so a stage renamed in the pipeline breaks that test, not a census.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np
import yaml
from bench_public import Case, find_cases  # benchmarks/ is on sys.path when a script in it runs
from numpy.typing import NDArray

from mapserver import cluster as cluster_stage
from mapserver import pipeline
from mapserver import refit as refit_stage
from mapserver.config import Config, load_config
from mapserver.grid import Grid
from mapserver.scoring import (
    Change,
    Difference,
    Result,
    Truth,
    parse_result,
    parse_truth,
    score_bundle,
)

# The re-fit's checks (pipeline._refit, in its order): the function, and whether its value
# explains a difference away.
_CHECKS: dict[str, tuple[ModuleType, str, Callable[[Any, dict[str, Any]], bool]]] = {
    "floor": (
        refit_stage,
        "floor_seen_share",
        lambda share, _: bool(share < pipeline._FLOOR_SEEN_SHARE),
    ),
    "faces": (
        refit_stage,
        "faces_seen_from_behind",
        lambda faces, kwargs: pipeline._folded(faces, kwargs["resolution"]),
    ),
    "refit": (refit_stage, "explained_by_refit", lambda value, _: bool(value)),
    "pass": (pipeline, "_seen_on_another_pass", lambda value, _: bool(value)),
    "ghost": (refit_stage, "ghost_of_wall", lambda value, _: bool(value)),
}
# Every function observed: (module, name).
OBSERVED = (
    (pipeline, "_diff"),
    (cluster_stage, "cluster_mask"),
    *((module, name) for module, name, _ in _CHECKS.values()),
)
CHECKS = tuple(_CHECKS)
# A change's polygon is grown by this many cells to count the mask under it (the masks of a
# drifted map lie a cell or two off the truth).
GROW_PX = 2


@dataclass(frozen=True)
class Verdict:
    """What one re-fit check made of a difference: ``explained`` (the check drops it)."""

    check: str
    explained: bool
    value: str


@dataclass
class Trace:
    """What one run of the pipeline on a bundle showed (the last comparison it made)."""

    grid: Grid | None = None
    masks: Any = None
    evidence: NDArray[np.bool_] | None = None
    clusters: list[cluster_stage.Difference] = field(default_factory=list)
    kept: list[cluster_stage.Difference] = field(default_factory=list)
    verdicts: dict[bytes, list[Verdict]] = field(default_factory=dict)

    def of(self, difference: cluster_stage.Difference) -> list[Verdict]:
        return self.verdicts.get(_key(difference.cells), []) if difference.cells is not None else []


def _key(cells: NDArray[np.intp]) -> bytes:
    return np.ascontiguousarray(cells).tobytes()


@contextmanager
def observing(trace: Trace) -> Iterator[Trace]:
    """The pipeline's stages wrapped so that ``trace`` collects what they made; undone on
    exit."""
    originals = {(module, name): getattr(module, name) for module, name in OBSERVED}
    diff = originals[(pipeline, "_diff")]
    cluster_mask = originals[(cluster_stage, "cluster_mask")]

    def observed_diff(aligned: Any, *args: Any, **kwargs: Any) -> Any:
        masks, evidence = diff(aligned, *args, **kwargs)
        trace.grid, trace.masks, trace.evidence = aligned.view.grid, masks, evidence
        trace.clusters.clear()
        trace.kept.clear()
        trace.verdicts.clear()
        return masks, evidence

    def observed_cluster_mask(mask: Any, grid: Grid, kind: str, **kwargs: Any) -> Any:
        kept = cluster_mask(mask, grid, kind, **kwargs)
        unfiltered = {**kwargs, "min_area_m2": 0.0, "evidence": None}
        trace.clusters.extend(cluster_mask(mask, grid, kind, **unfiltered))
        trace.kept.extend(kept)
        return kept

    def check(
        name: str, function: Callable[..., Any], verdict: Callable[[Any, dict[str, Any]], bool]
    ) -> Callable[..., Any]:
        """``function``, the re-fit check ``name``, recording its verdict on the cells it was
        given (its first argument, or that difference's cells)."""

        def observed(first: Any, *args: Any, **kwargs: Any) -> Any:
            value = function(first, *args, **kwargs)
            cells = first if isinstance(first, np.ndarray) else first.cells
            trace.verdicts.setdefault(_key(cells), []).append(
                Verdict(name, verdict(value, kwargs), _shown(value))
            )
            return value

        return observed

    wrapped = {
        (pipeline, "_diff"): observed_diff,
        (cluster_stage, "cluster_mask"): observed_cluster_mask,
        **{
            (module, attr): check(name, originals[(module, attr)], verdict)
            for name, (module, attr, verdict) in _CHECKS.items()
        },
    }
    try:
        for (module, name), function in wrapped.items():
            setattr(module, name, function)
        yield trace
    finally:
        for (module, name), function in originals.items():
            setattr(module, name, function)


def _shown(value: Any) -> str:
    if isinstance(value, refit_stage.Faces):
        return f"depth {value.depth_m:.2f} m, walls {value.walls}, behind {value.behind_share:.2f}"
    if isinstance(value, float | np.floating):
        return f"{float(value):.2f}"
    return str(bool(value))


def polygon_cells(grid: Grid, change: Change, grow_px: int) -> NDArray[np.bool_]:
    """(H, W) bool: the cells of ``grid`` inside the change's polygon, grown by ``grow_px``."""
    mask = np.zeros(grid.shape, np.uint8)
    corners = np.rint(grid.to_pixel(change.polygon_xy)).astype(np.int32)
    cv2.fillPoly(mask, [corners], 1)
    if grow_px:
        mask = cv2.dilate(mask, np.ones((2 * grow_px + 1,) * 2, np.uint8))
    return mask.astype(bool)


def _inside(
    differences: list[cluster_stage.Difference], kind: str, cells: NDArray[np.bool_]
) -> list[tuple[cluster_stage.Difference, int]]:
    """The differences of ``kind`` with cells in ``cells``, and how many."""
    out = []
    for d in differences:
        if d.kind != kind or d.cells is None:
            continue
        n = int(cells[d.cells[:, 0], d.cells[:, 1]].sum())
        if n:
            out.append((d, n))
    return out


def _decided(verdicts: list[Verdict]) -> str:
    """The check that explained a difference away, else ``reported``."""
    return next((v.check for v in verdicts if v.explained), "reported")


def _as_scored(d: cluster_stage.Difference, index: int) -> Difference:
    """A difference as scoring reads it (as if reported)."""
    min_x, min_y, max_x, max_y = d.bbox
    return Difference(index, d.kind, (d.centroid[0], d.centroid[1]), (min_x, min_y, max_x, max_y))


def miss_line(change: Change, trace: Trace, reported: bool) -> tuple[str, str]:
    """The stage that lost ``change`` and a line that says what each stage held of it."""
    p = change.polygon_xy
    head = (
        f"MISS {change.id} {change.kind} at ({p[:, 0].mean():.2f},{p[:, 1].mean():.2f}) "
        f"{np.ptp(p[:, 0]):.2f}x{np.ptp(p[:, 1]):.2f} m"
    )
    if trace.grid is None or trace.masks is None:
        return "not compared", f"{head}: not compared"
    grown = polygon_cells(trace.grid, change, GROW_PX)
    mask = getattr(trace.masks, change.kind) & grown
    line = f"{head}: polygon {int(polygon_cells(trace.grid, change, 0).sum())} cells, mask "
    line += f"{int(mask.sum())}"
    if change.kind == "removed" and trace.evidence is not None:
        line += f", evidence {int((trace.evidence & mask).sum())}"
    clusters = _inside(trace.clusters, change.kind, grown)
    kept = _inside(trace.kept, change.kind, grown)
    line += "; clusters " + (", ".join(f"{n}/{d.pixels} px" for d, n in clusters) or "none")
    kept_text = ", ".join(
        f"{n}/{d.pixels} px ({', '.join(_verdict_text(v) for v in trace.of(d)) or 'no check'})"
        for d, n in kept
    )
    line += f"; kept {kept_text or 'none'}"
    if not mask.any():
        stage = "no mask"
    elif not kept:
        stage = "filtered"
    elif reported or any(_decided(trace.of(d)) == "reported" for d, _ in kept):
        stage = "reported"
    else:
        stage = "judged"
    return stage, f"{line} -> {stage}"


def _verdict_text(v: Verdict) -> str:
    return f"{v.check} {v.value}{' EXPLAINED' if v.explained else ''}"


@dataclass
class Census:
    """Counts over a set: misses by the stage that lost them; judged differences by check and
    label."""

    misses: Counter[tuple[str, str]] = field(default_factory=Counter)
    judged: Counter[tuple[str, str, str]] = field(default_factory=Counter)


def census_of_bundle(
    case: Case, truth: Truth, result: Result, config: Config, census: Census, *, every: bool
) -> list[str]:
    """Re-run one bundle with observers; its lines, and its counts added to ``census``."""
    score = score_bundle(truth, result)
    false_positives = [s for s in score.differences if s.label == "false_positive"]
    if not every and not score.unmatched_change_ids and not false_positives:
        return []
    trace = Trace()
    with observing(trace):
        outcome = pipeline.process_bundle(case.bundle_dir, config)
    alignment = outcome.result.get("alignment") or {}
    lines = [
        f"== {case.bundle_id}: pieces {alignment.get('pieces')}, trusted share "
        f"{alignment.get('trusted_share')}, drift {alignment.get('drift_m')} m"
    ]
    changes = {c.id: c for c in truth.changes}
    for change_id in score.unmatched_change_ids:
        change = changes[change_id]
        reported = any(
            d.kind == change.kind and _near(d.centroid_xy, change) for d in result.differences
        )
        stage, line = miss_line(change, trace, reported)
        census.misses[(change.kind, stage)] += 1
        lines.append("  " + line)
    reported_by_id = {d.id: d for d in result.differences}
    for fp in false_positives:
        d = reported_by_id[fp.difference_id]
        same = [k for k in trace.kept if np.allclose(k.centroid, d.centroid_xy, atol=0.01)]
        checks = "; ".join(", ".join(_verdict_text(v) for v in trace.of(k)) for k in same)
        lines.append(
            f"  FP #{d.id} {d.kind} at ({d.centroid_xy[0]:.2f},{d.centroid_xy[1]:.2f}): "
            f"checks {checks or 'none ran'}"
        )
    if every:
        judged = [k for k in trace.kept if trace.of(k)]
        labels = score_bundle(
            truth,
            Result("ok", tuple(_as_scored(k, i) for i, k in enumerate(judged))),
        ).differences
        for k, s in zip(judged, labels, strict=True):
            decided = _decided(trace.of(k))
            census.judged[(k.kind, decided, s.label)] += 1
            lines.append(
                f"  JUDGED {s.label} {k.kind} at ({k.centroid[0]:.2f},{k.centroid[1]:.2f}) "
                f"{k.pixels} px -> {decided}: " + ", ".join(_verdict_text(v) for v in trace.of(k))
            )
    return lines


def _near(xy: tuple[float, float], change: Change, margin_m: float = 0.5) -> bool:
    lo, hi = change.polygon_xy.min(axis=0) - margin_m, change.polygon_xy.max(axis=0) + margin_m
    return bool(lo[0] <= xy[0] <= hi[0] and lo[1] <= xy[1] <= hi[1])


def summary_lines(census: Census) -> list[str]:
    lines = ["== misses by the stage that lost them"]
    for (kind, stage), n in sorted(census.misses.items()):
        lines.append(f"  {kind:8s} {stage:13s} {n:5d}")
    if census.judged:
        labels = ("correct", "neutral", "false_positive")
        lines.append("== differences the re-fit judged, by the check that decided (--all)")
        lines.append(f"  {'kind':8s} {'decided':9s} " + " ".join(f"{x:>14s}" for x in labels))
        for kind in ("added", "removed"):
            for decided in (*CHECKS, "reported"):
                row = [census.judged[(kind, decided, label)] for label in labels]
                if any(row):
                    lines.append(f"  {kind:8s} {decided:9s} " + " ".join(f"{n:14d}" for n in row))
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set_dir", type=Path, help="the benchmark set (as for bench_public.py)")
    parser.add_argument("outbox", type=Path, help="bench_public.py's --out of a run on it")
    parser.add_argument("bundles", nargs="*", help="only bundles whose id contains one of these")
    parser.add_argument("--all", action="store_true", help="every bundle and judged difference")
    parser.add_argument("--config", type=Path, help="the configuration the run used")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    census = Census()
    for case in find_cases(args.set_dir):
        if args.bundles and not any(b in case.bundle_id for b in args.bundles):
            continue
        result_path = args.outbox / case.bundle_id / "result.yaml"
        if not result_path.is_file():
            print(f"== {case.bundle_id}: no result in {args.outbox}")
            continue
        truth = parse_truth(yaml.safe_load(case.truth_path.read_text(encoding="utf-8")))
        result = parse_result(yaml.safe_load(result_path.read_text(encoding="utf-8")))
        for line in census_of_bundle(case, truth, result, config, census, every=args.all):
            print(line, flush=True)
    print("\n".join(summary_lines(census)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
