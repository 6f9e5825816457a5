"""The files of the map store, written the way Nav2's map_saver writes maps, each replaced by
rename so that a map_server loading one never sees it half-written.

Everything here is derived from the database and can be written again from it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapserver.fleet.lattice import Lattice
from mapserver.fsio import dump_yaml, replace_atomic
from mapserver.maps import FREE, OCCUPIED, state_to_pgm

CURRENT = "current.yaml"
KEEPOUT = "keepout"
CHANGES = "changes.yaml"


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

    A version file left by a crash before its database row was committed was never published:
    it is simply written again."""
    stem = version_stem(version)
    image = folder / f"{stem}.pgm"
    yaml_path = folder / f"{stem}.yaml"
    replace_atomic(image, pgm_bytes(state, lattice.resolution))
    replace_atomic(yaml_path, dump_yaml(map_yaml_document(image.name, lattice, origin_yaw)))
    return yaml_path, image


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
