"""ROS map_server maps: read and write them as :class:`OccupancyMap`; pixel <-> metre conversions.

Arrays are indexed ``[row, col]``; row 0 is the TOP of the map (contract section 1). The centre of
pixel ``(col c, row k)`` in an image ``h`` rows tall is ``x = ox + (c + 0.5) r``,
``y = oy + (h - k - 0.5) r``.

Reading follows Nav2 Humble's map_server (``nav2_map_server/src/map_io.cpp``) and the contract;
:func:`load_map` lists where the two differ. Images are read by this module's own header parsers
first, so that a file's claimed size is checked before a single pixel is decoded.
"""

from __future__ import annotations

import math
import os
import reprlib
import stat
import struct
import sys
from dataclasses import dataclass, field
from io import FileIO
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from mapserver.errors import MapFileError
from mapserver.geometry import MAX_COORDINATE_M

# Cell states, as stored in OccupancyMap.state (uint8).
FREE = 0
OCCUPIED = 100
UNKNOWN = 255

# What map_saver writes for each state.
PGM_OCCUPIED, PGM_UNKNOWN, PGM_FREE = 0, 205, 254

# The keys a map YAML must have (Nav2 requires all of them; `mode` is optional).
_REQUIRED_KEYS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")
_MODES = ("trinary", "scale", "raw")

# A map YAML is a handful of lines; anything this big is not one.
MAX_MAP_YAML_BYTES = 1 << 16
"""A map YAML is a few hundred bytes (six keys); one larger is refused before it is parsed (a
megabyte of YAML takes a second to parse, in the daemon's main loop for the completeness check)."""
# The first read of an image: enough for any sane PGM header (GIMP's comment line included) and
# for a PNG's IHDR.
_HEAD_BYTES = 1 << 16
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel
_PNM_SPACE = b" \t\n\r\v\f"
_ASCII_BLOCK_BYTES = 1 << 20
# Longest run of digits accepted as one ASCII PGM sample (leading zeros included).
_ASCII_MAX_DIGITS = 18
# Elements per step when a lookup goes through numpy indexing, which makes an intp copy of its
# indices: chunks keep that copy at 8 MB instead of 8 bytes per pixel.
_CHUNK = 1 << 20
# A grey level that map_saver's unknown 205 outnumbers by this much, against its neighbours 204
# and 206 together, is a plateau (a saved unknown area), not one step of a grey ramp.
_PLATEAU_RATIO = 4


@dataclass(frozen=True, eq=False)
class OccupancyMap:
    """An occupancy grid.

    Attributes
    ----------
    state
        (H, W) uint8, indexed [row, col], row 0 at the top: FREE, OCCUPIED or UNKNOWN.
    occupancy
        (H, W) uint8 occupancy probability ``p`` scaled to 0..255 (0 certainly free, 255 certainly
        occupied), for every cell including unknown ones. Alignment uses it to see walls that a
        map draws in grey, below ``occupied_thresh``.
    resolution
        Metres per pixel.
    origin
        ``(x, y, yaw)`` of the lower-left pixel's corner, metres and radians. The yaw is kept but,
        as in Nav2, the grid is never rotated by it.
    source
        The map YAML it was read from, as given to :func:`load_map`.
    image
        The image the YAML names (the YAML's directory joined with its ``image``), not resolved.
    warnings
        One line each, for ``result.yaml``: what in the map files was odd and how it was read.
    """

    state: NDArray[np.uint8]
    occupancy: NDArray[np.uint8]
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: Path | None = None
    image: Path | None = None
    warnings: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if self.state.ndim != 2 or self.state.shape != self.occupancy.shape:
            raise ValueError(
                f"state and occupancy must be 2-D arrays of one shape, got "
                f"{self.state.shape} and {self.occupancy.shape}"
            )

    @property
    def height(self) -> int:
        """Rows of the grid."""
        return int(self.state.shape[0])

    @property
    def width(self) -> int:
        """Columns of the grid."""
        return int(self.state.shape[1])

    def pixel_to_world(self, col: ArrayLike, row: ArrayLike) -> tuple[NDArray[np.float64], ...]:
        """Metres of pixel coordinates.

        Parameters
        ----------
        col, row
            Pixel coordinates, any matching shapes; integer values are pixel centres, row 0 is the
            top row.

        Returns
        -------
        x, y
            float64 arrays of the same shape, metres in the map frame (the origin's yaw ignored).
        """
        r = self.resolution
        x = self.origin[0] + (np.asarray(col, dtype=float) + 0.5) * r
        y = self.origin[1] + (self.height - np.asarray(row, dtype=float) - 0.5) * r
        return x, y

    def world_to_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], ...]:
        """Fractional pixel coordinates of points in metres; the inverse of :meth:`pixel_to_world`.

        Parameters
        ----------
        x, y
            Metres in the map frame, any matching shapes.

        Returns
        -------
        col, row
            float64 arrays of the same shape; a pixel's centre has integer coordinates.
        """
        r = self.resolution
        col = (np.asarray(x, dtype=float) - self.origin[0]) / r - 0.5
        row = self.height - (np.asarray(y, dtype=float) - self.origin[1]) / r - 0.5
        return col, row

    def extent(self) -> tuple[float, float, float, float]:
        """``(min_x, min_y, max_x, max_y)`` of the map's area in metres."""
        ox, oy = self.origin[0], self.origin[1]
        return (ox, oy, ox + self.width * self.resolution, oy + self.height * self.resolution)


