"""Durable file writes: new files fsynced, renames fsynced in their directories, and YAML
emitted by libyaml. The outbox and the map store write everything through these."""

from __future__ import annotations

import os
import secrets
from contextlib import suppress
from pathlib import Path
from typing import Any

import yaml

_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_new(path: Path, data: bytes) -> None:
    """Create ``path`` (it must not exist) with ``data``, fsynced."""
    with path.open("xb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def rename_durable(src: Path, dst: Path) -> None:
    """Rename and make the rename durable (both directories fsynced)."""
    os.rename(src, dst)
    fsync_dir(dst.parent)
    if src.parent != dst.parent:
        fsync_dir(src.parent)


def replace_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it over ``path``: a reader
    sees the old file or the new one, never a part. On any error (a full disk) the temporary
    file is removed and ``path`` is left as it was."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        write_new(tmp, data)
        rename_durable(tmp, path)
    except BaseException:
        with suppress(OSError):
            tmp.unlink()
        raise


def dump_yaml(document: Any) -> bytes:
    # libyaml's emitter when PyYAML has it: a result with a long ROI outline takes ~40 ms in the
    # pure-Python one, in the daemon's main process, for every bundle.
    text = yaml.dump(
        document,
        Dumper=_DUMPER,
        sort_keys=False,
        default_flow_style=None,
        allow_unicode=True,
    )
    return text.encode("utf-8")
