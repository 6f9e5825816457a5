"""Where the pipeline lost each missed change, and what let each false positive through: a
census of a ``bench_public.py`` run (issue 12's instrument).

Every bundle of SET whose result in OUTBOX misses a change or reports a false positive (every
bundle, with ``--all``) is processed again with observers on the pipeline's stages. For each
missed change it prints what each stage held of it: the cells of its polygon (grown by two
cells) in the raw difference mask of its kind and in the filtered one, the removal evidence
among them, the clusters made there (``clusters``: before the area and evidence filters;
``kept``: after) and, for the kept ones, what each of the re-fit's checks measured. Each miss
gets the stage that lost it:

* ``not compared``: the bundle failed, or its alignment was not trusted;
* ``no difference``: no cell of it in the raw difference mask (not seen in the aligned local
  map, or within a tolerance of the global map);
* ``diff filters``: in the raw mask, but not after the noise floor and the strips along walls;
* ``clusters``: in the mask, but every cluster there too small or without removal evidence;
* ``judged``: a kept cluster, explained away by one of the re-fit's checks, in the order
  ``explain.unexplained`` asks them (``floor``, ``faces``, ``faint fold``, ``band``, ``refit``,
  ``pass``, ``left out``, ``ghost``, ``elsewhere``, ``in front``, ``through``, ``thin line``);
* ``reported``: a cluster there survived, yet no difference matches the change (too large a
  box, the wrong kind...).

Each compared miss also says how many of its polygon's cells the aligned local map knows
(``seen``) and how many lie where a part of the map was left out of the comparison (``left
out``: an untrusted piece, a region off the building). For each false positive it prints the
checks it passed. With ``--all``, every difference the
re-fit judged is listed with its label (``score_bundle`` on it as if reported: ``correct``,
``neutral``, ``false_positive``) and the check that decided it (the first to explain it, or
``reported``), and a table counts them by that check and label: the census behind the
thresholds in ``explain.py``. With a map store in the configuration, the fleet's own
comparison against the stored map's current version is not recorded.

Usage (the same ``--config`` as the run, if it had one)::

    .venv/bin/python benchmarks/bench_public.py SET --out /tmp/run
    .venv/bin/python benchmarks/census.py SET /tmp/run [BUNDLE_SUBSTRING ...] [--all]

``--counts FILE`` also writes the summary's counts as JSON: ``run_sets.py census`` runs this on
many sets and adds them up. ``--judged FILE`` (with ``--all`` implied) also writes every judged
difference as a JSON line: bundle, kind, centroid, pixels, area, label, the check that decided
and each check's verdict and measured values (a dataclass's fields and shares), the table
behind a threshold, to be read with a few lines of Python (session 49 wrote three hooks in /tmp
to get at these). ``--clusters FILE`` (with ``--all`` implied) writes every cluster the cluster
stage made, before its floors on area and evidence, one JSON line each: bundle, kind, centroid,
pixels, area, whether the floors kept it, its label as if reported, and for a removed one the
cells of it in the removal evidence and their share: what the floors drop, real and false
(session 50 wrote that census as a script in /tmp).

The observers wrap module-level functions of the pipeline (``OBSERVED``); its tests run this
script on bundles, and check that the checks' verdicts as recorded here drop exactly what the
re-fit drops, so a stage renamed or a rule changed in the pipeline breaks a test, not a census.
A re-run that does not report what the outbox holds (another configuration, another commit)
is said so (``MISMATCH``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
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
from mapserver import diff as diff_stage
from mapserver import explain, piecewise, pipeline
from mapserver import refit as refit_stage
from mapserver.config import Config, load_config
from mapserver.errors import MapserverError
from mapserver.grid import Grid, box_of_cells
from mapserver.maps import UNKNOWN
from mapserver.outbox import RESULT
from mapserver.scoring import (
    Change,
    Difference,
    Result,
    Truth,
    parse_result,
    parse_truth,
    score_bundle,
)

# The re-fit's checks (explain.unexplained, in its order): the function, and whether its value
# explains a difference away (its keyword arguments at hand). Each is given the difference's
# cells (or the difference) first, but ``left out``, which is given its cells' nav2 points
# third (``_POINTS_AT``).
_CHECKS: dict[str, tuple[ModuleType, str, Callable[[Any, dict[str, Any]], bool]]] = {
    # Asked of every removed cluster, drifted or not, before the re-fit (explain.faint).
    "faint": (
        refit_stage,
        "faint_strip",
        lambda strip, kwargs: explain._faint_strip(strip, kwargs["resolution"]),
    ),
    "floor": (
        refit_stage,
        "floor_seen_share",
        lambda share, _: bool(share < explain._FLOOR_SEEN_SHARE),
    ),
    "faces": (
        refit_stage,
        "faces_seen_from_behind",
        lambda faces, kwargs: explain._folded(faces, kwargs["resolution"]),
    ),
    "faint fold": (explain, "_faint_and_folded", lambda value, _: bool(value)),
    "band": (
        refit_stage,
        "band_in_structure",
        lambda band, kwargs: explain._face_displaced(band, kwargs["resolution"]),
    ),
    "refit": (refit_stage, "explained_by_refit", lambda value, _: bool(value)),
    "pass": (explain, "_seen_on_another_pass", lambda value, _: bool(value)),
    "left out": (piecewise, "left_out_pass_near", lambda value, _: bool(value)),
    "ghost": (refit_stage, "ghost_of_wall", lambda value, _: bool(value)),
    "elsewhere": (refit_stage, "wall_drawn_elsewhere", lambda value, _: bool(value)),
    "in front": (refit_stage, "face_drawn_in_front", lambda value, _: bool(value)),
    "through": (refit_stage, "line_through_wall", lambda value, _: bool(value)),
    "thin line": (refit_stage, "thin_line_by_wall", lambda value, _: bool(value)),
}
CHECKS = tuple(_CHECKS)
# The checks given a difference's cells as nav2 points, and where among their arguments.
_POINTS_AT = {"left out": 2}
# Every function observed: (module, name).
OBSERVED = (
    (pipeline, "_diff"),
    (diff_stage, "raw_differences"),
    (cluster_stage, "cluster_mask"),
    (pipeline, "_judged_on_current"),
    *((module, name) for module, name, _ in _CHECKS.values()),
)
STAGES = ("not compared", "no difference", "diff filters", "clusters", "judged", "reported")
# A change's polygon is grown by this many cells to count the masks under it (the masks of a
# drifted map lie a cell or two off the truth).
GROW_PX = 2


@dataclass(frozen=True)
class Verdict:
    """What one re-fit check made of a difference: ``explained`` (the check drops it), what
    it measured as text, and the check's own value (``--judged`` writes it out)."""

    check: str
    explained: bool
    shown: str
    value: Any = field(default=None, compare=False)


