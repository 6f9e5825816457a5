"""Writing synthetic bundles and their truth to disk (contract sections 2 and 4)."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

import yaml

from mapserver.bundle import is_valid_bundle_id, sha256_file
from mapserver.geometry import Pose2D, Transform2D, wrap_angle
from mapserver.maps import OccupancyMap, save_map
from mapserver.synth.changes import Change
from mapserver.synth.scenario import SyntheticBundle


def _pose_dict(pose: Pose2D) -> dict[str, float]:
    return {
        "x": round(float(pose.x), 6),
        "y": round(float(pose.y), 6),
        "yaw": round(wrap_angle(float(pose.yaw)), 6),
    }


def _origin(m: OccupancyMap) -> tuple[float, float, float]:
    return (round(m.origin[0], 6), round(m.origin[1], 6), round(m.origin[2], 6))


def write_bundle(
    out_dir: str | Path,
    bundle_id: str,
    *,
    slam_map: OccupancyMap,
    nav2_map: OccupancyMap | None,
    pose_nav2: Pose2D,
    pose_slam: Pose2D,
    trajectory: Sequence[Pose2D] | None = None,
    robot: str = "sim-01",
    stamp: str | None = None,
) -> Path:
    """Write a bundle directory ``out_dir/bundle_id`` (contract section 2).

    Writes ``slam_map.yaml/.pgm``, ``nav2_map.yaml/.pgm`` (when ``nav2_map`` is given: the
    ORIGINAL global map, without the changes) and, last, ``bundle.yaml`` with the sha256 of every
    map file. ``stamp`` defaults to now (UTC). Existing files of the same names are replaced.

    Returns
    -------
    Path
        The bundle directory.
    """
    if not is_valid_bundle_id(bundle_id):
        raise ValueError(
            f"bundle_id must match [A-Za-z0-9][A-Za-z0-9._-]{{0,127}}, got {bundle_id!r}"
        )
    if not robot or not all(ch.isalnum() or ch in "._-" for ch in robot):
        raise ValueError(f"robot must match [A-Za-z0-9._-]+, got {robot!r}")
    if stamp is None:
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    directory = Path(out_dir) / bundle_id
    directory.mkdir(parents=True, exist_ok=True)
    files = ["slam_map.yaml", "slam_map.pgm"]
    save_map(directory / "slam_map.yaml", slam_map.state, slam_map.resolution, _origin(slam_map))
    if nav2_map is not None:
        save_map(
            directory / "nav2_map.yaml", nav2_map.state, nav2_map.resolution, _origin(nav2_map)
        )
        files += ["nav2_map.yaml", "nav2_map.pgm"]
    manifest: dict[str, object] = {
        "format": 1,
        "robot": robot,
        "stamp": stamp,
        "slam_map": "slam_map.yaml",
    }
    if nav2_map is not None:
        manifest["nav2_map"] = "nav2_map.yaml"
    manifest["pose"] = {"nav2": _pose_dict(pose_nav2), "slam": _pose_dict(pose_slam)}
    if trajectory:
        manifest["trajectory"] = [_pose_dict(p) for p in trajectory]
    manifest["checksums"] = {name: sha256_file(directory / name) for name in files}
    # The manifest last, under an in-flight name first: a watcher never sees a partial bundle.
    partial = directory / ".bundle.yaml.tmp"
    partial.write_text(
        yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None, width=100)
    )
    partial.replace(directory / "bundle.yaml")
    return directory


def write_truth(path: str | Path, transform: Transform2D, changes: Sequence[Change]) -> Path:
    """Write ``truth.yaml`` (contract section 4): the true slam -> nav2 transform and the changes.

    Returns
    -------
    Path
        ``path``.
    """
    document = {
        "format": 1,
        "transform": {
            "theta": round(float(transform.theta), 8),
            "tx": round(float(transform.tx), 6),
            "ty": round(float(transform.ty), 6),
        },
        "changes": [
            {
                "id": int(c.id),
                "kind": c.kind,
                "polygon": [[float(x), float(y)] for x, y in c.polygon],
                "observed": bool(c.observed),
            }
            for c in changes
        ],
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=100))
    return path


def write_scenario(
    scenario: SyntheticBundle,
    out_dir: str | Path,
    bundle_id: str,
    *,
    truth_path: str | Path | None = None,
    include_nav2_map: bool = True,
    robot: str = "sim-01",
    stamp: str | None = None,
) -> Path:
    """Write a scenario as a bundle (and its truth, when ``truth_path`` is given: keep it out of
    any inbox). Returns the bundle directory."""
    directory = write_bundle(
        out_dir,
        bundle_id,
        slam_map=scenario.slam_map,
        nav2_map=scenario.world if include_nav2_map else None,
        pose_nav2=scenario.pose_nav2,
        pose_slam=scenario.pose_slam,
        trajectory=scenario.trajectory,
        robot=robot,
        stamp=stamp,
    )
    if truth_path is not None:
        write_truth(truth_path, scenario.nav2_from_slam, scenario.changes)
    return directory
