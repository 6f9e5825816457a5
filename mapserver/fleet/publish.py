"""The files of the map store, written the way Nav2's map_saver writes maps, each replaced by
rename so that a map_server loading one never sees it half-written.

Everything here is derived from the database and can be written again from it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import Lattice
from mapserver.fsio import dump_yaml, rename_durable, replace_atomic
from mapserver.maps import FREE, OCCUPIED, state_to_pgm

CURRENT = "current.yaml"
KEEPOUT = "keepout"
CHANGES = "changes.yaml"
UNPUBLISHED = ".unpublished"
"""Where version files the database does not know are moved (:func:`set_aside`)."""

_VERSION_FILE = re.compile(r"v(\d{4,})\.(?:yaml|pgm)")
# fsio.replace_atomic's temporary files: ".<name>.<8 hex>.tmp".
_TEMPORARY = re.compile(r"\..+\.[0-9a-f]{8}\.tmp")


def version_stem(version: int) -> str:
    return f"v{version:04d}"


def map_yaml_document(image: str, lattice: Lattice, origin_yaw: float) -> dict[str, Any]:
    """A map_saver YAML (trinary, occupied 0.65, free 0.196) for ``image``."""
    return {
        "image": image,
        "mode": "trinary",
        "resolution": lattice.resolution,
        "origin": [lattice.x0, lattice.y0, origin_yaw],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }


def pgm_bytes(state: NDArray[np.uint8], resolution: float) -> bytes:
    """A binary PGM of a state array with map_saver's values (occupied 0, free 254, unknown 205)
    and its header comment."""
    pixels = state_to_pgm(state)
    header = (
        f"P5\n# CREATOR: map_saver.cpp {resolution:.3f} m/pix\n"
        f"{pixels.shape[1]} {pixels.shape[0]}\n255\n"
    )
    return header.encode("ascii") + np.ascontiguousarray(pixels).tobytes()


def write_version(
    folder: Path, version: int, state: NDArray[np.uint8], lattice: Lattice, origin_yaw: float
) -> tuple[Path, Path]:
    """Write ``vNNNN.pgm`` then ``vNNNN.yaml`` (each by rename). Returns (yaml, image).

    The store numbers a new version past every file on disk (:func:`highest_on_disk`), so
    nothing is overwritten but a file left by this very write."""
    stem = version_stem(version)
    image = folder / f"{stem}.pgm"
    yaml_path = folder / f"{stem}.yaml"
    replace_atomic(image, pgm_bytes(state, lattice.resolution))
    replace_atomic(yaml_path, dump_yaml(map_yaml_document(image.name, lattice, origin_yaw)))
    return yaml_path, image


def highest_on_disk(folder: Path) -> int:
    """The highest version number of any ``vNNNN`` file in ``folder`` or set aside in its
    ``.unpublished`` (0 when none): a number once written, perhaps loaded by a robot, is never
    given to other contents."""
    numbers = [
        int(m.group(1))
        for where in (folder, folder / UNPUBLISHED)
        if where.is_dir()
        for path in where.iterdir()
        if (m := _VERSION_FILE.fullmatch(path.name))
    ]
    return max(numbers, default=0)


def set_aside(folder: Path, known: set[str]) -> list[str]:
    """Tidy ``folder`` after a crash or a restore: remove the temporary files of interrupted
    writes, and move each version file not in ``known`` (the file names the database holds)
    into ``.unpublished/`` (a version written and never committed, or one a database restored
    from a backup does not know: it may have been published, so it is kept for a person to
    look at, never overwritten). Returns what was done, one line each. The caller holds the
    store's writer lock: no other write is in flight."""
    done = []
    for path in sorted(folder.iterdir()):
        if not path.is_file():
            continue
        if _TEMPORARY.fullmatch(path.name):
            path.unlink(missing_ok=True)
            done.append(f"removed {path.name}, left by an interrupted write")
        elif _VERSION_FILE.fullmatch(path.name) and path.name not in known:
            aside = folder / UNPUBLISHED
            aside.mkdir(exist_ok=True)
            target = aside / path.name
            n = 1
            while target.exists():
                target = aside / f"{path.name}.{n}"
                n += 1
            rename_durable(path, target)
            done.append(
                f"moved {path.name} to {UNPUBLISHED}/{target.name}: the database has no such "
                "version (a crash before its commit, or a database restored from an older backup)"
            )
    return done


def write_current(folder: Path, version_yaml: Path) -> Path:
    """``current.yaml``: the version's YAML, same image, replaced by rename."""
    path = folder / CURRENT
    replace_atomic(path, version_yaml.read_bytes())
    return path


def write_keepout(
    folder: Path, cells: NDArray[np.int64], lattice: Lattice, origin_yaw: float
) -> Path:
    """``keepout.pgm`` / ``keepout.yaml``: a Nav2 KeepoutFilter mask on the map's lattice,
    ``cells`` occupied (0), every other cell free (254)."""
    state = np.full((lattice.height, lattice.width), FREE, np.uint8)
    rows, cols = lattice.unflat(cells)
    state[rows, cols] = OCCUPIED
    image = folder / f"{KEEPOUT}.pgm"
    replace_atomic(image, pgm_bytes(state, lattice.resolution))
    path = folder / f"{KEEPOUT}.yaml"
    replace_atomic(path, dump_yaml(map_yaml_document(image.name, lattice, origin_yaw)))
    return path


def write_changes_text(folder: Path, text: bytes) -> Path:
    """``changes.yaml`` (its YAML text made by the store), replaced by rename."""
    path = folder / CHANGES
    replace_atomic(path, text)
    return path
