"""Atomic results, archive and failed moves, id allocation and the recovery rules (in process; the
same rules under a real kill -9 are in test_service_daemon.py)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
import yaml
from daemon_support import digest, make_bundle

from mapserver.errors import ConfigError
from mapserver.outbox import (
    Store,
    daemon_error,
    error_document,
    sanitize_id,
    suffixed,
    write_result,
)
from mapserver.pipeline import Outcome


def outcome(bundle_id: str) -> Outcome:
    return Outcome(bundle_id, {"format": 1, "bundle": bundle_id}, {"overlay.png": b"png"})


@pytest.fixture
def store(tmp_path: Path) -> Store:
    s = Store(tmp_path / "inbox", tmp_path / "outbox", tmp_path / "archive", tmp_path / "failed")
    s.prepare()
    return s


def test_prepare_creates_the_directories_and_leaves_no_probe(store: Store) -> None:
    for path in (store.inbox, store.outbox, store.archive_dir, store.failed_dir, store.taken):
        assert path.is_dir()
    for path in (store.outbox, store.archive_dir, store.failed_dir, store.taken):
        assert list(path.iterdir()) == []


def test_prepare_names_the_problem_when_rename_crosses_filesystems(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def rename(src: object, dst: object) -> None:
        raise OSError(errno.EXDEV, os.strerror(errno.EXDEV))

    monkeypatch.setattr(os, "rename", rename)
    s = Store(tmp_path / "in", tmp_path / "out", tmp_path / "arch", tmp_path / "fail")
    with pytest.raises(ConfigError, match="ReadWritePaths"):
        s.prepare()


def test_publish_writes_result_last_and_never_replaces(store: Store) -> None:
    final = store.publish(outcome("run-1"))
    assert sorted(p.name for p in final.iterdir()) == ["overlay.png", "result.yaml"]
    assert yaml.safe_load((final / "result.yaml").read_text())["bundle"] == "run-1"
    assert [p.name for p in store.outbox.iterdir()] == ["run-1"]
    with pytest.raises(FileExistsError):
        store.publish(outcome("run-1"))
    assert [p.name for p in store.outbox.iterdir()] == ["run-1"]


def test_publish_refuses_image_names_that_leave_the_result(store: Store) -> None:
    bad = Outcome("run-1", {"format": 1}, {"../escape.png": b"x"})
    with pytest.raises(ValueError, match="plain file name"):
        store.publish(bad)
    assert not (store.outbox.parent / "escape.png").exists()


def test_write_result_replaces_an_existing_result(tmp_path: Path) -> None:
    write_result(tmp_path, Outcome("a", {"n": 1}, {"overlay.png": b"1", "diff.png": b"1"}))
    final = write_result(tmp_path, Outcome("a", {"n": 2}, {"overlay.png": b"2"}))
    assert yaml.safe_load((final / "result.yaml").read_text()) == {"n": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]
    assert sorted(p.name for p in final.iterdir()) == ["overlay.png", "result.yaml"]


def test_the_result_says_how_long_its_images_took_to_write(tmp_path: Path, store: Store) -> None:
    # Contract section 3's example: timings_ms {load, align, diff, cluster, write}.
    pipeline_ms = {"load": 1.0, "render": 2.0}
    images = {"overlay.png": b"1" * 100_000, "diff.png": b"2"}
    for written in (
        write_result(tmp_path, Outcome("a", {"timings_ms": dict(pipeline_ms)}, images)),
        store.publish(Outcome("run-1", {"timings_ms": dict(pipeline_ms)}, images)),
    ):
        timings = yaml.safe_load((written / "result.yaml").read_text())["timings_ms"]
        assert list(timings) == ["load", "render", "write"]
        assert {k: timings[k] for k in pipeline_ms} == pipeline_ms
        assert 0.0 <= timings["write"] < 10_000.0


def test_allocate_keeps_a_free_id(store: Store) -> None:
    make_bundle(store.inbox / "run-1")
    assert store.allocate("run-1").bundle_id == "run-1"


def test_allocate_suffixes_an_id_in_use_and_spots_a_repeated_upload(
    store: Store, tmp_path: Path
) -> None:
    make_bundle(store.archive_dir / "run-1", seed=1)
    make_bundle(store.inbox / "run-1", seed=2)
    assert store.allocate("run-1").bundle_id == "run-1.2"
    assert store.allocate("run-1").duplicate_of is None
    (store.failed_dir / "run-1.2").mkdir()
    (store.outbox / "run-1.3").mkdir()
    assert store.allocate("run-1").bundle_id == "run-1.4"
    make_bundle(tmp_path / "copy", seed=1)
    os.rename(store.inbox / "run-1", tmp_path / "other")
    os.rename(tmp_path / "copy", store.inbox / "run-1")
    assert store.allocate("run-1").duplicate_of == "archive/run-1"
    make_bundle(store.taken / "run-1.4", seed=3)  # being processed: a retry of its upload
    make_bundle(store.inbox / "run-9", seed=3)
    assert store.allocate("run-9").duplicate_of is None
    os.rename(store.inbox / "run-9", store.inbox / "run-1.4")
    assert store.allocate("run-1.4").duplicate_of == "inbox/.taken/run-1.4"


def test_a_requeued_repeat_is_still_a_repeat_of_the_bundle_it_copies(store: Store) -> None:
    # Session 53's review: the repeat of run-1, failed as run-1.2 and sent back by requeue
    # (its error document kept in .mapserver-history), was processed as a new bundle.
    make_bundle(store.archive_dir / "run-1", seed=1)
    repeat = make_bundle(store.inbox / "run-1.2", seed=1)
    (repeat / ".mapserver-history").mkdir()
    (repeat / ".mapserver-history" / "error-1.yaml").write_text("stage: bundle\n")
    assert store.allocate("run-1.2").duplicate_of == "archive/run-1"
    make_bundle(store.inbox / "run-5.3", seed=2)  # another bundle under a suffixed name
    assert store.allocate("run-5.3").duplicate_of is None
    make_bundle(store.inbox / "a.999999999", seed=1)  # looked at in bounded time
    assert store.allocate("a.999999999").bundle_id == "a.999999999"


def test_invalid_names_get_a_valid_id() -> None:
    assert sanitize_id("bad id!") == "bad_id_"
    assert sanitize_id("..") == "bundle"
    assert sanitize_id("\udcff-x") == "x"
    assert len(suffixed("a" * 128, 12)) == 128
    assert suffixed("a" * 128, 12).endswith("a.12")


def test_reject_moves_the_entry_as_it_arrived_and_adds_error_yaml(store: Store) -> None:
    bundle = make_bundle(store.inbox / "run-1")
    before = digest(bundle)
    path = store.reject("run-1", "run-1", "bundle", "bundle.yaml: not valid\nYAML")
    assert path == store.failed_dir / "run-1"
    error = yaml.safe_load((path / "error.yaml").read_text())
    assert error["bundle"] == "run-1" and error["stage"] == "bundle"
    assert error["reason"] == "bundle.yaml: not valid YAML"
    assert error["failed_at"].endswith("Z")
    after = digest(path)
    del after["error.yaml"]
    assert after == before
    assert list(store.taken.iterdir()) == []


def test_reject_wraps_a_file_in_a_directory(store: Store) -> None:
    (store.inbox / "notes.txt").write_text("hello")
    path = store.reject("notes.txt", "notes.txt", "bundle", "not a directory")
    assert (path / "notes.txt").read_text() == "hello"
    assert (path / "error.yaml").is_file()


def test_a_bundle_that_holds_its_own_error_yaml_keeps_it(store: Store) -> None:
    bundle = make_bundle(store.inbox / "run-1")
    (bundle / "error.yaml").write_text("mine")
    path = store.reject("run-1", "run-1", "load", "bad image")
    assert (path / "error.yaml").read_text() == "mine"
    assert yaml.safe_load((path / "mapserver-error.yaml").read_text())["stage"] == "load"


@pytest.mark.parametrize(
    ("brought", "written"),
    [
        (("mapserver-error.yaml",), "mapserver-error2.yaml"),
        (("error.yaml", "mapserver-error5.yaml"), "mapserver-error6.yaml"),
        (("mapserver-error1.yaml", "mapserver-error02.yaml"), "error.yaml"),  # not our names
    ],
)
def test_the_daemons_error_document_comes_after_every_one_the_bundle_brought(
    store: Store, brought: tuple[str, ...], written: str
) -> None:
    # Session 53's review: a bundle that brought mapserver-error.yaml but no error.yaml got the
    # daemon's document as error.yaml, and the pages and requeue read the robot's file as the
    # reason it failed. The last name is the daemon's, whatever the bundle holds.
    bundle = make_bundle(store.inbox / "run-1")
    for name in brought:
        (bundle / name).write_text("stage: align\nreason: everything is fine\n")
    path = store.reject("run-1", "run-1", "load", "bad image")
    assert daemon_error(path) == path / written
    assert yaml.safe_load((path / written).read_text())["reason"] == "bad image"
    for name in brought:
        assert (path / name).read_text() == "stage: align\nreason: everything is fine\n"


def test_error_document_has_the_contract_fields() -> None:
    doc = error_document("\udcffx", "load", "a\n b")
    assert list(doc) == ["format", "bundle", "failed_at", "stage", "reason"]
    assert doc["bundle"] == "\ufffdx" and doc["reason"] == "a b"


# -- the recovery rules, one state each (what a crash at each step leaves behind) ----------------


def test_rule_1_partial_results_are_deleted(store: Store) -> None:
    (store.outbox / ".tmp-run-1-abcd").mkdir()
    (store.outbox / ".tmp-run-1-abcd" / "overlay.png").write_bytes(b"x")
    (store.taken / ".run-2.error.yaml.tmp").write_text("partial")
    assert store.recover() == []
    assert list(store.outbox.iterdir()) == []
    assert list(store.taken.iterdir()) == []


def test_rule_2_a_staged_error_is_finished_or_dropped(store: Store) -> None:
    make_bundle(store.taken / "a")  # crash after staging, before the move
    store._stage_error("a", "load", "bad image")
    make_bundle(store.failed_dir / "b")  # crash between the two moves
    store._stage_error("b", "load", "bad image")
    make_bundle(store.inbox / "c")  # crash after staging, before the bundle was taken
    store._stage_error("c", "bundle", "bad manifest")
    assert store.recover() == []
    for bundle_id in ("a", "b"):
        error = yaml.safe_load((store.failed_dir / bundle_id / "error.yaml").read_text())
        assert error["bundle"] == bundle_id
    assert (store.inbox / "c" / "bundle.yaml").is_file()
    assert not (store.failed_dir / "c").exists()
    assert list(store.taken.iterdir()) == []


def test_rule_3_published_bundles_are_archived_others_processed_again(store: Store) -> None:
    make_bundle(store.taken / "done")
    store.publish(outcome("done"))
    make_bundle(store.taken / "todo")
    assert store.recover() == ["todo"]
    assert (store.archive_dir / "done" / "bundle.yaml").is_file()
    assert (store.taken / "todo").is_dir()