@dataclass
class Trace:
    """What one run of the pipeline on a bundle showed: its comparison against the bundle's
    own global map (``compared``: False when its alignment was not trusted)."""

    compared: bool = False
    grid: Grid | None = None
    # The global and the aligned local map as compared, and the cells left out of the
    # comparison (None: none).
    global_state: NDArray[np.uint8] | None = None
    local_state: NDArray[np.uint8] | None = None
    left_out: NDArray[np.bool_] | None = None
    raw: diff_stage.DiffMasks | None = None
    masks: diff_stage.DiffMasks | None = None
    evidence: NDArray[np.bool_] | None = None
    clusters: list[cluster_stage.Difference] = field(default_factory=list)
    kept: list[cluster_stage.Difference] = field(default_factory=list)
    verdicts: dict[bytes, list[Verdict]] = field(default_factory=dict)
    # While the fleet's comparison against the stored map's current version runs.
    paused: bool = False

    def of(self, difference: cluster_stage.Difference) -> list[Verdict]:
        """The verdicts on ``difference``, in the order the re-fit asked them: those recorded
        on its cells and on their nav2 points (``explain._nav2_points`` on this trace's grid,
        as the re-fit makes them)."""
        if difference.cells is None:
            return []
        verdicts = list(self.verdicts.get(_key(difference.cells), []))
        if self.grid is not None:
            points = explain._nav2_points(self.grid, difference.cells)
            verdicts += self.verdicts.get(_key(points), [])
        return sorted(verdicts, key=lambda v: CHECKS.index(v.check))


