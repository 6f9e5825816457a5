"""mapserver.maps: ROS maps in every image format, mode and failure; pixel <-> metre conversions.

Every reading test starts from a known truth: grey levels whose states follow from the contract's
rule by hand (the tables below), written in each format, read back and compared cell by cell.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from mapserver.errors import MapFileError
from mapserver.maps import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    from_states,
    load_map,
    save_map,
)

F, W, U = FREE, OCCUPIED, UNKNOWN  # free, wall (occupied), unknown
DATA = Path(__file__).parent / "data" / "maps"
SHARED_MAPS = Path(__file__).parents[2] / "shared" / "maps"

# Grey levels around both thresholds, and their states by the contract's rule with map_saver's
# thresholds (occupied 0.65, free 0.196). negate 0: p = (255 - v) / 255, so occupied for v < 89.25
# and free for v > 205.02; negate 1: p = v / 255, occupied for v > 165.75, free for v < 49.98.
GREYS = np.array([0, 49, 50, 89, 90, 100, 150, 165, 166, 200, 204, 205, 206, 230, 254, 255])
TRINARY = np.array([W, W, W, W, U, U, U, U, U, U, U, U, F, F, F, F])
NEGATED = np.array([F, F, U, U, U, U, U, U, W, W, W, W, W, W, W, W])
# Two rows, the second reversed, so that a flipped or transposed image cannot pass.
GREY_IMAGE = np.stack([GREYS, GREYS[::-1]]).astype(np.uint8)


# --- writing test images ----------------------------------------------------------------------


def pgm_bytes(pixels: np.ndarray, *, maxval: int = 255, ascii: bool = False) -> bytes:
    """A PGM with a map_saver-style comment line; 16-bit samples big-endian."""
    h, w = pixels.shape
    header = f"{'P2' if ascii else 'P5'}\n# CREATOR: test 0.050 m/pix\n{w} {h}\n{maxval}\n"
    if ascii:
        body = "\n".join(" ".join(str(int(v)) for v in row) for row in pixels) + "\n"
        return header.encode() + body.encode()
    return header.encode() + pixels.astype(">u2" if maxval > 255 else np.uint8).tobytes()


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bytes(
    width: int, height: int, depth: int, colour: int, rows: bytes, extra: bytes = b""
) -> bytes:
    """A PNG built by hand (palette, grey+alpha, or a header that lies), ``rows`` unfiltered."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + png_chunk(b"IHDR", ihdr)
        + extra
        + png_chunk(b"IDAT", zlib.compress(rows))
        + png_chunk(b"IEND", b"")
    )


