"""benchmarks/run_sets.py: the benchmark sets issue 12 is measured on, kept in the repository
(``benchmarks/sets.tsv``), and the comparison of two runs over them."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
from bench_support import benchmark_module


@pytest.fixture(scope="module")
def rs() -> Iterator[ModuleType]:
    with benchmark_module("run_sets") as module:
        yield module


def test_every_listed_set_is_one_make_scenarios_can_make(rs: ModuleType, tmp_path: Path) -> None:
    with benchmark_module("make_scenarios") as ms:
        parser = ms.build_parser()
        sets = rs.read_sets(tmp_path, public=True)
        assert [s.name for s in sets[:2]] == ["public", "public-realism"]
        names = [s.name for s in sets]
        assert len(names) == len(set(names))
        for s in sets[2:]:
            assert s.role in ("tuning", "held")
            assert s.path == tmp_path / s.name
            args = parser.parse_args([str(s.path), *s.args])
            # Each case and session option named exists: a typo would make other scenarios
            # (make_scenarios.py says so and exits, through parser.error).
            assert set(args.cases.split(",")) <= set(ms.CASES), s.name
            assert args.count > 0
            ms._parse_overrides(args.override, parser)


def _run(directory: Path, role: str, **sets: tuple[int, int, int, int]) -> None:
    directory.mkdir()
    for name, (matched, observed, correct, fp) in sets.items():
        total = {
            "matched": matched,
            "observed": observed,
            "correct": correct,
            "false_positive": fp,
            "f1": 0.0,
        }
        (directory / f"{name}.json").write_text(json.dumps({"total": total, "role": role}))


def test_compare_names_the_sets_that_moved_and_sums_each_role(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path / "a", "tuning", one=(8, 10, 9, 1), two=(5, 5, 5, 0))
    _run(tmp_path / "b", "tuning", one=(9, 10, 10, 2), two=(5, 5, 5, 0))
    args = type("Args", (), {"before": str(tmp_path / "a"), "after": str(tmp_path / "b")})
    assert rs.compare(args) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("one ") and "found 8 -> 9 / 10" in out[0] and "FP 1 -> 2" in out[0]
    assert out[1] == "1 of 2 sets unchanged"
    # Before: P 14/15, R 13/15; after: P 15/17, R 14/15.
    before_f1 = 2 * (14 / 15) * (13 / 15) / (14 / 15 + 13 / 15)
    after_f1 = 2 * (15 / 17) * (14 / 15) / (15 / 17 + 14 / 15)
    assert out[2] == (
        f"tuning   2 sets: F1 {before_f1:.4f} -> {after_f1:.4f}  found 13 -> 14 / 15  FP 1 -> 2"
    )


def test_compare_sums_each_kind_of_set_too(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The sets of sets.tsv are summed per kind as well: drift123 and drift9191 (one tuning,
    one held out) as ``drifting,long,combo``, s20_1303 apart from them (another sensor)."""
    runs = {"drift123": (8, 10, 9, 1), "drift9191": (5, 5, 5, 0), "s20_1303": (1, 2, 1, 1)}
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        for set_name, (matched, observed, correct, fp) in runs.items():
            total = {"matched": matched, "observed": observed, "correct": correct}
            total |= {"false_positive": fp, "f1": 0.0}
            doc = {"total": total, "role": "held" if set_name == "drift9191" else "tuning"}
            (tmp_path / name / f"{set_name}.json").write_text(json.dumps(doc))
    args = type("Args", (), {"before": str(tmp_path / "a"), "after": str(tmp_path / "b")})
    rs.compare(args)
    out = capsys.readouterr().out.splitlines()
    # P 14/15, R 13/15 for the two drift sets.
    f1 = 2 * (14 / 15) * (13 / 15) / (14 / 15 + 13 / 15)
    assert (
        f"drifting,long,combo  2 sets: F1 {f1:.4f} -> {f1:.4f}  found 13 -> 13 / 15"
        in "\n".join(out)
    )
    assert any(line.startswith("drifting,long,combo, other sensors  1 sets:") for line in out)
    assert rs.kind_of(("--count", "30", "--seed", "99")) == "every case"


def test_a_set_that_fails_leaves_no_numbers_behind(rs: ModuleType, tmp_path: Path) -> None:
    """A stored set that is not there: its line says FAILED and why, and the run's earlier JSON
    document of it is gone (compare would read it as this run's)."""
    missing = rs.BenchSet("gone", "tuning", (), tmp_path / "no-such-set")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "gone.json").write_text("{}")
    done, line = rs._run_one(missing, run_dir, None)
    assert not done and line.startswith("gone") and "FAILED: bench_public.py:" in line
    assert not (run_dir / "gone.json").exists()


