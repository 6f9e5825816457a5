"""Crops of the work grid around each change of a bundle and each difference it reported that
was not judged correct: what the pipeline compared there, to look at (issue 12's instrument,
beside ``census.py``, which says where a change was lost in words and numbers).

Each bundle of SET whose id contains one of the given substrings (every bundle when none is
given) is processed again with the census's observers (``census.observing``), and for each of
its truth's changes and each of its reported differences labelled ``false_positive`` or
``neutral`` one PNG is written to OUT_DIR, named ``<bundle>_change<id>_<kind>_<found|MISS>.png``
or ``<bundle>_difference<id>_<kind>_<label>.png`` (a change of another kind, a walker, is
``unscored``, a change the robot could not see ``unobserved``). Three panels side by side, each a square of
``--half`` metres each way around the change's polygon's mean corner (or the difference's
centroid), cells scaled up ``--scale`` times:

* the global map on the work grid (free white, occupied black, unknown grey);
* the aligned local map as compared (the same shades);
* the masks over the local map, paled: raw removed cells red, raw added orange, the filtered
  removed mask magenta and added blue, the removal evidence green, cells left out of the
  comparison dark grey.

Every truth polygon is outlined on each panel: added ones cyan, removed ones yellow, others
white. Usage::

    .venv/bin/python benchmarks/bench_public.py SET --out /tmp/run
    .venv/bin/python benchmarks/crops.py SET /tmp/run /tmp/crops gen-04-long [--half 1.5]

Writing the crops needs the outbox only for the labels (``result.yaml`` of the run, not the
re-run's: a re-run of another commit draws today's masks under the run's labels, and says so
with a ``MISMATCH`` line as the census does). It was written in session 39 after the fourth
session in a row had rewritten such a script in /tmp and lost it with the machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml
from bench_public import Case, find_cases  # benchmarks/ is on sys.path when a script in it runs
from census import Trace, _mismatch, observing
from numpy.typing import NDArray

from mapserver import pipeline
from mapserver.config import Config, load_config
from mapserver.errors import MapserverError
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED
from mapserver.outbox import RESULT
from mapserver.scoring import Result, Truth, parse_result, parse_truth, score_bundle

# BGR, as cv2 writes them.
_OUTLINE = {"added": (255, 255, 0), "removed": (0, 255, 255)}
_OTHER_OUTLINE = (255, 255, 255)
_RAW_REMOVED, _RAW_ADDED = (0, 0, 255), (0, 140, 255)
_REMOVED, _ADDED = (255, 0, 255), (255, 120, 0)
_EVIDENCE, _LEFT_OUT = (0, 200, 0), (60, 60, 60)
_GAP_PX = 6


def shaded(state: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(H, W, 3) BGR image of cell states: free white, occupied black, anything else grey."""
    image = np.full((*state.shape, 3), 160, np.uint8)
    image[state == FREE] = 255
    image[state == OCCUPIED] = 0
    return image


def masks_panel(trace: Trace) -> NDArray[np.uint8]:
    """The masks a trace recorded, painted over its local map paled (module docstring)."""
    assert trace.local_state is not None
    panel = (shaded(trace.local_state).astype(np.float32) * 0.5 + 100).astype(np.uint8)
    if trace.left_out is not None:
        panel[trace.left_out] = _LEFT_OUT
    if trace.raw is not None:
        panel[trace.raw.removed] = _RAW_REMOVED
        panel[trace.raw.added] = _RAW_ADDED
    if trace.masks is not None:
        panel[trace.masks.removed] = _REMOVED
        panel[trace.masks.added] = _ADDED
    if trace.evidence is not None:
        panel[trace.evidence] = _EVIDENCE
    return panel