def write_yaml(directory: Path, image: Any, name: str = "map.yaml", **fields: Any) -> Path:
    """A map YAML with map_saver's values; a field set to None is left out."""
    document = {
        "image": image,
        "resolution": 0.05,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    document.update(fields)
    document = {key: value for key, value in document.items() if value is not None}
    path = directory / name
    path.write_text(yaml.safe_dump(document, default_flow_style=None))
    return path


def _grey16(v: np.ndarray) -> np.ndarray:
    # v * 257 is v scaled to 16 bits; +100 keeps the rounding back to v but makes the two bytes of
    # a sample differ, so that a byte-order mistake shows.
    return np.minimum(v.astype(np.int64) * 257 + 100, 65535).astype(np.uint16)


def _scaled(v: np.ndarray, maxval: int) -> np.ndarray:
    x = np.round(v.astype(np.float64) * maxval / 255).astype(np.int64)
    assert np.array_equal(np.round(x * 255 / maxval), v), "test data: not a lossless maxval"
    return x


def _palette_png(v: np.ndarray) -> bytes:
    levels = np.unique(v)
    palette = b"".join(bytes([g, g, g]) for g in levels)
    index = np.searchsorted(levels, v).astype(np.uint8)
    rows = b"".join(b"\0" + row.tobytes() for row in index)
    return png_bytes(v.shape[1], v.shape[0], 8, 3, rows, png_chunk(b"PLTE", palette))


def _grey_alpha_png(v: np.ndarray) -> bytes:
    pairs = np.dstack([v, np.full_like(v, 255)])
    rows = b"".join(b"\0" + row.tobytes() for row in pairs)
    return png_bytes(v.shape[1], v.shape[0], 8, 4, rows)


def _png(pixels: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", pixels)
    assert ok
    return encoded.tobytes()


# Each writes an image whose 8-bit grey level, by the contract, is v (uint8, (H, W)).
FORMATS: dict[str, tuple[str, Callable[[np.ndarray], bytes]]] = {
    "pgm-p5": ("map.pgm", lambda v: pgm_bytes(v)),
    "pgm-p2": ("map.pgm", lambda v: pgm_bytes(v, ascii=True)),
    "pgm-p5-16bit": ("map.pgm", lambda v: pgm_bytes(_grey16(v), maxval=65535)),
    "pgm-p2-16bit": ("map.pgm", lambda v: pgm_bytes(_grey16(v), maxval=65535, ascii=True)),
    "pgm-p5-maxval-1023": ("map.pgm", lambda v: pgm_bytes(_scaled(v, 1023), maxval=1023)),
    "pgm-p5-maxval-254": ("map.pgm", lambda v: pgm_bytes(_scaled(v, 254), maxval=254)),
    "png-grey-8": ("map.png", lambda v: _png(v)),
    "png-grey-16": ("map.png", lambda v: _png(_grey16(v))),
    "png-rgb-8": ("map.png", lambda v: _png(np.dstack([v, v, v]))),
    "png-rgba-8": ("map.png", lambda v: _png(np.dstack([v, v, v, np.full_like(v, 255)]))),
    "png-rgba-16": (
        "map.png",
        lambda v: _png(np.dstack([_grey16(v)] * 3 + [np.full(v.shape, 65535, np.uint16)])),
    ),
    "png-palette": ("map.png", _palette_png),
    "png-grey-alpha": ("map.png", _grey_alpha_png),
}


def write_map(directory: Path, fmt: str, grey: np.ndarray = GREY_IMAGE, **fields: Any) -> Path:
    name, encode = FORMATS[fmt]
    (directory / name).write_bytes(encode(grey))
    return write_yaml(directory, name, **fields)


def reason_of(error: pytest.ExceptionInfo[MapFileError]) -> str:
    text = str(error.value)
    assert "\n" not in text
    return text


# --- states, per format, mode and negate --------------------------------------------------------


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("negate", [0, 1])
def test_every_format_reads_the_contract_states(tmp_path: Path, fmt: str, negate: int) -> None:
    m = load_map(write_map(tmp_path, fmt, negate=negate))
    table = NEGATED if negate else TRINARY
    expected = np.stack([table, table[::-1]])
    assert m.state.dtype == np.uint8 and m.state.shape == GREY_IMAGE.shape
    np.testing.assert_array_equal(m.state, expected)
    # occupancy = round(255 p): 255 - v, or v when negated.
    np.testing.assert_array_equal(m.occupancy, GREY_IMAGE if negate else 255 - GREY_IMAGE)
    assert m.warnings == ()
    assert not np.shares_memory(m.state, m.occupancy)


def test_colour_is_the_rounded_mean_of_the_channels(tmp_path: Path) -> None:
    # Rows of B, G, R with their mean and the state it gives (thresholds as in TRINARY).
    cases = [
        ((0, 102, 51), W),  # mean 51, p = 0.8
        ((255, 200, 160), U),  # mean 205
        ((205, 205, 206), U),  # mean 205.33 -> 205
        ((205, 206, 206), F),  # mean 205.67 -> 206: rounded, not truncated
        ((210, 210, 201), F),  # mean 207
    ]
    pixels = np.array([[bgr for bgr, _ in cases]], np.uint8)
    (tmp_path / "map.png").write_bytes(_png(pixels))
    m = load_map(write_yaml(tmp_path, "map.png"))
    np.testing.assert_array_equal(m.state[0], [state for _, state in cases])
    np.testing.assert_array_equal(m.occupancy[0], 255 - np.array([51, 205, 205, 206, 207]))


def test_low_maxval_pgm_is_scaled_to_8_bits(tmp_path: Path) -> None:
    samples = np.arange(16).reshape(2, 8)  # maxval 15: sample s is grey 17 s
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(samples, maxval=15))
    m = load_map(write_yaml(tmp_path, "map.pgm"))
    np.testing.assert_array_equal(m.occupancy, 255 - 17 * samples)
    p = (255 - 17 * samples) / 255
    np.testing.assert_array_equal(m.state, np.where(p > 0.65, W, np.where(p < 0.196, F, U)))


def test_low_bit_depth_png_is_expanded(tmp_path: Path) -> None:
    # 1-bit grey: 0 is black (occupied), 1 is white (free).
    (tmp_path / "map.png").write_bytes(png_bytes(4, 1, 1, 0, b"\0" + bytes([0b0101_0000])))
    m = load_map(write_yaml(tmp_path, "map.png"))
    np.testing.assert_array_equal(m.state, [[W, F, W, F]])


def test_scale_mode_states_equal_trinary(tmp_path: Path) -> None:
    m = load_map(write_map(tmp_path, "pgm-p5", mode="scale"))
    np.testing.assert_array_equal(m.state, np.stack([TRINARY, TRINARY[::-1]]))


def test_mode_is_trinary_when_missing_or_written_in_capitals(tmp_path: Path) -> None:
    missing = load_map(write_map(tmp_path, "pgm-p5", mode=None))
    capitals = load_map(write_map(tmp_path, "pgm-p5", mode="Trinary"))
    np.testing.assert_array_equal(missing.state, capitals.state)
    np.testing.assert_array_equal(missing.state, np.stack([TRINARY, TRINARY[::-1]]))


def test_raw_mode_reads_percentages(tmp_path: Path) -> None:
    # p = v / 100 with the thresholds 0.65 / 0.196; above 100 is unknown.
    v = np.array([[0, 19, 20, 50, 65, 66, 100, 101, 205, 255]], np.uint8)
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(v))
    m = load_map(write_yaml(tmp_path, "map.pgm", mode="raw"))
    np.testing.assert_array_equal(m.state[0], [F, F, U, U, U, W, W, U, U, U])
    np.testing.assert_array_equal(m.occupancy[0], [0, 48, 51, 128, 166, 168, 255, 127, 127, 127])
    assert m.warnings == ()


