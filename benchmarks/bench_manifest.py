"""How long the daemon's main loop spends on a manifest with a long trajectory.

The main loop checks every upload once its files stand still (``inbox.check_entry``): the
manifest parses, every file it names is there, the checksums match. It counts the trajectory's
poses against ``limits.max_trajectory_poses`` without reading them
(``parse_manifest(..., trajectory=False)``); the worker reads the whole manifest. This prints
both parses of a manifest of ``--poses`` poses (a seeded random walk, one flow mapping a
pose), the median of ``--runs`` each.

Usage::

    .venv/bin/python benchmarks/bench_manifest.py [--poses 100000] [--runs 3]

Target: the main loop's check of a 100,000-pose manifest (4-7 MiB; 100,000 poses are the most
a bundle may hold by default) under 1 s on 2 cores. The exit code is 0 whatever the figures.

``--junk-mib N`` also times a manifest with N MiB under a key the manifest does not know (a
robot's software that writes its own notes into it, or anything sent there): refused by both
parses, naming the key; the main loop's check does not read that value.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

from mapserver.bundle import parse_manifest
from mapserver.config import LimitsConfig
from mapserver.errors import BundleError

TARGET_S = 1.0


def manifest_text(poses: int, seed: int = 1) -> str:
    """A valid manifest with a random walk of ``poses`` poses, block style."""
    rng = np.random.default_rng(seed)
    xy = np.cumsum(rng.normal(0.0, 0.1, (poses, 2)), axis=0)
    yaw = rng.uniform(-3.14, 3.14, poses)
    lines = [
        "format: 1",
        "robot: r1",
        "stamp: 2026-11-21T10:15:00Z",
        "slam_map: slam_map.yaml",
        "nav2_map: nav2_map.yaml",
        "pose:",
        "  nav2: {x: 1.0, y: 2.0, yaw: 0.1}",
        "  slam: {x: 0.0, y: 0.0, yaw: 0.0}",
        "trajectory:",
    ]
    lines += [
        f"- {{x: {x:.4f}, y: {y:.4f}, yaw: {a:.5f}}}" for (x, y), a in zip(xy, yaw, strict=True)
    ]
    return "\n".join(lines) + "\n"


def median_s(fn: Callable[[], object], runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=100_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--junk-mib", type=float, default=16.0)
    args = parser.parse_args(argv)
    text = manifest_text(args.poses)
    limits = LimitsConfig(max_trajectory_poses=max(args.poses, 1))
    quick = median_s(lambda: parse_manifest(text, limits=limits, trajectory=False), args.runs)
    whole = median_s(lambda: parse_manifest(text, limits=limits), args.runs)
    print(f"manifest: {args.poses} poses, {len(text.encode()) / 2**20:.1f} MiB")
    print(f"  main loop's check (poses counted): {quick:.3f} s")
    print(f"  worker's parse (poses read):       {whole:.3f} s  ({whole / quick:.1f}x)")
    verdict = "PASS" if quick <= TARGET_S else "FAIL"
    print(f"target: main loop's check <= {TARGET_S} s: {verdict}")
    if args.junk_mib > 0:
        junk = junk_text(args.junk_mib)
        quick = median_s(lambda: refused(junk, trajectory=False), args.runs)
        whole = median_s(lambda: refused(junk, trajectory=True), args.runs)
        print(f"manifest: {len(junk.encode()) / 2**20:.1f} MiB under an unknown key")
        print(f"  main loop's check (its value not read): {quick:.3f} s")
        print(f"  worker's parse:                         {whole:.3f} s  ({whole / quick:.1f}x)")
    return 0


def junk_text(mib: float) -> str:
    """A manifest with ``mib`` MiB of small mappings under the unknown key ``notes``."""
    head = manifest_text(1)
    row = "  - {seq: 123456, level: info, text: the quick brown fox jumps}\n"
    return head + "notes:\n" + row * max(1, round(mib * 2**20 / len(row)))


def refused(text: str, *, trajectory: bool) -> None:
    """Parse ``text``, which must be refused for its unknown key."""
    try:
        parse_manifest(text, trajectory=trajectory)
    except BundleError as error:
        if "unknown key 'notes'" not in error.reason:
            raise
    else:
        raise AssertionError("a manifest with an unknown key was accepted")


if __name__ == "__main__":
    raise SystemExit(main())
