"""The command line as an operator meets it: ``process``'s report and refusals, ``status``,
``--version``, the help texts, poses typed with a minus, the default configuration."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from daemon_support import Daemon, layout, make_bundle, upload, wait_until
from daemon_support import write_config as write_daemon_config

import mapserver
from mapserver.cli import SAMPLES, main
from mapserver.config import parse_config
from mapserver.lock import daemon_lock

# ``run`` and ``process`` configure logging for the process (see conftest.py).
pytestmark = pytest.mark.usefixtures("keep_logging")


def test_process_refuses_to_write_into_the_outbox_of_a_running_daemon(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bundle = make_bundle(tmp_path / "src" / "run-1")
    config_file = tmp_path / "mapserver.yaml"
    config_file.write_text("workers: 1\n")
    with daemon_lock(parse_config({}, base_dir=tmp_path)):
        assert main(["process", "--config", str(config_file), str(bundle)]) == 1
        err = capsys.readouterr().err
        assert err.startswith("mapserver: error: another mapserver (pid ")
        assert f"{tmp_path / 'outbox'} is its outbox" in err and "--outbox" in err
        assert not (tmp_path / "outbox").exists()
        other = tmp_path / "mine"
        assert (
            main(["process", "--config", str(config_file), "--outbox", str(other), str(bundle)])
            == 0
        )
        assert (other / "run-1" / "result.yaml").is_file()
    assert main(["process", "--config", str(config_file), str(bundle)]) == 0  # no daemon now
    assert (tmp_path / "outbox" / "run-1" / "result.yaml").is_file()
    # With a map store the daemon feeds, --outbox alone is refused as well: say the whole way
    # (session 53's review: the message suggested --outbox, which was then refused).
    config_file.write_text("workers: 1\nmaps: ./maps\n")
    with daemon_lock(parse_config({}, base_dir=tmp_path)):
        assert main(["process", "--config", str(config_file), str(bundle)]) == 1
        err = capsys.readouterr().err
        assert "--outbox DIR and a configuration with maps: null" in err
        assert "upload the bundle to its inbox" in err


def test_process_says_what_each_wrong_path_is_in_one_line_and_processes_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    runs = tmp_path / "runs"
    good = make_bundle(runs / "run-0042", seed=1)
    make_bundle(runs / "run-0043", seed=2)
    (tmp_path / "empty").mkdir()
    args = [
        str(runs / "run-42"),  # misspelt
        str(good / "bundle.yaml"),  # the manifest instead of its folder
        str(runs),  # the folder of bundles
        str(tmp_path / "empty"),  # a folder that is no bundle
        str(tmp_path / "nowhere" / "run-0042"),  # a parent that does not exist
        str(good),
    ]
    assert main(["process", "--outbox", str(tmp_path / "out"), *args]) == 1
    out, err = capsys.readouterr()
    assert err.splitlines() == [
        f"mapserver: error: {runs / 'run-42'}: no such file or directory; did you mean "
        f"{runs / 'run-0042'} or {runs / 'run-0043'}?",
        f"mapserver: error: {good / 'bundle.yaml'}: a file, not a bundle folder; give the folder "
        f"that holds it: {good}",
        f"mapserver: error: {runs}: not a bundle: no bundle.yaml in it; it holds 2 bundle "
        "folders (run-0042, run-0043)",
        f"mapserver: error: {tmp_path / 'empty'}: not a bundle: no bundle.yaml in it",
        f"mapserver: error: {tmp_path / 'nowhere' / 'run-0042'}: no such file or directory "
        f"(there is no {tmp_path / 'nowhere'})",
    ]
    assert "run-0042: 1 differences" in out
    assert (tmp_path / "out" / "run-0042" / "result.yaml").is_file()


def test_a_misspelt_reference_map_stops_run_and_check_config_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "depot.yaml").write_text("image: depot.pgm\n")
    config_file = tmp_path / "mapserver.yaml"
    config_file.write_text("reference_map: maps/depo.yaml\n")
    expected = (
        f"mapserver: error: {maps / 'depo.yaml'}: reference_map: no such file or directory; "
        f"did you mean {maps / 'depot.yaml'}?\n"
    )
    for command in ("check-config", "run"):
        assert main([command, "--config", str(config_file)]) == 1
        assert capsys.readouterr().err == expected
    assert not (tmp_path / "inbox").exists()  # run stopped before it made anything


def test_a_reference_map_that_cannot_be_read_stops_run_and_check_config_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Session 53's review: a YAML whose image is gone, or the image given for the YAML, passed
    # check-config, and every bundle without a nav2_map then failed at stage load.
    sample = SAMPLES / "depot-demo-01"
    maps = tmp_path / "maps"
    maps.mkdir()
    shutil.copy(sample / "nav2_map.yaml", maps / "gone.yaml")
    shutil.copy(sample / "nav2_map.pgm", maps / "depot.pgm")
    config_file = tmp_path / "mapserver.yaml"
    for ref, problem in (
        ("gone.yaml", "cannot read image 'nav2_map.pgm'"),
        ("depot.pgm", "map YAML is larger than 65536 bytes; is it a map YAML?"),
    ):
        config_file.write_text(f"reference_map: maps/{ref}\n")
        for command in ("check-config", "run"):
            assert main([command, "--config", str(config_file)]) == 1
            err = capsys.readouterr().err
            assert err.startswith(f"mapserver: error: {maps / ref}: reference_map: "), err
            assert problem in err and err.count("\n") == 1
    assert not (tmp_path / "inbox").exists()  # run stopped before it made anything


def test_demo_in_a_folder_it_may_not_make_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "file").write_text("not a folder")
    assert main(["demo", "--dir", str(tmp_path / "file" / "demo")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapserver: error: ") and "cannot make the demo folder" in err
    assert err.count("\n") == 1


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out == f"mapserver {mapserver.__version__}\n"


def test_web_listen_on_the_command_line_is_checked_as_in_the_file(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Session 53's review: `mapserver web --listen nonsense` ended in a ValueError's traceback.
    assert main(["web", "--listen", "nonsense"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapserver: error: --listen: 'listen': String should match pattern")
    assert err.count("\n") == 1


def test_python_dash_m_mapserver_is_the_command() -> None:
    # Where the environment's scripts are not on the PATH (session 53's review used a wrapper).
    done = subprocess.run(
        [sys.executable, "-m", "mapserver", "--version"], capture_output=True, text=True, timeout=60
    )
    assert (done.returncode, done.stdout) == (0, f"mapserver {mapserver.__version__}\n")


@pytest.mark.parametrize(
    "command",
    [
        "run",
        "status",
        "process",
        "check-config",
        "bundle",
        "demo",
        "web",
        "requeue",
        "maps",
        "maps add",
        "maps list",
        "maps show",
        "maps rollback",
        "changes",
        "changes list",
        "changes approve",
        "changes reject",
        None,
    ],
)
def test_every_help_is_written_for_an_operator_and_ends_with_an_example(
    command: str | None, capsys: pytest.CaptureFixture[str]
) -> None:
    # Session 58's review: `maps list` and `changes list` had none, and their --config no help.
    with pytest.raises(SystemExit):
        main([*command.split(), "--help"] if command else ["--help"])
    text = capsys.readouterr().out
    assert "example" in text
    example = text.split("example", 1)[1]
    assert f"mapserver {command or ''}".strip() in example
    for developer_words in ("thin layer", "configures logging", "docstring"):
        assert developer_words not in text
    options = text.split("example", 1)[0]
    if "--config" in options.split("options:")[-1]:
        assert "--config FILE" in options and "$MAPSERVER_CONFIG" in options


def test_a_pose_may_be_typed_with_a_minus_and_no_equals_sign(tmp_path: Path) -> None:
    source = make_bundle(tmp_path / "src")
    out = tmp_path / "run-7"
    args = ["bundle", "--slam-map", str(source / "slam_map.yaml"), "--robot", "r1"]
    args += ["--nav2-pose", "-1,2,0", "--slam-pose", "-.5,-0.25,-1e-3", "-o", str(out)]
    assert main(args) == 0
    pose = yaml.safe_load((out / "bundle.yaml").read_text())["pose"]
    assert pose == {
        "nav2": {"x": -1.0, "y": 2.0, "yaw": 0.0},
        "slam": {"x": -0.5, "y": -0.25, "yaw": -0.001},
    }


def test_process_prints_each_difference_and_says_when_it_replaced_a_result(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bundle = make_bundle(tmp_path / "run-1")
    out = tmp_path / "out"
    for replaced in (False, True):
        assert main(["process", "--outbox", str(out), str(bundle)]) == 0
        lines = [line for line in capsys.readouterr().out.splitlines() if "INFO" not in line]
        result = yaml.safe_load((out / "run-1" / "result.yaml").read_text())
        [difference] = result["differences"]
        note = " (replaced the earlier result)" if replaced else ""
        c = difference["centroid"]
        assert lines[0] == f"run-1: 1 differences -> {out / 'run-1' / 'result.yaml'}{note}"
        assert lines[1].startswith(
            f"  1. added   {difference['area_m2']:7.2f} m2 at x={c['x']:.2f} y={c['y']:.2f}  (box x "
        )
        assert len(lines) == 2


def test_the_built_in_configuration_never_makes_folders_here_unseen(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MAPSERVER_CONFIG", raising=False)
    assert main(["run"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapserver: error: no configuration given (--config FILE, ")
    assert f"no inbox/ in the current directory {tmp_path}" in err
    assert list(tmp_path.iterdir()) == []
    bundle = make_bundle(tmp_path / "src" / "run-1")
    assert main(["process", str(bundle)]) == 0
    assert capsys.readouterr().err == (
        f"mapserver: results go to {tmp_path / 'outbox'} (the built-in default; choose with "
        "--outbox DIR or --config FILE)\n"
    )
    assert main(["process", str(bundle)]) == 0  # it is there now, and the results say where
    assert capsys.readouterr().err == ""


def _counts(inbox: Path) -> dict[str, int]:
    """Some counts from the daemon's status file."""
    document = yaml.safe_load((inbox / ".mapserver.status").read_text())
    return {key: document[key] for key in ("uploading", "results", "failed")}