def test_raw_mode_ignores_negate_with_a_warning(tmp_path: Path) -> None:
    v = np.array([[0, 100, 200]], np.uint8)
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(v))
    m = load_map(write_yaml(tmp_path, "map.pgm", mode="raw", negate=1))
    np.testing.assert_array_equal(m.state[0], [F, W, U])
    assert len(m.warnings) == 1 and "negate" in m.warnings[0] and "raw" in m.warnings[0]


def _rgba_with_transparency(tmp_path: Path) -> np.ndarray:
    # Transparent black, transparent white, opaque black, half-transparent white.
    bgra = np.array(
        [[[0, 0, 0, 0], [255, 255, 255, 0], [0, 0, 0, 255], [255, 255, 255, 128]]], np.uint8
    )
    (tmp_path / "map.png").write_bytes(_png(bgra))
    return bgra


def test_trinary_ignores_alpha_and_warns(tmp_path: Path) -> None:
    _rgba_with_transparency(tmp_path)
    m = load_map(write_yaml(tmp_path, "map.png"))
    np.testing.assert_array_equal(m.state[0], [W, F, W, F])
    assert len(m.warnings) == 1
    assert "3 pixels" in m.warnings[0] and "not opaque" in m.warnings[0]


def test_scale_mode_reads_transparent_pixels_as_unknown(tmp_path: Path) -> None:
    # As Nav2 does; its map_saver writes unknown cells of a scale map as transparent pixels.
    _rgba_with_transparency(tmp_path)
    m = load_map(write_yaml(tmp_path, "map.png", mode="scale"))
    np.testing.assert_array_equal(m.state[0], [U, U, W, U])
    assert m.warnings == ()


@pytest.mark.parametrize(
    ("depth", "rows", "key"),
    [
        # Four pixels: black, white, the key, white (each grey at its bit depth).
        (1, b"\0" + bytes([0b0101_0000]), 0),  # 1-bit: the key is black, so black is unknown
        (8, b"\0" + bytes([0, 255, 250, 255]), 250),  # 250 alone would read as free
        (16, b"\0" + struct.pack(">4H", 0, 65535, 64250, 65535), 64250),
    ],
    ids=["1-bit", "8-bit", "16-bit"],
)
def test_a_grey_png_with_a_transparent_key_reads_it_as_unknown_in_scale_mode(
    tmp_path: Path, depth: int, rows: bytes, key: int
) -> None:
    # Session 53's review: grey PNGs with a tRNS chunk decoded to one channel in OpenCV, their
    # transparency dropped: unexplored cells read as free floor, false removals.
    (tmp_path / "map.png").write_bytes(
        png_bytes(4, 1, depth, 0, rows, png_chunk(b"tRNS", struct.pack(">H", key)))
    )
    scale = load_map(write_yaml(tmp_path, "map.png", mode="scale"))
    if depth == 1:
        np.testing.assert_array_equal(scale.state[0], [U, F, U, F])
    else:
        np.testing.assert_array_equal(scale.state[0], [W, F, U, F])
    trinary = load_map(write_yaml(tmp_path, "map.png"))
    assert trinary.state[0, 1] == F and len(trinary.warnings) == 1
    assert "not opaque" in trinary.warnings[0]


def test_yaml_values_are_read_as_nav2_reads_them(tmp_path: Path) -> None:
    # PyYAML reads 5e-2 (no dot) and quoted numbers as strings; yaml-cpp reads them as numbers.
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(GREY_IMAGE))
    path = tmp_path / "map.yaml"
    path.write_text(
        "image: map.pgm\nresolution: 5e-2\norigin: ['-1.5', 2, 0]\nnegate: false\n"
        "occupied_thresh: '0.65'\nfree_thresh: 0.196\nextra_key: ignored\n"
    )
    m = load_map(path)
    assert m.resolution == 0.05 and m.origin == (-1.5, 2.0, 0.0)
    np.testing.assert_array_equal(m.state, np.stack([TRINARY, TRINARY[::-1]]))


# --- the free_thresh pitfall ----------------------------------------------------------------------


def _map_saver_image() -> np.ndarray:
    """8 x 8: a free room (254) with an occupied wall (0) and an unexplored corner (205)."""
    grey = np.full((8, 8), 254, np.uint8)
    grey[0, :] = 0
    grey[5:, 5:] = 205
    return grey


