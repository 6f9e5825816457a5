"""Scoring a fleet map's final version (contract section 7), from small hand-built maps and truths.

The grid: 80 rows x 100 columns of 0.05 m, origin (-1.0, 2.0). Cell (row k, col c) has its centre
at x = -1.0 + (c + 0.5) 0.05, y = 2.0 + (80 - k - 0.5) 0.05 (row 0 the top), computed here
independently of the module under test.
"""

from __future__ import annotations

import copy
import itertools
import re
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml

from mapserver.history_scoring import (
    HistoryScore,
    parse_history,
    polygon_mask,
    read_history,
    score_history,
    summarize_histories,
)
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, load_map, save_map
from mapserver.scoring import point_polygon_distance_m

H, W, RES = 80, 100, 0.05
OX, OY = -1.0, 2.0
CELL_M2 = RES * RES
T0 = datetime(2026, 11, 21, 8, 0, tzinfo=timezone.utc)


def centre(row: int, col: int) -> tuple[float, float]:
    return (OX + (col + 0.5) * RES, OY + (H - row - 0.5) * RES)


def block(r0: int, r1: int, c0: int, c1: int) -> list[list[float]]:
    """The outline of the cells rows r0..r1-1, cols c0..c1-1 (on cell edges, no centre on it)."""
    x0, x1 = OX + c0 * RES, OX + c1 * RES
    y_top, y_bottom = OY + (H - r0) * RES, OY + (H - r1) * RES
    return [[x0, y_bottom], [x1, y_bottom], [x1, y_top], [x0, y_top]]


def cells(r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int]]:
    return list(itertools.product(range(r0, r1), range(c0, c1)))


def flat(cell_list: list[tuple[int, int]]) -> list[int]:
    return [r * W + c for r, c in cell_list]