def _key(cells: NDArray[Any]) -> bytes:
    return np.ascontiguousarray(cells).tobytes()


@contextmanager
def observing(trace: Trace) -> Iterator[Trace]:
    """The pipeline's stages wrapped so that ``trace`` collects what they made; undone on exit,
    whatever happens."""
    originals = {(module, name): getattr(module, name) for module, name in OBSERVED}

    def observed_diff(aligned: Any, *args: Any, **kwargs: Any) -> Any:
        masks, evidence = originals[(pipeline, "_diff")](aligned, *args, **kwargs)
        trace.compared = bool(aligned.compared)
        trace.grid, trace.masks, trace.evidence = aligned.view.grid, masks, evidence
        trace.local_state, trace.left_out = aligned.local_state, aligned.left_out
        trace.global_state = aligned.view.state
        return masks, evidence

    def observed_raw(*args: Any, **kwargs: Any) -> Any:
        raw = originals[(diff_stage, "raw_differences")](*args, **kwargs)
        if not trace.paused:
            trace.raw = raw
        return raw

    def observed_cluster_mask(mask: Any, grid: Grid, kind: str, **kwargs: Any) -> Any:
        cluster_mask = originals[(cluster_stage, "cluster_mask")]
        kept = cluster_mask(mask, grid, kind, **kwargs)
        if not trace.paused:
            unfiltered = {**kwargs, "min_area_m2": 0.0, "evidence": None}
            trace.clusters.extend(cluster_mask(mask, grid, kind, **unfiltered))
            trace.kept.extend(kept)
        return kept

    def observed_current(*args: Any, **kwargs: Any) -> Any:
        trace.paused = True
        try:
            return originals[(pipeline, "_judged_on_current")](*args, **kwargs)
        finally:
            trace.paused = False

    def check(
        name: str, function: Callable[..., Any], verdict: Callable[[Any, dict[str, Any]], bool]
    ) -> Callable[..., Any]:
        """``function``, the re-fit check ``name``, recording its verdict on the cells it was
        given (its first argument, that difference's cells, or the nav2 points
        ``_POINTS_AT`` says)."""

        def observed(first: Any, *args: Any, **kwargs: Any) -> Any:
            value = function(first, *args, **kwargs)
            if not trace.paused:
                if name in _POINTS_AT:
                    cells = (first, *args)[_POINTS_AT[name]]
                else:
                    cells = first if isinstance(first, np.ndarray) else first.cells
                trace.verdicts.setdefault(_key(cells), []).append(
                    Verdict(name, verdict(value, kwargs), _shown(value), value)
                )
            return value

        return observed

    wrapped = {
        (pipeline, "_diff"): observed_diff,
        (diff_stage, "raw_differences"): observed_raw,
        (cluster_stage, "cluster_mask"): observed_cluster_mask,
        (pipeline, "_judged_on_current"): observed_current,
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
    if isinstance(value, refit_stage.Band):
        return (
            f"depth {value.depth_m:.2f} m, length {value.length_m:.2f} m, inner {value.inner}, "
            f"walled {value.walled_share:.2f}"
        )
    if isinstance(value, refit_stage.Strip):
        return (
            f"spread {value.spread_m:.3f} m, along {value.along_m:.2f} m, faces {value.faces}, "
            f"drawn {value.drawn_share:.2f}"
        )
    if isinstance(value, float | np.floating):
        return f"{float(value):.2f}"
    return str(bool(value))


def as_data(value: Any) -> dict[str, Any]:
    """A check's value as JSON-ready numbers: a dataclass's fields and its ``*_share``
    properties, a number or a bool as ``value``; TypeError for anything else."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        data: dict[str, Any] = {
            f.name: _number(getattr(value, f.name)) for f in dataclasses.fields(value)
        }
        for name in dir(type(value)):
            if name.endswith("_share") and isinstance(getattr(type(value), name), property):
                data[name] = _number(getattr(value, name))
        return data
    return {"value": _number(value)}


def _number(value: Any) -> float | int | bool:
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value)
    raise TypeError(f"a check's value of type {type(value).__name__} is no number")


def polygon_cells(
    grid: Grid, change: Change, grow_px: int
) -> tuple[tuple[slice, slice], NDArray[np.bool_], NDArray[np.bool_]]:
    """The change's polygon on ``grid``, in the box around it only: the box ((rows, cols)
    slices, room for ``grow_px`` included), its cells inside the polygon, and those grown by
    ``grow_px`` (both bool arrays of the box's shape)."""
    corners = np.rint(grid.to_pixel(change.polygon_xy)).astype(np.intp)
    box = box_of_cells(corners[:, 1], corners[:, 0], grow_px + 1, grid.shape)
    rows, cols = box
    filled = np.zeros((max(rows.stop - rows.start, 0), max(cols.stop - cols.start, 0)), np.uint8)
    if not filled.size:  # off the grid: an empty box
        nothing = np.zeros((0, 0), bool)
        return (slice(0, 0), slice(0, 0)), nothing, nothing
    # Filled as roi._fill fills a polygon on the whole grid (the corners rounded there), in the
    # box only.
    cv2.fillPoly(filled, [corners.astype(np.int32)], 1, offset=(-cols.start, -rows.start))
    kernel = np.ones((2 * grow_px + 1,) * 2, np.uint8)
    return box, filled.view(bool), np.asarray(cv2.dilate(filled, kernel).view(bool))


def _inside(
    differences: list[cluster_stage.Difference],
    kind: str,
    box: tuple[slice, slice],
    cells: NDArray[np.bool_],
) -> list[tuple[cluster_stage.Difference, int]]:
    """The differences of ``kind`` with cells in ``cells`` (a mask of ``box``), and how many."""
    (rows, cols), out = box, []
    for d in differences:
        if d.kind != kind or d.cells is None:
            continue
        r, c = d.cells[:, 0] - rows.start, d.cells[:, 1] - cols.start
        within = (r >= 0) & (r < cells.shape[0]) & (c >= 0) & (c < cells.shape[1])
        n = int(cells[r[within], c[within]].sum())
        if n:
            out.append((d, n))
    return out


def decided(verdicts: list[Verdict]) -> str:
    """The check that explained a difference away (the first: ``explain.unexplained`` asks no
    more), else ``reported``."""
    return next((v.check for v in verdicts if v.explained), "reported")


def _as_scored(d: cluster_stage.Difference, index: int) -> Difference:
    """A difference as scoring reads it (as if reported)."""
    return Difference(index, d.kind, d.centroid, d.bbox)


def _verdicts_text(verdicts: list[Verdict]) -> str:
    return ", ".join(f"{v.check} {v.shown}{' EXPLAINED' if v.explained else ''}" for v in verdicts)


def _seen_text(trace: Trace, box: tuple[slice, slice], inside: NDArray[np.bool_]) -> str:
    """Of a polygon's cells (``inside`` on ``box``), how many the aligned local map knows
    and how many were left out of the comparison (an untrusted piece, a region off the
    building): a change nothing shows was unseen, or seen where the comparison could not go."""
    parts = []
    if trace.local_state is not None:
        parts.append(f"seen {int((inside & (trace.local_state[box] != UNKNOWN)).sum())}")
    if trace.left_out is not None:
        parts.append(f"left out {int((inside & trace.left_out[box]).sum())}")
    return f" ({', '.join(parts)})" if parts else ""


def miss_line(change: Change, trace: Trace | None) -> tuple[str, str]:
    """The stage that lost ``change`` (one of ``STAGES``) and a line that says what each stage
    held of it (``trace`` None: the bundle failed)."""
    p = change.polygon_xy
    head = (
        f"MISS {change.id} {change.kind} at ({p[:, 0].mean():.2f},{p[:, 1].mean():.2f}) "
        f"{np.ptp(p[:, 0]):.2f}x{np.ptp(p[:, 1]):.2f} m"
    )
    if trace is None or not trace.compared:
        return "not compared", f"{head} -> not compared"
    assert trace.grid is not None and trace.raw is not None and trace.masks is not None
    box, inside, grown = polygon_cells(trace.grid, change, GROW_PX)
    raw = grown & getattr(trace.raw, change.kind)[box]
    mask = grown & getattr(trace.masks, change.kind)[box]
    line = f"{head}: polygon {int(inside.sum())} cells{_seen_text(trace, box, inside)}, "
    line += f"raw {int(raw.sum())}, mask "
    line += f"{int(mask.sum())}"
    if change.kind == "removed" and trace.evidence is not None:
        line += f", evidence {int((trace.evidence[box] & mask).sum())}"
    clusters = _inside(trace.clusters, change.kind, box, grown)
    kept = _inside(trace.kept, change.kind, box, grown)
    line += "; clusters " + (", ".join(f"{n}/{d.pixels} px" for d, n in clusters) or "none")
    kept_text = ", ".join(
        f"{n}/{d.pixels} px ({_verdicts_text(trace.of(d)) or 'no check'})" for d, n in kept
    )
    line += f"; kept {kept_text or 'none'}"
    if not raw.any():
        stage = "no difference"
    elif not mask.any():
        stage = "diff filters"
    elif not kept:
        stage = "clusters"
    elif any(decided(trace.of(d)) == "reported" for d, _ in kept):
        stage = "reported"
    else:
        stage = "judged"
    return stage, f"{line} -> {stage}"


@dataclass
class Census:
    """Counts over a set: misses by (kind, the stage that lost them); judged differences by
    (kind, the check that decided, label)."""

    misses: Counter[tuple[str, str]] = field(default_factory=Counter)
    judged: Counter[tuple[str, str, str]] = field(default_factory=Counter)
    # With every bundle and judged difference: one record per judged difference (``--judged``).
    records: list[dict[str, Any]] = field(default_factory=list)
    # ... and one per cluster, kept or not (``--clusters``).
    cluster_records: list[dict[str, Any]] = field(default_factory=list)

    def to_doc(self) -> dict[str, list[list[str | int]]]:
        """The counts as a JSON-ready document (``--counts``): rows of the keys and the count."""
        return {
            "misses": [[*key, n] for key, n in sorted(self.misses.items())],
            "judged": [[*key, n] for key, n in sorted(self.judged.items())],
        }

    def add_doc(self, doc: dict[str, list[list[Any]]]) -> None:
        """Add the counts of a :meth:`to_doc` document (another set's) to these."""
        for *key, n in doc["misses"]:
            self.misses[(key[0], key[1])] += int(n)
        for *key, n in doc["judged"]:
            self.judged[(key[0], key[1], key[2])] += int(n)


def census_of_bundle(
    case: Case, truth: Truth, result: Result | None, config: Config, census: Census, *, every: bool
) -> list[str]:
    """Re-run one bundle with observers (``result``: its result in the outbox, None when it
    has none); its lines, and its counts added to ``census``."""
    score = score_bundle(truth, result)
    false_positives = [s for s in score.differences if s.label == "false_positive"]
    if not every and not score.unmatched_change_ids and not false_positives:
        return []
    observed = Trace()
    failed = ""
    with observing(observed):
        try:
            outcome = pipeline.process_bundle(case.bundle_dir, config, bundle_id=case.bundle_id)
        except MapserverError as error:
            failed = f"{error.stage}: {error.reason}"
    trace = None if failed else observed  # a bundle that failed compared nothing
    if trace is None:
        lines = [f"== {case.bundle_id}: failed ({failed})"]
    else:
        alignment = outcome.result.get("alignment") or {}
        lines = [
            f"== {case.bundle_id}: trusted {alignment.get('trusted')}, pieces "
            f"{alignment.get('pieces')}, trusted share {alignment.get('trusted_share')}, drift "
            f"{alignment.get('drift_m')} m"
        ]
        lines += _mismatch(outcome.result, result)
    changes = {c.id: c for c in truth.changes}
    for change_id in score.unmatched_change_ids:
        change = changes[change_id]
        stage, line = miss_line(change, trace)
        census.misses[(change.kind, stage)] += 1
        lines.append("  " + line)
    reported = {d.id: d for d in result.differences} if result is not None else {}
    for fp in false_positives:
        d = reported[fp.difference_id]
        same = (
            []
            if trace is None
            else [k for k in trace.kept if np.allclose(k.centroid, d.centroid_xy, atol=0.01)]
        )
        if not same:
            checks = "not found in the re-run"
        else:
            checks = "; ".join(_verdicts_text(trace.of(k)) for k in same if trace is not None)
        lines.append(
            f"  FP #{d.id} {d.kind} at ({d.centroid_xy[0]:.2f},{d.centroid_xy[1]:.2f}): "
            f"{checks or 'no re-fit (the map did not drift)'}"
        )
    if every and trace is not None:
        census.cluster_records += cluster_records(case.bundle_id, truth, trace)
        judged = [k for k in trace.kept if trace.of(k)]
        labels = score_bundle(
            truth, Result("ok", tuple(_as_scored(k, i) for i, k in enumerate(judged)))
        ).differences
        for k, s in zip(judged, labels, strict=True):
            verdicts = trace.of(k)
            check = decided(verdicts)
            census.judged[(k.kind, check, s.label)] += 1
            census.records.append(judged_record(case.bundle_id, k, s.label, verdicts))
            lines.append(
                f"  JUDGED {s.label} {k.kind} at ({k.centroid[0]:.2f},{k.centroid[1]:.2f}) "
                f"{k.pixels} px -> {check}: {_verdicts_text(verdicts)}"
            )
    return lines


def cluster_records(bundle_id: str, truth: Truth, trace: Trace) -> list[dict[str, Any]]:
    """Every cluster of a bundle's comparison, before the floors on area and evidence, as
    JSON-ready records: where it lies, its size, its removal evidence (removed ones: the cells
    of it in the evidence mask, and their share), whether the cluster stage kept it, and its
    label (scored as if it alone were reported with the others: ``correct``, ``neutral``,
    ``false_positive``). The census of what the floors drop: the question a threshold on them
    asks."""
    clusters = [c for c in trace.clusters if c.cells is not None]
    if not clusters:
        return []
    kept = {_key(k.cells) for k in trace.kept if k.cells is not None}
    labels = score_bundle(
        truth, Result("ok", tuple(_as_scored(c, i) for i, c in enumerate(clusters)))
    ).differences
    out = []
    for c, scored in zip(clusters, labels, strict=True):
        assert c.cells is not None
        record = _where(bundle_id, c)
        record |= {"kept": _key(c.cells) in kept, "label": scored.label}
        if c.kind == "removed" and trace.evidence is not None:
            shown = trace.evidence[c.cells[:, 0], c.cells[:, 1]]
            record["evidence_px"] = int(shown.sum())
            record["evidence_share"] = round(float(shown.mean()), 4)
        out.append(record)
    return out


def judged_record(
    bundle_id: str, difference: cluster_stage.Difference, label: str, verdicts: list[Verdict]
) -> dict[str, Any]:
    """One judged difference as a JSON-ready record: where it lies, its label (scored as if
    reported), the check that decided, and each check's verdict and value."""
    return {
        **_where(bundle_id, difference),
        "label": label,
        "decided": decided(verdicts),
        "checks": {v.check: {"explained": v.explained, **as_data(v.value)} for v in verdicts},
    }


def _where(bundle_id: str, difference: cluster_stage.Difference) -> dict[str, Any]:
    """The first fields of a difference's JSON record: its bundle, kind, centroid, size."""
    return {
        "bundle": bundle_id,
        "kind": difference.kind,
        "centroid": [round(float(v), 3) for v in difference.centroid],
        "pixels": int(difference.pixels),
        "area_m2": round(float(difference.area_m2), 4),
    }


def _mismatch(rerun: dict[str, Any], result: Result | None) -> list[str]:
    """A line when the re-run does not report what the outbox holds (centroids to 1 mm)."""
    again = sorted(
        (d["kind"], round(d["centroid"]["x"], 3), round(d["centroid"]["y"], 3))
        for d in rerun.get("differences") or []
    )
    held = sorted(
        (d.kind, round(d.centroid_xy[0], 3), round(d.centroid_xy[1], 3))
        for d in (result.differences if result is not None else ())
    )
    if again == held:
        return []
    return [
        f"  MISMATCH: the re-run reports {len(again)} differences, the outbox {len(held)} "
        "(another configuration or commit?): the stages below are the re-run's"
    ]


def summary_lines(census: Census) -> list[str]:
    lines = ["== misses by the stage that lost them"]
    for kind in ("added", "removed"):
        for stage in STAGES:
            if census.misses[(kind, stage)]:
                lines.append(f"  {kind:8s} {stage:13s} {census.misses[(kind, stage)]:5d}")
    if census.judged:
        labels = ("correct", "neutral", "false_positive")
        lines.append("== differences the re-fit judged, by the check that decided (--all)")
        lines.append(f"  {'kind':8s} {'decided':9s} " + " ".join(f"{x:>14s}" for x in labels))
        for kind in ("added", "removed"):
            for check in (*CHECKS, "reported"):
                row = [census.judged[(kind, check, label)] for label in labels]
                if any(row):
                    lines.append(f"  {kind:8s} {check:9s} " + " ".join(f"{n:14d}" for n in row))
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set_dir", type=Path, help="the benchmark set (as for bench_public.py)")
    parser.add_argument("outbox", type=Path, help="bench_public.py's --out of a run on it")
    parser.add_argument("bundles", nargs="*", help="only bundles whose id contains one of these")
    parser.add_argument("--all", action="store_true", help="every bundle and judged difference")
    parser.add_argument("--config", type=Path, help="the configuration the run used")
    parser.add_argument("--counts", type=Path, help="also write the counts here, as JSON")
    parser.add_argument(
        "--judged",
        type=Path,
        help="also write every judged difference here, a JSON line each (implies --all)",
    )
    parser.add_argument(
        "--clusters",
        type=Path,
        help="also write every cluster, kept or dropped by the floors, here (implies --all)",
    )
    args = parser.parse_args(argv)
    every = args.all or args.judged is not None or args.clusters is not None
    config = load_config(args.config)
    census = Census()
    for case in find_cases(args.set_dir):
        if args.bundles and not any(b in case.bundle_id for b in args.bundles):
            continue
        truth = parse_truth(yaml.safe_load(case.truth_path.read_text(encoding="utf-8")))
        result_path = args.outbox / case.bundle_id / RESULT
        result = None
        if result_path.is_file():  # none: the bundle failed (bench_public writes no result)
            result = parse_result(yaml.safe_load(result_path.read_text(encoding="utf-8")))
        for line in census_of_bundle(case, truth, result, config, census, every=every):
            print(line, flush=True)
    print("\n".join(summary_lines(census)))
    if args.counts is not None:
        args.counts.write_text(json.dumps(census.to_doc()), encoding="utf-8")
    for path, records in ((args.judged, census.records), (args.clusters, census.cluster_records)):
        if path is not None:
            lines = (json.dumps({"set": args.set_dir.name, **r}) for r in records)
            path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