@pytest.mark.parametrize("free_thresh", [0.25, 0.2])
def test_unknown_205_read_as_free_is_noticed(tmp_path: Path, free_thresh: float) -> None:
    grey = _map_saver_image()
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(grey))
    m = load_map(write_yaml(tmp_path, "map.pgm", mode="trinary", free_thresh=free_thresh))
    expected = np.where(grey == 0, W, np.where(grey == 205, U, F))
    np.testing.assert_array_equal(m.state, expected)
    np.testing.assert_array_equal(m.occupancy, 255 - grey)  # still the pixel's probability
    assert len(m.warnings) == 1
    warning = m.warnings[0]
    assert f"free_thresh {free_thresh}" in warning and "205" in warning and "9 cells" in warning
    assert str(tmp_path / "map.yaml") in warning


def test_correct_free_thresh_gives_no_warning(tmp_path: Path) -> None:
    grey = _map_saver_image()
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(grey))
    m = load_map(write_yaml(tmp_path, "map.pgm"))
    np.testing.assert_array_equal(m.state, np.where(grey == 0, W, np.where(grey == 205, U, F)))
    assert m.warnings == ()


def test_205_in_a_grey_ramp_is_left_as_the_thresholds_say(tmp_path: Path) -> None:
    # A drawing or scan with every shade: 205 is one shade among many, not an unknown area.
    grey = np.tile(np.arange(256, dtype=np.uint8), (4, 1))
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(grey))
    m = load_map(write_yaml(tmp_path, "map.pgm", free_thresh=0.25))
    assert (m.state[:, 205] == F).all()
    assert m.warnings == ()


@pytest.mark.parametrize("fields", [{"negate": 1}, {"mode": "raw"}], ids=["negate", "raw"])
def test_205_rule_applies_only_to_map_saver_conventions(
    tmp_path: Path, fields: dict[str, Any]
) -> None:
    grey = _map_saver_image()
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(grey))
    m = load_map(write_yaml(tmp_path, "map.pgm", free_thresh=0.25, **fields))
    assert not any("free_thresh" in w for w in m.warnings)


# --- origin yaw -----------------------------------------------------------------------------------


def test_origin_yaw_is_kept_warned_about_and_not_applied(tmp_path: Path) -> None:
    flat = load_map(write_map(tmp_path, "pgm-p5", name="flat.yaml", origin=[1.0, 2.0, 0.0]))
    turned = load_map(write_map(tmp_path, "pgm-p5", name="turned.yaml", origin=[1.0, 2.0, 3.14]))
    assert turned.origin == (1.0, 2.0, 3.14)
    assert flat.warnings == ()
    assert turned.warnings == (
        f"origin yaw 3.14 rad in {tmp_path / 'turned.yaml'} is ignored, as Nav2 does: "
        "the grid is not rotated",
    )
    # Like Nav2: the grid and the pixel <-> metre conversion are those of yaw 0.
    np.testing.assert_array_equal(turned.state, flat.state)
    assert turned.pixel_to_world(3, 1) == flat.pixel_to_world(3, 1)
    assert turned.extent() == flat.extent()


# --- decompression bombs --------------------------------------------------------------------------


def test_pgm_bomb_is_rejected_from_its_header(tmp_path: Path) -> None:
    (tmp_path / "map.pgm").write_bytes(b"P5\n100000 100000\n255\n" + bytes(16))
    with pytest.raises(MapFileError) as error:
        load_map(write_yaml(tmp_path, "map.pgm"))
    reason = reason_of(error)
    assert reason.startswith(f"{tmp_path / 'map.pgm'}: ")
    assert "100000 x 100000" in reason and "max_image_pixels 100000000" in reason


def test_png_bomb_is_rejected_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_decoding(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the image was decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    (tmp_path / "map.png").write_bytes(png_bytes(100_000, 100_000, 8, 0, b"\0" * 64))
    with pytest.raises(MapFileError) as error:
        load_map(write_yaml(tmp_path, "map.png"))
    assert "100000 x 100000" in reason_of(error)


@pytest.mark.parametrize("fmt", ["pgm-p5", "pgm-p2", "png-grey-8"])
def test_max_pixels_is_a_limit_not_a_guess(tmp_path: Path, fmt: str) -> None:
    yaml_path = write_map(tmp_path, fmt)
    pixels = GREY_IMAGE.size
    assert load_map(yaml_path, max_pixels=pixels).state.size == pixels
    with pytest.raises(MapFileError, match=f"more than max_image_pixels {pixels - 1}"):
        load_map(yaml_path, max_pixels=pixels - 1)


# --- bad maps: one line naming the file and the problem --------------------------------------------


def _good(tmp_path: Path) -> Path:
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(GREY_IMAGE))
    return write_yaml(tmp_path, "map.pgm")


def _yaml_text(text: str) -> Callable[[Path], Path]:
    def make(tmp_path: Path) -> Path:
        _good(tmp_path)
        (tmp_path / "map.yaml").write_text(text)
        return tmp_path / "map.yaml"

    return make


