"""``mapserver run`` refuses a configuration it cannot work with, and says why."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapserver.cli import main

# ``run`` and ``process`` configure logging for the process (see conftest.py).
pytestmark = pytest.mark.usefixtures("keep_logging")


def test_run_with_an_unreadable_configuration_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["run", "--config", str(tmp_path / "missing.yaml")]) == 1
    assert "cannot read the configuration" in capsys.readouterr().err


def test_run_exits_1_when_bundles_cannot_move_by_rename(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def rename(src: object, dst: object) -> None:
        raise OSError(errno.EXDEV, os.strerror(errno.EXDEV))

    config = tmp_path / "mapserver.yaml"
    config.write_text("workers: 1\n")
    monkeypatch.setattr(os, "rename", rename)
    assert main(["run", "--config", str(config)]) == 1
    assert "one filesystem" in capsys.readouterr().err


def test_log_lines_carry_their_priority_when_stdout_is_the_journal(tmp_path: Path) -> None:
    out = tmp_path / "out.txt"
    script = (
        "import logging; from mapserver.cli import _setup_daemon_logging; "
        "_setup_daemon_logging('INFO'); log = logging.getLogger('mapserver.x'); "
        "log.info('run-1: load 1.0 ms'); log.warning('run-1: done: failed')"
    )
    for journal in (False, True):
        with out.open("w") as handle:
            st = os.fstat(handle.fileno())
            env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}" if journal else ""}
            subprocess.run([sys.executable, "-c", script], stdout=handle, env=env, check=True)
        lines = out.read_text().splitlines()
        prefix = ("<6>", "<4>") if journal else ("", "")
        assert lines == [
            f"{prefix[0]}INFO mapserver.x: run-1: load 1.0 ms",
            f"{prefix[1]}WARNING mapserver.x: run-1: done: failed",
        ]
