"""Atomic writing of results; archive and failed moves."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import yaml

from mapserver.pipeline import Outcome

RESULT = "result.yaml"


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write(path: Path, data: bytes) -> None:
    with path.open("wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def write_result(outbox: Path, outcome: Outcome) -> Path:
    """Write ``outbox/<bundle_id>/`` atomically (temp dir, fsync, rename; result.yaml last).

    Returns the result directory. An existing result directory for the id is replaced.
    """
    outbox.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{outcome.bundle_id}-", dir=outbox))
    for name, data in outcome.images.items():
        _write(tmp / name, data)
    text = yaml.safe_dump(outcome.result, sort_keys=False, default_flow_style=None)
    _write(tmp / RESULT, text.encode("utf-8"))
    _fsync_dir(tmp)
    final = outbox / outcome.bundle_id
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".old-{outcome.bundle_id}-", dir=outbox))
        os.rename(final, old / "x")
        os.rename(tmp, final)
        for child in (old / "x").iterdir():
            child.unlink()
        (old / "x").rmdir()
        old.rmdir()
    else:
        os.rename(tmp, final)
    _fsync_dir(outbox)
    return final
