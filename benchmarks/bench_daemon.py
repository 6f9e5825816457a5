"""The daemon under load, killed with -9 in the middle: nothing lost, nothing duplicated.

    .venv/bin/python benchmarks/bench_daemon.py [--bundles 100] [--robots 4] [--interval 1.0]
        [--settle 2.0] [--workers 0] [--kill-after 0.5] [--rsync] [--seed 1] [--out DIR]

Robots (threads) upload ``--bundles`` bundles into the inbox of a running ``mapserver run`` the
way rsync does (each file under a dot-temp name, then renamed; the maps first, bundle.yaml last),
each robot pausing a random time (mean ``--interval`` s) between bundles. Once ``--kill-after``
of the results exist, the daemon and its workers are killed with SIGKILL (as systemd's watchdog
would) and started again while the robots go on uploading. At the end it checks that every
bundle is in archive/ or failed/ exactly once, that every archived bundle has exactly one
result, that nothing is left in the inbox or half-written in the outbox, and that every bundle is
byte-identical to what was uploaded. It prints the latency from "bundle complete" (bundle.yaml
renamed into place) to ``result.yaml`` (its mtime), median and p95, and the throughput.

The bundles are copies (unique ids) of the shipped samples in mapserver/data/samples, or of the
bundle folders in ``--template``.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from mapserver.bundle import sha256_file

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "mapserver" / "data" / "samples"


@dataclass
class Upload:
    bundle_id: str
    source: Path
    complete: float = 0.0  # wall clock: bundle.yaml renamed into place


@dataclass
class Run:
    uploads: list[Upload] = field(default_factory=list)
    kill_time: float = 0.0
    ready_again: float = 0.0


def digest(path: Path) -> dict[str, str]:
    return {
        str(p.relative_to(path)): sha256_file(p) for p in sorted(path.rglob("*")) if p.is_file()
    }


def upload_like_rsync(source: Path, target: Path, rng: random.Random) -> float:
    """Maps first, bundle.yaml last; each file under ``.name.XXXXXX`` in chunks, then renamed."""
    target.mkdir()
    files = sorted(p.name for p in source.iterdir())
    files.sort(key=lambda n: n == "bundle.yaml")
    for name in files:
        temp = target / f".{name}.{rng.getrandbits(32):08x}"
        with (source / name).open("rb") as src, temp.open("wb") as dst:
            while block := src.read(256 * 1024):
                dst.write(block)
        shutil.copystat(source / name, temp)
        os.rename(temp, target / name)
    return time.time()


def upload_with_rsync(source: Path, target: Path) -> float:
    """The README's two rsync calls."""
    subprocess.run(["rsync", "-a", "--exclude=bundle.yaml", f"{source}/", f"{target}/"], check=True)
    subprocess.run(["rsync", "-a", f"{source}/bundle.yaml", f"{target}/"], check=True)
    return time.time()


class Daemon:
    def __init__(self, config: Path, log: Path) -> None:
        self._log = log.open("ab")
        self.log_path = log
        self.process = subprocess.Popen(
            [sys.executable, "-m", "mapserver.cli", "run", "--config", str(config)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.ready_lines = log.read_text(errors="replace").count("ready:")

    def wait_ready(self, timeout: float = 120) -> float:
        deadline = time.monotonic() + timeout
        while self.log_path.read_text(errors="replace").count("ready:") <= self.ready_lines:
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"the daemon did not start; see {self.log_path}")
            time.sleep(0.05)
        return time.time()

    def kill9(self) -> None:
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self._log.close()

    def stop(self) -> int:
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=120)
        self._log.close()
        return code


