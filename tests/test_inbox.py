"""The event handler, the fingerprint, the stability tracker and the entry checks."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path
from queue import Empty, SimpleQueue

import pytest
import yaml
from daemon_support import make_bundle, no_leaked_threads, upload, wait_until
from watchdog.events import FileCreatedEvent, FileMovedEvent
from watchdog.observers import Observer

from mapserver.errors import BundleError, BundleIncomplete
from mapserver.inbox import (
    EVENT_TYPES,
    InboxHandler,
    Ready,
    Rejected,
    StabilityTracker,
    check_entry,
    entry_name,
    fingerprint,
    scan,
)

__all__ = ["no_leaked_threads"]


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize(
    ("path", "name"),
    [
        ("/in/run-1", "run-1"),
        ("/in/run-1/slam_map.pgm", "run-1"),
        ("/in/run-1/.slam_map.pgm.Ab12Cd", "run-1"),
        ("/in", None),
        ("/elsewhere/run-1", None),
        ("/in/.taken/run-1", None),
        ("/in/.run-1.XyZ123", None),
        ("/in/run-1.part", None),
        (b"/in/run-2/bundle.yaml", "run-2"),
    ],
)
def test_entry_name(path: str | bytes, name: str | None) -> None:
    assert entry_name("/in", path) == name


def test_handler_enqueues_both_names_of_a_move_and_never_raises() -> None:
    hints: SimpleQueue[str | None] = SimpleQueue()
    handler = InboxHandler(Path("/in"), hints)
    handler.dispatch(FileMovedEvent("/in/run-1/.bundle.yaml.x1", "/in/run-1/bundle.yaml"))
    handler.dispatch(FileMovedEvent("/in/.staging", "/in/run-2"))
    assert [hints.get_nowait(), hints.get_nowait()] == ["run-1", "run-1"]
    assert hints.get_nowait() == "run-2"

    class Broken(SimpleQueue):  # type: ignore[type-arg]
        def put(self, item: object, block: bool = True, timeout: float | None = None) -> None:
            raise RuntimeError("full")

    InboxHandler(Path("/in"), Broken()).dispatch(FileCreatedEvent("/in/run-3/x"))


@pytest.mark.usefixtures("no_leaked_threads")
def test_a_real_observer_hints_at_an_rsync_upload_by_its_final_name(tmp_path: Path) -> None:
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    source = make_bundle(tmp_path / "src" / "run-1")
    hints: SimpleQueue[str | None] = SimpleQueue()
    observer = Observer()
    observer.schedule(
        InboxHandler(inbox, hints), str(inbox), recursive=True, event_filter=EVENT_TYPES
    )
    observer.start()
    try:
        upload(source, inbox)
        (inbox / "run-1" / "slam_map.pgm").read_bytes()  # reads are not events we ask for
        seen: set[str | None] = set()

        def all_seen() -> bool:
            try:
                while True:
                    seen.add(hints.get_nowait())
            except Empty:
                return seen == {"run-1"}

        wait_until(all_seen, timeout=5, what="a hint for run-1")
    finally:
        observer.stop()
        observer.join()


def test_scan_lists_entries_but_not_in_flight_names(tmp_path: Path) -> None:
    for name in ("b", "a", ".taken", ".a.XYZ", "c.tmp"):
        (tmp_path / name).mkdir()
    (tmp_path / "file").write_text("x")
    assert scan(tmp_path) == ["a", "b", "file"]


def test_fingerprint_sees_growing_temp_files_renames_and_rewrites(tmp_path: Path) -> None:
    bundle = make_bundle(tmp_path / "b")
    first = fingerprint(bundle)
    assert first == fingerprint(bundle)
    temp = bundle / ".extra.XYZ"
    temp.write_bytes(b"1")
    second = fingerprint(bundle)
    assert second != first
    temp.write_bytes(b"12")
    assert fingerprint(bundle) != second
    before = fingerprint(bundle)
    data = (bundle / "slam_map.pgm").read_bytes()
    stat = (bundle / "slam_map.pgm").stat()
    (bundle / "new.pgm").write_bytes(data)
    os.utime(bundle / "new.pgm", ns=(stat.st_atime_ns, stat.st_mtime_ns))
    os.rename(bundle / "new.pgm", bundle / "slam_map.pgm")  # same size, same mtime
    assert fingerprint(bundle) != before
    assert fingerprint(tmp_path / "gone") is None


def tracker(inbox: Path, clock: Clock, **kw: float) -> StabilityTracker:
    return StabilityTracker(
        inbox,
        settle_seconds=kw.get("settle", 2.0),
        stale_after_seconds=kw.get("stale", 60.0),
        clock=clock,
    )


def test_a_complete_bundle_is_ready_once_it_has_settled(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    make_bundle(tmp_path / "run-1")
    t.touch("run-1")
    assert t.poll() == [] and t.next_deadline() == 102.0
    clock.now = 101.9
    assert t.poll() == []
    clock.now = 102.0
    assert t.poll() == [Ready("run-1", 2.0)]
    assert t.poll() == [] and len(t) == 0  # decided once, then forgotten


def test_a_change_restarts_the_settle_time(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    bundle = make_bundle(tmp_path / "run-1")
    t.touch("run-1")
    clock.now = 101.5
    (bundle / ".late.XYZ").write_bytes(b"still uploading")
    t.touch("run-1")
    clock.now = 102.5
    assert t.poll() == []
    clock.now = 103.5
    assert [d.name for d in t.poll()] == ["run-1"]


def test_a_change_missed_by_events_is_caught_at_the_deadline(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    bundle = make_bundle(tmp_path / "run-1")
    t.touch("run-1")
    (bundle / "extra.txt").write_text("no event for this one")
    clock.now = 102.0
    assert t.poll() == []
    assert t.next_deadline() == 104.0
    clock.now = 104.0
    assert [d.name for d in t.poll()] == ["run-1"]


def test_an_incomplete_bundle_waits_then_goes_stale_with_its_reason(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock, stale=30.0)
    bundle = make_bundle(tmp_path / "run-1")
    (bundle / "slam_map.pgm").unlink()
    t.touch("run-1")
    clock.now = 110.0
    assert t.poll() == []
    assert t.next_deadline() == 130.0
    clock.now = 130.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and decision.stage == "upload"
    assert "slam_map.pgm" in decision.reason and "30 s" in decision.reason


def test_an_incomplete_bundle_completes_when_the_last_file_arrives(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    source = make_bundle(tmp_path / "src")
    bundle = tmp_path / "run-1"
    bundle.mkdir()
    shutil.copy2(source / "bundle.yaml", bundle)  # the manifest first
    t.touch("run-1")
    clock.now = 103.0
    assert t.poll() == []
    for name in ("nav2_map.yaml", "nav2_map.pgm", "slam_map.yaml", "slam_map.pgm"):
        shutil.copy2(source / name, bundle)
    t.touch("run-1")
    clock.now = 105.0
    assert [d.name for d in t.poll()] == ["run-1"]


def test_a_bundle_that_can_never_be_right_is_rejected_after_settling(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    bundle = make_bundle(tmp_path / "run-1")
    (bundle / "bundle.yaml").write_text("format: 1\nrobot: [a, list]\n")  # YAML, not a manifest
    t.touch("run-1")
    clock.now = 102.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and decision.stage == "bundle"
    assert "bundle.yaml" in decision.reason


def test_a_manifest_that_does_not_parse_yet_is_waited_for_until_stale(tmp_path: Path) -> None:
    """Complete only once bundle.yaml parses (contract section 2): a manifest written in place
    (cp, scp) by an uploader that pauses is not failed after settling (session 58's review:
    it went to failed/ and the rest of the upload then failed); it is once stale, with what
    does not parse."""
    clock = Clock()
    t = tracker(tmp_path, clock, stale=60.0)
    bundle = make_bundle(tmp_path / "run-1")
    whole = (bundle / "bundle.yaml").read_text()
    (bundle / "bundle.yaml").write_text(whole[: whole.index("stamp:") + 12])  # in a quote
    t.touch("run-1")
    clock.now = 102.0
    assert t.poll() == []  # settled, does not parse: still coming
    (bundle / "bundle.yaml").write_text(whole)
    t.touch("run-1")
    clock.now = 104.5
    assert [d.name for d in t.poll()] == ["run-1"]
    # One that never parses is failed once stale, saying why.
    other = make_bundle(tmp_path / "run-2")
    (other / "bundle.yaml").write_text("format: 1\nrobot: [unclosed\n")
    t.touch("run-2")
    clock.now = 107.0
    assert t.poll() == []
    clock.now = 104.5 + 61.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and decision.stage == "upload"
    assert "still incomplete" in decision.reason and "not valid YAML" in decision.reason


def test_poll_stops_at_its_time_budget_and_decides_the_rest_next_time(tmp_path: Path) -> None:
    clock = Clock()
    seen = []

    def slow_check(path: Path) -> None:
        seen.append(path.name)
        clock.now += 0.6  # a checksum of a big bundle

    t = StabilityTracker(
        tmp_path, settle_seconds=1.0, stale_after_seconds=60.0, clock=clock, check=slow_check
    )
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
        t.touch(name)
    clock.now = 101.0
    first = t.poll(budget_s=1.0)
    assert [d.name for d in first] == ["a", "b"] and len(t) == 1
    assert [d.name for d in t.poll(budget_s=1.0)] == ["c"]


def test_a_check_that_breaks_rejects_the_entry_instead_of_stopping_the_daemon(
    tmp_path: Path,
) -> None:
    def broken(path: Path) -> None:
        raise KeyError("a bug")

    clock = Clock()
    t = StabilityTracker(
        tmp_path, settle_seconds=1.0, stale_after_seconds=60.0, clock=clock, check=broken
    )
    (tmp_path / "a").mkdir()
    t.touch("a")
    clock.now = 101.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and "KeyError" in decision.reason


def test_entries_that_vanish_are_forgotten(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    make_bundle(tmp_path / "run-1")
    make_bundle(tmp_path / "run-2")
    t.touch("run-1")
    t.touch("run-2")
    shutil.rmtree(tmp_path / "run-1")
    t.touch("run-1")
    assert "run-1" not in t and "run-2" in t
    t.forget_missing(set())
    assert len(t) == 0


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (
            lambda b: (
                (b / "slam_map.pgm").unlink() or os.symlink("/etc/hostname", b / "slam_map.pgm")
            ),
            "outside",
        ),
        (lambda b: os.symlink("../../secret", b / "extra"), "outside"),
        (lambda b: os.mkfifo(b / "pipe"), "not a regular file"),
        (lambda b: os.symlink("loop", b / "loop"), "loop"),
    ],
    ids=["absolute-symlink", "relative-symlink-escaping", "fifo", "symlink-loop"],
)
def test_check_entry_rejects_unsafe_bundles(tmp_path: Path, make, match: str) -> None:  # type: ignore[no-untyped-def]
    bundle = make_bundle(tmp_path / "inbox" / "run-1")
    make(bundle)
    with pytest.raises(BundleError, match=match) as info:
        check_entry(bundle)
    assert not isinstance(info.value, BundleIncomplete)


def test_check_entry_rejects_what_is_not_a_bundle_directory(tmp_path: Path) -> None:
    make_bundle(tmp_path / "real")
    os.symlink(tmp_path / "real", tmp_path / "link")
    (tmp_path / "file").write_text("x")
    make_bundle(tmp_path / "bad id")
    with pytest.raises(BundleError, match="symbolic link"):
        check_entry(tmp_path / "link")
    with pytest.raises(BundleError, match="not a directory"):
        check_entry(tmp_path / "file")
    with pytest.raises(BundleError, match="invalid bundle id"):
        check_entry(tmp_path / "bad id")


def test_check_entry_accepts_a_symlink_inside_the_bundle(tmp_path: Path) -> None:
    bundle = make_bundle(tmp_path / "run-1", checksums=False)
    os.rename(bundle / "slam_map.pgm", bundle / "real.pgm")
    os.symlink("real.pgm", bundle / "slam_map.pgm")
    assert check_entry(bundle).manifest.robot == "r1"
    doc = yaml.safe_load((bundle / "bundle.yaml").read_text())
    assert doc["slam_map"] == "slam_map.yaml"


def test_a_complete_bundle_whose_checksum_does_not_match_is_rejected_within_a_minute(
    tmp_path: Path,
) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock, settle=2.0, stale=600.0)
    bundle = make_bundle(tmp_path / "run-1")
    good = (bundle / "slam_map.pgm").read_bytes()
    expected = yaml.safe_load((bundle / "bundle.yaml").read_text())["checksums"]["slam_map.pgm"]
    (bundle / "slam_map.pgm").write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    t.touch("run-1")
    clock.now = 102.0
    assert t.poll() == []  # checked: it may still be rewritten
    assert t.next_deadline() == 120.0  # 10 x settle_seconds, not stale_after_seconds
    clock.now = 110.0
    (bundle / "slam_map.pgm").write_bytes(good[:-1] + bytes([good[-1] ^ 2]))  # it was rewritten
    t.touch("run-1")
    clock.now = 112.0
    assert t.poll() == []
    assert t.next_deadline() == 130.0  # 20 s after the last change
    clock.now = 129.9
    assert t.poll() == []
    clock.now = 130.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and decision.stage == "upload"
    actual = hashlib.sha256((bundle / "slam_map.pgm").read_bytes()).hexdigest()
    assert decision.reason == (
        f"{bundle / 'slam_map.pgm'}: sha256 of 'slam_map.pgm' does not match the manifest: "
        f"expected {expected}, actual {actual} (every file there, nothing changed for 20 s)"
    )


def test_a_mismatch_that_is_fixed_in_time_is_a_bundle_after_all(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock, settle=2.0, stale=600.0)
    bundle = make_bundle(tmp_path / "run-1")
    good = (bundle / "slam_map.pgm").read_bytes()
    (bundle / "slam_map.pgm").write_bytes(b"P5\n1 1\n255\n\x00")
    t.touch("run-1")
    clock.now = 102.0
    assert t.poll() == []
    clock.now = 115.0
    (bundle / "slam_map.pgm").write_bytes(good)
    t.touch("run-1")
    clock.now = 117.0
    assert [type(d) for d in t.poll()] == [Ready]


def test_a_folder_of_bundles_is_not_a_bundle_and_is_rejected_at_once(tmp_path: Path) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock)
    make_bundle(tmp_path / "runs" / "run-1")
    make_bundle(tmp_path / "runs" / "run-2")
    t.touch("runs")
    clock.now = 102.0
    [decision] = t.poll()
    assert isinstance(decision, Rejected) and decision.stage == "bundle"
    assert decision.reason == (
        "runs: not a bundle: no bundle.yaml in it; it holds 2 bundle folders (run-1, run-2); "
        "upload each bundle folder directly into the inbox"
    )


def test_a_mismatch_while_a_file_is_still_missing_waits_like_any_incomplete_upload(
    tmp_path: Path,
) -> None:
    clock = Clock()
    t = tracker(tmp_path, clock, settle=2.0, stale=600.0)
    bundle = make_bundle(tmp_path / "run-1")
    manifest = yaml.safe_load((bundle / "bundle.yaml").read_text())
    manifest["checksums"]["notes.txt"] = "0" * 64  # listed last, still to come
    (bundle / "bundle.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    (bundle / "nav2_map.pgm").write_bytes(b"P5\n1 1\n255\n\x00")  # listed first: no match
    t.touch("run-1")
    clock.now = 102.0
    assert t.poll() == []
    assert t.next_deadline() == 700.0  # stale_after_seconds: the upload is not over