def _fields(**fields: Any) -> Callable[[Path], Path]:
    def make(tmp_path: Path) -> Path:
        _good(tmp_path)
        return write_yaml(tmp_path, fields.pop("image", "map.pgm"), **fields)

    return make


def _without(*keys: str) -> Callable[[Path], Path]:
    def make(tmp_path: Path) -> Path:
        path = _good(tmp_path)
        document = yaml.safe_load(path.read_text())
        for key in keys:
            del document[key]
        path.write_text(yaml.safe_dump(document))
        return path

    return make


YAML_ERRORS = {
    "negative resolution": (_fields(resolution=-0.05), "'resolution' must be > 0, got -0.05"),
    "zero resolution": (_fields(resolution=0), "'resolution' must be > 0, got 0.0"),
    "nan resolution": (
        _fields(resolution=float("nan")),
        "'resolution' must be a finite number, got nan",
    ),
    "text resolution": (_fields(resolution="fine"), "'resolution' must be a number, got 'fine'"),
    "bool resolution": (_fields(resolution=True), "'resolution' must be a number, got True"),
    "missing key": (_without("resolution"), "missing key 'resolution'"),
    "missing keys": (_without("origin", "negate"), "missing keys 'origin', 'negate'"),
    "short origin": (_fields(origin=[1, 2]), "'origin' must be [x, y, yaw], got [1, 2]"),
    "text origin": (_fields(origin="0 0 0"), "'origin' must be [x, y, yaw], got '0 0 0'"),
    "infinite origin": (
        _fields(origin=[0, float("inf"), 0]),
        "'origin'[1] must be a finite number, got inf",
    ),
    "origin 1e300 m off": (
        _fields(origin=[1e300, 0, 0]),
        "'origin' must lie within 1e+07 m of the map frame's origin, got [1e+300, 0]",
    ),
    "occupied_thresh > 1": (
        _fields(occupied_thresh=1.5),
        "'occupied_thresh' must be between 0 and 1, got 1.5",
    ),
    "free_thresh < 0": (
        _fields(free_thresh=-0.1),
        "'free_thresh' must be between 0 and 1, got -0.1",
    ),
    "thresholds crossed": (
        _fields(free_thresh=0.7),
        "'free_thresh' (0.7) must be below 'occupied_thresh' (0.65)",
    ),
    "bad negate": (_fields(negate=2), "'negate' must be 0 or 1, got 2"),
    "bad mode": (_fields(mode="bogus"), "'mode' must be trinary, scale or raw, got 'bogus'"),
    "empty image": (_fields(image=""), "'image' must be a file name, got ''"),
    "numeric image": (_fields(image=42), "'image' must be a file name, got 42"),
    "syntax error": (
        _yaml_text("image: [map.pgm\nresolution: 0.05\n"),
        "YAML syntax error at line 2",
    ),
    "not a mapping": (
        _yaml_text("- image\n- map.pgm\n"),
        "must be a mapping with keys image, resolution",
    ),
    "empty file": (_yaml_text(""), "got an empty file"),
    "missing image": (_fields(image="nothere.pgm"), "cannot read image 'nothere.pgm'"),
    "image is a directory": (_fields(image="."), "not a regular file"),
}


def test_a_value_made_huge_by_yaml_aliases_is_shown_short_and_at_once(tmp_path: Path) -> None:
    # Session 53's review: 500 bytes of aliases (9 levels of 9) are a list of 9^9 items; its
    # full repr, cut to 60 characters only afterwards, took 30 s and 2.3 GB (one level more ran
    # out of memory). The message shows a few items of a few levels.
    _good(tmp_path)
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    lines += [
        f"{n}: &{n} [{', '.join([f'*{p}'] * 9)}]"
        for p, n in zip("abcdefgh", "bcdefghi", strict=True)
    ]
    path = tmp_path / "map.yaml"
    kept = [line for line in path.read_text().splitlines() if not line.startswith("negate:")]
    path.write_text("\n".join([*lines, *kept, "negate: *i", ""]))
    assert path.stat().st_size < 600
    with pytest.raises(MapFileError) as error:
        load_map(path)
    assert reason_of(error) == (
        f"{path}: 'negate' must be 0 or 1, got [[[[...], [...], [...], [...], ...], [[...], [...], [...]..."
    )


@pytest.mark.parametrize("case", YAML_ERRORS)
def test_bad_yaml_names_the_yaml_and_the_problem(tmp_path: Path, case: str) -> None:
    make, problem = YAML_ERRORS[case]
    yaml_path = make(tmp_path)
    with pytest.raises(MapFileError) as error:
        load_map(yaml_path)
    assert error.value.file == yaml_path
    assert reason_of(error).startswith(f"{yaml_path}: ")
    assert problem in reason_of(error)


def test_missing_yaml(tmp_path: Path) -> None:
    with pytest.raises(MapFileError) as error:
        load_map(tmp_path / "none.yaml")
    assert (
        reason_of(error)
        == f"{tmp_path / 'none.yaml'}: cannot read map YAML: No such file or directory"
    )