def from_states(
    state: NDArray[np.uint8],
    resolution: float,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> OccupancyMap:
    """An :class:`OccupancyMap` from a state array (occupancy set to 0, 127 or 255)."""
    state = np.ascontiguousarray(state, dtype=np.uint8)
    occupancy = np.full(state.shape, 127, np.uint8)
    occupancy[state == FREE] = 0
    occupancy[state == OCCUPIED] = 255
    return OccupancyMap(state, occupancy, float(resolution), tuple(origin))  # type: ignore[arg-type]


def state_to_pgm(state: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """The map_saver grey values (0 / 205 / 254) of a state array."""
    out = np.full(state.shape, PGM_UNKNOWN, np.uint8)
    out[state == FREE] = PGM_FREE
    out[state == OCCUPIED] = PGM_OCCUPIED
    return out


def save_map(
    yaml_path: Path,
    state: NDArray[np.uint8],
    resolution: float,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    image_name: str | None = None,
) -> Path:
    """Write a map the way map_saver does: a P5 PGM (0 / 205 / 254) and its YAML. Returns the YAML.

    :func:`load_map` reads it back with the same states, resolution and origin.
    """
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    image_path = yaml_path.parent / image_name
    pixels = state_to_pgm(state)
    header = f"P5\n# CREATOR: mapserver {resolution:.3f} m/pix\n{pixels.shape[1]} {pixels.shape[0]}\n255\n"
    image_path.write_bytes(header.encode("ascii") + pixels.tobytes())
    document = {
        "image": image_name,
        "mode": "trinary",
        "resolution": float(resolution),
        "origin": [float(v) for v in origin],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    yaml_path.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))
    return yaml_path


def load_map(
    yaml_path: str | Path,
    *,
    max_pixels: int = 100_000_000,
    confine_to: str | Path | None = None,
    resolution_range_m: tuple[float, float] | None = None,
    max_extent_m: float | None = None,
) -> OccupancyMap:
    """Read a ROS map YAML and the image it names.

    Parameters
    ----------
    yaml_path
        The map YAML: ``image`` (relative to the YAML's directory, or absolute), ``resolution``,
        ``origin: [x, y, yaw]``, ``negate``, ``occupied_thresh``, ``free_thresh`` and optionally
        ``mode`` (``trinary`` when missing, ``scale`` or ``raw``).
    max_pixels
        Larger images are rejected from their header, before any decoding (decompression bombs).
    confine_to
        When given, the YAML and the image, with symlinks followed, must lie inside this
        directory (a bundle must not make the server read files outside it).
    resolution_range_m
        When given, ``(low, high)``: a resolution outside it (metres per cell) is rejected
        before the image is opened.
    max_extent_m
        When given, an image wider or taller than this many metres is rejected from its
        header, before any decoding.

    Returns
    -------
    OccupancyMap
        ``state`` and ``occupancy`` (H, W) uint8, ``warnings`` for anything odd that was read
        leniently.

    Raises
    ------
    MapFileError
        For every bad map, naming the file and the problem in one line.

    Notes
    -----
    The image is PGM (binary P5 or ASCII P2, any maxval, 16-bit big-endian) or PNG (1- to
    16-bit, grey, palette or colour, with or without alpha). It becomes one 8-bit grey level ``v``
    per pixel: a 16-bit (or other maxval) sample is scaled to 0..255 and rounded, colour is the
    mean of R, G and B. Then, with ``p = (255 - v) / 255`` (``v / 255`` with ``negate: 1``),
    a cell is OCCUPIED if ``p > occupied_thresh``, FREE if ``p < free_thresh``, else UNKNOWN
    (modes trinary and scale), and ``occupancy = round(255 p)``. In mode raw, ``v`` is the
    occupancy in percent: above 100 it is UNKNOWN (occupancy 127), else the same three-way rule
    applies to ``p = v / 100``.

    Where this differs from Nav2 Humble, on purpose:

    - Trinary mode averages alpha in with the colour in Nav2 ("to preserve existing behavior"),
      which makes an opaque RGBA copy of a map read differently from the grey original. Alpha is
      ignored here, with a warning when some pixels are not opaque. Scale mode keeps Nav2's rule:
      a pixel that is not fully opaque is UNKNOWN (Nav2's map_saver writes unknown cells that way).
    - Nav2 reads a ``free_thresh`` above 50/255 as it stands, so older Humble map_saver output
      (``free_thresh: 0.25``) comes back with its unknown grey 205 as FREE. Here, when 205 would
      read as free, ``negate`` is 0, and 205 is a plateau in the image (not one step of a grey
      ramp), those cells are UNKNOWN and a warning says so (contract section 1).
    - A non-zero origin yaw gets a warning; like Nav2, the grid is not rotated.
    """
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be >= 1, got {max_pixels}")
    yaml_path = Path(yaml_path)
    root = _resolve_root(confine_to)
    if root is not None:
        _confine(yaml_path, root, "the map YAML", yaml_path)
    meta = _read_map_yaml(yaml_path)
    if resolution_range_m is not None:
        low, high = resolution_range_m
        if not low <= meta.resolution <= high:
            raise MapFileError(
                f"'resolution' {meta.resolution:g} m per cell is outside the range this server "
                f"accepts, {low:g}..{high:g} m (limits.min_resolution_m, "
                "limits.max_resolution_m); is the map YAML right?",
                file=yaml_path,
            )
    size_limit = _SizeLimit(max_pixels, meta.resolution, max_extent_m)
    image_path = yaml_path.parent / meta.image  # an absolute `image` wins, as in Nav2
    if root is not None:
        resolved = _confine(image_path, root, f"image path {meta.image!r}", yaml_path)
    else:
        resolved = _resolve(image_path, yaml_path)
    decoded = _read_image(resolved, image_path, yaml_path, meta.image, size_limit)

    warnings: list[str] = []
    state_lut, occupancy_lut = _lookup_tables(meta)
    plateau = _unknown_plateau_read_as_free(meta, state_lut, decoded.grey)
    if plateau:
        state_lut[PGM_UNKNOWN] = UNKNOWN
        warnings.append(
            f"free_thresh {meta.free_thresh} in {yaml_path} reads map_saver's unknown grey 205 as "
            f"free ({plateau} cells; older Humble map_saver wrote 0.25, the "
            f"right value is 0.196): those cells are read as unknown"
        )
    state = cast("NDArray[np.uint8]", cv2.LUT(decoded.grey, state_lut))
    # The grey image is not needed after this: the occupancy takes over its buffer, so a map
    # costs two bytes per pixel (state and occupancy) at the peak, not three.
    occupancy = cast("NDArray[np.uint8]", cv2.LUT(decoded.grey, occupancy_lut, dst=decoded.grey))
    transparent = decoded.transparent
    del decoded

    if transparent is not None:
        if meta.mode == "scale":
            state[transparent] = UNKNOWN
        else:
            warnings.append(
                f"{int(np.count_nonzero(transparent))} pixels of {image_path} are not opaque; "
                f"alpha is ignored in mode {meta.mode}, so their colour decides their state"
            )
        del transparent
    if meta.mode == "raw" and meta.negate:
        warnings.append(f"negate: 1 in {yaml_path} is ignored in mode raw, as Nav2 does")
    yaw = meta.origin[2]
    if yaw != 0.0:
        warnings.append(
            f"origin yaw {yaw} rad in {yaml_path} is ignored, as Nav2 does: the grid is not rotated"
        )
    return OccupancyMap(
        state,
        occupancy,
        meta.resolution,
        meta.origin,
        source=yaml_path,
        image=image_path,
        warnings=tuple(warnings),
    )


# --- the YAML -------------------------------------------------------------------------------


@dataclass(frozen=True)
class _MapYaml:
    image: str
    resolution: float
    origin: tuple[float, float, float]
    negate: bool
    occupied_thresh: float
    free_thresh: float
    mode: str


# How error messages show a YAML value: a few levels and items of it only. YAML aliases make a
# value of 500 bytes of text a nest of lists billions of items long (shared, so cheap to hold):
# a full repr cut afterwards took 30 s and 2.3 GB, and one level more ran out of memory.
_SHORT = reprlib.Repr()  # keyword arguments from Python 3.12 on
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxtuple, _SHORT.maxdict = 3, 4, 4, 4
_SHORT.maxstring = _SHORT.maxother = 50


def _show(value: Any) -> str:
    """A short repr for an error message (a YAML value can be arbitrarily large)."""
    text = _SHORT.repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _read_map_yaml(path: Path) -> _MapYaml:
    try:
        with _open_regular(path) as f:
            data = _read_up_to(f, MAX_MAP_YAML_BYTES + 1)
    except OSError as error:
        raise MapFileError(f"cannot read map YAML: {_os_reason(error)}", file=path) from None
    if len(data) > MAX_MAP_YAML_BYTES:
        raise MapFileError(
            f"map YAML is larger than {MAX_MAP_YAML_BYTES} bytes; is it a map YAML?", file=path
        )
    try:
        document = yaml.safe_load(data)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise MapFileError(
            f"YAML syntax error{where}: {error.problem or error.context}", file=path
        ) from None
    except (yaml.YAMLError, ValueError, RecursionError) as error:
        # ValueError: PyYAML's constructors reject e.g. an impossible date.
        raise MapFileError(f"invalid YAML: {error}", file=path) from None
    if not isinstance(document, dict):
        got = "an empty file" if document is None else f"a {type(document).__name__}"
        raise MapFileError(
            f"a map YAML must be a mapping with keys {', '.join(_REQUIRED_KEYS)}; got {got}",
            file=path,
        )
    missing = [key for key in _REQUIRED_KEYS if key not in document]
    if missing:
        names = ", ".join(repr(key) for key in missing)
        raise MapFileError(f"missing key{'s' if len(missing) > 1 else ''} {names}", file=path)

    image = document["image"]
    if not isinstance(image, str) or not image.strip() or "\0" in image:
        raise MapFileError(f"'image' must be a file name, got {_show(image)}", file=path)
    resolution = _number(document, "resolution", path)
    if resolution <= 0:
        raise MapFileError(f"'resolution' must be > 0, got {resolution}", file=path)
    origin = document["origin"]
    if not isinstance(origin, (list, tuple)) or len(origin) != 3:
        raise MapFileError(f"'origin' must be [x, y, yaw], got {_show(origin)}", file=path)
    x, y, yaw = (_number(dict(enumerate(origin)), i, path, "origin") for i in range(3))
    if max(abs(x), abs(y)) > MAX_COORDINATE_M:
        raise MapFileError(
            f"'origin' must lie within {MAX_COORDINATE_M:.0e} m of the map frame's origin, "
            f"got [{x:g}, {y:g}]",
            file=path,
        )
    occupied = _number(document, "occupied_thresh", path)
    free = _number(document, "free_thresh", path)
    for key, value in (("occupied_thresh", occupied), ("free_thresh", free)):
        if not 0.0 <= value <= 1.0:
            raise MapFileError(f"{key!r} must be between 0 and 1, got {value}", file=path)
    if not free < occupied:
        raise MapFileError(
            f"'free_thresh' ({free}) must be below 'occupied_thresh' ({occupied})", file=path
        )
    return _MapYaml(
        image=image,
        resolution=resolution,
        origin=(x, y, yaw),
        negate=_negate(document["negate"], path),
        occupied_thresh=occupied,
        free_thresh=free,
        mode=_mode(document.get("mode"), path),
    )


def _number(document: dict[Any, Any], key: Any, path: Path, parent: str | None = None) -> float:
    """A finite float from a YAML value. Numeric strings count: PyYAML reads ``5e-2`` (no dot) as
    a string, where yaml-cpp, and so Nav2, reads a number."""
    value = document[key]
    name = f"{parent!r}[{key}]" if parent else repr(key)
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise MapFileError(f"{name} must be a number, got {_show(value)}", file=path)
    try:
        number = float(value)
    except (ValueError, OverflowError):
        raise MapFileError(f"{name} must be a number, got {_show(value)}", file=path) from None
    if not math.isfinite(number):
        raise MapFileError(f"{name} must be a finite number, got {_show(value)}", file=path)
    return number


def _negate(value: Any, path: Path) -> bool:
    # Nav2 reads negate as an int, else as a bool.
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip() in ("0", "1"):
        return value.strip() == "1"
    raise MapFileError(f"'negate' must be 0 or 1, got {_show(value)}", file=path)


def _mode(value: Any, path: Path) -> str:
    if value is None:  # missing or empty: Nav2's default
        return "trinary"
    if isinstance(value, str) and value.strip().lower() in _MODES:
        return value.strip().lower()
    raise MapFileError(f"'mode' must be trinary, scale or raw, got {_show(value)}", file=path)


# --- paths and files ------------------------------------------------------------------------


def _resolve_root(confine_to: str | Path | None) -> Path | None:
    if confine_to is None:
        return None
    try:
        return Path(confine_to).resolve()
    except (OSError, RuntimeError) as error:
        raise MapFileError(f"cannot resolve the directory: {error}", file=confine_to) from None


def _resolve(path: Path, named_in: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError) as error:  # RuntimeError: a symlink loop before Python 3.13
        raise MapFileError(f"cannot resolve {str(path)!r}: {error}", file=named_in) from None


def _confine(path: Path, root: Path, what: str, named_in: Path) -> Path:
    """``path`` resolved (symlinks followed); a MapFileError if that is not inside ``root``."""
    resolved = _resolve(path, named_in)
    if not resolved.is_relative_to(root):
        raise MapFileError(
            f"{what} leaves the bundle: it resolves to {resolved}, outside {root}", file=named_in
        )
    return resolved


def _open_regular(path: Path) -> FileIO:
    """Open a regular file unbuffered. O_NONBLOCK keeps a FIFO from hanging the open."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(0, "not a regular file")
        return open(fd, "rb", buffering=0)
    except BaseException:
        os.close(fd)
        raise


def _os_reason(error: OSError) -> str:
    return error.strerror or str(error)


def _read_up_to(f: FileIO, size: int) -> bytes:
    """Up to ``size`` bytes; fewer only at the end of the file."""
    parts = []
    while size > 0:
        part = f.read(min(size, 1 << 24))
        if not part:
            break
        parts.append(part)
        size -= len(part)
    return b"".join(parts)


def _read_into(f: FileIO, array: NDArray[Any]) -> int:
    """Fill ``array``'s buffer from the file; returns the bytes read (short only at end of file)."""
    view = array.reshape(-1).view(np.uint8).data
    done = 0
    while done < len(view):
        got = f.readinto(view[done:])
        if not got:
            break
        done += got
    return done


# --- the image ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _SizeLimit:
    """What an image header may give: pixels, and metres when ``max_extent_m`` is set."""

    max_pixels: int
    resolution: float
    max_extent_m: float | None = None


@dataclass(frozen=True)
class _Decoded:
    grey: NDArray[np.uint8]  # (H, W), 0..255, a buffer the caller may overwrite
    transparent: NDArray[np.bool_] | None  # (H, W), only when some pixel is not fully opaque


def _read_image(
    resolved: Path, image_path: Path, yaml_path: Path, name: str, limit: _SizeLimit
) -> _Decoded:
    try:
        f = _open_regular(resolved)
    except OSError as error:
        raise MapFileError(
            f"cannot read image {name!r} ({image_path}): {_os_reason(error)}", file=yaml_path
        ) from None
    try:
        with f:
            head = _read_up_to(f, _HEAD_BYTES)
            if head.startswith(_PNG_SIGNATURE):
                return _read_png(f, head, image_path, limit)
            if head[:2] in (b"P2", b"P5"):
                return _read_pgm(f, head, image_path, limit)
    except OSError as error:
        raise MapFileError(f"cannot read image: {_os_reason(error)}", file=image_path) from None
    raise MapFileError(_not_an_image(head), file=image_path)


def _not_an_image(head: bytes) -> str:
    if not head:
        return "the image file is empty"
    if head[:1] == b"P" and head[1:2] in b"134679":
        return f"a Netpbm {head[:2].decode()} image is not a map image; use PGM (P2, P5) or PNG"
    return f"not a PGM or PNG image (it starts with {head[:12]!r})"


def _check_size(width: int, height: int, limit: _SizeLimit, image_path: Path) -> None:
    if width < 1 or height < 1:
        raise MapFileError(f"the header gives an empty image, {width} x {height}", file=image_path)
    if width * height > limit.max_pixels:
        raise MapFileError(
            f"the header gives {width} x {height} = {width * height} pixels, more than "
            f"max_image_pixels {limit.max_pixels}; not decoded",
            file=image_path,
        )
    if limit.max_extent_m is not None:
        width_m, height_m = width * limit.resolution, height * limit.resolution
        if max(width_m, height_m) > limit.max_extent_m:
            raise MapFileError(
                f"the map is {width_m:.0f} m x {height_m:.0f} m ({width} x {height} pixels at "
                f"{limit.resolution:g} m), larger than limits.max_map_extent_m "
                f"{limit.max_extent_m:g} m; not decoded",
                file=image_path,
            )


def _read_pgm(f: FileIO, head: bytes, image_path: Path, limit: _SizeLimit) -> _Decoded:
    width, height, maxval, offset = _parse_pgm_header(head, image_path)
    _check_size(width, height, limit, image_path)
    count = width * height
    dtype = np.uint8 if maxval < 256 else np.uint16
    f.seek(offset)
    if head[1:2] == b"5":
        raster = np.empty(count, dtype)
        got = _read_into(f, raster)
        if got < raster.nbytes:
            raise MapFileError(
                f"PGM is truncated: {got} of {raster.nbytes} pixel bytes present", file=image_path
            )
        if dtype == np.uint16 and sys.byteorder == "little":
            raster.byteswap(inplace=True)  # 16-bit P5 samples are big-endian
    else:
        raster = _read_ascii_raster(f, count, dtype, maxval, image_path)
    return _Decoded(_to_8bit(raster.reshape(height, width), maxval, image_path), None)


def _parse_pgm_header(head: bytes, image_path: Path) -> tuple[int, int, int, int]:
    """``(width, height, maxval, raster offset)`` of a P2/P5 header; comments may sit between
    the fields."""
    if len(head) < 3:
        raise _header_cut(head, image_path)
    if head[2] != ord("#") and head[2] not in _PNM_SPACE:
        raise MapFileError(
            f"bad PGM header: {head[:2].decode()} not followed by a space", file=image_path
        )
    pos = 2
    fields = []
    for name in ("width", "height", "maxval"):
        while True:  # skip blanks and comments
            if pos >= len(head):
                raise _header_cut(head, image_path)
            if head[pos] in _PNM_SPACE:
                pos += 1
            elif head[pos] == ord("#"):
                ends = [i for i in (head.find(b"\n", pos), head.find(b"\r", pos)) if i >= 0]
                if not ends:
                    raise _header_cut(head, image_path)
                pos = min(ends) + 1
            else:
                break
        end = pos
        while end < len(head) and 48 <= head[end] <= 57:
            end += 1
        if end == pos or end - pos > _ASCII_MAX_DIGITS:
            raise MapFileError(
                f"bad PGM header: {name} is not a number ({head[pos : pos + 12]!r})",
                file=image_path,
            )
        if end == len(head):
            raise _header_cut(head, image_path)
        fields.append(int(head[pos:end]))
        pos = end
    width, height, maxval = fields
    if not 1 <= maxval <= 65535:
        raise MapFileError(
            f"bad PGM header: maxval must be 1..65535, got {maxval}", file=image_path
        )
    if head[pos] not in _PNM_SPACE:
        raise MapFileError("bad PGM header: maxval not followed by a space", file=image_path)
    return width, height, maxval, pos + 1


def _header_cut(head: bytes, image_path: Path) -> MapFileError:
    if len(head) >= _HEAD_BYTES:
        return MapFileError(f"PGM header is longer than {_HEAD_BYTES} bytes", file=image_path)
    return MapFileError("PGM is truncated inside its header", file=image_path)


# Bytes allowed in an ASCII raster: digits and Netpbm white space.
_ASCII_OK = np.zeros(256, bool)
_ASCII_OK[list(b"0123456789" + _PNM_SPACE)] = True


def _read_ascii_raster(
    f: FileIO, count: int, dtype: type[np.unsignedinteger[Any]], maxval: int, image_path: Path
) -> NDArray[Any]:
    """The ``count`` samples of a P2 raster, read in blocks so memory stays near the output's."""
    out = np.empty(count, dtype)
    filled = 0
    carry = b""
    # Generous (a sample is at most 5 digits and a space), but a tiny header on a huge file of
    # blanks must not be scanned to its end.
    budget = 32 * count + _HEAD_BYTES
    scanned = 0
    while True:
        block = f.read(_ASCII_BLOCK_BYTES)
        scanned += len(block)
        data = carry + block
        if block:
            body = data.rstrip(b"0123456789")  # a number may go on in the next block
            carry = data[len(body) :]
            if len(carry) > _ASCII_MAX_DIGITS:
                raise MapFileError(
                    f"ASCII PGM: a number has more than {_ASCII_MAX_DIGITS} digits", file=image_path
                )
        else:
            body, carry = data, b""
        values, stop = _ascii_numbers(body, image_path)
        take = min(values.size, count - filled)
        if take and int(values[:take].max()) > maxval:
            raise MapFileError(f"ASCII PGM: a sample exceeds maxval {maxval}", file=image_path)
        out[filled : filled + take] = values[:take]
        filled += take
        if filled == count:
            return out
        if stop is not None:
            raise MapFileError(
                f"ASCII PGM: unexpected {stop!r} after {filled} of {count} samples", file=image_path
            )
        if not block:
            raise MapFileError(
                f"ASCII PGM is truncated: {filled} of {count} samples present", file=image_path
            )
        if scanned > budget:
            raise MapFileError(
                f"ASCII PGM: only {filled} of {count} samples in the first {scanned} bytes",
                file=image_path,
            )


def _ascii_numbers(body: bytes, image_path: Path) -> tuple[NDArray[np.int64], bytes | None]:
    """The decimal numbers in ``body`` up to its first byte that is neither digit nor blank,
    and that byte (None when there is none)."""
    buf = np.frombuffer(body, np.uint8)
    bad = np.flatnonzero(~_ASCII_OK[buf])
    stop = None
    if bad.size:
        stop = body[bad[0] : bad[0] + 1]
        buf = buf[: bad[0]]
    digit = (buf - 48) < 10  # uint8 arithmetic wraps, so blanks land far above 9
    edges = np.diff(digit.view(np.int8), prepend=np.int8(0), append=np.int8(0))
    starts = np.flatnonzero(edges == 1)
    lengths = np.flatnonzero(edges == -1) - starts
    values = np.zeros(starts.size, np.int64)
    longest = int(lengths.max()) if lengths.size else 0
    if longest > _ASCII_MAX_DIGITS:
        raise MapFileError(
            f"ASCII PGM: a number has more than {_ASCII_MAX_DIGITS} digits", file=image_path
        )
    for k in range(longest):  # one pass per digit position, all numbers at once
        has = lengths > k
        values[has] = values[has] * 10 + (buf[starts[has] + k] - 48)
    return values, stop


def _to_8bit(raster: NDArray[Any], maxval: int, image_path: Path) -> NDArray[np.uint8]:
    """Samples 0..maxval as 0..255 (rounded), in a fresh or reused uint8 buffer."""
    if raster.dtype == np.uint8 and maxval == 255:
        return raster
    peak = int(raster.max())
    if peak > maxval:
        raise MapFileError(
            f"a pixel value {peak} exceeds the header's maxval {maxval}", file=image_path
        )
    lut = np.round(np.arange(maxval + 1) * (255.0 / maxval)).astype(np.uint8)
    if raster.dtype == np.uint8:
        lut = np.concatenate([lut, np.zeros(255 - maxval, np.uint8)])
        return cast("NDArray[np.uint8]", cv2.LUT(raster, lut, dst=raster))
    out = np.empty(raster.shape, np.uint8)
    flat_in, flat_out = raster.reshape(-1), out.reshape(-1)
    for start in range(0, flat_in.size, _CHUNK):
        np.take(lut, flat_in[start : start + _CHUNK], out=flat_out[start : start + _CHUNK])
    return out


def _read_png(f: FileIO, head: bytes, image_path: Path, size_limit: _SizeLimit) -> _Decoded:
    # IHDR must be the first chunk: length 13 at byte 8, type at 12, fields from 16.
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise MapFileError("PNG has no IHDR header (truncated or corrupt)", file=image_path)
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    _check_size(width, height, size_limit, image_path)
    channels = _PNG_CHANNELS.get(colour)
    if channels is None or depth not in (1, 2, 4, 8, 16):
        raise MapFileError(
            f"PNG has an invalid bit depth {depth} / colour type {colour}", file=image_path
        )
    # Deflate never needs much more than the raw rows; anything far beyond is not this image.
    raw = height * ((width * channels * depth + 7) // 8 + 1)
    limit = 2 * raw + (64 << 20)
    data = head + _read_up_to(f, limit + 1 - len(head))
    if len(data) > limit:
        raise MapFileError(
            f"PNG file is over {limit} bytes, far more than {width} x {height} pixels need",
            file=image_path,
        )
    trns = _check_png_chunks(data, image_path)
    try:
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        decoded = None
    del data
    if decoded is None:
        raise MapFileError("cannot decode the PNG (corrupt image data)", file=image_path)
    if decoded.shape[:2] != (height, width):
        raise MapFileError(
            f"PNG decoded to {decoded.shape[1]} x {decoded.shape[0]}, its header says "
            f"{width} x {height}",
            file=image_path,
        )
    keyed = _grey_key_transparent(decoded, trns, colour, depth)
    grey = _grey_of(decoded, image_path)
    return grey if keyed is None else _Decoded(grey.grey, keyed)


def _check_png_chunks(data: bytes, image_path: Path) -> bytes | None:
    """Walk the chunk list: a truncated file (cv2 may decode part of it) has no complete IEND.
    Returns the data of its tRNS chunk, if any."""
    pos = len(_PNG_SIGNATURE)
    trns = None
    while pos + 8 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        if kind == b"tRNS" and pos + 8 + length <= len(data):
            trns = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if pos > len(data):
            break
        if kind == b"IEND":
            return trns
    raise MapFileError("PNG is truncated: it ends before its IEND chunk", file=image_path)


def _grey_key_transparent(
    decoded: NDArray[Any], trns: bytes | None, colour: int, depth: int
) -> NDArray[np.bool_] | None:
    """The pixels a grey PNG's tRNS chunk makes transparent: those whose sample is its key
    (cv2 decodes such a PNG to one channel and drops that transparency, where colour palettes
    and RGB keys come out with an alpha channel). None when there is no such key."""
    if colour != 0 or trns is None or len(trns) != 2 or decoded.ndim != 2:
        return None
    key = struct.unpack(">H", trns)[0]
    if depth < 8:  # decoded scaled up to 8 bits, as libpng expands low bit depths
        key = key * 255 // ((1 << depth) - 1)
    transparent = np.asarray(decoded == key)
    return transparent if transparent.any() else None


def _grey_of(decoded: NDArray[Any], image_path: Path) -> _Decoded:
    """One 8-bit grey level per pixel from cv2's (H, W), (H, W, 3) BGR or (H, W, 4) BGRA array,
    8- or 16-bit: the mean of the colour channels scaled to 0..255, alpha set aside."""
    maxval = 65535 if decoded.dtype == np.uint16 else 255
    if decoded.dtype not in (np.uint8, np.uint16) or decoded.ndim not in (2, 3):
        raise MapFileError(
            f"unsupported PNG pixel layout {decoded.dtype} {decoded.shape}", file=image_path
        )
    if decoded.ndim == 2:
        return _Decoded(_to_8bit(decoded, maxval, image_path), None)
    channels = decoded.shape[2]
    transparent = None
    if channels == 4 and int(decoded[:, :, 3].min()) < maxval:
        transparent = decoded[:, :, 3] < maxval
    # cv2.transform: one pass, one output channel, rounded to nearest. sum * 255 / (3 maxval) is
    # never exactly half-way for maxval 255 or 65535, so the rounding mode does not matter.
    weights = np.zeros((1, channels))
    weights[0, :3] = 255.0 / (3 * maxval)
    grey = cv2.transform(decoded, weights)
    if grey.dtype != np.uint8:
        grey = grey.astype(np.uint8)  # values are already 0..255
    return _Decoded(cast("NDArray[np.uint8]", grey), transparent)


# --- pixels to states -----------------------------------------------------------------------


def _lookup_tables(meta: _MapYaml) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The state and the occupancy of each grey level 0..255, as two (256,) uint8 tables."""
    v = np.arange(256, dtype=np.float64)
    if meta.mode == "raw":
        known = v <= 100
        p = v / 100.0
        occupancy = np.where(known, np.round(v * 255.0 / 100.0), 127)
    else:
        known = np.ones(256, bool)
        p = v / 255.0 if meta.negate else (255.0 - v) / 255.0
        occupancy = np.round(p * 255.0)
    state = np.full(256, UNKNOWN, np.uint8)
    state[known & (p < meta.free_thresh)] = FREE
    state[known & (p > meta.occupied_thresh)] = OCCUPIED
    return state, occupancy.astype(np.uint8)


def _grey_counts(grey: NDArray[np.uint8], levels: tuple[int, ...]) -> list[int]:
    """How many pixels of ``grey`` have each of ``levels`` (no per-pixel temporary beyond one
    chunk's comparison)."""
    flat = grey.reshape(-1)
    counts = [0] * len(levels)
    for start in range(0, flat.size, _CHUNK * 16):
        chunk = flat[start : start + _CHUNK * 16]
        for i, level in enumerate(levels):
            counts[i] += int(np.count_nonzero(chunk == level))
    return counts


def _unknown_plateau_read_as_free(
    meta: _MapYaml, state_lut: NDArray[np.uint8], grey: NDArray[np.uint8]
) -> int:
    """The number of map_saver's unknown grey 205 pixels when the thresholds read them as free
    in a map that has them; 0 otherwise.

    Not tied to the value 0.25: any threshold that reads 205 as free is the same mistake. 205
    must be a plateau, more common than its neighbours 204 and 206 together by ``_PLATEAU_RATIO``,
    because in a map of smooth greys (a drawing, a scan) 205 is just one shade among many and
    the thresholds mean what they say. map_saver only writes ``negate: 0``. The pixels are
    counted only when the thresholds read 205 as free (most maps: never).
    """
    if meta.mode == "raw" or meta.negate or state_lut[PGM_UNKNOWN] != FREE:
        return 0
    below, plateau, above = _grey_counts(grey, (PGM_UNKNOWN - 1, PGM_UNKNOWN, PGM_UNKNOWN + 1))
    return plateau if plateau > 0 and plateau >= _PLATEAU_RATIO * (below + above) else 0
