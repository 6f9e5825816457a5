"""The faults a server meets, all in one run: nothing lost, nothing duplicated, no result
written twice.

    .venv/bin/python benchmarks/bench_faults.py [--bundles 100] [--robots 4] [--interval 2.0]
        [--full-seconds 30] [--timeout 10] [--seed 1] [--out DIR]

Robots (threads) upload ``--bundles`` good bundles (copies of the shipped samples) and 30
malformed ones (10 kinds, 3 of each, from the daemon tests' table) with the README's two rsync
calls (``mapserver.bundle.upload_commands``; the rsync-like copy of bench_daemon.py when rsync
is missing), pausing a random time (mean ``--interval`` s) between bundles and retrying a call
that fails (as a robot does on a full disk). Meanwhile, in the same run:

- the daemon and its workers are killed with -9 three times (after 20% of the results, 10 s
  into the full disk, after 70%) and started again;
- a second ``mapserver run`` on the same inbox is started: it must exit 1 at once;
- two good bundles hang in stage align (``MAPSERVER_TEST_FAULT``) and must fail past
  ``bundle_timeout_seconds`` (``--timeout``);
- the disk fills for ``--full-seconds``: the daemon's four folders are on a small tmpfs, filled
  to the last byte and freed again. Mounting needs root; otherwise the benchmark runs itself
  again under ``unshare -rm`` (a user and mount namespace); where neither works that part is
  skipped, and the reason printed.

It prints what was archived and what failed (each with its reason), lost (in neither archive/
nor failed/), duplicated (in both, or under a second id), results modified (a result.yaml that
changed after it first appeared), the longest a good bundle waited from its upload to its
result, and how long a hung bundle held its worker. Exit code 1 when any check fails.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import bench_daemon as base  # the daemon process, the rsync-like copy, digests
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from daemon_support import fill_disk, make_bundle  # noqa: E402  (the tests' helpers)
from test_service_daemon import BAD  # noqa: E402  (the tests' table of malformed bundles)

from mapserver.board import FAULT_ENV  # noqa: E402
from mapserver.bundle import upload_commands  # noqa: E402

KINDS = [
    "corrupt-image",
    "truncated-image",
    "text-as-pgm",
    "empty-image",
    "yaml-syntax",
    "missing-key",
    "nan-pose",
    "image-dotdot",
    "symlink-out",
    "checksum-mismatch",
]
UNSHARED = "MAPSERVER_BENCH_UNSHARED"


@dataclass
class Upload:
    bundle_id: str
    source: Path
    expect: str  # "archived", or the failure: "stage: word of the reason"
    complete: float = 0.0  # wall clock: the second rsync call returned
    retries: int = 0


def mount_small_disk(path: Path, size_mb: int) -> str | None:
    """Mount a tmpfs at ``path``; the reason when it cannot be done."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return "not root, and no user namespace to mount a tmpfs in (unshare -rm)"
    command = ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "bench-faults", str(path)]
    done = subprocess.run(command, capture_output=True, text=True)
    return None if done.returncode == 0 else f"cannot mount a tmpfs: {done.stderr.strip()}"


def make_uploads(work: Path, bundles: int, rng: random.Random) -> list[Upload]:
    templates = sorted(p for p in base.SAMPLES.iterdir() if (p / "bundle.yaml").is_file())
    sources = work / "sources"
    uploads = []
    for i in range(bundles):
        source = sources / f"bench-{i:03d}"
        shutil.copytree(templates[i % len(templates)], source, symlinks=True)
        uploads.append(Upload(source.name, source, "archived"))
    table = {row[0]: row for row in BAD}
    for n, kind in enumerate(KINDS):
        _, breaks, stage, word = table[kind]
        for copy in range(3):
            source = sources / f"bad-{kind}-{copy}"
            make_bundle(source, seed=100 + 3 * n + copy, checksums=kind == "checksum-mismatch")
            breaks(source)
            uploads.append(Upload(source.name, source, f"{stage}: {word}"))
    rng.shuffle(uploads)
    return uploads


