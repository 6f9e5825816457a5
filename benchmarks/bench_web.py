"""Latency of the operator's pages on a year-like site (issue 10): the dashboard, a map page and
``current.yaml`` (with and without ETag), p50 and p95 over repeated requests to a real
``mapserver web`` on this machine.

The site: the depot samples processed into a map store in review mode, then ``--bundles``
results in the outbox (copies of the samples' results, other ids and times; the images are hard
links), ``--failures`` failed bundles, and ``--changes`` tracked changes in the store (planted
observations: sightings that a later bundle contradicts, as people and carts make them).

    .venv/bin/python benchmarks/bench_web.py [--bundles 5000] [--requests 200]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Sequence
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapserver.cli import SAMPLES  # noqa: E402
from mapserver.cli import main as cli  # noqa: E402
from mapserver.config import load_config  # noqa: E402
from mapserver.fleet.evidence import pack_tiles  # noqa: E402
from mapserver.fleet.lattice import Window  # noqa: E402
from mapserver.fleet.observe import Found, Observation  # noqa: E402
from mapserver.fleet.store import FleetStore  # noqa: E402


def build(root: Path, n_bundles: int, n_failures: int, n_changes: int) -> Path:
    depot = sorted(SAMPLES.glob("depot-demo-*"))
    cfg = root / "mapserver.yaml"
    cfg.write_text(
        yaml.safe_dump({"maps": "maps", "update": {"mode": "review"}, "log_level": "WARNING"})
    )
    cli(["maps", "add", "depot", str(depot[0] / "nav2_map.yaml"), "--config", str(cfg)])
    cli(["process", "--config", str(cfg), *map(str, depot)])
    config = load_config(cfg)
    source = config.outbox / depot[0].name
    doc = yaml.safe_load((source / "result.yaml").read_text())
    t0 = datetime(2025, 11, 25, tzinfo=timezone.utc)
    for i in range(n_bundles):
        bundle_id = f"run-{i:05d}"
        target = config.outbox / bundle_id
        target.mkdir()
        for image in ("overlay.png", "diff.png"):
            os.link(source / image, target / image)
        when = t0 + timedelta(minutes=105 * i)
        doc.update(
            bundle=bundle_id, robot=f"r{i % 20:02d}", stamp=when.isoformat().replace("+00:00", "Z")
        )
        doc["processed_at"] = (when + timedelta(seconds=3)).isoformat().replace("+00:00", "Z")
        (target / "result.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    for i in range(n_failures):
        target = config.failed / f"bad-{i:04d}"
        target.mkdir(parents=True)
        (target / "error.yaml").write_text(
            yaml.safe_dump(
                {
                    "format": 1,
                    "bundle": target.name,
                    "failed_at": f"2026-01-{1 + i % 28:02d}T00:00:00Z",
                    "stage": "bundle",
                    "reason": "bundle.yaml: missing key 'pose'",
                }
            )
        )
    assert config.maps is not None
    rng = np.random.default_rng(5)
    with FleetStore(config.maps, config.update) as store:
        lattice = store.map_info("depot").lattice
        window = Window(0, 0, lattice.height, lattice.width)
        occupied = np.zeros((lattice.height, lattice.width), bool)
        free = np.ones((lattice.height, lattice.width), bool)
        tiles = pack_tiles(window, occupied, free)
        for i in range(n_changes):
            r, c = (
                int(rng.integers(20, lattice.height - 20)),
                int(rng.integers(20, lattice.width - 20)),
            )
            cells = np.array(
                [(r + dr) * lattice.width + c + dc for dr in range(3) for dc in range(3)], np.int64
            )
            for j, found in enumerate(((Found("added", cells),), ())):
                stamp = (t0 + timedelta(hours=2 * i + j)).isoformat().replace("+00:00", "Z")
                bid = f"plant-{i:05d}-{j}"
                store.apply(
                    Observation(
                        "depot",
                        bid,
                        hashlib.sha256(bid.encode()).hexdigest(),
                        "r00",
                        stamp,
                        1,
                        1,
                        window,
                        occupied,
                        free,
                        found,
                        (),
                        tiles,
                    )
                )
    return cfg


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure(url: str, n: int, headers: dict[str, str] | None = None) -> tuple[float, float, int]:
    times = []
    status = 0
    for _ in range(n):
        request = urllib.request.Request(url, headers=headers or {})
        start = time.perf_counter()
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                response.read()
                status = response.status
        except urllib.error.HTTPError as error:  # 304 arrives as an HTTPError
            status = error.code
        times.append((time.perf_counter() - start) * 1000.0)
    return float(np.percentile(times, 50)), float(np.percentile(times, 95)), status


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bundles", type=int, default=5000)
    parser.add_argument("--failures", type=int, default=300)
    parser.add_argument("--changes", type=int, default=1000)
    parser.add_argument("--requests", type=int, default=200)
    args = parser.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="bench-web-"))
    try:
        start = time.perf_counter()
        cfg = build(root, args.bundles, args.failures, args.changes)
        print(
            f"site: {args.bundles} results, {args.failures} failures, {args.changes} tracked changes, built in {time.perf_counter() - start:.1f} s"
        )
        port = free_port()
        server = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "mapserver.cli",
                "web",
                "--config",
                str(cfg),
                "--listen",
                f"127.0.0.1:{port}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    health = urllib.request.urlopen(base + "/healthz", timeout=5).read()
                    if yaml.safe_load(health)["results_indexed"] >= args.bundles:
                        break
                except OSError:
                    pass
                if time.monotonic() > deadline:
                    raise SystemExit("mapserver web did not come up")
                time.sleep(0.2)
            print(
                f"mapserver web up and indexed in {time.perf_counter() - start:.1f} s from the start"
            )
            with urllib.request.urlopen(base + "/maps/depot/current.yaml") as response:
                etag = response.headers["ETag"]
            for label, path, headers in (
                ("dashboard", "/", None),
                ("bundles page", "/bundles", None),
                ("map page", "/maps/depot", None),
                ("map picture", "/maps/depot/picture.png", None),
                ("current.yaml", "/maps/depot/current.yaml", None),
                (
                    "current.yaml, If-None-Match",
                    "/maps/depot/current.yaml",
                    {"If-None-Match": etag},
                ),
                ("/api/bundles", "/api/bundles?limit=50", None),
                ("/metrics", "/metrics", None),
            ):
                p50, p95, status = measure(base + path, args.requests, headers)
                print(
                    f"{label:<30} p50 {p50:7.1f} ms   p95 {p95:7.1f} ms   (HTTP {status}, {args.requests} requests)"
                )
        finally:
            server.terminate()
            server.wait(timeout=10)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
