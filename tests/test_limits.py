"""Sanity limits on a bundle's inputs (configuration ``limits:``): refused before any heavy work,
with the limit named."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from daemon_support import make_bundle

from mapserver.bundle import check_bundle_files, parse_manifest
from mapserver.config import Config, LimitsConfig, parse_config
from mapserver.errors import BundleError, ConfigError, MapFileError
from mapserver.mapcache import MapCache
from mapserver.maps import FREE, MAX_MAP_YAML_BYTES, OCCUPIED, load_map, save_map
from mapserver.pipeline import process_bundle


def write_map(path: Path, *, resolution: float, size: int = 40) -> Path:
    grid = np.full((size, size), FREE, np.uint8)
    grid[:2, :] = OCCUPIED
    return save_map(path, grid, resolution, (0.0, 0.0, 0.0))


def set_resolution(map_yaml: Path, resolution: float) -> None:
    doc = yaml.safe_load(map_yaml.read_text())
    doc["resolution"] = resolution
    map_yaml.write_text(yaml.safe_dump(doc))


@pytest.mark.parametrize(
    ("resolution", "refused"),
    [(1e-9, True), (0.004, True), (0.005, False), (0.05, False), (1.0, False), (1.5, True)],
)
def test_a_resolution_outside_the_plausible_range_is_refused_before_the_image_is_read(
    tmp_path: Path, resolution: float, refused: bool
) -> None:
    map_yaml = write_map(tmp_path / "m.yaml", resolution=0.05)
    set_resolution(map_yaml, resolution)
    (tmp_path / "m.pgm").write_bytes(b"not read when the resolution is refused")
    if not refused:
        with pytest.raises(MapFileError, match="not a PGM or PNG"):  # it went on to the image
            load_map(map_yaml, resolution_range_m=(0.005, 1.0))
        return
    with pytest.raises(MapFileError) as caught:
        load_map(map_yaml, resolution_range_m=(0.005, 1.0))
    reason = caught.value.reason
    assert reason.startswith(f"{map_yaml}: 'resolution' {resolution:g} m per cell is outside")
    assert "0.005..1 m" in reason and "limits.min_resolution_m" in reason


def test_a_map_larger_than_the_extent_limit_is_refused_from_its_header(tmp_path: Path) -> None:
    map_yaml = write_map(tmp_path / "m.yaml", resolution=0.5, size=40)  # 20 m x 20 m
    assert load_map(map_yaml, max_extent_m=20.0).width == 40
    with pytest.raises(MapFileError) as caught:
        load_map(map_yaml, max_extent_m=19.9)
    assert "the map is 20 m x 20 m (40 x 40 pixels at 0.5 m)" in caught.value.reason
    assert "limits.max_map_extent_m 19.9 m" in caught.value.reason
    assert load_map(map_yaml).width == 40  # no limit given: none applied


def test_the_map_cache_applies_the_limits_to_a_map_it_holds(tmp_path: Path) -> None:
    map_yaml = write_map(tmp_path / "m.yaml", resolution=0.5, size=40)
    cache = MapCache()
    image = tmp_path / "m.pgm"
    assert cache.load(map_yaml, image, max_pixels=10_000).width == 40
    with pytest.raises(MapFileError, match="max_map_extent_m"):
        cache.load(map_yaml, image, max_pixels=10_000, max_extent_m=10.0)
    with pytest.raises(MapFileError, match="outside the range"):
        cache.load(map_yaml, image, max_pixels=10_000, resolution_range_m=(0.01, 0.1))


def manifest(**changes: Any) -> str:
    doc: dict[str, Any] = {
        "format": 1,
        "robot": "r1",
        "stamp": "2026-11-21T10:15:00Z",
        "slam_map": "slam_map.yaml",
        "pose": {"nav2": {"x": 0, "y": 0, "yaw": 0}, "slam": {"x": 0, "y": 0, "yaw": 0}},
    }
    doc.update(changes)
    return yaml.safe_dump(doc)


def test_a_trajectory_longer_than_the_limit_is_refused_before_its_poses_are_read() -> None:
    limits = LimitsConfig(max_trajectory_poses=3)
    poses = [{"x": i, "y": 0, "yaw": 0} for i in range(3)]
    assert len(parse_manifest(manifest(trajectory=poses), limits=limits).trajectory or []) == 3
    # The fourth pose is not even a pose: the count is checked first.
    with pytest.raises(BundleError) as caught:
        parse_manifest(manifest(trajectory=[*poses, "junk"]), limits=limits)
    assert "the trajectory has 4 poses, more than limits.max_trajectory_poses 3" in (
        caught.value.reason
    )


@pytest.mark.parametrize("flow", [False, True], ids=["block", "flow"])
def test_the_daemon_s_check_counts_a_trajectory_s_poses_without_reading_them(flow: bool) -> None:
    """``trajectory=False`` (the daemon's main loop): the manifest without its trajectory, the
    same as the whole parse otherwise, whether the trajectory comes first or last, in block or
    flow style; the count is checked as before; a bad pose is left to the worker's parse."""
    limits = LimitsConfig(max_trajectory_poses=3)
    poses = [{"x": i, "y": 0.5, "yaw": 0.1} for i in range(3)]
    whole = parse_manifest(manifest(trajectory=poses), limits=limits)
    for text in (
        yaml.safe_dump({"trajectory": poses, **yaml.safe_load(manifest())}, sort_keys=False),
        manifest(trajectory=poses) + "# the end\n",
    ):
        if flow:
            text = yaml.safe_dump(yaml.safe_load(text), default_flow_style=True, sort_keys=False)
        light = parse_manifest(text, limits=limits, trajectory=False)
        assert light.trajectory is None
        assert light.model_copy(update={"trajectory": whole.trajectory}) == whole
    with pytest.raises(BundleError, match="the trajectory has 4 poses, more than"):
        parse_manifest(manifest(trajectory=[*poses, "junk"]), limits=limits, trajectory=False)
    broken = manifest(trajectory=[poses[0], {"x": 1}])
    assert parse_manifest(broken, trajectory=False).trajectory is None
    with pytest.raises(BundleError, match="trajectory"):
        parse_manifest(broken)


def test_a_manifest_the_quick_check_cannot_read_gets_the_whole_parse_s_reason() -> None:
    """A trajectory that another key refers to (a YAML alias), cut out by the quick check, is
    not a problem of its own: the reason given is the whole parse's (an unknown key)."""
    text = manifest() + "trajectory: &route [{x: 0, y: 0, yaw: 0}]\nagain: *route\n"
    with pytest.raises(BundleError) as whole:
        parse_manifest(text)
    with pytest.raises(BundleError) as quick:
        parse_manifest(text, trajectory=False)
    assert quick.value.reason == whole.value.reason
    assert "again" in whole.value.reason


def test_the_quick_check_leaves_what_it_cannot_cut_to_the_whole_parse() -> None:
    """A trajectory given twice (YAML keeps the last), or given as a mapping: the whole parse
    decides, the same with or without the poses read. A value YAML cannot construct
    (``!!float abc``, a ValueError inside PyYAML) is a bundle error, not a crash."""
    limits = LimitsConfig(max_trajectory_poses=3)
    poses = [{"x": i, "y": 0, "yaw": 0} for i in range(4)]
    twice = manifest(trajectory=poses) + "trajectory: []\n"
    for quick in (False, True):
        assert parse_manifest(twice, limits=limits, trajectory=not quick).trajectory in ([], None)
        with pytest.raises(BundleError, match="'trajectory': Input should be a valid list"):
            parse_manifest(manifest(trajectory={"a": 1, "b": 2}), trajectory=not quick)
        with pytest.raises(BundleError, match="not valid YAML: could not convert"):
            parse_manifest(manifest().replace("x: 0", "x: !!float abc", 1), trajectory=not quick)


def _reasons(text: str) -> tuple[str, str]:
    """The reasons the whole parse and the quick check (``trajectory=False``) refuse
    ``text`` for."""
    reasons = []
    for quick in (False, True):
        with pytest.raises(BundleError) as caught:
            parse_manifest(text, trajectory=not quick)
        reasons.append(caught.value.reason)
    return reasons[0], reasons[1]


@pytest.mark.parametrize("flow", [False, True], ids=["block", "flow"])
@pytest.mark.parametrize("with_trajectory", [False, True])
def test_the_quick_check_refuses_an_unknown_key_without_reading_its_value(
    flow: bool, with_trajectory: bool
) -> None:
    """A key the manifest does not know, holding a large value: the quick check (the daemon's
    main loop) names it as the whole parse does, without reading the value (16 MiB of it took
    16 s): a value YAML cannot construct (``!!float abc``) under it makes the whole parse
    refuse the YAML, the quick check still the key."""
    poses = [{"x": 0, "y": 0, "yaw": 0}] if with_trajectory else None
    junk = {"rows": [{"a": i, "b": [i, i + 1]} for i in range(200)], "note": "x" * 100}
    doc = yaml.safe_load(manifest(junk=junk, trajectory=poses))
    if not with_trajectory:
        del doc["trajectory"]
    text = yaml.safe_dump(doc, default_flow_style=flow, sort_keys=False)
    whole, quick = _reasons(text)
    assert quick == whole
    assert "unknown key 'junk'" in whole
    if flow:
        return
    # A scalar under a second unknown key: both named.
    whole, quick = _reasons(text + "extra_note: some words\n")
    assert quick == whole
    assert "unknown key 'extra_note'" in whole
    whole, quick = _reasons(text.replace("note:", "note: !!float abc\n  old_note:", 1))
    assert "not valid YAML: could not convert" in whole
    assert "unknown key 'junk'" in quick


def test_what_the_quick_check_cannot_cut_alone_gets_the_whole_parse_s_reason() -> None:
    """An unknown key's value that a known key refers to (a YAML alias into it): the cut text
    does not read, and the whole parse gives the reason. A quoted key is a string as a plain
    one is (cut, named the same); a key YAML reads as no string (``yes``: a bool) is not cut,
    and the whole parse judges it."""
    for text in (
        manifest().replace("robot: r1", "junk: &who r1\nrobot: *who"),
        manifest() + "'quoted': [1, 2]\n",
        manifest() + "yes: [1, 2]\n",
    ):
        whole, quick = _reasons(text)
        assert quick == whole
    assert (
        "unknown key 'junk'"
        in _reasons(manifest().replace("robot: r1", "junk: &who r1\nrobot: *who"))[0]
    )


def test_a_manifest_larger_than_the_limit_is_refused_unread(tmp_path: Path) -> None:
    bundle = make_bundle(tmp_path / "run-1")
    size = (bundle / "bundle.yaml").stat().st_size
    assert check_bundle_files(bundle, limits=LimitsConfig(max_manifest_bytes=size))
    with pytest.raises(BundleError) as caught:
        check_bundle_files(bundle, limits=LimitsConfig(max_manifest_bytes=size - 1))
    assert caught.value.stage == "bundle"
    assert f"the manifest is {size} bytes, more than limits.max_manifest_bytes {size - 1}" in (
        caught.value.reason
    )


def test_a_map_yaml_of_megabytes_is_refused_unparsed(tmp_path: Path) -> None:
    """Session 44's review: the completeness check (the daemon's main loop) parsed a 16 MiB map
    YAML for a minute. A map YAML is six keys; one past 64 KiB is not one."""
    bundle = make_bundle(tmp_path / "run-1", checksums=False)
    slam = bundle / yaml.safe_load((bundle / "bundle.yaml").read_text())["slam_map"]
    text = slam.read_text()
    slam.write_text(text + "# " + "x" * (MAX_MAP_YAML_BYTES - len(text) - 3) + "\n")
    assert slam.stat().st_size == MAX_MAP_YAML_BYTES
    assert check_bundle_files(bundle)  # at the limit: read
    slam.write_text(text + "junk: [" + "1, " * 400_000 + "1]\n")
    with pytest.raises(BundleError, match="larger than 65536: is it a map YAML"):
        check_bundle_files(bundle)
    with pytest.raises(MapFileError, match="larger than 65536 bytes"):
        load_map(slam)


def test_limits_in_the_configuration_are_checked(tmp_path: Path) -> None:
    assert Config().limits == LimitsConfig()
    with pytest.raises(ConfigError, match="min_resolution_m must not be larger"):
        parse_config({"limits": {"min_resolution_m": 2.0}}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"unknown key 'limits\.max_poses'"):
        parse_config({"limits": {"max_poses": 2}}, base_dir=tmp_path)


def test_a_bundle_with_a_nanometre_map_fails_at_load_with_the_reason_not_in_align(
    tmp_path: Path,
) -> None:
    # It used to reach warpAffine and fail with "align failed unexpectedly ... please report".
    bundle = make_bundle(tmp_path / "run-1", checksums=False)
    set_resolution(bundle / "slam_map.yaml", 1e-9)
    with pytest.raises(MapFileError) as caught:
        process_bundle(bundle, Config())
    assert caught.value.stage == "load"
    assert "slam_map.yaml: 'resolution' 1e-09 m per cell is outside" in caught.value.reason
    assert "report" not in caught.value.reason


def test_a_map_image_the_daemon_may_not_read_fails_at_load_saying_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Session 44's review: an image of mode 0600 owned by another user failed the bundle with
    "load failed unexpectedly (PermissionError ...) please report this bundle". (Root reads
    anything, so the hash's open is made to refuse it here.)"""
    import mapserver.mapcache

    bundle = make_bundle(tmp_path / "run-1", checksums=False)
    real = mapserver.mapcache.sha256_file

    def sha256_file(path: Path) -> str:
        if Path(path).name.endswith(".pgm"):
            raise PermissionError(13, "Permission denied", str(path))
        return real(path)

    monkeypatch.setattr(mapserver.mapcache, "sha256_file", sha256_file)
    with pytest.raises(MapFileError) as caught:
        process_bundle(bundle, Config())
    assert caught.value.stage == "load"
    assert "cannot read image: Permission denied" in caught.value.reason
    assert "report" not in caught.value.reason