def test_status_of_a_running_daemon_and_of_a_stopped_one(tmp_path: Path) -> None:
    good = make_bundle(tmp_path / "src" / "good")
    bad = make_bundle(tmp_path / "src" / "bad", seed=1, checksums=False)
    (bad / "slam_map.pgm").write_bytes(b"P5\n100 100\n255\n")
    config = write_daemon_config(tmp_path, workers=1)
    dirs = layout(tmp_path)

    def status() -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "mapserver.cli", "status", "--config", str(config)]
        return subprocess.run(command, capture_output=True, text=True, timeout=60)

    with Daemon(config) as daemon:
        daemon.wait_ready()
        upload(good, dirs["inbox"])
        upload(bad, dirs["inbox"])
        (dirs["inbox"] / "half").mkdir()  # an upload that has not finished
        wait_until(
            lambda: (
                (dirs["archive"] / "good").is_dir()
                and (dirs["failed"] / "bad" / "error.yaml").is_file()
            ),
            timeout=30,
            what="both decided",
        )
        wait_until(
            lambda: _counts(dirs["inbox"]) == {"uploading": 1, "results": 1, "failed": 1},
            timeout=10,
            what="the daemon's status file",
        )
        running = status()
        assert daemon.stop() == 0
    assert running.returncode == 0, running.stderr
    lines = running.stdout.splitlines()
    assert lines[0].startswith(f"daemon:    running, pid {daemon.process.pid}, since 20")
    assert lines[1] == "health:    ok"
    assert lines[2].startswith("queue:     1 uploading, 0 queued, 0 processing (the daemon's ")
    assert lines[3] == "last 24 h: 1 results, 1 failed"
    assert lines[4].startswith("  failed bad at 20") and ", stage load: slam_map.pgm: " in lines[4]
    assert lines[5] == "free space:"
    for name, line in zip(["inbox", "outbox", "archive", "failed"], lines[6:], strict=True):
        assert line.startswith(f"  {name:<8} {dirs[name]}") and " GiB free of " in line

    stopped = status()
    assert stopped.returncode == 3, stopped.stderr
    lines = stopped.stdout.splitlines()
    assert lines[0] == f"daemon:    not running (no mapserver run holds {dirs['inbox']})"
    assert lines[1] == ("queue:     1 in the inbox (judged when it starts), 0 queued, 0 processing")
    assert lines[2] == "last 24 h: 1 results, 1 failed"


