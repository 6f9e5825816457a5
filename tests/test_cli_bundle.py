"""``mapserver bundle``: the robot side writes a bundle the server takes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mapserver.bundle import check_bundle_files, sha256_file
from mapserver.cli import main
from mapserver.maps import FREE, OCCUPIED, save_map


@pytest.fixture
def maps(tmp_path: Path) -> tuple[Path, Path]:
    state = np.full((40, 50), FREE, np.uint8)
    state[:2, :] = OCCUPIED
    (tmp_path / "robot" / "img").mkdir(parents=True)
    slam = save_map(tmp_path / "robot" / "map.yaml", state, 0.05, image_name="img/session.pgm")
    nav2 = save_map(tmp_path / "robot" / "global.yaml", state, 0.05, (-1.0, -2.0, 0.0))
    return slam, nav2


def test_bundle_writes_a_complete_bundle_with_checksums(
    tmp_path: Path, maps: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    slam, nav2 = maps
    trajectory = tmp_path / "route.txt"
    trajectory.write_text("# x y yaw\n0 0 0\n1.0, 0.5, 0.1\n")
    out = tmp_path / "out" / "run-0042"
    code = main(
        [
            "bundle",
            "--slam-map", str(slam),
            "--nav2-map", str(nav2),
            "--nav2-pose", "12.3,-4.5,1.5708",
            "--slam-pose=-0.8,0.1,0.02",
            "--trajectory", str(trajectory),
            "--robot", "sedia-01",
            "--stamp", "2026-11-21T10:15:00Z",
            "-o", str(out),
        ]
    )  # fmt: skip
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "bundle.yaml",
        "nav2_map.pgm",
        "nav2_map.yaml",
        "slam_map.pgm",
        "slam_map.yaml",
    ]
    files = check_bundle_files(out)
    manifest = yaml.safe_load((out / "bundle.yaml").read_text())
    assert manifest["robot"] == "sedia-01" and manifest["stamp"] == "2026-11-21T10:15:00Z"
    assert manifest["pose"]["nav2"] == {"x": 12.3, "y": -4.5, "yaw": 1.5708}
    assert manifest["pose"]["slam"] == {"x": -0.8, "y": 0.1, "yaw": 0.02}
    assert manifest["trajectory"] == [
        {"x": 0.0, "y": 0.0, "yaw": 0.0},
        {"x": 1.0, "y": 0.5, "yaw": 0.1},
    ]
    assert manifest["checksums"] == {p.name: sha256_file(p) for p in files.paths()}
    assert (out / "slam_map.pgm").read_bytes() == (slam.parent / "img/session.pgm").read_bytes()
    assert "rsync" in capsys.readouterr().out


def test_bundle_written_in_the_current_folder_uploads_into_a_folder_named_by_its_id(
    tmp_path: Path,
    maps: tuple[Path, Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Session 53's review: `-o .` printed rsync calls to "/srv/inbox//", the inbox's root.
    slam, nav2 = maps
    (tmp_path / "run-0053").mkdir()
    monkeypatch.chdir(tmp_path / "run-0053")
    args = ["bundle", "--slam-map", str(slam), "--nav2-map", str(nav2), "--nav2-pose", "5,5,0"]
    assert main([*args, "--slam-pose", "5,5,0", "-o", ".", "--upload-to", "/srv/inbox/"]) == 0
    out = capsys.readouterr().out.splitlines()
    lines = [line.split() for line in out if line.strip().startswith(("rsync", "&& rsync"))]
    assert [line[-2:] for line in lines] == [
        ["/srv/inbox/run-0053/", "\\"],
        ["./bundle.yaml", "/srv/inbox/run-0053/"],
    ]
    assert lines[0][-3] == "./"


def test_bundle_reads_a_yaml_trajectory_and_leaves_nav2_map_out(
    tmp_path: Path, maps: tuple[Path, Path]
) -> None:
    slam, _ = maps
    trajectory = tmp_path / "route.yaml"
    trajectory.write_text(yaml.safe_dump([{"x": 1, "y": 2, "yaw": 0.5}, [3, 4, 0.25]]))
    out = tmp_path / "b1"
    args = ["--nav2-pose", "1,2,0", "--slam-pose", "0,0,0", "--trajectory", str(trajectory)]
    assert main(["bundle", "--slam-map", str(slam), *args, "-o", str(out)]) == 0
    manifest = yaml.safe_load((out / "bundle.yaml").read_text())
    assert "nav2_map" not in manifest
    assert manifest["trajectory"][1] == {"x": 3.0, "y": 4.0, "yaw": 0.25}


@pytest.mark.parametrize(
    ("output", "extra", "message"),
    [
        ("bad id!", [], "not a valid one"),
        ("taken", [], "not empty"),
        ("b2", ["--trajectory", "route.txt"], "pose 1"),
        ("b3", ["--robot", "no spaces"], "robot"),
        ("b4", ["--nav2-map", "missing.yaml"], "missing.yaml"),
        # Session 53's review: both were written, and refused by the server after the upload.
        (
            "b5",
            ["--nav2-map", "no-resolution.yaml"],
            "no-resolution.yaml: missing key 'resolution'",
        ),
        ("b6", ["--nav2-map", "text.yaml"], "not a PGM or PNG image"),
    ],
)
def test_bundle_refuses_what_the_server_would_reject(
    tmp_path: Path,
    maps: tuple[Path, Path],
    capsys: pytest.CaptureFixture[str],
    output: str,
    extra: list[str],
    message: str,
) -> None:
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "x").write_text("x")
    (tmp_path / "route.txt").write_text("0 0\n")
    good = yaml.safe_load(maps[1].read_text())
    (tmp_path / "robot" / "no-resolution.yaml").write_text(
        yaml.safe_dump({k: v for k, v in good.items() if k != "resolution"})
    )
    (tmp_path / "robot" / "notes.pgm").write_text("a text file saved as a map image\n")
    (tmp_path / "robot" / "text.yaml").write_text(yaml.safe_dump({**good, "image": "notes.pgm"}))
    args = ["--slam-map", str(maps[0]), "--nav2-pose", "1,2,0", "--slam-pose", "0,0,0"]
    here = {"no-resolution.yaml": "robot/no-resolution.yaml", "text.yaml": "robot/text.yaml"}
    extra = [str(tmp_path / here.get(e, e)) if e.endswith((".txt", ".yaml")) else e for e in extra]
    assert main(["bundle", *args, *extra, "-o", str(tmp_path / output)]) == 1
    assert message in capsys.readouterr().err
    assert output == "taken" or not (tmp_path / output).exists()  # nothing half-made


def test_bundle_rejects_a_pose_that_is_not_three_finite_numbers(
    tmp_path: Path, maps: tuple[Path, Path]
) -> None:
    args = ["--slam-map", str(maps[0]), "--slam-pose", "0,0,0", "-o", str(tmp_path / "b")]
    with pytest.raises(SystemExit) as info:
        main(["bundle", *args, "--nav2-pose", "1,nan,0"])
    assert info.value.code == 2
