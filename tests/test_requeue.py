"""``mapserver requeue``: failed bundles go back to the inbox by one rename while a real daemon
runs, each keeping its earlier error documents as history; ids not in failed/ are refused in
one line and nothing moves."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from daemon_support import Daemon, digest, layout, make_bundle, upload, visible, wait_until
from daemon_support import write_config as write_daemon_config

from mapserver.cli import main
from mapserver.requeue import HISTORY


def test_requeue_while_the_daemon_runs_keeps_every_error_as_history(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dirs = layout(tmp_path)
    long_route = {"trajectory": [{"x": 0.0, "y": 0.0, "yaw": 0.0}] * 10}
    source = make_bundle(tmp_path / "src" / "run-1", manifest=long_route)
    good = make_bundle(tmp_path / "src" / "run-2", seed=2)
    error = dirs["failed"] / "run-1" / "error.yaml"
    config = write_daemon_config(tmp_path, limits={"max_trajectory_poses": 5})
    with Daemon(config) as strict:
        strict.wait_ready()
        upload(source, dirs["inbox"])
        upload(good, dirs["inbox"])
        wait_until(error.is_file, timeout=30, what="run-1 failed")
        wait_until(lambda: (dirs["archive"] / "run-2").is_dir(), timeout=30, what="run-2")
        first = error.read_bytes()
        assert yaml.safe_load(first)["stage"] == "bundle"
        capsys.readouterr()
        assert main(["requeue", "--config", str(config), "run-1"]) == 0
        out = capsys.readouterr().out
        assert out == (
            f"requeued run-1 (failed {yaml.safe_load(first)['failed_at']} at stage bundle: "
            f"{yaml.safe_load(first)['reason']}) -> {dirs['inbox'] / 'run-1'}\n"
        )
        # The same limit: it fails again, its first error kept as history.
        wait_until(error.is_file, timeout=30, what="run-1 failed again")
        second = error.read_bytes()
        assert second != first
        assert (dirs["failed"] / "run-1" / HISTORY / "error-1.yaml").read_bytes() == first
        assert strict.stop() == 0, strict.log()

    # Refused in one line, nothing moved: an unknown id, and one that is archived, not failed.
    assert main(["requeue", "--config", str(config), "run-1", "nope", "run-2"]) == 1
    err = capsys.readouterr().err
    assert err == (
        f"mapserver: error: nope: not in {dirs['failed']}; run-2: not in {dirs['failed']} "
        "(nothing was requeued)\n"
    )
    assert error.read_bytes() == second and (dirs["archive"] / "run-2").is_dir()

    config = write_daemon_config(tmp_path)  # the fix: the default limits
    with Daemon(config) as fixed:
        fixed.wait_ready()
        assert main(["requeue", "--config", str(config), "--failed-since", "2000-01-01"]) == 0
        assert capsys.readouterr().out.startswith("requeued run-1 (failed ")
        result = dirs["outbox"] / "run-1" / "result.yaml"
        wait_until(result.is_file, timeout=30, what="run-1's result")
        wait_until(lambda: (dirs["archive"] / "run-1").is_dir(), timeout=10, what="archived")
        assert fixed.stop() == 0, fixed.log()
    assert visible(dirs["failed"]) == [] and visible(dirs["inbox"]) == []
    archived = dirs["archive"] / "run-1"
    history = archived / HISTORY
    assert (history / "error-1.yaml").read_bytes() == first
    assert (history / "error-2.yaml").read_bytes() == second
    kept = digest(archived)
    for name in ("error-1.yaml", "error-2.yaml"):
        del kept[f"{HISTORY}/{name}"]
    assert kept == digest(source)  # the bundle itself as it was uploaded
    assert yaml.safe_load(result.read_text())["bundle"] == "run-1"

    assert main(["requeue", "--config", str(config), "--failed-since", "2100-01-01"]) == 0
    assert capsys.readouterr().out.startswith(f"no bundle in {dirs['failed']} failed since 2100")


def test_requeue_needs_ids_or_a_date_and_refuses_a_date_it_cannot_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_daemon_config(tmp_path)
    assert main(["requeue", "--config", str(config)]) == 1
    assert "give the ids of failed bundles, or --failed-since DATE" in capsys.readouterr().err
    assert main(["requeue", "--config", str(config), "--failed-since", "yesterday"]) == 1
    assert "--failed-since: not a date or time: 'yesterday'" in capsys.readouterr().err


def test_a_requeue_that_cannot_move_the_bundle_says_so_and_leaves_it_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Session 53's review: with no inbox, or a folder the operator's user may not write, a
    # traceback, and error.yaml already moved into the history: the bundle in failed/ without
    # its reason.
    config = write_daemon_config(tmp_path)
    dirs = layout(tmp_path)
    failed = dirs["failed"] / "run-0043"
    make_bundle(failed)
    reason = "failed_at: '2026-12-07T00:00:00Z'\nstage: load\nreason: cannot read slam_map.pgm\n"
    (failed / "error.yaml").write_text(reason)
    before = digest(failed)
    assert not dirs["inbox"].exists()  # no daemon ever started here
    assert main(["requeue", "--config", str(config), "run-0043"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapserver: error: ") and "is not there" in err and err.count("\n") == 1
    assert digest(failed) == before
    dirs["inbox"].mkdir()

    import mapserver.requeue as requeue_module

    real = requeue_module.rename_durable

    def refused(src: Path, dst: Path) -> None:
        if Path(dst).parent == dirs["inbox"]:  # the move of the bundle itself
            raise PermissionError(13, "Permission denied", str(dst))
        real(src, dst)

    monkeypatch.setattr(requeue_module, "rename_durable", refused)
    assert main(["requeue", "--config", str(config), "run-0043"]) == 1
    err = capsys.readouterr().err
    assert "run-0043: cannot move it: Permission denied" in err and "stays in" in err
    assert err.count("\n") == 1
    assert digest(failed) == before and not (failed / HISTORY).exists()
    assert (failed / "error.yaml").read_text() == reason
