"""The command line as an operator meets it: ``process``'s report and refusals, ``status``,
``--version``, the help texts, poses typed with a minus, the default configuration."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemon_support import make_bundle

from mapserver.cli import main
from mapserver.config import parse_config
from mapserver.lock import daemon_lock


@pytest.fixture(autouse=True)
def keep_logging() -> Iterator[None]:
    """``process`` configures logging for the process: put pytest's back afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


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