def send(upload: Upload, inbox: Path, use_rsync: bool, rng: random.Random) -> None:
    """Upload one bundle the README's way; a failed call (a full disk) is tried again."""
    while True:
        try:
            if use_rsync:
                for command in upload_commands(str(upload.source), f"{inbox}/"):
                    subprocess.run(command, check=True, capture_output=True)
                upload.complete = time.time()
            else:
                target = inbox / upload.bundle_id
                shutil.rmtree(target, ignore_errors=True)  # no bundle.yaml yet: never taken
                upload.complete = base.upload_like_rsync(upload.source, target, rng)
            return
        except (subprocess.CalledProcessError, OSError):
            upload.retries += 1
            time.sleep(2.0)


class Results:
    """Watches the outbox: each result.yaml's digest and mtime when it first appeared."""

    def __init__(self, outbox: Path) -> None:
        self.outbox = outbox
        self.first: dict[str, tuple[str, int]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.25):
            self.look()

    def look(self) -> None:
        try:
            names = [e.name for e in os.scandir(self.outbox) if not e.name.startswith(".")]
        except OSError:
            return
        for name in names:
            if name not in self.first:
                seen = fingerprint(self.outbox / name / "result.yaml")
                if seen is not None:
                    self.first[name] = seen

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.look()


def fingerprint(path: Path) -> tuple[str, int] | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns
    except OSError:
        return None


def visible(path: Path) -> set[str]:
    return (
        {p.name for p in path.iterdir() if not p.name.startswith(".")} if path.exists() else set()
    )


def second_daemon(config: Path) -> tuple[int, float, str]:
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "mapserver.cli", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    return done.returncode, time.monotonic() - start, done.stderr.strip()


def main() -> Run:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundles", type=int, default=100, help="good bundles")
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--interval", type=float, default=2.0, help="mean pause per robot, s")
    parser.add_argument("--full-seconds", type=float, default=30.0, help="the disk stays full")
    parser.add_argument("--timeout", type=float, default=10.0, help="bundle_timeout_seconds")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, help="work here and keep it (default: a temp dir)")
    args = parser.parse_args()
    if os.geteuid() != 0 and UNSHARED not in os.environ and _can_unshare():
        env = {**os.environ, UNSHARED: "1"}
        os.execvpe("unshare", ["unshare", "-rm", "--", sys.executable, *sys.argv], env)

    work = args.out or Path(tempfile.mkdtemp(prefix="bench-faults-"))
    if args.out and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    uploads = make_uploads(work, args.bundles, rng)
    good = [u for u in uploads if u.expect == "archived"]
    hung = [good[len(good) // 5], good[3 * len(good) // 5]]
    for upload in hung:
        upload.expect = "align: over the time limit"
    size_mb = 64 + sum(bundle_bytes(u.source) for u in uploads) * 3 // 2**20
    disk = work / "disk"
    no_disk = mount_small_disk(disk, size_mb)
    folders = {n: str(disk / n) for n in ("inbox", "outbox", "archive", "failed")}
    config = work / "mapserver.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                **folders,
                "settle_seconds": 1.0,
                "rescan_seconds": 10,
                "stale_after_seconds": 600,
                "bundle_timeout_seconds": args.timeout,
            }
        )
    )
    inbox, outbox, archive, failed = (disk / n for n in ("inbox", "outbox", "archive", "failed"))
    os.environ[FAULT_ENV] = ",".join(f"{u.bundle_id}@align=hang" for u in hung)
    use_rsync = shutil.which("rsync") is not None
    log = work / "daemon.log"
    print(
        f"work folder {work}; {len(uploads)} uploads by {args.robots} robots with "
        f"{'rsync (the README commands)' if use_rsync else 'an rsync-like copy (no rsync here)'}"
        f": {len(good)} good ({len(hung)} made to hang in align), {len(uploads) - len(good)} "
        f"malformed of {len(KINDS)} kinds"
    )
    print(f"the daemon's folders: {'a ' + str(size_mb) + ' MiB tmpfs' if not no_disk else disk}")

    daemon = base.Daemon(config, log)
    daemon.wait_ready()
    results = Results(outbox)

    def robot(k: int) -> None:
        robot_rng = random.Random(args.seed * 1000 + k)
        for upload in uploads[k :: args.robots]:
            send(upload, inbox, use_rsync, robot_rng)
            threading.Event().wait(robot_rng.expovariate(1 / args.interval))

    robots = [threading.Thread(target=robot, args=(k,)) for k in range(args.robots)]
    for thread in robots:
        thread.start()

    events: list[str] = []
    kills: list[float] = []

    def kill_and_restart(why: str) -> None:
        nonlocal daemon
        n = base.count_results(outbox)
        killed = time.time()
        daemon.kill9()
        daemon = base.Daemon(config, log)
        ready = daemon.wait_ready()
        kills.append(killed)
        events.append(
            f"kill -9 {len(kills)} ({why}) at {n} results: ready again in {ready - killed:.2f} s"
        )

    expected_total = len(uploads)
    full_at = max(1, round(0.35 * len(good)))
    filler: Path | None = None
    full_since = 0.0
    full_seconds = 0.0
    checked_second = False
    second = (0, 0.0, "")
    ids = {u.bundle_id for u in uploads}
    deadline = time.monotonic() + 1800
    while True:
        n = base.count_results(outbox)
        decided = len(visible(archive) & ids) + len(visible(failed) & ids)
        if daemon.process.poll() is not None:
            raise SystemExit(f"the daemon died; see {log}")
        if time.monotonic() > deadline:
            raise SystemExit(f"not every bundle was decided in time; see {log}")
        if len(kills) == 0 and n >= 0.2 * len(good):
            kill_and_restart("busy")
        elif len(kills) == 1 and not checked_second:
            second = second_daemon(config)
            checked_second = True
        elif no_disk is None and filler is None and full_seconds == 0.0 and n >= full_at:
            filler = fill_disk(disk)
            full_since = time.monotonic()
            events.append(f"disk full at {n} results")
        elif (
            filler is not None
            and len(kills) == 1
            and time.monotonic() - full_since >= min(10.0, args.full_seconds / 3)
        ):
            kill_and_restart("on the full disk")
        elif filler is not None and time.monotonic() - full_since >= args.full_seconds:
            filler.unlink()
            filler = None
            full_seconds = time.monotonic() - full_since
            events.append(f"disk freed after {full_seconds:.1f} s")
        elif (no_disk is not None and len(kills) == 1 and n >= 0.45 * len(good)) or (
            len(kills) == 2 and filler is None and n >= 0.7 * len(good)
        ):
            kill_and_restart("busy")
        if decided == expected_total and not any(t.is_alive() for t in robots):
            break
        time.sleep(0.1)
    for thread in robots:
        thread.join()
    code = daemon.stop()
    results.stop()
    return Run(args, work, log, uploads, hung, results, events, second, code, no_disk)


