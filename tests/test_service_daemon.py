"""A real ``mapserver run`` subprocess: kill -9 at every step and restart, a random kill, signals,
real rsync uploads, and the bad-input table (every malformed bundle ends in failed/)."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from daemon_support import (
    Daemon,
    assert_settled,
    layout,
    make_bundle,
    upload,
    visible,
    wait_until,
    write_config,
)

from mapserver.service import CRASH_ENV


def finished(root: Path, ids: list[str]) -> Callable[[], bool]:
    dirs = layout(root)

    def check() -> bool:
        return all(
            ((dirs["outbox"] / i / "result.yaml").is_file() and (dirs["archive"] / i).is_dir())
            or (dirs["failed"] / i / "error.yaml").is_file()
            for i in ids
        )

    return check


def bad_image(path: Path) -> Path:
    """A bundle that passes the completeness check and fails in a worker (stage load)."""
    bundle = make_bundle(path, checksums=False)
    (bundle / "slam_map.pgm").write_text("this is not an image\n")
    return bundle


def bad_manifest(path: Path) -> Path:
    """A bundle the tracker rejects straight from the inbox (stage bundle): YAML, but no
    manifest (one that is no YAML is waited for until stale, an upload writing it in place)."""
    bundle = make_bundle(path)
    (bundle / "bundle.yaml").write_text("format: 1\nrobot: [a, list]\n")
    return bundle


# Each row: the step after which the daemon kills itself, the bundle, what the crash must have
# left behind (proof that it died at that step), and the recovery rule that finishes the job.
def _tmp_results(root: Path) -> list[Path]:
    return list((root / "outbox").glob(".tmp-*"))


def _staged(root: Path) -> Path:
    return root / "inbox" / ".taken" / ".run-1.error.yaml"


CRASHES = [
    ("claimed", make_bundle, lambda r: (r / "inbox/.taken/run-1").is_dir(), "processing again"),
    (
        "result-written",
        make_bundle,
        lambda r: _tmp_results(r) and (r / "inbox/.taken/run-1").is_dir(),
        "removing partial result",
    ),
    (
        "published",
        make_bundle,
        lambda r: (
            (r / "outbox/run-1/result.yaml").is_file() and (r / "inbox/.taken/run-1").is_dir()
        ),
        "result already published, archiving",
    ),
    (
        "error-staged",
        bad_manifest,
        lambda r: _staged(r).is_file() and (r / "inbox/run-1").is_dir(),
        None,  # the staged error is dropped; the bundle is judged again
    ),
    (
        "error-staged",
        bad_image,
        lambda r: _staged(r).is_file() and (r / "inbox/.taken/run-1").is_dir(),
        "finishing the move to failed/",
    ),
    (
        "failed-moved",
        bad_image,
        lambda r: _staged(r).is_file() and not (r / "failed/run-1/error.yaml").exists(),
        "adding error.yaml",
    ),
]


@pytest.mark.parametrize(
    ("point", "make", "left_behind", "recovery"),
    CRASHES,
    ids=[f"{c[0]}-{c[1].__name__}" for c in CRASHES],
)
def test_kill_9_at_each_step_then_restart_finishes_the_bundle_exactly_once(
    tmp_path: Path,
    point: str,
    make: Callable[[Path], Path],
    left_behind: Callable[[Path], bool],
    recovery: str | None,
) -> None:
    source = make(tmp_path / "src" / "run-1")
    config = write_config(tmp_path, workers=1)
    with Daemon(config, env={CRASH_ENV: point}) as first:
        first.wait_ready()
        upload(source, layout(tmp_path)["inbox"])
        assert first.wait_exit() == -signal.SIGKILL, first.log()
        # Only the main process was killed: its fork server and workers follow it.
        wait_until(first.group_gone, timeout=10, what="the workers to exit")
    assert left_behind(tmp_path), f"not the state a crash at {point} leaves"
    result = tmp_path / "outbox/run-1/result.yaml"
    published = result.read_bytes() if point == "published" else None
    with Daemon(config) as second:
        wait_until(finished(tmp_path, ["run-1"]), timeout=30, what="run-1 finished")
        assert second.stop() == 0, second.log()
    if recovery is not None:
        assert recovery in second.log()
    failed = set() if make is make_bundle else {"run-1"}
    assert_settled(tmp_path, {"run-1": source}, failed=failed)
    if published is not None:
        assert result.read_bytes() == published  # archived, not processed again


def test_kill_9_at_a_random_moment_loses_and_duplicates_nothing(tmp_path: Path) -> None:
    seed = int(os.environ.get("MAPSERVER_TEST_SEED", "20261121"))
    rng = random.Random(seed)
    n = 8
    sources = {f"run-{i}": make_bundle(tmp_path / "src" / f"run-{i}", seed=i) for i in range(n)}
    sources["bad"] = bad_image(tmp_path / "src" / "bad")
    config = write_config(tmp_path)
    inbox = layout(tmp_path)["inbox"]
    kill_after = rng.randrange(n)  # results seen before the kill
    with Daemon(config) as first:
        first.wait_ready()
        uploads = [
            threading.Thread(target=upload, args=(s, inbox), kwargs={"order": order})
            for s, order in zip(
                sources.values(),
                rng.choices(["manifest-last", "manifest-first", "random"], k=len(sources)),
                strict=True,
            )
        ]
        for thread in uploads:
            thread.start()
        wait_until(
            lambda: len(list((tmp_path / "outbox").glob("*/result.yaml"))) >= kill_after,
            timeout=60,
            what=f"{kill_after} results",
        )
        first.kill_group()
        for thread in uploads:
            thread.join()
    with Daemon(config) as second:
        wait_until(finished(tmp_path, list(sources)), timeout=60, what=f"all (seed {seed})")
        assert second.stop() == 0, second.log()
    assert_settled(tmp_path, sources, failed={"bad"})


def test_sigterm_finishes_what_is_in_hand_exits_0_and_a_restart_does_the_rest(
    tmp_path: Path,
) -> None:
    sources = {f"run-{i}": make_bundle(tmp_path / "src" / f"run-{i}", seed=i) for i in range(4)}
    config = write_config(tmp_path, workers=1)
    with Daemon(config) as first:
        first.wait_ready()
        for source in sources.values():
            upload(source, layout(tmp_path)["inbox"])
        wait_until(lambda: ": queue " in first.log(), timeout=30, what="a bundle in a worker")
        assert first.stop(timeout=30) == 0, first.log()
        assert "stopped:" in first.log()
    assert not _tmp_results(tmp_path)
    with Daemon(config, env={}) as second:
        wait_until(finished(tmp_path, list(sources)), timeout=30, what="the rest")
        second.process.send_signal(signal.SIGINT)
        assert second.wait_exit() == 0, second.log()
    assert_settled(tmp_path, sources)


@pytest.mark.skipif(shutil.which("rsync") is None, reason="rsync is not installed")
def test_real_rsync_uploads(tmp_path: Path) -> None:
    sources = {
        "two-calls": make_bundle(tmp_path / "src" / "two-calls", seed=1),
        "one-call": make_bundle(tmp_path / "src" / "one-call", seed=2),
    }
    config = write_config(tmp_path)
    inbox = layout(tmp_path)["inbox"]
    with Daemon(config) as daemon:
        daemon.wait_ready()
        src = sources["two-calls"]
        rsync = ["rsync", "-a"]
        subprocess.run(
            [*rsync, "--exclude=bundle.yaml", f"{src}/", f"{inbox}/two-calls/"], check=True
        )
        subprocess.run([*rsync, f"{src}/bundle.yaml", f"{inbox}/two-calls/"], check=True)
        subprocess.run([*rsync, f"{sources['one-call']}", f"{inbox}/"], check=True)
        wait_until(finished(tmp_path, list(sources)), timeout=30, what="both results")
        assert daemon.stop() == 0, daemon.log()
    assert_settled(tmp_path, sources)


# -- the bad-input table ---------------------------------------------------------------------------


def _manifest(**changes: object) -> Callable[[Path], None]:
    def apply(bundle: Path) -> None:
        doc = yaml.safe_load((bundle / "bundle.yaml").read_text())
        for key, value in changes.items():
            if value is None:
                del doc[key]
            else:
                doc[key] = value
        (bundle / "bundle.yaml").write_text(yaml.safe_dump(doc))

    return apply


def _map_yaml(**changes: object) -> Callable[[Path], None]:
    def apply(bundle: Path) -> None:
        doc = yaml.safe_load((bundle / "slam_map.yaml").read_text())
        doc.update(changes)
        (bundle / "slam_map.yaml").write_text(yaml.safe_dump(doc))

    return apply


def _write(name: str, data: bytes) -> Callable[[Path], None]:
    return lambda bundle: (bundle / name).write_bytes(data)


def _truncate(bundle: Path) -> None:
    data = (bundle / "slam_map.pgm").read_bytes()
    (bundle / "slam_map.pgm").write_bytes(data[: len(data) // 2])


def _symlink_out(bundle: Path) -> None:
    (bundle / "slam_map.pgm").unlink()
    os.symlink("/etc/hostname", bundle / "slam_map.pgm")


def _fifo(bundle: Path) -> None:
    os.mkfifo(bundle / "extra")


def _nan(bundle: Path) -> None:
    text = (bundle / "bundle.yaml").read_text().replace("x: 1.0", "x: .nan", 1)
    (bundle / "bundle.yaml").write_text(text)


def _inf(bundle: Path) -> None:
    text = (bundle / "bundle.yaml").read_text().replace("yaw: 0.0", "yaw: -.inf", 1)
    (bundle / "bundle.yaml").write_text(text)


def _bad_checksum(bundle: Path) -> None:
    doc = yaml.safe_load((bundle / "bundle.yaml").read_text())
    doc["checksums"]["slam_map.pgm"] = "0" * 64
    (bundle / "bundle.yaml").write_text(yaml.safe_dump(doc))


def _pad_manifest(bundle: Path) -> None:
    with (bundle / "bundle.yaml").open("a") as manifest:
        manifest.write("# padding\n" * 500)


def _never_complete(bundle: Path) -> None:
    (bundle / "slam_map.pgm").unlink()


def _too_big(bundle: Path) -> None:
    header = b"P5\n300 300\n255\n"
    (bundle / "slam_map.pgm").write_bytes(header + bytes([254]) * 90000)


def _bomb(bundle: Path) -> None:
    (bundle / "slam_map.pgm").write_bytes(b"P5\n100000 100000\n255\n" + bytes(64))


# id, how to break a good bundle (checksums off unless the row is about them), stage, a word of
# the reason. Stage "upload": never complete, failed after stale_after_seconds.
BAD = [
    (
        "corrupt-image",
        _write("slam_map.pgm", b"P5\n100 100\n255\n" + bytes(10)),
        "load",
        "slam_map.pgm",
    ),
    ("truncated-image", _truncate, "load", "slam_map.pgm"),
    ("text-as-pgm", _write("slam_map.pgm", b"hello, I am text\n"), "load", "slam_map.pgm"),
    ("empty-image", _write("slam_map.pgm", b""), "load", "slam_map.pgm"),
    # Complete only once bundle.yaml parses (contract section 2): failed once stale.
    ("yaml-syntax", _write("bundle.yaml", b"format: 1\nrobot: [unclosed\n"), "upload", "YAML"),
    ("missing-key", _manifest(pose=None), "bundle", "pose"),
    (
        "mistyped-key",
        _manifest(
            pose={"nav2": {"x": "north", "y": 0, "yaw": 0}, "slam": {"x": 0, "y": 0, "yaw": 0}}
        ),
        "bundle",
        "pose",
    ),
    ("nan-pose", _nan, "bundle", "finite"),
    ("inf-pose", _inf, "bundle", "finite"),
    ("image-dotdot", _map_yaml(image="../other/slam_map.pgm"), "bundle", "outside"),
    ("image-absolute", _map_yaml(image="/etc/hostname"), "bundle", "/etc/hostname"),
    ("symlink-out", _symlink_out, "bundle", "outside"),
    ("fifo", _fifo, "bundle", "not a regular file"),
    ("too-big", _too_big, "load", "max_image_pixels"),
    ("bomb", _bomb, "load", "max_image_pixels"),
    (
        "bad-map-yaml",
        _write("slam_map.yaml", b"image: slam_map.pgm\nresolution: -1\n"),
        "load",
        "slam_map.yaml",
    ),
    ("resolution-tiny", _map_yaml(resolution=1e-9), "load", "limits.min_resolution_m"),
    ("map-too-wide", _map_yaml(resolution=0.9), "load", "limits.max_map_extent_m"),
    ("trajectory-too-long", _manifest(trajectory=[[0, 0, 0]] * 60), "bundle", "max_trajectory"),
    # Only counted in the main loop (a 100,000-pose trajectory held it for seconds): the worker
    # reads the poses and fails the bundle.
    ("bad-pose", _manifest(trajectory=[{"x": 0, "y": 0, "yaw": "north"}]), "bundle", "yaw"),
    ("manifest-too-big", _pad_manifest, "bundle", "limits.max_manifest_bytes"),
    ("checksum-mismatch", _bad_checksum, "upload", "sha256"),
    ("never-complete", _never_complete, "upload", "slam_map"),
]


def test_every_malformed_bundle_ends_in_failed_and_the_daemon_keeps_serving(
    tmp_path: Path,
) -> None:
    sources: dict[str, Path] = {}
    failed: set[str] = set()
    for i, (bundle_id, breaks, _, _) in enumerate(BAD):
        checksums = bundle_id in ("checksum-mismatch", "never-complete")
        bundle = make_bundle(tmp_path / "src" / bundle_id, seed=i, checksums=checksums)
        breaks(bundle)
        sources[bundle_id] = bundle
        failed.add(bundle_id)
    sources["good"] = make_bundle(tmp_path / "src" / "good", seed=99)
    # An id that was used before: the same bytes again are a repeated upload (failed/), other
    # bytes are a new bundle, processed under a suffixed id.
    dirs = layout(tmp_path)
    make_bundle(dirs["archive"] / "again", seed=50)
    make_bundle(dirs["outbox"] / "again")  # stands in for its result
    make_bundle(dirs["archive"] / "reused", seed=51)
    (dirs["outbox"] / "reused").mkdir()
    again = make_bundle(tmp_path / "src" / "again", seed=50)
    reused = make_bundle(tmp_path / "src" / "reused", seed=52)
    # The table's maps are 5 m wide, their manifests about 1 kB.
    limits = {"max_map_extent_m": 50, "max_trajectory_poses": 50, "max_manifest_bytes": 4000}
    config = write_config(tmp_path, stale_after_seconds=2.0, max_image_pixels=40_000, limits=limits)
    dirs["inbox"].mkdir()
    shutil.copytree(sources["corrupt-image"], dirs["inbox"] / "corrupt-image")  # at start-up
    with Daemon(config) as daemon:
        daemon.wait_ready()
        for bundle_id, source in sources.items():
            if bundle_id != "corrupt-image":
                upload(source, dirs["inbox"])
        upload(again, dirs["inbox"])
        upload(reused, dirs["inbox"])
        upload(sources["good"], dirs["inbox"], name="bad id!")
        (dirs["inbox"] / "notes.txt").write_text("not a bundle")
        os.symlink(sources["good"], dirs["inbox"] / "linked")
        ids = [*sources, "again.2", "reused.2", "bad_id_", "notes.txt", "linked"]
        wait_until(finished(tmp_path, ids), timeout=60, what="every bundle decided")
        assert daemon.process.poll() is None
        assert daemon.stop() == 0, daemon.log()
        log = daemon.log()

    for bundle_id, _, stage, word in BAD:
        error = yaml.safe_load((dirs["failed"] / bundle_id / "error.yaml").read_text())
        assert (error["stage"], error["bundle"]) == (stage, bundle_id), error
        assert word in error["reason"], error
        assert str(tmp_path) not in error["reason"], error  # names files within the bundle
        # The log line names them as error.yaml does (session 58's review: in .taken/).
        line = next(x for x in log.splitlines() if f": {bundle_id}: done: failed at" in x)
        assert error["reason"] in line and ".taken" not in line, line
        kept = {p.name for p in (dirs["failed"] / bundle_id).iterdir()} - {"error.yaml"}
        assert kept == {p.name for p in sources[bundle_id].iterdir()}
    for bundle_id, word in [
        ("again.2", "repeated upload"),
        ("bad_id_", "invalid bundle id"),
        ("notes.txt", "not a directory"),
        ("linked", "symbolic link"),
    ]:
        error = yaml.safe_load((dirs["failed"] / bundle_id / "error.yaml").read_text())
        assert word in error["reason"], error
    assert (dirs["failed"] / "notes.txt" / "notes.txt").read_text() == "not a bundle"
    assert (dirs["failed"] / "linked" / "linked").is_symlink()
    result = yaml.safe_load((dirs["outbox"] / "reused.2" / "result.yaml").read_text())
    assert result["bundle"] == "reused.2"
    assert (dirs["archive"] / "reused.2" / "bundle.yaml").is_file()
    assert (dirs["outbox"] / "good" / "result.yaml").is_file()
    assert visible(dirs["inbox"]) == []
    assert sorted(visible(dirs["failed"])) == sorted(
        [*failed, "again.2", "bad_id_", "notes.txt", "linked"]
    )
