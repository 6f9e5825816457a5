"""``mapserver run`` refuses a configuration it cannot work with, and says why."""

from __future__ import annotations

import errno
import logging
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from mapserver.cli import main


@pytest.fixture(autouse=True)
def keep_logging() -> Iterator[None]:
    """``run`` configures logging for the process: put pytest's back afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


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