def stamp(t: datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def change(
    id_: int,
    kind: str,
    polygon: list[list[float]],
    *,
    until: datetime | None = None,
    sessions: int = 5,
    span_h: float = 48.0,
    erase: list[int] | None = None,
) -> dict:
    doc = {
        "id": id_,
        "kind": kind,
        "polygon": polygon,
        "from": stamp(T0 - timedelta(hours=1)),
        "until": None if until is None else stamp(until),
        "sessions": sessions,
        "seen_from": stamp(T0) if sessions else None,
        "seen_until": stamp(T0 + timedelta(hours=span_h)) if sessions else None,
    }
    if erase is not None:
        doc["erase"] = erase
    return doc


def history_doc(*changes: dict) -> dict:
    return {"format": 1, "map": "site", "changes": list(changes)}


def free_state() -> np.ndarray:
    state = np.full((H, W), FREE, np.uint8)
    state[:2, :] = UNKNOWN  # some unexplored rows: unknown is a state like the others
    return state


def painted(state: np.ndarray, cell_list: list[tuple[int, int]], value: int = OCCUPIED):
    out = state.copy()
    for r, c in cell_list:
        out[r, c] = value
    return out


@pytest.fixture
def on_disk(tmp_path: Path):
    """Maps as the benchmark reads them: written like map_saver and loaded back."""
    count = itertools.count()

    def make(state: np.ndarray) -> OccupancyMap:
        path = save_map(tmp_path / f"map{next(count)}.yaml", state, RES, (OX, OY, 0.0))
        return load_map(path)

    return make


def score(on_disk, reference: np.ndarray, final: np.ndarray, *changes: dict, **kw) -> HistoryScore:
    return score_history(
        on_disk(reference), on_disk(final), parse_history(history_doc(*changes)), **kw
    )


# --------------------------------------------------------------------------------------------
# Cells of polygons


def test_polygon_mask_is_the_cells_whose_centre_is_inside() -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    expected = np.zeros((H, W), bool)
    expected[30:32, 10:30] = True
    assert np.array_equal(polygon_mask(grid, block(30, 32, 10, 30)), expected)


def test_polygon_mask_includes_centres_on_the_boundary() -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    # Corners on the centres of cells (40, 40) and (44, 49): the outline passes through centres.
    (x0, y0), (x1, y1) = centre(44, 40), centre(40, 49)
    square = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    expected = np.zeros((H, W), bool)
    expected[40:45, 40:50] = True
    assert np.array_equal(polygon_mask(grid, square), expected)


NOTCHED = [[0.03, 2.11], [2.57, 2.4], [1.61, 3.17], [2.2, 5.01], [1.1, 4.2], [0.33, 5.3]]


@pytest.mark.parametrize("grow_m", [0.0, 0.1, 0.3])
def test_polygon_mask_agrees_with_the_point_distance_of_scoring(grow_m: float) -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    mask = polygon_mask(grid, NOTCHED, grow_m=grow_m)
    oracle = np.array(
        [
            [point_polygon_distance_m(centre(r, c), NOTCHED) <= grow_m for c in range(W)]
            for r in range(H)
        ]
    )
    assert mask.any()
    assert np.array_equal(mask, oracle)


def test_polygon_mask_clips_to_the_map() -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    # Half of it hangs over the left edge; another lies wholly outside.
    assert np.count_nonzero(polygon_mask(grid, block(10, 12, -5, 5))) == 2 * 5
    assert not polygon_mask(grid, [[-9.0, -9.0], [-8.0, -9.0], [-8.0, -8.0]]).any()


# --------------------------------------------------------------------------------------------
# Added and temporary changes

WALL = block(30, 32, 10, 30)  # 2 x 20 cells; grown by one cell: rows 29..32, cols 9..30
WALL_CELLS = cells(30, 32, 10, 30)


@pytest.mark.parametrize(
    ("paint", "turned", "held"),
    [
        pytest.param(WALL_CELLS, 40, True, id="wall painted"),
        pytest.param(WALL_CELLS[:3], 3, True, id="3 cells"),
        pytest.param(WALL_CELLS[:2], 2, False, id="2 cells"),
        pytest.param([(29, 12), (32, 20), (29, 9)], 3, True, id="ring and diagonal corner"),
        pytest.param([(28, 12), (28, 13), (33, 20)], 0, False, id="two cells out"),
        pytest.param([(29, 30), (32, 30), (30, 8)], 2, False, id="two ring corners, one two out"),
    ],
)
def test_added_is_held_with_three_cells_of_the_polygon_grown_by_one(
    on_disk, paint: list[tuple[int, int]], turned: int, held: bool
) -> None:
    reference = free_state()
    final = painted(reference, paint)
    s = score(on_disk, reference, final, change(1, "added", WALL))
    (c,) = s.changes
    assert (c.cells, c.of_cells, c.held) == (turned, 4 * 22, held)
    assert c.role == "expected"
    assert s.update_recall == (1.0 if held else 0.0)


def test_added_counts_only_cells_not_occupied_in_the_reference(on_disk) -> None:
    reference = painted(free_state(), [(30, 10), (30, 11)])  # already occupied
    final = painted(reference, [(30, 12), (31, 12)])
    final[30, 13] = UNKNOWN  # unknown is not occupied
    (c,) = score(on_disk, reference, final, change(1, "added", WALL)).changes
    assert (c.cells, c.of_cells, c.held) == (2, 4 * 22 - 2, False)


def test_temporaries_in_the_map(on_disk) -> None:
    reference = painted(free_state(), cells(60, 62, 10, 40))
    gone = T0 + timedelta(hours=30)
    changes = [
        change(1, "temporary", block(10, 14, 10, 14), sessions=1, span_h=0.0),  # painted: in map
        change(2, "temporary", block(10, 14, 30, 34), sessions=0),  # painted 2 cells: not held
        change(3, "added", block(10, 14, 50, 54), until=gone),  # gone, painted: in map
        change(4, "removed", block(60, 62, 10, 20), until=gone, erase=flat(cells(60, 62, 10, 20))),
        change(5, "removed", block(60, 62, 30, 40), until=gone, erase=flat(cells(60, 62, 30, 40))),
    ]
    final = painted(reference, [*cells(11, 13, 11, 13), (11, 31), (11, 32), *cells(11, 12, 50, 54)])
    final = painted(final, cells(60, 62, 10, 20), FREE)  # 4 still shown erased: in map
    s = score(on_disk, reference, final, *changes)
    assert [(c.role, c.held, c.cells) for c in s.changes] == [
        ("temporary", True, 4),
        ("temporary", False, 2),
        ("temporary", True, 4),
        ("temporary", True, 20),
        ("temporary", False, 0),  # 5 came back: the map kept it
    ]
    assert (s.n_temporaries, s.n_temporaries_in_map) == (5, 3)
    assert (s.n_expected, s.update_recall) == (0, 1.0)
    assert s.false_edit_cells == 0


# --------------------------------------------------------------------------------------------
# Removed changes


@pytest.mark.parametrize(
    ("n_erased", "n_gone", "held"),
    [
        pytest.param(30, 9, True, id="30%"),
        pytest.param(30, 8, False, id="27% and < 10 cells"),
        pytest.param(31, 9, False, id="29% and < 10 cells"),
        pytest.param(10, 3, True, id="3 of 10"),
        pytest.param(100, 10, True, id="10 cells"),
        pytest.param(100, 9, False, id="9%, 9 cells"),
        pytest.param(30, 0, False, id="nothing"),
    ],
)
def test_removed_is_held_with_30_percent_or_10_erased_cells_gone(
    on_disk, n_erased: int, n_gone: int, held: bool
) -> None:
    structure = cells(40, 50, 20, 30)[:n_erased]  # row by row, the last row maybe partial
    reference = painted(free_state(), structure)
    final = painted(reference, structure[:n_gone], FREE)
    s = score(
        on_disk,
        reference,
        final,
        change(1, "removed", block(40, 50, 20, 30), erase=flat(structure)),
    )
    (c,) = s.changes
    assert (c.cells, c.of_cells, c.held) == (n_gone, n_erased, held)


def test_removed_counts_only_erased_cells_occupied_in_the_reference(on_disk) -> None:
    structure = cells(40, 42, 20, 30)  # 20 cells, of which 10 are grey (unknown) in the reference
    reference = painted(painted(free_state(), structure[:10]), structure[10:], UNKNOWN)
    final = painted(reference, structure[:2], UNKNOWN)  # unknown is "no longer occupied"
    final = painted(final, structure[2:3], FREE)
    erase = flat(structure) + flat(structure[:4])  # repeats count once
    (c,) = score(
        on_disk, reference, final, change(1, "removed", block(40, 42, 20, 30), erase=erase)
    ).changes
    assert (c.cells, c.of_cells, c.held) == (3, 10, True)


# --------------------------------------------------------------------------------------------
# False edits

# Corners on the centres of cells (40, 40) and (44, 49): distances from the outline to other
# centres are whole multiples of 0.05 m.
_X0, _Y0 = centre(44, 40)
_X1, _Y1 = centre(40, 49)
ON_CENTRES = [[_X0, _Y0], [_X1, _Y0], [_X1, _Y1], [_X0, _Y1]]


@pytest.mark.parametrize(
    ("cell", "distance_m", "false_edit"),
    [
        ((42, 49 + 4), 0.2, False),
        ((42, 49 + 6), 0.3, False),  # the margin is inclusive
        ((42, 49 + 7), 0.35, True),
        ((42, 49 + 10), 0.5, True),
        ((40 - 4, 49 + 4), 0.2 * 2**0.5, False),  # Euclidean, not 4 cells of a square dilation
        ((40 - 5, 49 + 5), 0.25 * 2**0.5, True),
    ],
)
def test_false_edit_is_an_edit_farther_than_0_3_m_from_every_change(
    on_disk, cell: tuple[int, int], distance_m: float, false_edit: bool
) -> None:
    assert point_polygon_distance_m(centre(*cell), ON_CENTRES) == pytest.approx(distance_m)
    reference = free_state()
    final = painted(reference, [cell])
    s = score(on_disk, reference, final, change(1, "added", ON_CENTRES))
    assert s.false_edit_cells == int(false_edit)
    assert s.false_edit_m2 == pytest.approx(false_edit * CELL_M2)


def test_false_edits_are_any_change_of_state_and_their_area(on_disk) -> None:
    reference = painted(free_state(), cells(70, 71, 0, 100))  # a wall along the bottom
    final = painted(reference, cells(70, 71, 60, 63), FREE)  # 3 wall cells gone
    final = painted(final, cells(20, 22, 80, 82), UNKNOWN)  # 4 free cells unknown
    final = painted(final, [(1, 5)], FREE)  # 1 unknown cell free
    final = painted(final, [(40, 44)], OCCUPIED)  # inside the change: not a false edit
    s = score(on_disk, reference, final, change(1, "added", ON_CENTRES))
    assert s.false_edit_cells == 3 + 4 + 1
    assert s.false_edit_m2 == pytest.approx(8 * CELL_M2)


def test_false_edits_spare_every_change_even_temporary_and_unexpected_ones(on_disk) -> None:
    reference = free_state()
    changes = [
        change(1, "temporary", block(10, 12, 10, 12), sessions=1, span_h=0.0),
        change(2, "added", block(10, 12, 30, 32), sessions=1, span_h=0.0),  # not expected
        change(3, "added", block(10, 12, 50, 52), until=T0 + timedelta(hours=3)),  # gone
    ]
    # Each painted 0.125 m beyond its change's polygon: inside the margin.
    final = painted(reference, [(11, 14), (11, 34), (11, 54)])
    s = score(on_disk, reference, final, *changes)
    assert s.false_edit_cells == 0
    final = painted(reference, [(11, 18), (11, 38), (11, 58)])  # 0.325 m beyond: false edits
    assert score(on_disk, reference, final, *changes).false_edit_cells == 3


def test_unchanged_map_scores_no_edit_at_all(on_disk) -> None:
    reference = painted(free_state(), cells(40, 50, 20, 30))
    structure = cells(40, 50, 20, 30)
    changes = [
        change(1, "added", WALL),
        change(2, "removed", block(40, 50, 20, 30), erase=flat(structure)),
    ]
    s = score(on_disk, reference, reference.copy(), *changes)
    assert [(c.held, c.cells) for c in s.changes] == [(False, 0), (False, 0)]
    assert (s.n_expected, s.n_expected_held, s.update_recall, s.false_edit_cells) == (2, 0, 0.0, 0)


# --------------------------------------------------------------------------------------------
# Which changes are expected


@pytest.mark.parametrize(
    ("kind", "sessions", "span_h", "until", "confirm", "role"),
    [
        ("added", 3, 12.0, None, {}, "expected"),
        ("removed", 3, 12.0, None, {}, "expected"),
        ("added", 2, 48.0, None, {}, "unconfirmable"),
        ("added", 3, 11.99, None, {}, "unconfirmable"),
        ("added", 0, 0.0, None, {}, "unconfirmable"),
        ("added", 9, 48.0, T0 + timedelta(hours=60), {}, "temporary"),
        ("temporary", 9, 48.0, T0 + timedelta(hours=60), {}, "temporary"),
        ("temporary", 9, 48.0, None, {}, "temporary"),
        ("added", 2, 5.0, None, {"confirm_sessions": 2, "confirm_span_hours": 5}, "expected"),
        ("added", 3, 12.0, None, {"confirm_sessions": 4}, "unconfirmable"),
        ("added", 3, 12.0, None, {"confirm_span_hours": 12.5}, "unconfirmable"),
    ],
)
def test_expected_means_still_there_and_seen_in_enough_sessions_over_enough_hours(
    on_disk,
    kind: str,
    sessions: int,
    span_h: float,
    until: datetime | None,
    confirm: dict,
    role: str,
) -> None:
    structure = cells(40, 42, 20, 30)
    reference = painted(free_state(), structure)
    erase = flat(structure) if kind == "removed" else None
    doc = change(
        1, kind, block(40, 42, 20, 30), sessions=sessions, span_h=span_h, until=until, erase=erase
    )
    (c,) = score(on_disk, reference, reference, doc, **confirm).changes
    assert c.role == role
    assert c.expected == (role == "expected")


def test_update_recall_and_totals_over_histories(on_disk) -> None:
    reference = free_state()
    two = [change(1, "added", WALL), change(2, "added", block(50, 52, 10, 30))]
    final = painted(reference, [*WALL_CELLS, (75, 90), (75, 91)])  # the first, and 2 false edits
    first = score(on_disk, reference, final, *two)
    assert (first.n_expected, first.n_expected_held, first.update_recall) == (2, 1, 0.5)
    none_expected = score(on_disk, reference, reference, change(1, "temporary", WALL, sessions=1))
    assert (none_expected.n_expected, none_expected.update_recall) == (0, 1.0)
    leak = score(on_disk, reference, painted(reference, WALL_CELLS), change(1, "temporary", WALL))
    total = summarize_histories([first, none_expected, leak])
    assert (total.n_histories, total.n_expected, total.n_expected_held) == (3, 2, 1)
    assert (total.n_temporaries, total.n_temporaries_in_map) == (2, 1)
    assert total.update_recall == 0.5
    assert total.false_edit_cells == 2
    assert total.false_edit_m2 == pytest.approx(2 * CELL_M2)
    assert total.false_edit_m2_max == pytest.approx(2 * CELL_M2)
    empty = summarize_histories([])
    assert (empty.update_recall, empty.false_edit_m2_max) == (1.0, 0.0)


def test_scoring_modifies_neither_map() -> None:
    reference_state = painted(free_state(), cells(40, 50, 20, 30))
    final_state = painted(reference_state, WALL_CELLS)
    reference = from_states(reference_state, RES, (OX, OY, 0.0))
    final = from_states(final_state, RES, (OX, OY, 0.0))
    history = parse_history(
        history_doc(
            change(1, "added", WALL),
            change(2, "removed", block(40, 50, 20, 30), erase=flat(cells(40, 50, 20, 30))),
        )
    )
    score_history(reference, final, history)
    assert np.array_equal(reference.state, reference_state)
    assert np.array_equal(final.state, final_state)


# --------------------------------------------------------------------------------------------
# Bad input


def test_maps_of_different_grids_are_refused() -> None:
    history = parse_history(history_doc(change(1, "added", WALL)))
    reference = from_states(free_state(), RES, (OX, OY, 0.0))
    with pytest.raises(ValueError, match="100 x 79 cells"):
        score_history(reference, from_states(free_state()[1:], RES, (OX, OY, 0.0)), history)
    with pytest.raises(ValueError, match="resolution"):
        score_history(reference, from_states(free_state(), 0.1, (OX, OY, 0.0)), history)
    with pytest.raises(ValueError, match="origin"):
        score_history(reference, from_states(free_state(), RES, (OX + RES, OY, 0.0)), history)


def test_an_erased_cell_outside_the_map_is_refused() -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    history = parse_history(history_doc(change(7, "removed", WALL, erase=[5, H * W])))
    with pytest.raises(ValueError, match=r"change 7: erase holds a cell index outside"):
        score_history(grid, grid, history)


def test_confirm_settings_are_checked() -> None:
    grid = from_states(free_state(), RES, (OX, OY, 0.0))
    history = parse_history(history_doc())
    with pytest.raises(ValueError, match="confirm_sessions"):
        score_history(grid, grid, history, confirm_sessions=0)
    with pytest.raises(ValueError, match="confirm_span_hours"):
        score_history(grid, grid, history, confirm_span_hours=-1.0)


def test_parse_history_reads_the_contract_example() -> None:
    text = """
format: 1
map: site
changes:
  - id: 3
    kind: removed
    polygon: [[0, 0], [1, 0], [1, 1]]
    from: 2026-11-21T10:00:00Z
    until: null
    sessions: 5
    seen_from: "2026-11-21T14:25:00Z"
    seen_until: "2026-11-24T08:25:00+01:00"
    erase: [237486, 237487]
  - kind: temporary
    shape: cart
    polygon: [[0, 0], [1, 0], [1, 1]]
    until: "2026-11-22T10:00:00Z"
    sessions: 0
"""
    history = parse_history(yaml.safe_load(text))
    assert history.map == "site"
    first, second = history.changes
    assert (first.id, first.kind, first.sessions, first.gone) == (3, "removed", 5, False)
    assert first.since == datetime(2026, 11, 21, 10, tzinfo=timezone.utc)
    assert first.span_hours == pytest.approx(3 * 24 - 6 - 1)
    assert first.erase.tolist() == [237486, 237487]
    assert (second.id, second.shape, second.gone, second.span_hours) == (2, "cart", True, None)


BASE = change(1, "removed", WALL, erase=[1, 2])


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(format=2), "unsupported format 2"),
        (lambda d: d.update(map="no/slash"), "history.map must be a map name"),
        (lambda d: d.pop("map"), "missing key 'map'"),
        (lambda d: d.update(changes="all"), "history.changes must be a list"),
        (lambda d: d["changes"][0].update(kind="moved"), r"changes\[0\].kind must be one of"),
        (lambda d: d["changes"][0].pop("until"), r"changes\[0\]: missing key 'until'"),
        (lambda d: d["changes"][0].update(until="yesterday"), r"until must be an ISO 8601 time"),
        (lambda d: d["changes"][0].update(until="2026-11-22T10:00:00"), "must have a zone"),
        (lambda d: d["changes"][0].update(until="2026-11-20T00:00:00Z"), "is before from"),
        (lambda d: d["changes"][0].update(polygon=[[0, 0], [1, 1]]), "at least 3"),
        (lambda d: d["changes"][0].update(polygon=[[0, 0], [1, "a"], [2, 2]]), "at least 3"),
        (lambda d: d["changes"][0].update(polygon=[[0, 0], [1, 1e999], [2, 2]]), "finite"),
        (lambda d: d["changes"][0].update(sessions=-1), r"sessions must be an integer >= 0"),
        (lambda d: d["changes"][0].update(sessions=True), r"sessions must be an integer >= 0"),
        (lambda d: d["changes"][0].update(seen_from=None), "required when sessions > 0"),
        (
            lambda d: d["changes"][0].update(seen_from=stamp(T0 + timedelta(days=9))),
            "before seen_from",
        ),
        (lambda d: d["changes"][0].pop("erase"), r"missing key 'erase'"),
        (lambda d: d["changes"][0].update(erase=[1, -2]), r"erase\[1\] must be an integer >= 0"),
        (lambda d: d["changes"][0].update(erase=[]), "non-empty list"),
        (lambda d: d["changes"].append(copy.deepcopy(d["changes"][0])), "id 1 is used twice"),
    ],
)
def test_parse_history_names_the_bad_field(edit, message: str) -> None:
    doc = history_doc(copy.deepcopy(BASE))
    parse_history(copy.deepcopy(doc))  # the base document is valid
    edit(doc)
    with pytest.raises(ValueError, match=message):
        parse_history(doc)


def test_read_history_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "history.yaml"
    path.write_text(yaml.safe_dump(history_doc(change(1, "added", WALL, sessions=-3))))
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: .*sessions must be"):
        read_history(path)
    path.write_text(yaml.safe_dump(history_doc(change(1, "added", WALL))))
    assert read_history(path).changes[0].kind == "added"