def crop(
    panels: list[NDArray[np.uint8]],
    grid: Grid,
    truth: Truth,
    centre_xy: NDArray[np.float64],
    *,
    half_m: float,
    scale: int,
) -> NDArray[np.uint8]:
    """The panels (each (H, W, 3) on ``grid``) cropped to ``half_m`` around the nav2 point
    ``centre_xy``, truth polygons outlined, scaled ``scale`` times, side by side."""
    col, row = grid.to_pixel(np.asarray([centre_xy], float))[0]
    half = max(1, round(half_m / grid.resolution))
    r0, c0 = max(round(row) - half, 0), max(round(col) - half, 0)
    r1, c1 = min(round(row) + half, grid.shape[0]), min(round(col) + half, grid.shape[1])
    out = []
    for panel in panels:
        drawn = panel.copy()
        for change in truth.changes:
            corners = np.rint(grid.to_pixel(change.polygon_xy)).astype(np.int32)
            colour = _OUTLINE.get(change.kind, _OTHER_OUTLINE)
            cv2.polylines(drawn, [corners], True, colour, 1)
        crop = drawn[r0:r1, c0:c1]
        if not crop.size:  # off the grid: one grey cell
            crop = np.full((1, 1, 3), 160, np.uint8)
        part = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        out += [part, np.full((part.shape[0], _GAP_PX, 3), 255, np.uint8)]
    return np.hstack(out[:-1])


def crops_of_bundle(
    case: Case, outbox: Path, config: Config, out_dir: Path, *, half_m: float, scale: int
) -> list[str]:
    """Re-run one bundle with observers and write its crops (labelled by its result in
    ``outbox``, the re-run's when it has none there); its lines (one per file)."""
    truth = parse_truth(yaml.safe_load(case.truth_path.read_text()))
    result_path = outbox / case.bundle_id / RESULT
    result: Result | None = None
    if result_path.is_file():
        result = parse_result(yaml.safe_load(result_path.read_text()))
    trace = Trace()
    with observing(trace):
        try:
            outcome = pipeline.process_bundle(case.bundle_dir, config, bundle_id=case.bundle_id)
        except MapserverError as error:
            return [f"== {case.bundle_id}: failed ({error.stage}: {error.reason}), no crops"]
    if (
        not trace.compared
        or trace.grid is None
        or trace.local_state is None
        or trace.global_state is None
    ):
        return [f"== {case.bundle_id}: nothing compared (alignment not trusted), no crops"]
    lines = [f"== {case.bundle_id}"]
    if result is not None:
        lines += _mismatch(outcome.result, result)
    scored = result if result is not None else parse_result(outcome.result)
    score = score_bundle(truth, scored)
    labels = {s.difference_id: s.label for s in score.differences}
    spots: list[tuple[str, NDArray[np.float64]]] = []
    for change in truth.changes:
        if change.id in score.unmatched_change_ids:
            state = "MISS"
        elif change.kind not in _OUTLINE:  # a walker or a door is never to be found
            state = "unscored"
        else:  # scored only when the robot could see it
            state = "found" if change.observed else "unobserved"
        spots.append((f"change{change.id}_{change.kind}_{state}", change.polygon_xy.mean(axis=0)))
    for d in scored.differences:
        label = labels.get(d.id)
        if label in ("false_positive", "neutral"):
            spots.append((f"difference{d.id}_{d.kind}_{label}", np.asarray(d.centroid_xy)))
    panels = [shaded(trace.global_state), shaded(trace.local_state), masks_panel(trace)]
    for name, xy in spots:
        image = crop(panels, trace.grid, truth, xy, half_m=half_m, scale=scale)
        path = out_dir / f"{case.bundle_id}_{name}.png"
        cv2.imwrite(str(path), image)
        lines.append(f"  {path}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set_dir", type=Path, help="a benchmark set (scenario folders)")
    parser.add_argument("outbox", type=Path, help="the run's outbox (bench_public.py --out)")
    parser.add_argument("out_dir", type=Path, help="where the PNG files go")
    parser.add_argument("bundles", nargs="*", help="only bundles whose id contains one of these")
    parser.add_argument("--half", type=float, default=3.0, help="metres each way (3)")
    parser.add_argument("--scale", type=int, default=5, help="pixels per cell (5)")
    parser.add_argument("--config", type=Path, help="the run's configuration, if it had one")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    cases = find_cases(args.set_dir)
    chosen = [c for c in cases if not args.bundles or any(b in c.bundle_id for b in args.bundles)]
    if not chosen:
        print(f"no bundle of {args.set_dir} matches {args.bundles}", file=sys.stderr)
        return 1
    for case in chosen:
        lines = crops_of_bundle(
            case, args.outbox, config, args.out_dir, half_m=args.half, scale=args.scale
        )
        print("\n".join(lines), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