def test_yaml_that_is_a_directory(tmp_path: Path) -> None:
    with pytest.raises(MapFileError, match="cannot read map YAML: not a regular file"):
        load_map(tmp_path)


def _png_cut(data: bytes) -> bytes:
    return data[:-20]


def _png_bad_idat(data: bytes) -> bytes:
    # A well-formed chunk list around data that does not inflate.
    ihdr = data[8:33]
    return (
        data[:8] + ihdr + png_chunk(b"IDAT", b"\x78\x9cnot deflate data") + png_chunk(b"IEND", b"")
    )


IMAGE_ERRORS: dict[str, tuple[str, bytes, str]] = {
    "empty": ("map.pgm", b"", "the image file is empty"),
    "text named pgm": (
        "map.pgm",
        b"hello, this is not an image\n",
        "not a PGM or PNG image (it starts with b'hello, this '",
    ),
    "ppm": ("map.pgm", b"P6\n1 1\n255\n\0\0\0", "a Netpbm P6 image is not a map image"),
    "jpeg named png": ("map.png", b"\xff\xd8\xff\xe0\0\x10JFIF", "not a PGM or PNG image"),
    "truncated p5": (
        "map.pgm",
        b"P5\n4 3\n255\n" + bytes(5),
        "PGM is truncated: 5 of 12 pixel bytes present",
    ),
    "truncated 16-bit p5": (
        "map.pgm",
        b"P5\n2 2\n65535\n" + bytes(7),
        "PGM is truncated: 7 of 8 pixel bytes",
    ),
    "header cut": ("map.pgm", b"P5\n4 ", "PGM is truncated inside its header"),
    "bad width": ("map.pgm", b"P5\nabc 3\n255\n", "bad PGM header: width is not a number"),
    "maxval 0": ("map.pgm", b"P5\n1 1\n0\n\0", "maxval must be 1..65535, got 0"),
    "maxval too big": ("map.pgm", b"P5\n1 1\n70000\n\0\0", "maxval must be 1..65535, got 70000"),
    "zero width": ("map.pgm", b"P5\n0 3\n255\n", "the header gives an empty image, 0 x 3"),
    "sample above maxval": (
        "map.pgm",
        b"P5\n2 1\n100\n\x10\xc8",
        "a pixel value 200 exceeds the header's maxval 100",
    ),
    "huge comment": (
        "map.pgm",
        b"P5\n#" + b"x" * 70_000 + b"\n1 1\n255\n\0",
        "PGM header is longer than 65536 bytes",
    ),
    "p2 too few": (
        "map.pgm",
        b"P2\n3 2\n255\n1 2 3\n4 5\n",
        "ASCII PGM is truncated: 5 of 6 samples present",
    ),
    "p2 not a number": (
        "map.pgm",
        b"P2\n3 1\n255\n1 x 3\n",
        "ASCII PGM: unexpected b'x' after 1 of 3 samples",
    ),
    "p2 above maxval": (
        "map.pgm",
        b"P2\n2 1\n255\n1 256\n",
        "ASCII PGM: a sample exceeds maxval 255",
    ),
    "png cut": (
        "map.png",
        _png_cut(_png(GREY_IMAGE)),
        "PNG is truncated: it ends before its IEND chunk",
    ),
    "png bad data": ("map.png", _png_bad_idat(_png(GREY_IMAGE)), "cannot decode the PNG"),
    "png no ihdr": ("map.png", b"\x89PNG\r\n\x1a\n\0\0", "PNG has no IHDR header"),
    "png bad colour": (
        "map.png",
        png_bytes(1, 1, 8, 5, b"\0\0"),
        "invalid bit depth 8 / colour type 5",
    ),
}


@pytest.mark.parametrize("case", IMAGE_ERRORS)
def test_bad_image_names_the_image_and_the_problem(tmp_path: Path, case: str) -> None:
    name, data, problem = IMAGE_ERRORS[case]
    (tmp_path / name).write_bytes(data)
    with pytest.raises(MapFileError) as error:
        load_map(write_yaml(tmp_path, name))
    assert error.value.file == tmp_path / name
    assert reason_of(error).startswith(f"{tmp_path / name}: ")
    assert problem in reason_of(error)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_fifo_as_image_does_not_hang(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "map.pgm")
    with pytest.raises(MapFileError, match="not a regular file"):
        load_map(write_yaml(tmp_path, "map.pgm"))


def test_symlink_loop_as_image(tmp_path: Path) -> None:
    (tmp_path / "map.pgm").symlink_to(tmp_path / "map.pgm")
    with pytest.raises(MapFileError) as error:
        load_map(write_yaml(tmp_path, "map.pgm"))
    assert error.value.file == tmp_path / "map.yaml"


# --- confine_to -----------------------------------------------------------------------------------


