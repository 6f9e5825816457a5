"""How far each piece of a bundle aligned in pieces lands from the truth (issue 12's drift sets).

A generated set's truth holds one rigid transform per bundle, the best fit of a bent map; it
cannot tell a piece that landed right from one that did not. The simulator's drift model is
known, though (``mapserver.synth.session._drifted``: each step's motion scaled by ``1 +-
drift_scale`` and its heading turned by ``+-drift_yaw_deg_per_m`` per metre), so the true
route is rebuilt from the bundle's slam trajectory by running that model backwards, for the
four sign choices (the scenario names only the magnitudes); the choice whose end lands nearest
the pose prior (the true final pose plus AMCL noise) wins, and the rebuilt route is put in the
nav2 frame through the truth transform. A piece's error is then the distance, at each pose of
its run, between where its transform puts the slam pose and the true pose.

Only for drift that is a bias (``drifting``, ``long``, ``combo`` cases), not a random walk
(``wandering``: the draws are not in the files). Usage::

    .venv/bin/python benchmarks/piece_truth.py SET [BUNDLE_SUBSTRING ...]

prints, per bundle aligned in pieces, how well the route was rebuilt (``end match``: metres
between its end and the prior) and one row per piece: score, trusted, area, error max/mean.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from bench_public import Case, find_cases  # benchmarks/ is on sys.path when a script in it runs
from numpy.typing import NDArray

from mapserver import piecewise, pipeline
from mapserver.bundle import read_manifest
from mapserver.config import Config, load_config
from mapserver.geometry import Transform2D, fit_rigid, wrap_angle
from mapserver.scoring import parse_truth

FloatArray = NDArray[np.float64]


def undrift(est: FloatArray, yaw_rate_rad_per_m: float, scale: float) -> FloatArray:
    """The true poses (N, 3) in the slam frame's start (x, y, yaw) whose slam estimates, by the
    simulator's drift model, are ``est`` (N, 3): each step's motion seen from the previous pose
    divided by ``scale``, its turn less ``yaw_rate`` times its true length."""
    true = np.empty_like(est)
    true[0] = est[0]
    for i in range(1, len(est)):
        dx, dy = est[i, :2] - est[i - 1, :2]
        c, s = math.cos(est[i - 1, 2]), math.sin(est[i - 1, 2])
        fx, fy = (c * dx + s * dy) / scale, (-s * dx + c * dy) / scale
        turn = wrap_angle(est[i, 2] - est[i - 1, 2]) - yaw_rate_rad_per_m * math.hypot(fx, fy)
        c, s = math.cos(true[i - 1, 2]), math.sin(true[i - 1, 2])
        true[i, 0] = true[i - 1, 0] + c * fx - s * fy
        true[i, 1] = true[i - 1, 1] + s * fx + c * fy
        true[i, 2] = true[i - 1, 2] + turn
    return true


def true_route(
    est: FloatArray,
    truth: Transform2D,
    prior_xy: tuple[float, float],
    yaw_deg_per_m: float,
    scale_error: float,
) -> tuple[FloatArray, float]:
    """The true route (N, 2), nav2 frame, of slam trajectory ``est`` (N, 3), and how far its end
    is from ``prior_xy`` (metres), over the four signs of the drift's two magnitudes."""
    best: tuple[float, FloatArray] | None = None
    for yaw_sign in (1, -1):
        for scale_sign in (1, -1):
            q = undrift(est, yaw_sign * math.radians(yaw_deg_per_m), 1.0 + scale_sign * scale_error)
            # ``truth`` is the fit of ``est`` onto the true route; the rebuilt route is that
            # route up to one rigid transform, which the same fit pins down.
            route = truth.compose(fit_rigid(est[:, :2], q[:, :2]).inverse()).apply(q[:, :2])
            miss = float(np.hypot(*(route[-1] - np.asarray(prior_xy))))
            if best is None or miss < best[0]:
                best = (miss, route)
    assert best is not None
    return best[1], best[0]


def _scenario_params(case: Case) -> dict[str, Any]:
    """The generator's parameters of the scenario ``case`` belongs to (``scenario.yaml``)."""
    doc = yaml.safe_load((case.bundle_dir.parent.parent / "scenario.yaml").read_text())
    return dict(doc["params"])


def _pieces_of(bundle_dir: Path, config: Config) -> piecewise.Pieces | None:
    """The pieces the pipeline compared ``bundle_dir`` in (its last alignment in pieces), None
    when it compared the map whole (pieces tried and put aside, or never tried)."""
    calls: list[piecewise.Pieces | None] = []
    align_pieces = piecewise.align_pieces

    def spy(*a: Any, **k: Any) -> piecewise.Pieces | None:
        out = align_pieces(*a, **k)
        calls.append(out)
        return out

    piecewise.align_pieces = spy
    try:
        result = pipeline.process_bundle(bundle_dir, config).result
    finally:
        piecewise.align_pieces = align_pieces
    in_pieces = "pieces" in result["alignment"]
    return calls[-1] if calls and in_pieces else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set", type=Path, help="a generated scenario set")
    parser.add_argument("bundles", nargs="*", help="only bundles whose id holds one of these")
    args = parser.parse_args(argv)
    config = load_config(None)
    for case in find_cases(args.set):
        if args.bundles and not any(b in case.bundle_id for b in args.bundles):
            continue
        bundle_dir, params = case.bundle_dir, _scenario_params(case)
        if params.get("drift_walk"):
            print(f"{bundle_dir.name}: heading drift a random walk, cannot be rebuilt")
            continue
        truth = parse_truth(yaml.safe_load(case.truth_path.read_text())).nav2_from_slam
        manifest = read_manifest(bundle_dir)
        est = np.array([[p.x, p.y, p.yaw] for p in manifest.trajectory_poses()], float)
        prior = manifest.pose.nav2.to_pose()
        route, miss = true_route(
            est,
            truth,
            (prior.x, prior.y),
            params.get("drift_yaw_deg_per_m", 0.0),
            params.get("drift_scale", 0.0),
        )
        pieces = _pieces_of(bundle_dir, config)
        print(f"{bundle_dir.name}: end match {miss:.2f} m", "" if pieces else "(compared whole)")
        if pieces is None:
            continue
        for piece in pieces.pieces:
            at = [int(np.argmin(np.hypot(*(est[:, :2] - xy).T))) for xy in piece.run]
            error = np.hypot(*(piece.nav2_from_slam.apply(est[at, :2]) - route[at]).T)
            print(
                f"  piece {piece.index:2d} score {piece.score:.3f} "
                f"{'trusted' if piece.trusted else 'left out'} "
                f"{'aligned' if piece.aligned else 'unaligned'} area {piece.area_m2:6.1f} m2 "
                f"error max {error.max():.3f} mean {error.mean():.3f} m"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