def test_status_without_a_daemon_exits_3_and_counts_from_the_folders(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config_file = tmp_path / "mapserver.yaml"
    config_file.write_text("maps: maps\n")
    make_bundle(tmp_path / "inbox" / "uploading")
    make_bundle(tmp_path / "inbox" / ".taken" / "taken-before")
    (tmp_path / "maps").mkdir()
    assert main(["status", "--config", str(config_file)]) == 3
    lines = capsys.readouterr().out.splitlines()
    assert lines[:3] == [
        f"daemon:    not running (no mapserver run holds {tmp_path / 'inbox'})",
        # Without a daemon nothing tells an upload going on from a complete one (session
        # 58's review: complete uploads read "uploading" after a kill -9).
        "queue:     1 in the inbox (judged when it starts), 1 queued, 0 processing (taken "
        "before the daemon stopped: processed at its next start)",
        "last 24 h: 0 results, 0 failed",
    ]
    assert lines[-1].startswith(f"  maps     {tmp_path / 'maps'}  ") and "GiB free" in lines[-1]
    assert lines[-3] == f"  archive  {tmp_path / 'archive'}  not there"


def test_status_lists_a_failure_by_the_daemons_error_document_not_the_bundles_own(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bundle that brought an error.yaml of its own (an old mtime, as rsync -a keeps it): the
    daemon's document is mapserver-error.yaml, and status read the bundle's (session 54's
    review: "failed run-0043 at ?, stage ?: (unreadable error.yaml)", or not listed at all)."""
    config_file = tmp_path / "mapserver.yaml"
    config_file.write_text("{}\n")
    failed = tmp_path / "failed" / "run-0043"
    failed.mkdir(parents=True)
    (failed / "error.yaml").write_text("mine: 1\n")
    os.utime(failed / "error.yaml", (0, 0))
    (failed / "mapserver-error.yaml").write_text(
        "failed_at: '2026-12-07T09:00:00Z'\nstage: bundle\nreason: 'slam_map.pgm: checksum'\n"
    )
    assert main(["status", "--config", str(config_file)]) == 3
    out = capsys.readouterr().out
    assert "last 24 h: 0 results, 1 failed" in out
    assert "failed run-0043 at 2026-12-07T09:00:00Z, stage bundle: slam_map.pgm: checksum" in out


def test_process_never_replaces_the_bundle_itself_with_its_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``cd runs && mapserver process --outbox . run-1``: the "earlier result" outbox/run-1 is
    the bundle; replacing it deleted the input (session 44's review). Now it is refused, the
    bundle is untouched and nothing is written beside it."""
    runs = tmp_path / "runs"
    bundle = make_bundle(runs / "run-1")
    before = {p.name: p.read_bytes() for p in bundle.iterdir()}
    monkeypatch.chdir(runs)
    assert main(["process", "--outbox", ".", "run-1"]) == 1
    err = capsys.readouterr().err
    assert "is not an earlier result but a bundle (it holds bundle.yaml)" in err
    assert {p.name: p.read_bytes() for p in bundle.iterdir()} == before
    assert sorted(p.name for p in runs.iterdir()) == ["run-1"]


def test_process_says_when_it_cannot_write_a_result_and_goes_on_with_the_next(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An outbox it cannot write (here a path under a regular file: the same OSError path as a
    full disk) gives one error line per bundle, no traceback, and every bundle is tried."""
    first, second = make_bundle(tmp_path / "a"), make_bundle(tmp_path / "b", seed=1)
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["process", "--outbox", str(blocker / "out"), str(first), str(second)]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mapserver")]
    assert len(err) == 2, err
    assert err[0].startswith(f"mapserver: error: {first}: cannot write its result to ")
    assert err[1].startswith(f"mapserver: error: {second}: cannot write its result to ")


def test_process_calls_a_file_a_complete_bundle_lacks_missing_not_late(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The daemon waits for a file an upload has not brought yet; ``process`` runs on bundles
    said to be complete (session 58's review: it said "is not there yet")."""
    bundle = make_bundle(tmp_path / "run-1")
    manifest = yaml.safe_load((bundle / "bundle.yaml").read_text())
    manifest["nav2_map"] = "gone.yaml"
    (bundle / "bundle.yaml").write_text(yaml.safe_dump(manifest))
    assert main(["process", "--outbox", str(tmp_path / "out"), str(bundle)]) == 1
    err = capsys.readouterr().err
    assert err == f"mapserver: error: {bundle / 'bundle.yaml'}: nav2_map 'gone.yaml' is missing\n"


def test_check_config_refuses_what_run_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Session 58's review: check-config passed a failed/ on another filesystem, a missing
    web token file and a public address without a token, and run then stopped at once on
    each (the README has check-config run before systemctl start)."""
    config_file = tmp_path / "mapserver.yaml"
    cases = [
        ({"web": {"token_file": "nowhere/token"}}, "cannot read the web token"),
        ({"web": {"listen": "0.0.0.0:8397"}}, "refusing to serve on 0.0.0.0 without"),
    ]
    shm = Path("/dev/shm")
    if shm.is_dir() and os.stat(shm).st_dev != os.stat(tmp_path).st_dev:
        cases.append(
            (
                {"failed": str(shm / f"mapserver-test-{os.getpid()}" / "failed")},
                "on another filesystem than inbox",
            )
        )
    for doc, problem in cases:
        config_file.write_text(yaml.safe_dump(doc))
        assert main(["check-config", "--config", str(config_file)]) == 1, doc
        err = capsys.readouterr().err
        assert problem in err and err.count("\n") == 1, err
    assert not any(p.name.startswith("mapserver-test-") for p in shm.glob("*")), "made a folder"
    config_file.write_text(yaml.safe_dump({"web": {"listen": "127.0.0.1:8397"}}))
    assert main(["check-config", "--config", str(config_file)]) == 0
    capsys.readouterr()