@pytest.fixture
def bundle(tmp_path: Path) -> Path:
    """A bundle directory, with a valid image just outside it."""
    (tmp_path / "bundle").mkdir()
    (tmp_path / "outside.pgm").write_bytes(pgm_bytes(GREY_IMAGE))
    (tmp_path / "bundle" / "map.pgm").write_bytes(pgm_bytes(GREY_IMAGE))
    return tmp_path / "bundle"


def test_image_leaving_the_bundle_is_refused(bundle: Path) -> None:
    yaml_path = write_yaml(bundle, "../outside.pgm")
    assert load_map(yaml_path).state.shape == GREY_IMAGE.shape  # fine when not confined
    with pytest.raises(MapFileError) as error:
        load_map(yaml_path, confine_to=bundle)
    assert error.value.file == yaml_path
    assert reason_of(error).startswith(
        f"{yaml_path}: image path '../outside.pgm' leaves the bundle"
    )


@pytest.mark.parametrize("absolute", [False, True])
def test_symlink_or_absolute_path_out_of_the_bundle_is_refused(
    bundle: Path, absolute: bool
) -> None:
    if absolute:
        name = str(bundle.parent / "outside.pgm")
    else:
        name = "link.pgm"
        (bundle / name).symlink_to(bundle.parent / "outside.pgm")
    with pytest.raises(MapFileError, match="leaves the bundle"):
        load_map(write_yaml(bundle, name), confine_to=bundle)


def test_symlink_inside_the_bundle_is_fine(bundle: Path) -> None:
    (bundle / "sub").mkdir()
    (bundle / "sub" / "link.pgm").symlink_to(bundle / "map.pgm")
    m = load_map(write_yaml(bundle / "sub", "link.pgm"), confine_to=str(bundle))
    np.testing.assert_array_equal(m.state, np.stack([TRINARY, TRINARY[::-1]]))


def test_yaml_outside_the_bundle_is_refused(bundle: Path) -> None:
    yaml_path = write_yaml(bundle.parent, "bundle/map.pgm")
    with pytest.raises(MapFileError, match="the map YAML leaves the bundle"):
        load_map(yaml_path, confine_to=bundle)


# --- PGM details ----------------------------------------------------------------------------------


def test_ascii_pgm_across_read_blocks(tmp_path: Path) -> None:
    # About 1.4 MB of text: numbers are split across the reader's 1 MiB blocks.
    grey = np.random.default_rng(7).integers(0, 256, (500, 700)).astype(np.uint8)
    (tmp_path / "map.pgm").write_bytes(pgm_bytes(grey, ascii=True))
    m = load_map(write_yaml(tmp_path, "map.pgm"))
    np.testing.assert_array_equal(m.occupancy, 255 - grey)


def test_pgm_header_forms(tmp_path: Path) -> None:
    # Comments between any fields, one line, CRLF, tabs; a trailing second image is ignored.
    grey = GREY_IMAGE[:, :3]
    raster = grey.tobytes()
    headers = [
        b"P5 3 2 255\n",
        b"P5\r\n#c1\r\n3\t#c2\n2\n# c3\n255\n",
        b"P5\n3 2\n255 ",
    ]
    for i, header in enumerate(headers):
        (tmp_path / f"{i}.pgm").write_bytes(header + raster + b"P5\n1 1\n255\n\0")
        m = load_map(write_yaml(tmp_path, f"{i}.pgm", name=f"{i}.yaml"))
        np.testing.assert_array_equal(m.occupancy, 255 - grey, err_msg=repr(header))
    # A raster byte that happens to look like white space must not be eaten by the header.
    (tmp_path / "ws.pgm").write_bytes(b"P5\n2 1\n255\n\x0a\x20")
    np.testing.assert_array_equal(load_map(write_yaml(tmp_path, "ws.pgm")).occupancy, [[245, 223]])


# --- pixels and metres ----------------------------------------------------------------------------


def test_pixel_centres_follow_the_contract_with_a_non_zero_origin() -> None:
    m = from_states(np.zeros((4, 6), np.uint8), 0.05, (-10.0, -5.0, 0.0))
    # x = ox + (c + 0.5) r, y = oy + (h - k - 0.5) r, with h = 4 rows.
    x, y = m.pixel_to_world(0, 0)
    assert (x, y) == pytest.approx((-10.0 + 0.025, -5.0 + 3.5 * 0.05))
    x, y = m.pixel_to_world(5, 3)
    assert (x, y) == pytest.approx((-10.0 + 5.5 * 0.05, -5.0 + 0.5 * 0.05))
    assert m.extent() == pytest.approx((-10.0, -5.0, -9.7, -4.8))
    # The extent's corners are pixel corners: the top-left one is (col, row) = (-0.5, -0.5).
    assert m.world_to_pixel(-10.0, -4.8) == pytest.approx((-0.5, -0.5))