def test_compare_says_which_sets_only_one_run_has(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path / "a", "held", one=(5, 5, 5, 0), two=(4, 5, 4, 1))
    _run(tmp_path / "b", "held", one=(5, 5, 5, 0))
    args = type("Args", (), {"before": str(tmp_path / "a"), "after": str(tmp_path / "b")})
    rs.compare(args)
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"two          only in {tmp_path / 'a'}: not compared"
    assert out[1] == "1 of 1 sets unchanged"


def test_census_of_a_set_the_run_does_not_hold_fails_and_says_so(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A set with no outbox in the run: its line says FAILED and why, no counts of it are left
    behind (an earlier census's would be pooled as this one's), and the exit status is 1."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "census").mkdir()
    (run_dir / "census" / "gen99.json").write_text('{"misses": [], "judged": []}')
    args = type(
        "Args",
        (),
        {
            "run_dir": str(run_dir),
            "sets": str(tmp_path / "sets"),
            "only": "gen99",
            "public": False,
            "config": None,
            "all": False,
            "jobs": 1,
        },
    )
    assert rs.census(args) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"gen99        FAILED: no run of it in {run_dir}"
    assert out[1] == "== misses by the stage that lost them"
    assert not (run_dir / "census" / "gen99.json").exists()


def test_table_writes_each_sets_row_and_names_what_it_cannot(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README's rows of totals are found by the set's arguments in backticks (or the
    public set's name), their numbers replaced and their labels kept; every other line is left
    alone, and a set of the run with no row is named (exit status 1)."""

    def total(f1: float, p90: float) -> dict[str, float]:
        return {"precision": 0.9, "recall": 0.8, "f1": f1, "alignment_error_p90_m": p90}

    for name, f1, p90 in (("a", 0.5, 0.04), ("b", 0.75, 0.03)):
        (tmp_path / name).mkdir()
        for set_name in ("public", "gen99", "drift123"):
            doc = {"total": total(f1, p90), "role": "tuning"}
            (tmp_path / name / f"{set_name}.json").write_text(json.dumps(doc))
    readme = tmp_path / "README.md"
    text = (
        "Totals:\n\n| set | precision | recall | F1 | before | p90 |\n|---|---|---|---|---|---|\n"
        "| public (6) | 1 | 1 | 1 | 1 | 0 m (0) |\n"
        "| generated, `--count 30 --seed 99` (tuning) | 1 | 1 | 1 | 1 | 0 m (0) |\n"
        "| `--count 31 --seed 99` | 1 | 1 | 1 | 1 | 0 m (0) |\n"
    )
    readme.write_text(text)
    args = type(
        "Args", (), {"before": str(tmp_path / "a"), "after": str(tmp_path / "b"), "readme": readme}
    )
    assert rs.table(args) == 1
    lines = readme.read_text().splitlines()
    assert lines[:4] == text.splitlines()[:4]
    assert lines[4] == "| public (6) | 0.900 | 0.800 | 0.750 | 0.500 | 0.030 m (0.040) |"
    assert lines[5] == (
        "| generated, `--count 30 --seed 99` (tuning) | 0.900 | 0.800 | 0.750 | 0.500"
        " | 0.030 m (0.040) |"
    )
    assert lines[6] == text.splitlines()[6]  # no set has these arguments
    out = capsys.readouterr().out
    assert "drift123: no row" in out and "2 rows written" in out


def test_compare_pools_the_alignment_error_where_the_true_map_is_rigid(
    rs: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 12's alignment target for sessions without drift: the p90 over the bundles of
    every set whose true map bends under 0.05 m; bent ones, and ones whose scenario does not
    say, are left out; a run from before the record says so."""
    total = {"matched": 1, "observed": 1, "correct": 1, "false_positive": 0, "f1": 1.0}
    rigid = [{"bend_m": 0.01, "alignment_error_m": e / 100} for e in range(1, 11)]
    other = [
        {"bend_m": 0.2, "alignment_error_m": 0.5},
        {"bend_m": None, "alignment_error_m": 0.5},
        {"bend_m": 0.0, "alignment_error_m": None},  # a failed bundle: no transform
    ]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for name, bundles in (("one", rigid[:5] + other), ("two", rigid[5:])):
        (tmp_path / "a" / f"{name}.json").write_text(json.dumps({"total": total}))
        doc = {"total": total, "bundles": bundles}
        (tmp_path / "b" / f"{name}.json").write_text(json.dumps(doc))
    args = type("Args", (), {"before": str(tmp_path / "a"), "after": str(tmp_path / "b")})
    assert rs.compare(args) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    # numpy's p90 of 0.01 .. 0.10 (linear): 0.091.
    assert last == "alignment error p90 where the true map is rigid: - -> 0.0910 m (10 bundles)"
