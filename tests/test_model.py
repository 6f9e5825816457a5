"""Geometry, the bundle manifest, and the configuration: plain models with clear errors."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

import mapserver
from mapserver import bundle as bundle_module
from mapserver.bundle import (
    check_bundle_files,
    is_in_flight,
    is_valid_bundle_id,
    parse_manifest,
    safe_member,
)
from mapserver.config import Config, dump_config, load_config
from mapserver.errors import BundleError, BundleIncomplete, ConfigError
from mapserver.geometry import Pose2D, Transform2D, fit_rigid, wrap_angle, yaw_from_quaternion

# --- geometry --------------------------------------------------------------------------------


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0, math.pi - 1e-3])
def test_quaternion_to_yaw(yaw: float) -> None:
    q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    assert yaw_from_quaternion(*q) == pytest.approx(yaw)
    assert yaw_from_quaternion(*(2 * v for v in q)) == pytest.approx(yaw)  # not normalised


def test_zero_quaternion_is_rejected() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        yaw_from_quaternion(0, 0, 0, 0)


def test_transform_from_poses_maps_one_pose_onto_the_other() -> None:
    nav2, slam = Pose2D(12.3, -4.5, 1.5708), Pose2D(0.8, 0.1, 0.02)
    t = Transform2D.from_poses(nav2, slam)
    assert t.theta == pytest.approx(1.5508)
    assert t.apply([slam.x, slam.y]) == pytest.approx([nav2.x, nav2.y])


def test_compose_and_inverse() -> None:
    a, b = Transform2D(0.4, 1.0, -2.0), Transform2D(-1.1, 3.0, 0.5)
    p = [[1.0, 2.0], [-3.0, 0.5]]
    assert a.compose(b).apply(p) == pytest.approx(a.apply(b.apply(p)))
    assert a.inverse().apply(a.apply(p)) == pytest.approx(np.array(p))
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)


# --- bundle manifest -------------------------------------------------------------------------

MANIFEST = {
    "format": 1,
    "robot": "sedia-01",
    "stamp": "2026-11-21T10:15:00Z",
    "slam_map": "slam_map.yaml",
    "pose": {
        "nav2": {"x": 12.3, "y": -4.5, "yaw": 1.5708},
        "slam": {"x": 0.8, "y": 0.1, "yaw": 0.02},
    },
}


def _parse(**changes: object) -> object:
    data = yaml.safe_load(yaml.safe_dump(MANIFEST))
    for key, value in changes.items():
        node = data
        *path, last = key.split("__")
        for p in path:
            node = node[p]
        if value is None:
            del node[last]
        else:
            node[last] = value
    return parse_manifest(yaml.safe_dump(data))


def test_manifest_with_yaw_or_quaternion() -> None:
    m = _parse()
    assert m.nav2_from_slam_prior().theta == pytest.approx(1.5508)
    q = {"x": 0.0, "y": 0.0, "z": math.sin(0.785), "w": math.cos(0.785)}
    m = _parse(pose__nav2={"x": 1.0, "y": 2.0, "orientation": q})
    assert m.pose.nav2.to_pose().yaw == pytest.approx(1.57)


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"robot": None}, "missing key 'robot'"),
        ({"slam_map": None}, "missing key 'slam_map'"),
        ({"pose__slam__x": "left"}, "'pose.slam.x'"),
        ({"pose__nav2__x": float("nan")}, "finite"),
        ({"pose__nav2__yaw": float("inf")}, "finite"),
        # Finite, yet past any building: transforms overflow and arrays sized by it too.
        (
            {"pose__nav2__x": 1e300},
            "'pose.nav2': Value error, pose x and y must lie within 1e+07 m",
        ),
        ({"pose__slam__y": -2e7}, "got (0.8, -2e+07)"),
        # A valid text whose UTC time falls before year 1.
        ({"stamp": "0001-01-01T00:30:00+01:00"}, "outside the years 1-9999 in UTC"),
        ({"pose__slam__yaw": None}, "exactly one of 'yaw' and 'orientation'"),
        ({"format": 2}, "unsupported format 2"),
        ({"robot": "bad robot!"}, "'robot'"),
        ({"colour": "red"}, "unknown key 'colour'"),
        ({"checksums": {"a.pgm": "xyz"}}, "'checksums.a.pgm'"),
    ],
)
def test_bad_manifest_fields_are_named(changes: dict[str, object], expected: str) -> None:
    with pytest.raises(BundleError) as info:
        _parse(**changes)
    assert expected in info.value.reason
    assert "bundle.yaml" in info.value.reason


def test_manifest_yaml_syntax_error() -> None:
    with pytest.raises(BundleError, match="not valid YAML"):
        parse_manifest("format: 1\npose: {nav2: [unclosed\n")


@pytest.mark.parametrize(
    ("name", "valid"),
    [
        ("run-0042", True),
        ("a", True),
        ("A.b_c-1", True),
        (".hidden", False),
        ("-x", False),
        ("a/b", False),
        ("x" * 129, False),
        ("ü", False),
    ],
)
def test_bundle_ids(name: str, valid: bool) -> None:
    assert is_valid_bundle_id(name) is valid


def test_in_flight_names() -> None:
    assert all(map(is_in_flight, [".slam_map.pgm.AbC123", "x.tmp", "x.part", "x~"]))
    assert not is_in_flight("slam_map.pgm")


def _bundle(tmp_path: Path) -> Path:
    d = tmp_path / "b"
    d.mkdir()
    (d / "slam_map.yaml").write_text("image: slam_map.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    (d / "slam_map.pgm").write_bytes(b"P5\n2 2\n255\n\x00\x00\x00\x00")
    (d / "bundle.yaml").write_text(yaml.safe_dump(MANIFEST))
    return d


def test_completeness_waits_for_files_and_checksums(tmp_path: Path) -> None:
    d = _bundle(tmp_path)
    files = check_bundle_files(d)
    assert files.slam_image == d / "slam_map.pgm" and files.nav2_yaml is None
    data = dict(MANIFEST, nav2_map="nav2_map.yaml")
    (d / "bundle.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(BundleIncomplete, match=r"nav2_map 'nav2_map\.yaml' is not there yet"):
        check_bundle_files(d)
    data = dict(MANIFEST, checksums={"slam_map.pgm": "0" * 64})
    (d / "bundle.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(BundleIncomplete, match=r"sha256 of 'slam_map\.pgm' does not match"):
        check_bundle_files(d)


def test_checksums_verified_before_are_not_hashed_again(tmp_path: Path) -> None:
    # The daemon verifies them when it takes a bundle; its workers only check the files are
    # there (a wrong checksum passes, a missing checksummed file does not).
    d = _bundle(tmp_path)
    data = dict(MANIFEST, checksums={"slam_map.pgm": "0" * 64})
    (d / "bundle.yaml").write_text(yaml.safe_dump(data))
    assert check_bundle_files(d, verify_checksums=False).slam_image == d / "slam_map.pgm"
    data = dict(MANIFEST, checksums={"slam_map.pgm": "0" * 64, "extra.bin": "0" * 64})
    (d / "bundle.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(BundleIncomplete, match=r"'extra\.bin' is not there yet"):
        check_bundle_files(d, verify_checksums=False)


def test_paths_that_leave_the_bundle_are_errors(tmp_path: Path) -> None:
    d = _bundle(tmp_path)
    for name in ("../outside.yaml", "/etc/passwd"):
        with pytest.raises(BundleError, match="slam_map"):
            (d / "bundle.yaml").write_text(yaml.safe_dump(dict(MANIFEST, slam_map=name)))
            check_bundle_files(d)
    (tmp_path / "secret.pgm").write_bytes(b"P5\n1 1\n255\n\x00")
    os.symlink(tmp_path / "secret.pgm", d / "link.pgm")
    with pytest.raises(BundleError, match="points outside the bundle"):
        safe_member(d, "link.pgm", what="map image", source=d / "slam_map.yaml")


def test_a_symlink_loop_and_an_unreadable_checksummed_file_are_the_bundles_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Session 53's review: both were "load failed unexpectedly ...; please report this bundle"
    # with a traceback (Path.resolve raises RuntimeError on a loop before Python 3.13).
    d = _bundle(tmp_path)
    os.symlink("loop", d / "loop")
    (d / "bundle.yaml").write_text(yaml.safe_dump(dict(MANIFEST, slam_map="loop")))
    with pytest.raises(BundleError, match=r"bundle\.yaml: slam_map 'loop' is a symlink loop$"):
        check_bundle_files(d)
    data = dict(MANIFEST, checksums={"slam_map.pgm": "0" * 64})
    (d / "bundle.yaml").write_text(yaml.safe_dump(data))

    def refused(path: Path) -> str:
        raise PermissionError(13, "Permission denied", str(path))

    # A file mode 000 (root, which runs the tests, reads any file: the refusal is simulated).
    monkeypatch.setattr(bundle_module, "sha256_file", refused)
    with pytest.raises(BundleError) as info:
        check_bundle_files(d)
    assert info.value.reason == (
        f"{d / 'slam_map.pgm'}: checksummed file 'slam_map.pgm' cannot be read: Permission denied"
    )


# --- configuration ---------------------------------------------------------------------------


def test_defaults_work_in_the_current_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MAPSERVER_CONFIG", raising=False)
    c = load_config()
    assert c.inbox == tmp_path / "inbox" and c.failed == tmp_path / "failed"
    assert c.settle_seconds == 2.0 and c.max_image_pixels == 100_000_000
    assert c.worker_count() == (os.cpu_count() or 1)


def test_relative_paths_follow_the_config_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "etc").mkdir()
    path = tmp_path / "etc" / "m.yaml"
    path.write_text("inbox: ../spool/in\nworkers: 3\npipeline: {roi: {strategy: box}}\n")
    monkeypatch.setenv("MAPSERVER_CONFIG", str(path))
    c = load_config()
    assert c.inbox == tmp_path / "spool" / "in" and c.workers == 3
    assert c.pipeline.roi.strategy == "box"
    assert yaml.safe_load(dump_config(c))["workers"] == 3


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("inbx: ./in\n", "unknown key 'inbx'"),
        ("pipeline: {diff: {tolerence_m: 1}}\n", "unknown key 'pipeline.diff.tolerence_m'"),
        ("workers: -1\n", "'workers'"),
        ("observer: magic\n", "'observer'"),
        ("- a\n- b\n", "mapping"),
        ("inbox: [\n", "not valid YAML"),
    ],
)
def test_bad_config_names_the_key(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert expected in info.value.reason and "bad.yaml" in info.value.reason


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        # Session 53's review: retention deleted outbox/maps, the whole map store.
        ("outbox: data\nmaps: data/maps\n", "maps ({d}/data/maps) lies inside outbox ({d}/data)"),
        ("outbox: data\ninbox: data/inbox\n", "inbox ({d}/data/inbox) lies inside outbox"),
        ("archive: ./done\nfailed: done\n", "archive and failed are one folder ({d}/done)"),
        ("inbox: spool\nfailed: spool/../spool/bad\n", "failed ({d}/spool/bad) lies inside inbox"),
    ],
)
def test_folders_inside_one_another_are_refused(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert expected.format(d=tmp_path) in info.value.reason
    assert "must be apart" in info.value.reason
    # Side by side, as the example configuration has them: fine.
    path.write_text("inbox: data/inbox\noutbox: data/outbox\nmaps: data/maps\n")
    assert load_config(path).maps == tmp_path / "data" / "maps"


def test_config_is_frozen() -> None:
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen-instance error
        Config().workers = 4  # type: ignore[misc]


def test_public_api_is_pinned() -> None:
    assert sorted(mapserver.__all__) == [
        "BundleError",
        "BundleIncomplete",
        "Config",
        "ConfigError",
        "MapFileError",
        "MapserverError",
        "OccupancyMap",
        "Outcome",
        "Pose2D",
        "ProcessingError",
        "Transform2D",
        "load_config",
        "load_map",
        "process_bundle",
    ]
    assert all(hasattr(mapserver, name) for name in mapserver.__all__)


def test_fit_rigid_recovers_a_transform_and_is_the_least_squares_one() -> None:
    rng = np.random.default_rng(3)
    src = rng.uniform(-10, 10, size=(50, 2))
    true = Transform2D(math.radians(-37.0), 4.0, -2.5)
    got = fit_rigid(src, true.apply(src))
    assert (got.theta, got.tx, got.ty) == pytest.approx((true.theta, true.tx, true.ty))
    # Noisy targets: the fit beats the true transform on the squared residuals.
    noisy = true.apply(src) + rng.normal(0, 0.3, size=src.shape)
    fit = fit_rigid(src, noisy)
    assert np.sum((fit.apply(src) - noisy) ** 2) <= np.sum((true.apply(src) - noisy) ** 2)
    with pytest.raises(ValueError, match="as many src as dst"):
        fit_rigid(np.zeros((0, 2)), np.zeros((0, 2)))