def test_pixel_world_round_trip() -> None:
    m = from_states(np.zeros((300, 200), np.uint8), 0.037, (12.5, -3.25, 0.0))
    rng = np.random.default_rng(3)
    col, row = rng.uniform(-10, 210, 1000), rng.uniform(-10, 310, 1000)
    back_col, back_row = m.world_to_pixel(*m.pixel_to_world(col, row))
    np.testing.assert_allclose(back_col, col, atol=1e-9)
    np.testing.assert_allclose(back_row, row, atol=1e-9)
    x, y = rng.uniform(12, 20, 100), rng.uniform(-4, 8, 100)
    np.testing.assert_allclose(m.pixel_to_world(*m.world_to_pixel(x, y)), (x, y), atol=1e-9)


# --- save_map -------------------------------------------------------------------------------------


def test_save_map_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    state = rng.choice(np.array([F, W, U], np.uint8), size=(37, 53))
    yaml_path = save_map(tmp_path / "saved.yaml", state, 0.05, (-12.9, -65.8, 0.0))
    image = (tmp_path / "saved.pgm").read_bytes()
    assert image.startswith(b"P5\n# CREATOR: ")
    assert set(np.unique(np.frombuffer(image[-state.size :], np.uint8))) == {0, 205, 254}
    m = load_map(yaml_path)
    np.testing.assert_array_equal(m.state, state)
    assert (m.resolution, m.origin, m.warnings) == (0.05, (-12.9, -65.8, 0.0), ())
    assert m.source == yaml_path and m.image == tmp_path / "saved.pgm"


# --- real maps ------------------------------------------------------------------------------------


def _counts(state: np.ndarray) -> tuple[int, ...]:
    return tuple(int(np.count_nonzero(state == s)) for s in (FREE, OCCUPIED, UNKNOWN))


def test_real_turtlebot3_world() -> None:
    m = load_map(DATA / "tb3_world" / "map.yaml")
    assert m.state.shape == (384, 384)
    assert (m.resolution, m.origin, m.warnings) == (0.05, (-10.0, -10.0, 0.0), ())
    # Its pixels are 7 939 x 254, 795 x 0 and 138 722 x 205.
    assert _counts(m.state) == (7939, 795, 138722)
    assert m.pixel_to_world(0, 383) == pytest.approx((-9.975, -9.975))


def test_real_depot_has_the_free_thresh_pitfall(tmp_path: Path) -> None:
    m = load_map(DATA / "nav2_depot" / "depot.yaml")
    assert m.state.shape == (307, 604)
    assert _counts(m.state) == (170587, 5947, 8894)  # all 8 894 cells of grey 205 unknown
    assert (
        len(m.warnings) == 1
        and "free_thresh 0.25" in m.warnings[0]
        and "8894 cells" in m.warnings[0]
    )
    # Read as with the right threshold, only without the warning.
    fixed = write_yaml(tmp_path, str(DATA / "nav2_depot" / "depot.pgm"), mode="trinary")
    right = load_map(fixed)
    np.testing.assert_array_equal(right.state, m.state)
    assert right.warnings == ()


def _reference_states(yaml_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The contract's rule written the slow, obvious way on an independently decoded image:
    (states, grey levels)."""
    meta = yaml.safe_load(yaml_path.read_text())
    image = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    maxval = 65535.0 if image.dtype == np.uint16 else 255.0
    v = image.astype(np.float64)
    if v.ndim == 3:
        v = v[..., :3].mean(axis=2)
    v = np.floor(v * 255.0 / maxval + 0.5)
    p = v / 255.0 if meta["negate"] else (255.0 - v) / 255.0
    state = np.full(v.shape, UNKNOWN, np.uint8)
    state[p < meta["free_thresh"]] = FREE
    state[p > meta["occupied_thresh"]] = OCCUPIED
    return state, v


def _shared_yamls() -> list[Path | None]:
    found = sorted(SHARED_MAPS.glob("*/*.yaml")) if SHARED_MAPS.is_dir() else []
    return list(found) or [None]


# Which shared maps must warn, and about what; every other one must not warn.
EXPECTED_WARNINGS = {"nav2_depot": "free_thresh 0.25", "mit_stata_basement": "origin yaw 3.14 rad"}


@pytest.mark.parametrize(
    "yaml_path", _shared_yamls(), ids=lambda p: p.parent.name if p else "absent"
)
def test_every_shared_map_reads_sanely(yaml_path: Path | None) -> None:
    if yaml_path is None:
        pytest.skip(f"no shared maps at {SHARED_MAPS}")
    m = load_map(yaml_path)
    free, occupied, unknown = _counts(m.state)
    assert free > 0 and occupied > 0 and free + occupied + unknown == m.state.size
    expected, grey = _reference_states(yaml_path)
    name = yaml_path.parent.name
    if name in EXPECTED_WARNINGS:
        assert len(m.warnings) == 1 and EXPECTED_WARNINGS[name] in m.warnings[0]
    else:
        assert m.warnings == ()
    if name == "nav2_depot":
        expected[grey == 205] = UNKNOWN
    np.testing.assert_array_equal(m.state, expected)