def count_results(outbox: Path) -> int:
    # A result folder appears whole (renamed in, result.yaml written last): one directory
    # read, not a glob of every folder (this loop shares the cores with the daemon).
    with os.scandir(outbox) as entries:
        return sum(1 for e in entries if not e.name.startswith("."))


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundles", type=int, default=100)
    parser.add_argument("--robots", type=int, default=4, help="uploading in parallel")
    parser.add_argument("--interval", type=float, default=1.0, help="mean pause per robot, s")
    parser.add_argument("--settle", type=float, default=2.0, help="settle_seconds")
    parser.add_argument("--workers", type=int, default=0, help="0: the number of cores")
    parser.add_argument("--kill-after", type=float, default=0.5, help="share of results")
    parser.add_argument("--rsync", action="store_true", help="upload with the rsync command")
    parser.add_argument("--template", type=Path, default=SAMPLES)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, help="work here and keep it (default: a temp dir)")
    args = parser.parse_args()
    if args.rsync and shutil.which("rsync") is None:
        raise SystemExit("--rsync: rsync is not installed")
    templates = sorted(p for p in args.template.iterdir() if (p / "bundle.yaml").is_file())
    if not templates:
        raise SystemExit(f"no bundle folders in {args.template}")

    work = args.out or Path(tempfile.mkdtemp(prefix="bench-daemon-"))
    if args.out and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    config = work / "mapserver.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "settle_seconds": args.settle,
                "rescan_seconds": 10,
                "stale_after_seconds": 600,
                "workers": args.workers,
            }
        )
    )
    inbox, outbox, archive, failed = (work / n for n in ("inbox", "outbox", "archive", "failed"))
    run = Run(
        [Upload(f"bench-{i:03d}", templates[i % len(templates)]) for i in range(args.bundles)]
    )
    expected = {t: digest(t) for t in templates}
    log = work / "daemon.log"
    print(f"work folder {work}; {args.bundles} bundles from {len(templates)} templates")

    start = time.time()
    daemon = Daemon(config, log)
    daemon.wait_ready()
    started = time.time()
    print(f"daemon ready in {started - start:.2f} s")

    def robot(k: int) -> None:
        rng = random.Random(args.seed * 1000 + k)
        for upload in run.uploads[k :: args.robots]:
            target = inbox / upload.bundle_id
            if args.rsync:
                upload.complete = upload_with_rsync(upload.source, target)
            else:
                upload.complete = upload_like_rsync(upload.source, target, rng)
            threading.Event().wait(rng.expovariate(1 / args.interval) if args.interval else 0)

    robots = [threading.Thread(target=robot, args=(k,)) for k in range(args.robots)]
    for thread in robots:
        thread.start()

    kill_at = max(1, round(args.kill_after * args.bundles))
    while count_results(outbox) < kill_at:
        if daemon.process.poll() is not None:
            raise SystemExit(f"the daemon died; see {log}")
        time.sleep(0.01)
    run.kill_time = time.time()
    in_hand = len([p for p in (inbox / ".taken").iterdir() if not p.name.startswith(".")])
    daemon.kill9()
    print(
        f"kill -9 of the daemon and its workers after {count_results(outbox)} results "
        f"({in_hand} bundles in hand)"
    )
    daemon = Daemon(config, log)
    run.ready_again = daemon.wait_ready()
    print(f"restarted: ready again {run.ready_again - run.kill_time:.2f} s after the kill")

    for thread in robots:
        thread.join()
    ids = {u.bundle_id for u in run.uploads}
    deadline = time.monotonic() + 600
    while count_results(outbox) + sum(1 for p in failed.iterdir() if p.name in ids) < len(ids):
        if daemon.process.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"not every bundle finished; see {log}")
        time.sleep(0.05)
    code = daemon.stop()

    # -- checks ---------------------------------------------------------------------------
    problems = []
    archived = {p.name for p in archive.iterdir() if not p.name.startswith(".")}
    rejected = {p.name for p in failed.iterdir() if not p.name.startswith(".")}
    results = {p.name for p in outbox.iterdir()}
    # The daemon's own files there (its lock and status, .taken) are not uploads left behind.
    left = [p.name for p in inbox.iterdir() if not p.name.startswith((".taken", ".mapserver."))]
    left += [p.name for p in (inbox / ".taken").iterdir()]
    if code != 0:
        problems.append(f"the daemon exited {code} on SIGTERM")
    if archived | rejected != ids or archived & rejected:
        problems.append(f"not exactly the {len(ids)} bundles in archive/ + failed/")
    if results != archived:
        problems.append(f"results != archived bundles: {sorted(results ^ archived)[:5]}")
    if left:
        problems.append(f"left in the inbox: {left[:5]}")
    by_id = {u.bundle_id: u for u in run.uploads}
    for bundle_id in archived | rejected:
        where = archive if bundle_id in archived else failed
        got = digest(where / bundle_id)
        got.pop("error.yaml", None)
        if got != expected[by_id[bundle_id].source]:
            problems.append(f"{bundle_id}: not byte-identical to the upload")

    # -- numbers ----------------------------------------------------------------------------
    latencies: list[float] = []
    spanning: list[float] = []
    for upload in run.uploads:
        result = outbox / upload.bundle_id / "result.yaml"
        if not result.exists():
            continue
        latency = result.stat().st_mtime - upload.complete
        crossed = upload.complete < run.kill_time < result.stat().st_mtime
        (spanning if crossed else latencies).append(latency)
    every = latencies + spanning
    first = min(u.complete for u in run.uploads)
    last = max((outbox / i / "result.yaml").stat().st_mtime for i in archived)
    print()
    print(f"bundles: {len(ids)}; archived {len(archived)}, failed {len(rejected)}")
    print(
        f"latency complete -> result.yaml (settle_seconds {args.settle} included): "
        f"median {statistics.median(latencies):.2f} s, p95 {percentile(latencies, 0.95):.2f} s "
        f"over {len(latencies)} bundles not caught by the kill"
    )
    if spanning:
        print(
            f"  the {len(spanning)} bundles complete before the kill and finished after it: "
            f"median {statistics.median(spanning):.2f} s, max {max(spanning):.2f} s; all "
            f"{len(every)}: median {statistics.median(every):.2f} s, "
            f"p95 {percentile(every, 0.95):.2f} s"
        )
    print(
        f"throughput: {len(archived) / (last - first):.2f} bundles/s from the first upload "
        f"complete to the last result ({last - first:.1f} s, the kill and restart included); "
        + (
            f"offered {args.robots / args.interval:.1f}/s by {args.robots} robots"
            if args.interval
            else f"{args.robots} robots uploading as fast as they can"
        )
    )
    if problems:
        print("FAILED:")
        for problem in problems:
            print(f"  {problem}")
        return 1
    print(
        "checks: every bundle in archive/ or failed/ exactly once, one result per archived "
        "bundle, nothing left in the inbox, inputs byte-identical: OK"
    )
    if args.out is None:
        shutil.rmtree(work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