@dataclass
class Run:
    args: argparse.Namespace
    work: Path
    log: Path
    uploads: list[Upload]
    hung: list[Upload]
    results: Results
    events: list[str]
    second: tuple[int, float, str]
    code: int
    no_disk: str | None

    def report(self) -> int:
        """Check every bundle and print the numbers; 1 when a check failed."""
        disk = self.work / "disk"
        inbox, outbox, archive, failed = (
            disk / n for n in ("inbox", "outbox", "archive", "failed")
        )
        ids = {u.bundle_id for u in self.uploads}
        archived, rejected, published = visible(archive), visible(failed), visible(outbox)
        lost = ids - archived - rejected
        # A robot whose rsync failed (the full disk) uploads again; when the daemon had taken
        # the first upload already (a malformed one is rejected before it is complete), the
        # second is a new upload under a suffixed id: the robot's doing, in failed/.
        retried = {u.bundle_id for u in self.uploads if u.retries}
        suffixed = (archived | rejected | published) - ids
        again = {i for i in suffixed & rejected if i.rsplit(".", 1)[0] in retried}
        duplicated = (archived & rejected) | (suffixed - again)
        modified = {
            i
            for i, first in self.results.first.items()
            if fingerprint(outbox / i / "result.yaml") != first
        } | (published - archived)
        left = visible(inbox) | visible(inbox / ".taken")
        problems = []
        if self.code != 0:
            problems.append(f"the daemon exited {self.code} on SIGTERM")
        if left:
            problems.append(f"left in the inbox: {sorted(left)[:5]}")
        waits: list[tuple[float, str]] = []
        print()
        print(f"archived {len(archived & ids)}")
        print(f"failed {len(rejected & ids) + len(again)}:")
        for upload in sorted(self.uploads, key=lambda u: u.bundle_id):
            where = archive if upload.expect == "archived" else failed
            if upload.bundle_id not in visible(where):
                problems.append(f"{upload.bundle_id}: not in {where.name}/ ({upload.expect})")
                continue
            if upload.expect == "archived":
                result = outbox / upload.bundle_id / "result.yaml"
                if not result.is_file():
                    problems.append(f"{upload.bundle_id}: archived without a result")
                    continue
                if base.digest(where / upload.bundle_id) != base.digest(upload.source):
                    problems.append(f"{upload.bundle_id}: not byte-identical to its upload")
                waits.append((result.stat().st_mtime - upload.complete, upload.bundle_id))
                continue
            error = yaml.safe_load((where / upload.bundle_id / "error.yaml").read_text())
            stage, word = upload.expect.split(": ", 1)
            reason = str(error.get("reason"))
            print(f"  {upload.bundle_id:<26} {error.get('stage')}: {_short(reason)}")
            if error.get("stage") != stage or word not in reason:
                problems.append(
                    f"{upload.bundle_id}: failed at {error.get('stage')}, not {upload.expect}"
                )
        for bundle_id in sorted(again):
            error = yaml.safe_load((failed / bundle_id / "error.yaml").read_text())
            print(f"  {bundle_id:<26} {error.get('stage')}: {_short(str(error.get('reason')))}")
        if again:
            print(
                f"  ({len(again)} of these: a robot's second upload after its rsync failed on the "
                "full disk, of a bundle the daemon had taken already)"
            )
        print(f"lost {len(lost)}, duplicated {len(duplicated)}, results modified {len(modified)}")
        for name, found in (("lost", lost), ("duplicated", duplicated), ("modified", modified)):
            if found:
                problems.append(f"{name}: {sorted(found)[:5]}")
        if waits:
            longest, which = max(waits)
            values = sorted(w for w, _ in waits)
            print(
                f"the longest a good bundle waited (upload complete -> result.yaml): "
                f"{longest:.1f} s ({which}); median {statistics.median(values):.1f} s, p95 "
                f"{base.percentile(values, 0.95):.1f} s over {len(values)} bundles"
            )
        held = []
        for upload in self.hung:
            path = failed / upload.bundle_id / "error.yaml"
            reason = str(yaml.safe_load(path.read_text()).get("reason")) if path.is_file() else ""
            match = re.search(r"after ([0-9.]+) s", reason)
            held.append(f"{match.group(1)} s" if match else "?")
        print(
            f"a hung bundle held its worker: {', '.join(held)} "
            f"(bundle_timeout_seconds: {self.args.timeout:g})"
        )
        self._faults(problems)
        if problems:
            print("FAILED:")
            for problem in problems:
                print(f"  {problem}")
            return 1
        print(
            "checks: every good bundle archived once, byte-identical, with one result written "
            "once; every bad one and both hung ones in failed/ with the expected stage: OK"
        )
        return 0

    def _faults(self, problems: list[str]) -> None:
        for event in self.events:
            print(event)
        code, seconds, text = self.second
        print(f"a second mapserver run: exit {code} after {seconds:.2f} s: {text}")
        if code != 1 or seconds > 10 or "another mapserver (pid " not in text:
            problems.append("the second daemon did not exit 1 at once")
        log = self.log.read_text(errors="replace")
        kills = sum(e.startswith("kill -9") for e in self.events)
        if kills != 3:
            problems.append(f"{kills} kills, not 3")
        retried = sum(u.retries for u in self.uploads)
        if self.no_disk is not None:
            print(f"disk full: skipped ({self.no_disk})")
            return
        first = log.count("WARNING mapserver.faults: degraded: ")
        again = log.count("WARNING mapserver.faults: still degraded after ")
        print(
            f"while the disk was full: 'degraded' warnings {first} (one per daemon process that "
            f"met it: one was killed on it), 'still degraded' {again} (once a minute), "
            f"'recovered' {log.count('recovered after')}; robots retried {retried} rsync calls"
        )
        if first == 0:
            problems.append("the full disk was never reported as degraded")


def _can_unshare() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0


def _short(text: str, width: int = 120) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def bundle_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def run_and_report() -> int:
    run = main()
    try:
        return run.report()
    finally:
        disk = run.work / "disk"
        if run.no_disk is None:
            subprocess.run(["umount", "--lazy", str(disk)], check=False, capture_output=True)
        if run.args.out is None:
            shutil.rmtree(run.work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(run_and_report())
