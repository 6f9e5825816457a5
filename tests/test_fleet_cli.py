"""``mapserver maps`` / ``changes`` and ``process --config`` with a map store: what an operator
types, what it prints, and that a refused command is one line, exit 1, and changes nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mapserver.cli import SAMPLES, main
from mapserver.maps import load_map
from tests.fleet_support import write_building

DEPOT = sorted(SAMPLES.glob("depot-demo-*"))


def config(tmp_path: Path, mode: str = "review") -> Path:
    path = tmp_path / "mapserver.yaml"
    path.write_text(
        yaml.safe_dump({"maps": "maps", "update": {"mode": mode}, "log_level": "WARNING"})
    )
    return path


def run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def tree(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


def test_maps_add_list_show_and_refusals(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(config(tmp_path))
    hall = write_building(tmp_path / "src")
    code, out, _ = run(capsys, "maps", "add", "hall", str(hall), "--config", cfg)
    assert code == 0 and "current.yaml" in out and "keepout.yaml" in out
    code, out, _ = run(capsys, "maps", "list", "--config", cfg)
    assert code == 0 and "hall" in out and "400x240" in out
    code, out, _ = run(capsys, "maps", "show", "hall", "--config", cfg)
    assert code == 0 and "current version 1" in out and "v1 " in out
    before = tree(tmp_path / "maps")
    for args, message in [
        (("maps", "add", "hall", str(hall)), "already in the store"),
        (("maps", "add", "other", str(tmp_path / "nope.yaml")), "nope.yaml"),
        (("maps", "show", "nope"), "no map named 'nope'"),
        (("maps", "rollback", "hall", "7"), "has no version 7"),
        (("changes", "approve", "3"), "no change 3"),
        (("changes", "reject", "3"), "no change 3"),
    ]:
        code, out, err = run(capsys, *args, "--config", cfg)
        assert code == 1 and out == "", args
        assert err.count("\n") == 1 and err.startswith("mapserver: error: ") and message in err, err
    assert tree(tmp_path / "maps") == before
    # Past SQLite's integers: argparse's usage error, not an OverflowError's traceback (session
    # 53's review; the web got its bound the same day).
    for args in (
        ("changes", "approve", "99999999999999999999"),
        ("maps", "rollback", "hall", str(2**63)),
    ):
        with pytest.raises(SystemExit) as done:
            main([*args, "--config", cfg])
        assert done.value.code == 2
        assert "must be at most 9223372036854775807" in capsys.readouterr().err
    assert tree(tmp_path / "maps") == before


def test_the_fleet_commands_need_a_map_store(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("maps: null\n")
    code, _, err = run(capsys, "maps", "list", "--config", str(path))
    assert code == 1 and "maps: null" in err


@pytest.mark.skipif(len(DEPOT) < 3, reason="the depot samples are not shipped")
def test_process_feeds_the_store_in_stamp_order_and_review_waits_for_approval(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(config(tmp_path, "review"))
    assert (
        run(capsys, "maps", "add", "depot", str(DEPOT[0] / "nav2_map.yaml"), "--config", cfg)[0]
        == 0
    )
    # Given newest first: applied by stamp all the same.
    code, out, err = run(
        capsys,
        "process",
        "--config",
        cfg,
        "--outbox",
        str(tmp_path / "out"),
        *map(str, reversed(DEPOT)),
    )
    assert code == 0, err
    assert out.index("depot-demo-01") < out.index("depot-demo-03") < out.index("depot-demo-04")
    result = yaml.safe_load((tmp_path / "out/depot-demo-04/result.yaml").read_text())
    assert result["map"]["name"] == "depot" and result["map"]["version"] == 1
    assert all(isinstance(d["change"], int) for d in result["differences"])
    code, out, _ = run(capsys, "changes", "list", "--state", "confirmed", "--config", cfg)
    confirmed = [int(line.split()[0]) for line in out.splitlines()]
    assert code == 0 and len(confirmed) >= 3
    keepout = load_map(tmp_path / "maps/depot/keepout.yaml")
    assert (keepout.state == 100).sum() > 0  # confirmed added obstacles wait in the mask
    code, out, _ = run(capsys, "changes", "approve", str(confirmed[0]), "--config", cfg)
    assert code == 0 and "version 2 published" in out
    code, _, err = run(capsys, "changes", "approve", str(confirmed[0]), "--config", cfg)
    assert code == 1 and "is published, not confirmed" in err
    code, out, _ = run(capsys, "maps", "rollback", "depot", "1", "--config", cfg)
    assert code == 0 and "version 3, equal to version 1" in out
    v1 = load_map(tmp_path / "maps/depot/v0001.yaml").state
    assert (load_map(tmp_path / "maps/depot/current.yaml").state == v1).all()
