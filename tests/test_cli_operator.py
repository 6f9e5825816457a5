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
