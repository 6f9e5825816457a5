"""Piecewise alignment: a local map bent beyond what one rigid transform and the smooth warp
explain is aligned in pieces along the route, and the changes in each piece are found."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
import pytest
import yaml
from worlds import changed, office

from mapserver import align as align_stage
from mapserver import piecewise, pipeline
from mapserver.bundle import sha256_file
from mapserver.config import Config
from mapserver.geometry import Transform2D
from mapserver.grid import Grid, resample
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, save_map
from mapserver.pipeline import process_bundle
from mapserver.trust import trust_notice

JUNCTION = (19.0, 5.0)  # nav2 = slam frame west of it; east of it the slam map is turned
BOXES = [(8.0, 2.0, 8.5, 2.5), (30.0, 2.0, 30.5, 2.5)]  # one planted in each piece (nav2)
_RUN = np.zeros((0, 2))  # a piece's route where a test does not need it


def _turn_about(point: tuple[float, float], deg: float) -> Transform2D:
    a = np.array(point)
    d = math.radians(deg)
    return Transform2D(0.0, *(a - Transform2D(d, 0.0, 0.0).apply(a))).compose(
        Transform2D(d, 0.0, 0.0)
    )


def test_route_pieces_cut_the_route_by_length() -> None:
    route = np.stack([np.linspace(0, 50, 101), np.zeros(101)], axis=1)  # 50 m, 0.5 m steps
    runs = piecewise.route_pieces(route, piece_m=20.0)
    assert len(runs) == 2  # 50 / 20 rounds to 2 pieces of 25 m
    assert [float(r[-1, 0] - r[0, 0]) for r in runs] == pytest.approx([25.0, 25.0], abs=0.5)
    assert np.array_equal(runs[0][-1], runs[1][0])  # neighbours share their junction
    with pytest.raises(ValueError, match="piece_m must be > 0, got 0"):
        piecewise.route_pieces(route, piece_m=0)


def test_a_cell_behind_a_wall_belongs_to_the_run_that_saw_it_not_the_nearest() -> None:
    """Two corridors 10 m long (0.05 m cells), one above the other, a wall between them; the
    route runs east along the lower one (run 0), then back west along the upper one (run 1).
    The upper corridor's cells near the wall are nearer, in a straight line, to run 0 (0.4 m
    below the wall) than to run 1 (1 m above it); the robot saw them from run 1."""
    state = np.full((60, 200), UNKNOWN, np.uint8)
    state[2:58, :] = FREE
    state[30, :] = OCCUPIED  # the wall between the corridors (y = 1.5 m)
    state[[1, 58], :] = OCCUPIED
    local = from_states(state, 0.05, (0.0, 0.0, 0.0))
    route = np.array([[0.5, 1.1], [9.5, 1.1], [9.5, 2.5], [0.5, 2.5]])  # y up: row 60 - y/0.05
    runs = [route[:2], route[2:]]
    labels = piecewise.label_cells(local, runs)
    # Away from the turn, and from the wall's own block (0.2 m: the wall seen from both sides).
    upper, lower = labels[4:26, 20:180], labels[35:56, 20:180]
    assert (upper == 1).all() and (lower == 0).all()
    assert (labels[state == UNKNOWN] == -1).all() and (labels[state != UNKNOWN] >= 0).all()


def _seen_at(world: OccupancyMap, points_xy: np.ndarray, range_m: float = 12.0) -> np.ndarray:
    """(H, W) float on the world's grid: the distance (m) from each cell to the nearest of
    ``points_xy`` (N, 2) whose 360-degree lidar sees it (each ray up to the first wall, which
    it sees); inf where none does."""
    grid = Grid.of_map(world)
    best = np.full(grid.shape, np.inf)
    angles = np.radians(np.arange(0.0, 360.0, 0.5))
    steps = np.arange(0.0, range_m, world.resolution / 2)
    for x, y in points_xy:
        px = grid.to_pixel(
            np.stack(
                [x + np.outer(np.cos(angles), steps), y + np.outer(np.sin(angles), steps)], axis=-1
            ).reshape(-1, 2)
        )
        c = np.rint(px[:, 0]).astype(int).reshape(len(angles), -1)
        r = np.rint(px[:, 1]).astype(int).reshape(len(angles), -1)
        inside = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
        wall = np.zeros(r.shape, bool)
        wall[inside] = world.state[r[inside], c[inside]] == OCCUPIED
        keep = inside & (np.cumsum(wall, axis=1) - wall == 0)  # up to the first wall
        dist = np.broadcast_to(steps, r.shape)
        np.minimum.at(best, (r[keep], c[keep]), dist[keep])
    return best


def _moved(mask: np.ndarray, grid: Grid, transform: Transform2D) -> np.ndarray:
    """``mask`` resampled through ``transform`` (as the east part of the slam map is drawn)."""
    state = np.where(mask, OCCUPIED, FREE).astype(np.uint8)
    return resample(state, grid, grid, transform) == OCCUPIED


def _bent_bundle(
    directory: Path,
    bend_deg: float,
    boxes: list[tuple[float, float, float, float]] = BOXES,
    prior_off: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Path:
    """``prior_off``: (metres east, metres north, degrees) the reported nav2 pose is off by."""
    world = office(width_m=40.0, height_m=20.0, seed=3)
    now = changed(world, [("add", *b) for b in boxes])
    grid = Grid.of_map(world)
    # nav2_from_slam: identity west of the junction, turned by BEND_DEG about it east of it.
    bend = _turn_about(JUNCTION, bend_deg)
    west = resample(now.state, grid, grid, Transform2D(0.0, 0.0, 0.0).inverse())
    east = resample(now.state, grid, grid, bend.inverse())
    xy = grid.to_world(
        np.stack(np.meshgrid(np.arange(grid.width), np.arange(grid.height)), axis=-1).reshape(-1, 2)
    )
    # The route along the southern rooms' corridor side, west to east: 36 m, which the pieces
    # (piece_m 20) cut in two at the junction, where the kink is.
    nav2_route = np.stack([np.linspace(1.0, 37.0, 73), np.full(73, JUNCTION[1])], axis=1)
    # A cell takes the drift of the part of the route the lidar saw it from (the nearer one when
    # both did); a cell neither saw, of the part on its side of the junction.
    west_of = nav2_route[:, 0] <= JUNCTION[0]
    d_west = _seen_at(now, nav2_route[west_of][::2])
    d_east = _seen_at(now, nav2_route[~west_of][::2])
    by_side = (xy[:, 0] > JUNCTION[0]).reshape(grid.shape)
    is_east = np.where(np.isfinite(d_west) | np.isfinite(d_east), d_east < d_west, by_side)
    # Each part of the world drawn where its part of the route puts it: the eastern cells turned
    # about the junction, the western ones in place. Where both land on one slam cell, a wall
    # drawn by either stays a wall (slam_toolbox counts the hits); where neither does, unknown.
    east_here = _moved(is_east, grid, bend.inverse())
    west_here = ~is_east
    state = np.full(grid.shape, UNKNOWN, np.uint8)
    state[west_here] = west[west_here]
    over = east_here & (~west_here | (state != OCCUPIED))
    state[over] = east[over]
    local = from_states(state, world.resolution, world.origin)
    directory.mkdir(parents=True)
    save_map(directory / "slam_map.yaml", local.state, local.resolution, local.origin)
    save_map(directory / "nav2_map.yaml", world.state, world.resolution, world.origin)
    slam_route = np.where(
        nav2_route[:, :1] > JUNCTION[0], bend.inverse().apply(nav2_route), nav2_route
    )
    end = slam_route[-1]
    nav2_end = bend.apply(end)  # the pose prior is right where the robot is
    manifest = {
        "format": 1,
        "robot": "test-01",
        "stamp": "2026-11-21T10:15:00Z",
        "slam_map": "slam_map.yaml",
        "nav2_map": "nav2_map.yaml",
        "pose": {
            "nav2": {
                "x": float(nav2_end[0]) + prior_off[0],
                "y": float(nav2_end[1]) + prior_off[1],
                "yaw": bend.theta + math.radians(prior_off[2]),
            },
            "slam": {"x": float(end[0]), "y": float(end[1]), "yaw": 0.0},
        },
        "trajectory": [{"x": float(x), "y": float(y), "yaw": 0.0} for x, y in slam_route],
    }
    names = ["slam_map.yaml", "slam_map.pgm", "nav2_map.yaml", "nav2_map.pgm"]
    manifest["checksums"] = {n: sha256_file(directory / n) for n in names}
    (directory / "bundle.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return directory


def test_a_map_bent_beyond_the_warp_is_compared_in_the_pieces_that_fit(tmp_path: Path) -> None:
    """A 20-degree kink: no rigid fit is trusted, so the whole-map comparison reports nothing.
    In pieces, the piece the pose prior anchors (east) is trusted and its planted box found;
    the western piece is beyond the pieces' search from its neighbour and is left out, and the
    result says which share was compared."""
    bundle = _bent_bundle(tmp_path / "bent", 20.0)
    whole = Config.model_validate({"pipeline": {"align": {"pieces": False}}})
    r = process_bundle(bundle, whole).result
    assert r["alignment"]["trusted"] is False and r["differences"] == []

    outcome = process_bundle(bundle, Config())
    r, a = outcome.result, outcome.result["alignment"]
    assert a["trusted"] is True and a["pieces"] == 2 and a["trusted_pieces"] == 1
    assert 0.3 <= a["trusted_share"] <= 0.7 and a["trusted_area_m2"] > 200
    assert a["theta"] == pytest.approx(math.radians(20.0), abs=0.01)  # the trusted piece's
    notice = trust_notice(a)
    assert notice is not None and notice.startswith("PARTLY TRUSTED alignment: ")
    assert any("aligned in 2 pieces" in w for w in r["warnings"])
    x0, y0, x1, y1 = BOXES[1]
    found = [
        d
        for d in r["differences"]
        if d["kind"] == "added"
        and abs(d["centroid"]["x"] - (x0 + x1) / 2) < 0.4
        and abs(d["centroid"]["y"] - (y0 + y1) / 2) < 0.4
    ]
    assert len(found) == 1, r["differences"]
    # Nothing from the piece left out (the western box stays unreported).
    assert all(d["centroid"]["x"] > 12.0 for d in r["differences"])


def _near(differences: list[dict], box: tuple[float, float, float, float]) -> list[dict]:
    x0, y0, x1, y1 = box
    return [
        d
        for d in differences
        if d["kind"] == "added"
        and abs(d["centroid"]["x"] - (x0 + x1) / 2) < 0.4
        and abs(d["centroid"]["y"] - (y0 + y1) / 2) < 0.4
    ]


SPECK = (33.0, 2.0, 33.1, 2.1)  # 0.01 m2: 4 cells, min_local_cells


def _with(config: Config, section: str, **update: object) -> Config:
    part = getattr(config.pipeline, section).model_copy(update=update)
    return config.model_copy(
        update={"pipeline": config.pipeline.model_copy(update={section: part})}
    )


def test_after_a_drifting_session_specks_are_not_reported(tmp_path: Path) -> None:
    """The same 0.1 m speck is a change in a session that fits, and is not reported after one
    aligned in pieces (drifted_min_area_m2), while the boxes beside it are found in both."""
    boxes = [*BOXES, SPECK]
    config = _with(Config(), "align", fit_check=True)
    straight = process_bundle(_bent_bundle(tmp_path / "straight", 0.0, boxes), config).result
    assert "pieces" not in straight["alignment"]
    assert all(len(_near(straight["differences"], b)) == 1 for b in boxes)

    bent = _bent_bundle(tmp_path / "bent", 12.0, boxes)
    r = process_bundle(bent, config).result
    assert r["alignment"]["pieces"] == 2 and r["alignment"]["trusted"] is True
    assert all(len(_near(r["differences"], b)) == 1 for b in BOXES)
    assert _near(r["differences"], SPECK) == []
    no_floor = _with(config, "diff", drifted_min_area_m2=0.0)
    assert len(_near(process_bundle(bent, no_floor).result["differences"], SPECK)) == 1


@pytest.mark.parametrize("bend_deg", [9.0, 12.0, 15.0])
def test_a_moderate_kink_is_not_trusted_whole(tmp_path: Path, bend_deg: float) -> None:
    """A kink one rigid fit scores over min_score (0.63 at 12 degrees) leaves the far side's
    walls off the building: it is aligned in pieces, and the planted box in each is found
    with nothing else reported."""
    config = _with(Config(), "align", fit_check=True)
    r = process_bundle(_bent_bundle(tmp_path / "bent", bend_deg), config).result
    assert r["alignment"]["trusted"] is True and r["alignment"]["pieces"] == 2
    assert len(r["differences"]) <= 4, len(r["differences"])
    for x0, y0, x1, y1 in BOXES:
        assert any(
            d["kind"] == "added"
            and abs(d["centroid"]["x"] - (x0 + x1) / 2) < 0.4
            and abs(d["centroid"]["y"] - (y0 + y1) / 2) < 0.4
            for d in r["differences"]
        ), (x0, r["differences"])


@pytest.mark.parametrize("bend_deg", [5.0, 7.0, 9.0])
def test_a_kink_the_warp_takes_for_drift_is_checked_without_fit_check(
    tmp_path: Path, bend_deg: float
) -> None:
    """A 5-9 degree kink is trusted whole, the drift warp bending the far side by up to 0.8 m
    (the largest shift it allows): with the fit check only on request (the default before),
    false changes are reported (at least two). A drift correction that large now runs the check
    and aligns the map in pieces too, which find the bend: the two planted boxes and nothing
    else. A session that did not drift does not pay for it."""
    bundle = _bent_bundle(tmp_path / "bent", bend_deg)
    unchecked = _with(Config(), "align", fit_check_drift_m=100.0)
    r = process_bundle(bundle, unchecked).result
    assert "pieces" not in r["alignment"] and r["alignment"]["drift_m"] >= 0.5
    false = [d for d in r["differences"] if not any(_near([d], box) for box in BOXES)]
    assert len(false) >= 2, r["differences"]

    r = process_bundle(bundle, Config()).result
    assert "fit" in r["timings_ms"] and r["alignment"]["pieces"] == 2
    assert r["alignment"]["trusted_pieces"] == 2 and trust_notice(r["alignment"]) is None
    (said,) = [w for w in r["warnings"] if "pieces along the route" in w]
    assert re.search(r"2 trusted: 100% of the observed area \(\d+ m2\) compared$", said), said
    assert len(r["differences"]) <= 4, r["differences"]
    assert all(len(_near(r["differences"], box)) == 1 for box in BOXES)

    straight = process_bundle(_bent_bundle(tmp_path / "straight", 0.0), Config()).result
    assert straight["alignment"]["drift_m"] < 0.2 and "fit" not in straight["timings_ms"]


def test_tiles_off_the_building_where_the_pieces_find_no_bend_are_compared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The fit check can take changes for a bend: a tile of a sparse hall whose only walls are
    new obstacles and a column gone looks like one off the building. Here it flags the tile of
    the eastern box on a straight session. The pieces, aligned for real, find the same
    transform as the whole map (no piece moves its cells 0.5 m from it): no bend, so nothing is
    left out and the map is compared whole (the tile was left out, its box unreported)."""
    real = piecewise.unfit_tiles
    calls: list[int] = []

    def flags_the_east_box(local_state: np.ndarray, *args: object, **kwargs: object) -> np.ndarray:
        unfit = real(local_state, *args, **kwargs)  # type: ignore[arg-type]
        calls.append(int(unfit.sum()))
        unfit[:, unfit.shape[1] * 3 // 4 :] = True  # the east quarter: the box at x = 30 m
        return unfit

    monkeypatch.setattr(piecewise, "unfit_tiles", flags_the_east_box)
    config = _with(Config(), "align", fit_check=True)
    r = process_bundle(_bent_bundle(tmp_path / "straight", 0.0), config).result
    assert calls[0] == 0  # the real check flags nothing on a straight session
    a = r["alignment"]
    assert "pieces" not in a and a["trusted"] is True and "trusted_share" not in a, a
    assert all(len(_near(r["differences"], box)) == 1 for box in BOXES), r["differences"]
    assert not any("left out" in w for w in r["warnings"]), r["warnings"]


def test_departure_is_how_far_a_piece_moves_its_cells_from_the_whole_fit() -> None:
    state = np.full((100, 200), FREE, np.uint8)  # 20 m x 10 m at 0.1 m, origin (0, 0)
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    west, east = np.zeros(state.shape, bool), np.zeros(state.shape, bool)
    west[:, :100], east[:, 100:] = True, True
    identity = Transform2D(0.0, 0.0, 0.0)
    turned = _turn_about((10.0, 0.0), 3.0)  # the east piece turned about its east end
    pieces = piecewise.Pieces(
        (
            piecewise.Piece(0, west, identity, 0.9, True, 50.0, (0.0, 2.5), _RUN, aligned=True),
            piecewise.Piece(1, east, turned, 0.9, True, 50.0, (10.0, 2.5), _RUN, aligned=True),
        ),
        100.0,
    )
    # Its corner farthest from the pivot (10, 0) is (20, 10), 14.1 m away, turned 3 degrees.
    expected = 2 * math.hypot(10.0, 10.0) * math.sin(math.radians(1.5))
    assert piecewise.departure(local, pieces, identity) == pytest.approx(expected, rel=0.02)
    # A piece left out of the chain that aligned on its own shows the bend too; one that did
    # not score shows nothing.
    left_out = dataclasses.replace(pieces.pieces[1], trusted=False)
    with_left_out = piecewise.Pieces((pieces.pieces[0], left_out), 100.0)
    assert piecewise.departure(local, with_left_out, identity) == pytest.approx(expected, rel=0.02)
    unaligned = dataclasses.replace(left_out, score=0.4, aligned=False)
    assert (
        piecewise.departure(local, piecewise.Pieces((pieces.pieces[0], unaligned), 100.0), identity)
        == 0.0
    )
    # One trusted on the structure that did not change scores under min_score, and aligned.
    unchanged = dataclasses.replace(left_out, score=0.4)
    assert piecewise.departure(
        local, piecewise.Pieces((pieces.pieces[0], unchanged), 100.0), identity
    ) == pytest.approx(expected, rel=0.02)


def test_the_reported_transform_carries_the_route_as_the_pieces_do() -> None:
    """Three pieces of a straight 60 m route east: the first two trusted (the second 0.3 m
    north of the first: drift), the third left out with a wrong match 5 m off. The transform
    reported is the least-squares fit of the route carried by the trusted pieces, the left-out
    run carried as its nearest trusted piece carries it: the wrong match weighs nothing, and
    the fit lies between the two trusted transforms, nearer the one that carries two runs."""
    mask = np.zeros((2, 2), bool)
    runs = [np.array([[20.0 * i, 0.0], [20.0 * i + 20.0, 0.0]]) for i in range(3)]
    moves = [Transform2D(0.0, 0.0, 0.0), Transform2D(0.0, 0.0, 0.3), Transform2D(0.5, 5.0, 5.0)]
    pieces = piecewise.Pieces(
        tuple(
            piecewise.Piece(
                i, mask, moves[i], 0.9, i < 2, 100.0, tuple(runs[i][0]), runs[i], aligned=i < 2
            )
            for i in range(3)
        ),
        300.0,
    )
    got = piecewise.fit_rigid(pieces)
    assert got is not None
    # Each run carried as a straight line (a third at y 0, two thirds at y 0.3) is fitted by
    # a small turn; the mean of the carried points moves two thirds of the way north.
    mid = got.apply(np.array([[30.0, 0.0]]))[0]
    assert mid[1] == pytest.approx(0.2, abs=0.01)
    assert abs(got.theta) < math.radians(1.0) and abs(mid[0] - 30.0) < 0.01
    # With no piece trusted there is nothing to report.
    none = piecewise.Pieces(tuple(dataclasses.replace(p, trusted=False) for p in pieces.pieces), 1)
    assert piecewise.fit_rigid(none) is None


def test_the_route_is_drawn_where_each_piece_carries_its_run() -> None:
    """Four pieces of a route east along y = 0: pieces 1 and 3 trusted (3 moved 0.4 m north),
    0 and 2 left out. Piece 0 is carried as piece 1 (its nearest), piece 2, as near to 1 as to
    3, as the later one, 3 (nearer where the robot reported its pose); the runs' shared
    junctions appear once."""
    mask = np.zeros((2, 2), bool)
    runs = [
        np.array([[10.0 * i, 0.0], [10.0 * i + 5.0, 0.0], [10.0 * i + 10.0, 0.0]]) for i in range(4)
    ]
    moves = {1: Transform2D(0.0, 0.0, 0.0), 3: Transform2D(0.0, 0.0, 0.4)}
    wrong = Transform2D(0.3, 5.0, -5.0)
    pieces = piecewise.Pieces(
        tuple(
            piecewise.Piece(
                i,
                mask,
                moves.get(i, wrong),
                0.9,
                i in moves,
                50.0,
                (10.0 * i, 0.0),
                runs[i],
                aligned=i in moves,
            )
            for i in range(4)
        ),
        200.0,
    )
    assert piecewise.carrier(pieces, 0) == moves[1] and piecewise.carrier(pieces, 2) == moves[3]
    route = piecewise.route_nav2(pieces)
    assert route is not None and len(route) == 9  # 4 runs of 3 points, 3 junctions shared
    assert route[:, 0] == pytest.approx(np.arange(0.0, 41.0, 5.0))
    assert route[:, 1] == pytest.approx([0.0] * 5 + [0.4] * 4)
    none = piecewise.Pieces(tuple(dataclasses.replace(p, trusted=False) for p in pieces.pieces), 1)
    assert piecewise.route_nav2(none) is None and piecewise.carrier(none, 0) is None


def test_a_map_compared_in_pieces_reports_the_drift_its_pieces_corrected(tmp_path: Path) -> None:
    """Each trusted piece gets its own drift correction; ``alignment.drift_m`` is the largest of
    them (it said 0 for every bundle aligned in pieces)."""
    config = _with(Config(), "align", fit_check=True)
    a = process_bundle(_bent_bundle(tmp_path / "bent", 12.0), config).result["alignment"]
    assert a["method"].endswith("+pieces") and a["trusted_pieces"] == 2
    assert 0.0 < a["drift_m"] <= Config().pipeline.align.deform_max_shift_m


def _piece(index: int, dx: float, score_ok: bool = True, area: float = 100.0) -> piecewise.Piece:
    """Piece ``index`` of a straight route east along y = 0 (20 m each), moved ``dx`` east."""
    mask = np.zeros((2, 2), bool)
    return piecewise.Piece(
        index,
        mask,
        Transform2D(0.0, dx, 0.0),
        0.9 if score_ok else 0.3,
        score_ok,
        area,
        (20.0 * index, 0.0),
        _RUN,
        aligned=score_ok,
    )


def test_the_largest_chain_of_pieces_that_agree_is_trusted_not_the_one_the_prior_anchors() -> None:
    """The last piece (where the prior anchors the search) took a wrong match 1.5 m off; the
    four before it agree with each other: they are trusted, it is not (only it was, with the
    rest left out for disagreeing with it). A piece that does not score is skipped, not a
    break; two chains apart, the larger wins."""
    pieces = [_piece(i, 0.05 * i) for i in range(4)] + [_piece(4, 1.5)]
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 3}
    pieces[2] = _piece(2, 3.0, score_ok=False)
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 3}
    # A kink between 1 and 2: two chains; the one with more area.
    kinked = [_piece(0, 0.0), _piece(1, 0.0), _piece(2, 2.0, area=150.0), _piece(3, 2.0, area=60)]
    assert piecewise.largest_chain(kinked, agree_m=0.5) == {2, 3}
    assert piecewise.largest_chain([_piece(0, 0.0, score_ok=False)], agree_m=0.5) == set()


def test_a_piece_turned_by_a_wrong_match_is_stepped_over_not_a_break_in_the_chain() -> None:
    """Six pieces of a straight route east; piece 3 found a wrong match turned 4 degrees about
    its start (its junction meets piece 2 within 0.05 m, its end lies 1.4 m off), so piece 4
    does not meet it. Pieces 2 and 4 agree across it (at the middle of its run): 3 is left
    out, the route either side is one chain (it was {0, 1, 2, 3}: 4 and 5 left out with the
    outlier's fault). Two pieces out in a row are a break: the larger side wins."""
    run = lambda i: np.array([[20.0 * i + s, 0.0] for s in (0.0, 10.0, 20.0)])  # noqa: E731

    def piece(i: int, t: Transform2D, area: float = 100.0) -> piecewise.Piece:
        return piecewise.Piece(
            i, np.zeros((2, 2), bool), t, 0.9, False, area, (20.0 * i, 0.0), run(i), aligned=True
        )

    right = Transform2D(0.0, 0.05, 0.0)
    wrong = _turn_about((60.0, 0.0), 4.0)
    pieces = [piece(i, wrong if i == 3 else right) for i in range(6)]
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 4, 5}
    # Without the two beyond it, stepping over 3 gains nothing: the chain keeps it.
    assert piecewise.largest_chain(pieces[:4], agree_m=0.5) == {0, 1, 2, 3}
    # Two wrong in a row (3 and 4, 1.5 m off): two chains, the larger by area wins.
    off = Transform2D(0.0, 1.5, 0.0)
    pieces = [piece(0, right), piece(1, right), piece(2, right), piece(3, off), piece(4, off, 50.0)]
    pieces += [piece(5, right, 200.0), piece(6, right, 200.0)]
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {5, 6}


def test_a_stepped_over_piece_is_measured_across_at_the_middle_of_its_run() -> None:
    """A route whose drift turns each 20 m piece 2 degrees more than the last (neighbours meet
    exactly). Piece 3, a wrong match turned 5 degrees more about its end, meets piece 4 there
    and lies 1.7 m off piece 2 where they join. Pieces 2 and 4 meet at the middle of 3's run
    (their turns about 3's two ends cancel there) but lie 0.7 m apart where 4 starts, and
    1.0 m at the middle of 2's own run: measured across the stepped-over run, the chain steps
    over 3 and holds the rest (before, 3-5 was the heavier chain and 0-2 was left out). An
    unaligned piece beside it widens the stretch measured across: 2 and 5 meet at the middle
    of 3's and 4's runs."""
    truth = _drifted(6, 2.0)
    wrong = truth[3].compose(_turn_about((80.0, 0.0), -5.0))
    pieces = [_on_route(i, wrong if i == 3 else truth[i]) for i in range(6)]
    pieces[5] = dataclasses.replace(pieces[5], area_m2=150.0)
    at = {"middle of 3": (70.0, 0.0), "start of 4": (80.0, 0.0), "middle of 2": (50.0, 0.0)}
    gaps = {k: piecewise.apart(truth[2], truth[4], np.array([v]))[0] for k, v in at.items()}
    assert gaps["middle of 3"] < 0.05 and gaps["start of 4"] > 0.5 and gaps["middle of 2"] > 0.5
    assert piecewise.apart(wrong, truth[2], np.array([[60.0, 0.0]]))[0] > 1.5
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 4, 5}
    # 3 wrong and 4 unaligned: 2 and 5 measured at the middle of 3's and 4's runs, (80, 0).
    truth = _drifted(7, 2.0)
    pieces = [_on_route(i, truth[i]) for i in range(7)]
    pieces[3] = _on_route(3, truth[3].compose(_turn_about((80.0, 0.0), -5.0)))
    pieces[4] = _on_route(4, Transform2D(0.0, 5.0, 0.0), trusted=False)
    assert piecewise.apart(truth[2], truth[5], np.array([[80.0, 0.0]]))[0] < 0.05
    assert piecewise.apart(truth[2], truth[5], np.array([[70.0, 0.0]]))[0] > 0.5
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 5, 6}


def test_pieces_either_side_of_one_that_did_not_align_are_measured_at_the_middle_of_its_run() -> (
    None
):
    """A route whose drift turns each 20 m piece 2 degrees more than the last; piece 3 did not
    align. Pieces 2 and 4 meet at the middle of 3's run but lie 0.7 m apart where 4 starts:
    measured there, they did not meet and the chain stepped over the right piece 2 instead
    ({0, 1, 4, 5}; session 27, seed 7117 `gen-00-drifting`: its piece 3, 0.12 m from piece 2
    where they meet, was stepped over beside piece 4, which did not align)."""
    truth = _drifted(6, 2.0)
    pieces = [_on_route(i, truth[i], trusted=i != 3) for i in range(6)]
    assert piecewise.apart(truth[2], truth[4], np.array([[70.0, 0.0]]))[0] < 0.05
    assert piecewise.apart(truth[2], truth[4], np.array([[80.0, 0.0]]))[0] > 0.5
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 4, 5}
    # Two that did not align: measured at the middle of both runs, (80, 0).
    truth = _drifted(7, 2.0)
    pieces = [_on_route(i, truth[i], trusted=i not in (3, 4)) for i in range(7)]
    assert piecewise.apart(truth[2], truth[5], np.array([[80.0, 0.0]]))[0] < 0.05
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2, 5, 6}
    # Where the later starts is not asked: piece 4 turned 4 degrees about that point (a wrong
    # match turned about its end meets there) lies 0.7 m off piece 2 at the middle of 3's run,
    # and is not joined (tried: joined when either place agrees, seed 6006's `gen-03-drifting`
    # trusted such a piece, 0.8 m off the true route: the bundle aligned 0.110 m off, against
    # 0.007 m measured midway only).
    still, turned = Transform2D(0.0, 0.0, 0.0), _turn_about((80.0, 0.0), 4.0)
    pieces = [_on_route(i, turned if i == 4 else still, trusted=i != 3) for i in range(5)]
    assert piecewise.apart(still, turned, np.array([[80.0, 0.0]]))[0] < 1e-9
    assert piecewise.apart(still, turned, np.array([[70.0, 0.0]]))[0] > 0.5
    assert piecewise.largest_chain(pieces, agree_m=0.5) == {0, 1, 2}


def _on_route(i: int, t: Transform2D, trusted: bool = True) -> piecewise.Piece:
    """Piece ``i`` of a straight route east along y = 0, 20 m each (its run's start, middle and
    end), carried by ``t``; one left out scores 0.3."""
    run = np.array([[20.0 * i, 0.0], [20.0 * i + 10.0, 0.0], [20.0 * i + 20.0, 0.0]])
    mask = np.zeros((2, 2), bool)
    return piecewise.Piece(
        i, mask, t, 0.9 if trusted else 0.3, trusted, 100.0, (20.0 * i, 0.0), run, aligned=trusted
    )


def _drifted(n: int, deg: float) -> list[Transform2D]:
    """The transforms of ``n`` pieces of that route whose drift turns each one ``deg`` more
    than the last, about where it meets the one before (so neighbours meet exactly)."""
    drifted = [Transform2D(0.0, 0.0, 0.0)]
    for i in range(1, n):
        drifted.append(drifted[-1].compose(_turn_about((20.0 * i, 0.0), deg)))
    return drifted


def test_the_chain_grows_with_pieces_aligned_again_from_its_ends() -> None:
    """Pieces 2 and 3 are the chain. Aligned again from 2, piece 1 agrees and joins; 0 does
    not. Beyond 3: 4 does not score and is stepped over; 5, turned 3 degrees about the middle
    of 4's run, meets 3 there (10 m from where 5 starts, 0.52 m apart) and joins; 6 and 7 do
    not join, which ends the growth before 8 (which would) is aligned at all."""

    still = Transform2D(0.0, 0.0, 0.0)
    refits = {
        1: (Transform2D(0.0, 0.1, 0.0), True),
        0: (Transform2D(0.0, 2.0, 0.0), True),
        4: (still, False),
        5: (_turn_about((90.0, 0.0), 3.0), True),
        6: (Transform2D(0.0, 0.0, -1.5), True),
        7: (still, False),
        8: (still, True),
    }
    starts: dict[int, Transform2D] = {}

    pivots: dict[int, int] = {}

    def fit(i: int, start: Transform2D, pivot_at: int) -> piecewise.Piece:
        starts[i], pivots[i] = start, pivot_at
        return _on_route(i, *refits[i])

    # As first aligned: all but the chain took wrong matches from a wrong start.
    pieces = [_on_route(i, Transform2D(0.0, 3.0, 0.0)) for i in range(9)]
    pieces[2], pieces[3] = _on_route(2, still), _on_route(3, still)
    grown, chain = piecewise.grow_chain(pieces, {2, 3}, fit, agree_m=0.5)
    assert chain == {1, 2, 3, 5}
    assert sorted(starts) == [0, 1, 4, 5, 6, 7]
    assert starts[0] == refits[1][0] and starts[1] == still and starts[5] == still
    # Turned about where each meets the chain: its run's end going back, its start going on.
    assert pivots == {1: -1, 0: -1, 4: 0, 5: 0, 6: 0, 7: 0}
    assert grown[1].nav2_from_slam == refits[1][0] and grown[5].nav2_from_slam == refits[5][0]
    assert grown[0] == pieces[0] and grown[4] == pieces[4]
    # Measured where 5 starts, the same turn keeps it out.
    assert piecewise.apart(still, refits[5][0], np.array([[100.0, 0.0]]))[0] > 0.5


def test_a_piece_whose_alignment_again_took_a_wrong_match_joins_with_its_first_fit() -> None:
    """A route east whose drift turns each 20 m piece 1 degree more than the last. The chain
    is pieces 0-3; piece 4, aligned again from piece 3, takes a wrong match 2 m to the side,
    but its first fit (from the route's later pieces) is the drifted truth: it joins with that
    one, and piece 5 (whose alignment again is right) joins after it. A first fit that is
    wrong too (2 m off, or meeting the end but turned off the drift's trend) leaves the piece
    stepped over, as before; when both are right, the alignment again is taken."""
    truth = _drifted(6, 1.0)
    wrong = Transform2D(truth[4].theta, truth[4].tx, truth[4].ty + 2.0)

    def fit(i: int, start: Transform2D, pivot_at: int) -> piecewise.Piece:
        return _on_route(i, wrong if i == 4 else truth[i])

    pieces = [_on_route(i, truth[i]) for i in range(6)]
    grown, chain = piecewise.grow_chain(pieces, {0, 1, 2, 3}, fit, agree_m=0.5)
    assert chain == {0, 1, 2, 3, 4, 5}
    assert grown[4].nav2_from_slam == truth[4]
    pieces[4] = _on_route(4, Transform2D(truth[4].theta, truth[4].tx, truth[4].ty - 2.0))
    grown, chain = piecewise.grow_chain(pieces, {0, 1, 2, 3}, fit, agree_m=0.5)
    assert chain == {0, 1, 2, 3, 5} and grown[4] == pieces[4]
    # A first fit that meets the end but turns 8 degrees off the drift's trend: stepped over.
    pieces[4] = _on_route(4, truth[4].compose(_turn_about((80.0, 0.0), 8.0)))
    assert piecewise.apart(pieces[4].nav2_from_slam, truth[3], np.array([[80.0, 0.0]]))[0] < 0.01
    grown, chain = piecewise.grow_chain(pieces, {0, 1, 2, 3}, fit, agree_m=0.5)
    assert chain == {0, 1, 2, 3, 5} and grown[4] == pieces[4]
    # Both right: the alignment again (from the chain's end) is taken.
    pieces[4] = _on_route(4, Transform2D(truth[4].theta, truth[4].tx, truth[4].ty + 0.1))
    grown, chain = piecewise.grow_chain(
        pieces, {0, 1, 2, 3}, lambda i, t, at: _on_route(i, truth[i]), 0.5
    )
    assert chain == {0, 1, 2, 3, 4, 5} and grown[4].nav2_from_slam == truth[4]


def test_a_piece_turned_off_the_chain_s_drift_does_not_join_it() -> None:
    """A route east along y = 0 in 20 m pieces whose drift turns each one 1.5 degrees more
    than the last, about where it meets the one before (so neighbours meet exactly). Piece 4,
    a wrong match, turns 5.5 degrees the other way about its start: it meets piece 3 where
    they join as well as a right one would, yet it is 7 degrees off the heading the chain's
    drift predicts for it, and is stepped over; piece 5, on the trend, joins across it.
    Without the heading rule, piece 4 joins."""

    drifted = _drifted(6, 1.5)
    wrong = drifted[3].compose(_turn_about((80.0, 0.0), -5.5))
    refits = {4: _on_route(4, wrong), 5: _on_route(5, drifted[5])}

    def fit(i: int, start: Transform2D, pivot_at: int) -> piecewise.Piece:
        return refits[i]

    pieces = [_on_route(i, drifted[i]) for i in range(4)] + [refits[4], refits[5]]
    assert piecewise.heading_trend(pieces[:4], 4) == pytest.approx(math.radians(6.0))
    assert piecewise.apart(wrong, drifted[3], np.array([[80.0, 0.0]]))[0] < 1e-9
    _, chain = piecewise.grow_chain(pieces, {0, 1, 2, 3}, fit, agree_m=0.5)
    assert chain == {0, 1, 2, 3, 5}
    _, without = piecewise.grow_chain(pieces, {0, 1, 2, 3}, fit, agree_m=0.5, max_turn_rad=1.0)
    assert 4 in without


def test_growing_backwards_a_piece_turned_off_the_trend_is_stepped_over() -> None:
    """The same drifting route grown backwards from the chain {2, 3, 4, 5}: piece 1, a wrong
    match turned 5.5 degrees the other way about its run's end (where it meets piece 2), is
    stepped over; piece 0, on the trend, joins across it."""

    drifted = _drifted(6, 1.5)
    # Piece 1 meets piece 2 at (40, 0); turned about that point from piece 2's transform.
    wrong = drifted[2].compose(_turn_about((40.0, 0.0), -1.5 - 5.5))
    refits = {1: _on_route(1, wrong), 0: _on_route(0, drifted[0])}
    pivots: dict[int, int] = {}

    def fit(i: int, start: Transform2D, pivot_at: int) -> piecewise.Piece:
        pivots[i] = pivot_at
        return refits[i]

    pieces = [refits[0], refits[1]] + [_on_route(i, drifted[i]) for i in range(2, 6)]
    chain_back = [pieces[4], pieces[3], pieces[2]]  # growth order going back: the end last
    assert piecewise.heading_trend(chain_back, 1) == pytest.approx(math.radians(1.5))
    assert piecewise.apart(wrong, drifted[2], np.array([[40.0, 0.0]]))[0] < 1e-9
    _, chain = piecewise.grow_chain(pieces, {2, 3, 4, 5}, fit, agree_m=0.5)
    assert chain == {0, 2, 3, 4, 5} and pivots == {1: -1, 0: -1}
    _, without = piecewise.grow_chain(pieces, {2, 3, 4, 5}, fit, agree_m=0.5, max_turn_rad=1.0)
    assert 1 in without


def test_the_route_counts_by_the_ground_it_covered_not_the_time_spent() -> None:
    """Poses recorded while the robot stood still at the start collapse into one point: the
    route 0-10 m east, sampled every 2.5 m of path, is 5 points whatever the pauses."""
    parked = np.array([[0.0, 0.0]] * 50 + [[5.0, 0.0], [10.0, 0.0]])
    pts = piecewise.along_route(parked, 2.5)
    assert pts[:, 0] == pytest.approx([0.0, 2.5, 5.0, 7.5, 10.0])
    assert piecewise.along_route(np.array([[1.0, 2.0]] * 3), 0.1).tolist() == [[1.0, 2.0]]


def test_a_piece_lands_within_a_view_only_with_the_room_to_spare() -> None:
    local = from_states(np.full((40, 60), FREE, np.uint8), 0.1, (0.0, 0.0, 0.0))
    mask = np.zeros((40, 60), bool)
    mask[10:30, 10:50] = True  # x 1..5 m, y 1..3 m
    identity = Transform2D(0.0, 0.0, 0.0)
    piece = piecewise.Piece(0, mask, identity, 0.9, True, 8.0, (0.0, 0.0), _RUN, aligned=True)
    view = Grid(-3.0, -3.0, 0.1, 120, 100)  # x -3..9 m, y -3..7 m: 4 m to spare all round
    assert piecewise.lands_within(local, piecewise.Pieces((piece,), 8.0), view, 2.0)
    assert not piecewise.lands_within(local, piecewise.Pieces((piece,), 8.0), view, 4.5)
    moved = dataclasses.replace(piece, nav2_from_slam=Transform2D(0.0, 3.5, 0.0))  # 0.5 m east
    assert not piecewise.lands_within(local, piecewise.Pieces((moved,), 8.0), view, 2.0)
    # One searched that did not align (its search may have run off the view) is asked; one
    # never searched (too few walls: no score) is not.
    unaligned = dataclasses.replace(moved, score=0.4, trusted=False, aligned=False)
    assert not piecewise.lands_within(local, piecewise.Pieces((unaligned,), 8.0), view, 2.0)
    idle = dataclasses.replace(unaligned, score=0.0)
    assert piecewise.lands_within(local, piecewise.Pieces((idle,), 8.0), view, 2.0)


def test_compose_keeps_only_trusted_pieces_and_marks_the_rest_left_out() -> None:
    state = np.full((40, 60), UNKNOWN, np.uint8)
    state[10:30, 5:55] = 0  # FREE
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    mask_a = np.zeros(state.shape, bool)
    mask_a[:, :30] = True
    identity = Transform2D(0.0, 0.0, 0.0)
    pieces = piecewise.Pieces(
        (
            piecewise.Piece(
                0, mask_a & (state != UNKNOWN), identity, 0.9, True, 5.0, (0, 0), _RUN, aligned=True
            ),
            piecewise.Piece(
                1,
                ~mask_a & (state != UNKNOWN),
                identity,
                0.3,
                False,
                5.0,
                (3, 0),
                _RUN,
                aligned=False,
            ),
        ),
        10.0,
    )
    before = state.copy()
    out, left_out = piecewise.compose(local, pieces, Grid.of_map(local))
    assert np.array_equal(state, before)  # inputs untouched
    assert (out[10:30, 5:30] == 0).all() and (out[:, 30:] == UNKNOWN).all()
    assert left_out[10:30, 30:55].all() and not left_out[:, :30].any()
    assert pieces.trusted_share == pytest.approx(0.5)


def _walls_every(step_px: int, shape: tuple[int, int]) -> np.ndarray:
    walls = np.zeros(shape, bool)
    walls[::step_px, :] = True
    walls[:, ::step_px] = True
    return walls


@pytest.mark.parametrize("shift_px", [0, 15])
def test_unfit_tiles_are_where_the_local_walls_land_off_the_global_ones(shift_px: int) -> None:
    """Rooms of 3 m (0.1 m cells); the local map's east half is shifted by 1.5 m (a bend the
    warp did not take out) or not at all. Only the shifted tiles are unfit; a tile whose own
    walls are a new obstacle beside a removed wall is not."""
    walls = _walls_every(30, (240, 240))
    local_walls = walls.copy()
    local_walls[:, 120:] = np.roll(walls, (shift_px, shift_px), axis=(0, 1))[:, 120:]
    # A new block and a removed wall in one tile of the west half.
    local_walls[62:88, 30:60] = True
    local_walls[60, 0:60] = False
    state = np.where(local_walls, OCCUPIED, FREE).astype(np.uint8)
    before = state.copy()
    unfit = piecewise.unfit_tiles(state, walls, resolution=0.1, tile_m=6.0)
    assert np.array_equal(state, before)
    assert not unfit[:, :120].any()
    # Most of the shifted half (its edge tiles borrow fitting neighbours); one unfit tile is
    # enough for the pipeline to align the map in pieces.
    assert (unfit[:, 120:].mean() > 0.5) if shift_px else not unfit.any()
    with pytest.raises(ValueError, match="resolution must be > 0, got 0"):
        piecewise.unfit_tiles(state, walls, resolution=0)


def test_pieces_start_from_the_whole_map_s_fit_when_the_prior_is_off(tmp_path: Path) -> None:
    """A 12-degree kink and a pose prior 1.5 m and 20 degrees off: the whole-map search finds
    the building but no rigid fit is trusted; the pieces, started from the prior alone, find
    nothing (it is beyond their search), started from the whole map's fit too, both fit."""
    config = _with(Config(), "align", fit_check=True)
    bundle = _bent_bundle(tmp_path / "bent", 12.0, prior_off=(1.5, -1.0, 20.0))
    r = process_bundle(bundle, config).result
    a = r["alignment"]
    assert a["trusted"] is True and a["pieces"] == 2 and a["trusted_pieces"] >= 1, a
    for box in BOXES[a["pieces"] - a["trusted_pieces"] :]:
        assert len(_near(r["differences"], box)) == 1, r["differences"]


def test_a_piece_starts_from_the_fit_it_can_trust_not_the_one_that_scores_more(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One piece aligned from two starts: from the prior, a fit scoring 0.58 and not trusted;
    from the whole map's fit, one scoring 0.5 trusted on the structure that did not change.
    The piece keeps the trusted one (before, it kept the one that scored more)."""
    state = np.full((60, 200), FREE, np.uint8)  # a 20 m x 6 m corridor at 0.1 m
    state[[0, -1], :] = OCCUPIED
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    prior, whole = Transform2D(0.0, 0.0, 0.0), Transform2D(0.0, 0.3, 0.0)
    fits = {
        prior: align_stage.Alignment(prior, "pose+correlative+icp", True, 0.58, 0.58, False),
        whole: align_stage.Alignment(whole, "pose+correlative+icp", True, 0.5, 0.2, True, (), 0.9),
    }
    monkeypatch.setattr(piecewise.align_stage, "align", lambda sub, view, t0, **kw: fits[t0])
    route = np.array([[1.0, 3.0], [19.0, 3.0]])
    view = cast(align_stage.GlobalView, None)  # the faked alignment never reads it
    got = piecewise.align_pieces(local, view, route, prior, also_from=whole, piece_m=20.0)
    assert got is not None and len(got.pieces) == 1
    (piece,) = got.pieces
    assert piece.nav2_from_slam == whole and piece.score == 0.5
    assert piece.aligned and piece.trusted


def _recorded(monkeypatch: pytest.MonkeyPatch, name: str, angle: str) -> list[float]:
    """The ``angle`` keyword (radians) of every call of ``mapserver.align``'s ``name``, from now
    on, in a list that grows as they are made."""
    real = getattr(pipeline.align_stage, name)
    seen: list[float] = []

    def recording(*args: object, **kwargs: object) -> object:
        seen.append(float(kwargs[angle]))  # type: ignore[arg-type]
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline.align_stage, name, recording)
    return seen


def test_a_bent_map_whose_last_piece_confirms_the_prior_skips_the_wide_search(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 20-degree kink, the pose prior right: the narrow search finds no fit of the whole map
    to trust; the last piece, aligned first, puts the robot where the prior does: the map is
    bent, the prior holds, and the wide search (a third of a long drifting route's time) never
    runs; the pieces are timed as their own stage. Pieces that land near the narrow view's edge
    are aligned again on the wide view. The same map with the prior 1.5 m and 20 degrees off:
    the last piece finds nothing near the prior, and the wide search runs."""
    searched = _recorded(monkeypatch, "_search", "theta_half_rad")
    r = process_bundle(_bent_bundle(tmp_path / "right", 20.0), Config()).result
    a = r["alignment"]
    assert a["trusted"] is True and a["pieces"] == 2 and a["trusted_pieces"] == 1, a
    assert max(searched) < math.radians(10.5)  # the narrow search and the pieces' (10 degrees)
    assert {"align", "pieces"} <= set(r["timings_ms"])

    # A piece near the narrow view's edge: the pieces again on the wide view, still no search
    # over the wide angle.
    searched.clear()
    views = _recorded(monkeypatch, "make_view", "search_theta_rad")
    monkeypatch.setattr(piecewise, "lands_within", lambda *args: False)
    a = process_bundle(_bent_bundle(tmp_path / "edge", 20.0), Config()).result["alignment"]
    assert a["trusted"] is True and a["trusted_pieces"] == 1, a
    assert views == [pytest.approx(math.radians(8.0)), pytest.approx(math.radians(35.0))]
    assert max(searched) < math.radians(10.5)

    searched.clear()
    off = _bent_bundle(tmp_path / "off", 12.0, prior_off=(1.5, -1.0, 20.0))
    a = process_bundle(off, Config()).result["alignment"]
    assert a["trusted"] is True
    assert max(searched) == pytest.approx(math.radians(35.0))


def test_compared_whole_when_no_piece_is_trusted_reports_the_share_compared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The whole map's fit is trusted, the fit check sends it to pieces, and none of them is:
    the whole map is compared (less the tiles off the building), and result.yaml says which
    share that was, not 0."""
    real = piecewise.align_pieces

    def none_trusted(*args: object, **kwargs: object) -> piecewise.Pieces | None:
        found = real(*args, **kwargs)  # type: ignore[arg-type]
        if found is None:
            return None
        return dataclasses.replace(
            found, pieces=tuple(dataclasses.replace(p, trusted=False) for p in found.pieces)
        )

    monkeypatch.setattr(piecewise, "align_pieces", none_trusted)
    config = _with(Config(), "align", fit_check=True)
    a = process_bundle(_bent_bundle(tmp_path / "bent", 12.0), config).result["alignment"]
    assert a["trusted"] is True and a["pieces"] == 2 and a["trusted_pieces"] == 0
    assert 0.0 < a["trusted_share"] <= 1.0 and a["trusted_area_m2"] > 0


def _fold_pieces(
    other_index: int = 2,
    other_shift_m: float = 1.0,
    other_run_x: tuple[float, float] = (10.0, 20.0),
    other_score: float = 0.9,
    run_y: float = 5.0,
) -> tuple[OccupancyMap, piecewise.Pieces]:
    """A 20 m x 10 m local map at 0.1 m: the west half one trusted piece (identity, its run
    along y = ``run_y``), and another piece (aligned when ``other_score`` is 0.6 or more) whose
    transform puts everything ``other_shift_m`` north, its run along y = 5 over
    ``other_run_x``."""
    state = np.full((100, 200), FREE, np.uint8)
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    west = np.zeros(state.shape, bool)
    west[:, :100] = True
    run = np.column_stack([np.linspace(0.0, 10.0, 101), np.full(101, run_y)])
    other_run = np.array([[other_run_x[0], 5.0], [other_run_x[1], 5.0]])
    identity = Transform2D(0.0, 0.0, 0.0)
    first = piecewise.Piece(0, west, identity, 0.9, True, 50.0, (0.0, 5.0), run, aligned=True)
    other = piecewise.Piece(
        other_index,
        ~west,
        Transform2D(0.0, 0.0, other_shift_m),
        other_score,
        other_score >= 0.6,
        50.0,
        (other_run_x[0], 5.0),
        other_run,
        aligned=other_score >= 0.6,
    )
    return local, piecewise.Pieces((first, other), 100.0)


def _wall_at_y(y: float) -> Callable[[np.ndarray, float], np.ndarray]:
    return lambda xy, _run_m: np.abs(xy[:, 1] - y) <= 0.15


def test_an_obstacle_another_pass_saw_on_a_wall_is_a_fold_not_a_change() -> None:
    """The west piece's cells at (7.5..8.5, 5) are a wall the other pass saw: through that
    pass's transform (1 m north) they lie on the building's wall at y = 6; through the
    piece's own they stand in open floor."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    local, pieces = _fold_pieces()
    assert piecewise.another_pass_explains(local, pieces, xy, _wall_at_y(6.0))
    # No wall there after that move: a new obstacle.
    assert not piecewise.another_pass_explains(local, pieces, xy, _wall_at_y(7.0))
    # The other pass never came within a lidar's reach (its run 17 m away and more).
    far = _fold_pieces(other_run_x=(25.0, 40.0))
    assert not piecewise.another_pass_explains(*far, xy, _wall_at_y(6.0))
    assert piecewise.another_pass_explains(*far, xy, _wall_at_y(6.0), reach_m=20.0)
    # The piece next on the route meets this one within the chain's agreement, and its run
    # came farther from the cells than the piece's own: not a pass.
    assert not piecewise.another_pass_explains(*_fold_pieces(other_index=1), xy, _wall_at_y(6.0))
    # Two passes that put it only 0.3 m apart: the re-fit's business, not a fold.
    near = _fold_pieces(other_shift_m=0.3)
    assert not piecewise.another_pass_explains(*near, xy, _wall_at_y(5.3))
    # A pass that did not align (under min_score) gives no transform to trust; one trusted on
    # the structure that did not change, under min_score too, does.
    local, weak = _fold_pieces(other_score=0.4)
    assert not piecewise.another_pass_explains(local, weak, xy, _wall_at_y(6.0))
    first, other = weak.pieces
    unchanged = piecewise.Pieces((first, dataclasses.replace(other, aligned=True)), 100.0)
    assert piecewise.another_pass_explains(local, unchanged, xy, _wall_at_y(6.0))


def test_a_pass_s_fit_is_asked_with_how_near_its_run_came() -> None:
    """``fits`` is given the landed points and how near that pass's run came to them: the
    cells' centre (8, 5), the other run from x = 25 m along y = 5: 17 m."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    asked: list[float] = []

    def fits(points: np.ndarray, run_m: float) -> np.ndarray:
        asked.append(run_m)
        return np.abs(points[:, 1] - 6.0) <= 0.15 + 0.02 * run_m

    far = _fold_pieces(other_run_x=(25.0, 40.0))
    assert piecewise.another_pass_explains(*far, xy, fits, reach_m=20.0)
    assert asked == [pytest.approx(17.0)]


def test_a_pass_much_farther_than_the_robots_own_does_not_explain_an_obstacle() -> None:
    """The cells at (7.5..8.5, 5) as above, the other pass's run 2.0 m from their centre, a
    3 m reach. With ``near_ratio`` 4, the piece's own run 1 m from them (y = 4): that pass came
    near enough to have drawn them. The piece's own run 0.4 m from them (y = 4.6): the robot
    saw the place from five times nearer than that pass did, and what it drew there is its
    own view. Within half the reach (a 5 m one), any pass is near enough."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    wall = _wall_at_y(6.0)
    near_own = _fold_pieces(run_y=4.0)
    assert piecewise.another_pass_explains(*near_own, xy, wall, reach_m=3.0, near_ratio=4.0)
    assert not piecewise.another_pass_explains(*near_own, xy, wall, reach_m=3.0, near_ratio=1.5)
    # Never past the reach, however far the piece's own run.
    assert not piecewise.another_pass_explains(*near_own, xy, wall, reach_m=1.8, near_ratio=4.0)
    close_own = _fold_pieces(run_y=4.6)
    assert piecewise.another_pass_explains(*close_own, xy, wall, reach_m=3.0)
    assert not piecewise.another_pass_explains(*close_own, xy, wall, reach_m=3.0, near_ratio=4.0)
    assert piecewise.another_pass_explains(*close_own, xy, wall, reach_m=5.0, near_ratio=4.0)


def _cell(local: OccupancyMap, x: float, y: float) -> tuple[int, int]:
    """(row, col) of the local map's cell at slam point (x, y)."""
    col, row = np.rint(Grid.of_map(local).to_pixel(np.array([[x, y]])))[0]
    return int(row), int(col)


def test_a_structure_alone_seen_gone_from_beside_it_is_no_fold_of_a_far_pass() -> None:
    """A removed column's cells at (7.5..8.5, 5), the whole map seen free: through any pass's
    transform they land on open floor, and that pass did not draw the place open (a fold, as
    far as the landing tells). With ``plain_sight``, the piece's own run 1 m from them (y = 4)
    and the other pass's 6 m (x from 14 m): the robot saw the floor where the column stood,
    from beside it, and the far pass explains nothing. One as near as four times the robot's
    run still does; so does any pass when a local wall stands within 0.5 m of the cells (the
    column drawn again beside its place), when the line from the robot's pose to the cells
    crosses a wall or unseen cells, or when the robot's run came no nearer than 2.5 m."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])

    def on_floor(points: np.ndarray, _run_m: float) -> np.ndarray:
        return np.ones(len(points), bool)

    def not_open(points: np.ndarray) -> np.ndarray:
        return np.zeros(len(points), bool)

    sight = piecewise.PlainSight(run_m=2.5, ratio=4.0, clear_m=0.5)

    def explains(local: OccupancyMap, pieces: piecewise.Pieces, **kw: object) -> bool:
        return piecewise.another_pass_explains(
            local,
            pieces,
            xy,
            on_floor,
            open_there=not_open,
            **kw,  # type: ignore[arg-type]
        )

    local, pieces = _fold_pieces(run_y=4.0, other_run_x=(14.0, 20.0))
    assert explains(local, pieces)
    assert not explains(local, pieces, plain_sight=sight)
    # A pass within four times the robot's run (4 m: its run from x = 12 m) still explains.
    assert explains(*_fold_pieces(run_y=4.0, other_run_x=(12.0, 20.0)), plain_sight=sight)
    # A local wall 0.3 m from the cells: not a structure standing alone.
    walled = from_states(local.state.copy(), 0.1, (0.0, 0.0, 0.0))
    walled.state[_cell(walled, 8.0, 5.3)] = OCCUPIED
    assert explains(walled, pieces, plain_sight=sight)
    # The robot's run 2 m away (y = 3), a wall 1.2 m from the cells across its line of sight.
    local, pieces = _fold_pieces(run_y=3.0, other_run_x=(17.0, 20.0))
    assert not explains(local, pieces, plain_sight=sight)
    blocked = from_states(local.state.copy(), 0.1, (0.0, 0.0, 0.0))
    row, col = _cell(blocked, 7.0, 3.8)
    blocked.state[row, col : col + 20] = OCCUPIED  # y = 3.8, x 7..9
    assert explains(blocked, pieces, plain_sight=sight)
    blocked.state[row, col : col + 20] = UNKNOWN  # never seen there: no sight across them
    assert explains(blocked, pieces, plain_sight=sight)
    # The robot's run 3 m away (y = 2): not beside it.
    assert explains(*_fold_pieces(run_y=2.0, other_run_x=(17.0, 20.0)), plain_sight=sight)


def test_the_piece_next_on_the_route_explains_what_it_passed_nearer_than_the_piece_s_own() -> None:
    """The cells at (7.5..8.5, 5) as above; the other piece is the next one on the route, its
    run from (10, 5) on, 2 m from their centre. The piece's own run along y = 0.5, 4.5 m from
    them: the next piece saw the place from nearer, its transform is the better there, and
    through it they lie on the wall at y = 6. Its own run along y = 4, 1 m from them: the
    piece's own transform is the better, and the next one's move says nothing."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    wall = _wall_at_y(6.0)
    assert piecewise.another_pass_explains(*_fold_pieces(other_index=1, run_y=0.5), xy, wall)
    assert not piecewise.another_pass_explains(*_fold_pieces(other_index=1, run_y=4.0), xy, wall)
    # A run as near as the piece's own: no nearer, the piece's transform stands.
    assert not piecewise.another_pass_explains(*_fold_pieces(other_index=1, run_y=3.0), xy, wall)
    # The piece without a run: nothing to compare with, and the neighbour is not asked.
    local, pieces = _fold_pieces(other_index=1, run_y=0.5)
    first, other = pieces.pieces
    runless = piecewise.Pieces((dataclasses.replace(first, run=np.empty((0, 2))), other), 100.0)
    assert not piecewise.another_pass_explains(local, runless, xy, wall)
    # Not on a wall through the next piece's transform either: a change, wherever its run.
    assert not piecewise.another_pass_explains(
        *_fold_pieces(other_index=1, run_y=0.5), xy, _wall_at_y(7.0)
    )


def test_a_place_a_left_out_pass_came_as_near_to_as_the_piece_s_own_may_be_its_drawing() -> None:
    """Cells at (7.5..8.5, 5) of the west piece (trusted); the other piece did not align (left
    out), its run from (10, 5) on, 2 m from their centre. The west piece's run 1.5 m from them
    (y = 3.5): the left-out pass came within twice that, and the map there may be its drawing.
    The west piece's run 0.5 m from them (y = 4.5): the robot saw the place from four times
    nearer, and it is the trusted piece's."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    assert piecewise.left_out_pass_near(*_fold_pieces(other_score=0.4, run_y=3.5), xy)
    assert not piecewise.left_out_pass_near(*_fold_pieces(other_score=0.4, run_y=4.5), xy)
    assert piecewise.left_out_pass_near(*_fold_pieces(other_score=0.4, run_y=4.5), xy, ratio=5.0)
    # Beyond the sensor's reach that pass drew nothing here.
    far = _fold_pieces(other_score=0.4, run_y=3.5)
    assert not piecewise.left_out_pass_near(*far, xy, reach_m=1.5)
    # A pass that aligned on its own but was left out of the chain (drift turned it past the
    # chain's agreement) is left out too: no trusted transform carries its drawing.
    local, weak = _fold_pieces(other_score=0.4, run_y=3.5)
    first, other = weak.pieces
    broke = piecewise.Pieces((first, dataclasses.replace(other, aligned=True)), 100.0)
    assert piecewise.left_out_pass_near(local, broke, xy)
    # A trusted pass's drawing is in a frame the comparison carries: the fold checks' business.
    assert not piecewise.left_out_pass_near(*_fold_pieces(other_score=0.9, run_y=3.5), xy)
    # The piece the cells belong to has no run to compare with.
    runless = piecewise.Pieces((dataclasses.replace(first, run=np.empty((0, 2))), other), 100.0)
    assert not piecewise.left_out_pass_near(local, runless, xy)
    # Cells no trusted piece holds: nothing to say.
    off = np.column_stack([np.linspace(27.5, 28.5, 11), np.full(11, 5.0)])
    assert not piecewise.left_out_pass_near(*_fold_pieces(other_score=0.4, run_y=3.5), off)


def test_a_structure_both_passes_saw_open_is_a_removal_not_a_fold() -> None:
    """Removed cells at (7.5..8.5, 5): through the other pass's transform (1 m north) they
    land on open floor, as a fold's would. But had that pass seen the structure standing, it
    would have drawn it where its transform takes the building's place back to (y = 4 in the
    slam frame): open there too, both passes saw it gone, and it is a removal."""
    xy = np.column_stack([np.linspace(7.5, 8.5, 11), np.full(11, 5.0)])
    local, pieces = _fold_pieces()

    def on_floor(nav2_xy: np.ndarray, _run_m: float) -> np.ndarray:
        return np.abs(nav2_xy[:, 1] - 5.0) > 0.3

    def open_but_the_wall_at_y4(slam_xy: np.ndarray) -> np.ndarray:
        return np.abs(slam_xy[:, 1] - 4.0) > 0.15

    def open_everywhere(slam_xy: np.ndarray) -> np.ndarray:
        return np.ones(len(slam_xy), bool)

    assert piecewise.another_pass_explains(local, pieces, xy, on_floor)
    assert piecewise.another_pass_explains(
        local, pieces, xy, on_floor, open_there=open_but_the_wall_at_y4
    )
    assert not piecewise.another_pass_explains(
        local, pieces, xy, on_floor, open_there=open_everywhere
    )
    # The other pass's run came within 2.0 m of the cells and 2.24 m of the place back: with a
    # reach between the two, the place back's floor is some other pass's and says nothing.
    assert piecewise.another_pass_explains(
        local, pieces, xy, on_floor, reach_m=2.1, open_there=open_everywhere
    )
    assert not piecewise.another_pass_explains(
        local, pieces, xy, on_floor, reach_m=2.3, open_there=open_everywhere
    )


@pytest.mark.parametrize("seen_m", [8.0, 20.0])
def test_the_sensor_reach_is_how_far_from_the_route_the_map_saw(seen_m: float) -> None:
    """A route along y = 25 m from x = 5 to x = 25 m (0.1 m cells), the map seen free within
    ``seen_m`` of it on either side (a lidar of that range in a hall, walls beyond it) and
    unknown past that: the reach is that range, the farthest cell centre's distance (0.05 m
    less), never more and at most a block's diagonal (0.28 m) less."""
    state = np.full((500, 300), UNKNOWN, np.uint8)  # 30 m x 50 m; row r: y = 50 - (r + 0.5) / 10
    ys = 50.0 - (np.arange(500) + 0.5) * 0.1
    rows = np.abs(ys - 25.0) <= seen_m
    state[rows, 50:250] = FREE  # x 5..25
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    route = np.array([[5.0, 25.0], [15.0, 25.0], [25.0, 25.0]])
    farthest = float(np.abs(ys[rows] - 25.0).max())
    assert farthest - 0.3 <= piecewise.seen_reach_m(local, route) <= farthest
    # Seen only up to 3 m away on the far side of a wall: the map never reached further.
    walled = state.copy()
    walled[np.abs(ys - 25.0) > 3.0, :] = UNKNOWN
    reach = piecewise.seen_reach_m(from_states(walled, 0.1, (0.0, 0.0, 0.0)), route)
    assert 2.95 - 0.3 <= reach <= 2.95
    # Nothing seen, or no route: no reach at all.
    nothing = from_states(np.full((500, 300), UNKNOWN, np.uint8), 0.1, (0.0, 0.0, 0.0))
    assert piecewise.seen_reach_m(nothing, route) == 0.0
    assert piecewise.seen_reach_m(local, np.zeros((0, 2))) == 0.0


def test_the_sensor_reach_of_a_map_whose_size_is_no_multiple_of_the_blocks() -> None:
    """0.05 m cells in 0.2 m blocks, a 333 x 251 cell map (16.65 m x 12.55 m): the last row and
    column of blocks are part padding. Seen only south of a route along y = 9 m, down to the
    map's bottom row (y 0.025 m): the reach is that cell's distance, from the padded blocks."""
    state = np.full((251, 333), UNKNOWN, np.uint8)  # row r: y = 12.55 - (r + 0.5) * 0.05
    ys = 12.55 - (np.arange(251) + 0.5) * 0.05
    state[ys <= 9.0, 20:320] = FREE  # x 1..16
    local = from_states(state, 0.05, (0.0, 0.0, 0.0))
    route = np.array([[1.0, 9.0], [16.0, 9.0]])
    assert 9.0 - 0.025 - 0.3 <= piecewise.seen_reach_m(local, route) <= 9.0 - 0.025


def test_a_route_off_the_map_is_measured_from_the_map_s_edge() -> None:
    """A route 1 m east of the map's east edge (x 10 m), everything within 2 m of the edge seen:
    the reach is about 2 m (the route taken at the edge, nearer than it is), not the distance
    of those cells from the part of the route on the map."""
    state = np.full((200, 100), UNKNOWN, np.uint8)  # 10 m x 20 m; row r: y = 20 - (r + 0.5) / 10
    state[:, 80:] = FREE  # x 8..10
    local = from_states(state, 0.1, (0.0, 0.0, 0.0))
    route = np.array([[5.0, 1.0], [5.0, 2.0], [11.0, 2.0], [11.0, 19.0]])
    assert piecewise.seen_reach_m(local, route) <= 2.0


def _corridor_pieces(
    run_m: float = 20.0,
) -> tuple[OccupancyMap, list[piecewise.Piece]]:
    """A corridor 3 x run_m m long and 4 m wide (0.2 m cells), walls along both sides, cut into
    three pieces of a route east along its middle: 0 and 2 trusted, 1 left out."""
    res, width_m = 0.2, 4.0
    h, w = round(width_m / res), round(3 * run_m / res)
    state = np.full((h, w), FREE, np.uint8)
    state[0, :] = state[-1, :] = OCCUPIED
    local = from_states(state, res, (0.0, 0.0, 0.0))
    xs = (np.arange(w) + 0.5) * res
    pieces = []
    for i in range(3):
        x0 = i * run_m
        run = np.stack([np.linspace(x0, x0 + run_m, 21), np.full(21, width_m / 2)], axis=1)
        mask = np.zeros((h, w), bool)
        mask[:, (xs >= x0) & (xs < x0 + run_m)] = True
        trusted = i != 1
        pieces.append(
            piecewise.Piece(
                i,
                mask,
                Transform2D(0.0, 0.0, 0.0) if trusted else Transform2D(0.0, 2.0, 0.0),
                0.9 if trusted else 0.4,
                trusted,
                float(mask.sum()) * res**2,
                (x0, width_m / 2),
                run,
                aligned=trusted,
            )
        )
    return local, pieces


def _fit_halves(
    shifts: dict[tuple[float, int], float], calls: list[tuple[float, float, int]]
) -> Callable[..., piecewise.Piece]:
    """A fake ``fit_cells``: the half whose run starts at x, aligned about ``pivot_at``,
    lands ``shifts[(x, pivot_at)]`` metres east of its start's transform (0.1 when not
    given), scoring 0.8 (0.7 for the east half); each call is recorded as (x, start's tx,
    pivot)."""

    def fit_cells(
        i: int,
        mask: np.ndarray,
        run: np.ndarray,
        area: float,
        walls: int,
        starts: list[Transform2D],
        pivot_at: int,
    ) -> piecewise.Piece:
        x, start = float(run[0, 0]), starts[0]
        calls.append((x, round(start.tx, 3), pivot_at))
        t = Transform2D(0.0, start.tx + shifts.get((x, pivot_at), 0.1), 0.0)
        score = 0.7 if x >= 30.0 else 0.8
        return piecewise.Piece(i, mask, t, score, False, area, (x, 2.0), run, aligned=True)

    return fit_cells


def test_a_piece_left_out_is_aligned_again_in_halves_from_the_chain_either_side() -> None:
    """Piece 1 did not align whole. Its west half, aligned from piece 0's transform, joins
    (0.1 m off where they meet); its east half, from piece 2's, joins too, and the two meet at
    the middle. The pieces are numbered again in route order, each half holding the cells
    seen from its half of the run."""
    local, pieces = _corridor_pieces()
    calls: list[tuple[float, float, int]] = []
    out = piecewise._split_left_out(local, pieces, _fit_halves({}, calls), 0.5, min_walls=10)
    assert [p.index for p in out] == [0, 1, 2, 3]
    assert [p.trusted for p in out] == [True, True, True, True]
    west, east = out[1], out[2]
    assert (west.run[0, 0], west.run[-1, 0]) == (20.0, 30.0)
    assert (east.run[0, 0], east.run[-1, 0]) == (30.0, 40.0)
    assert not (west.mask & east.mask).any()
    assert np.array_equal(west.mask | east.mask, pieces[1].mask)
    xs = (np.nonzero(west.mask)[1] + 0.5) * 0.2
    assert xs.min() >= 20.0 and xs.max() < 30.5
    # Each half from the trusted piece beside it, turned about where they meet.
    assert calls == [(20.0, 0.0, 0), (30.0, 0.0, -1)]


def test_a_half_beside_no_trusted_piece_joins_from_the_other_half() -> None:
    """Piece 2 is left out too: piece 1's east half is aligned from its west half (turned
    about the middle) and joins. When it lands 0.7 m off the west half it does not."""
    local, pieces = _corridor_pieces()
    pieces[2] = dataclasses.replace(pieces[2], trusted=False, aligned=False)
    calls: list[tuple[float, float, int]] = []
    out = piecewise._split_left_out(local, pieces, _fit_halves({}, calls), 0.5, min_walls=10)
    assert [p.trusted for p in out] == [True, True, True, False]
    assert calls == [(20.0, 0.0, 0), (30.0, 0.1, 0)]
    assert out[2].nav2_from_slam.tx == pytest.approx(0.2)
    off = _fit_halves({(30.0, 0): 0.7}, [])
    out = piecewise._split_left_out(local, pieces, off, 0.5, min_walls=10)
    assert [p.trusted for p in out] == [True, True, False, False]
    assert out[2].nav2_from_slam == pieces[1].nav2_from_slam  # left out as its piece was


def test_halves_that_do_not_meet_where_the_chain_needs_them_to_are_not_both_trusted() -> None:
    """Session 58's review: each half was measured only against the piece it joined from.
    Joined from either side, halves 0.8 m apart at the middle: the better scoring one (the
    west, 0.8 against 0.7) is kept. Joined from the west half, an east half that misses
    piece 2 by 0.8 m at its end is left out."""
    local, pieces = _corridor_pieces()
    apart = _fit_halves({(30.0, -1): 1.0}, [])  # the east half, from piece 2: 1.1 m east
    # It misses piece 2 at its own end, so it does not join from there; from the west half
    # (0.2 m east) it would miss piece 2 by 0.2 m: that one joins.
    out = piecewise._split_left_out(local, pieces, apart, 0.5, min_walls=10)
    assert [p.trusted for p in out] == [True, True, True, True]
    assert out[2].nav2_from_slam.tx == pytest.approx(0.2)
    # Each joins its own side (0.4 m off it, within 0.5 m) but they are 0.8 m apart.
    both = _fit_halves({(20.0, 0): -0.4, (30.0, -1): 0.4, (30.0, 0): 0.9}, [])
    out = piecewise._split_left_out(local, pieces, both, 0.5, min_walls=10)
    assert [p.trusted for p in out] == [True, True, False, True]
    assert out[1].nav2_from_slam.tx == pytest.approx(-0.4)
    # From the west half (0.4 m east), the east half lands 0.8 m east: it meets the west half
    # (0.4 m) but misses piece 2 at its own end (0.8 m): not joined.
    far = _fit_halves({(20.0, 0): 0.4, (30.0, -1): 2.0, (30.0, 0): 0.4}, [])
    out = piecewise._split_left_out(local, pieces, far, 0.5, min_walls=10)
    assert [p.trusted for p in out] == [True, True, False, True]


def test_a_left_out_piece_with_no_cells_is_not_cut() -> None:
    """Session 58's review: a run whose blocks another run took has no cells; cutting it
    crashed the bundle (an empty sub-map)."""
    local, pieces = _corridor_pieces()
    pieces[1] = dataclasses.replace(pieces[1], mask=np.zeros_like(pieces[1].mask), area_m2=0.0)

    def never(*args: object) -> piecewise.Piece:
        raise AssertionError("a piece with no cells was aligned")

    assert piecewise._split_left_out(local, pieces, never, 0.5, min_walls=10) == pieces


def test_a_piece_whose_halves_join_nothing_stays_as_it_was() -> None:
    local, pieces = _corridor_pieces()

    def nowhere(i, mask, run, area, walls, starts, pivot_at):  # type: ignore[no-untyped-def]
        t = Transform2D(0.0, starts[0].tx + 2.0, 0.0)
        return piecewise.Piece(i, mask, t, 0.8, False, area, (0.0, 0.0), run, aligned=True)

    assert piecewise._split_left_out(local, pieces, nowhere, 0.5, min_walls=10) == pieces
    # A piece whose run is under _SPLIT_MIN_RUN_M is not cut at all.
    local, short = _corridor_pieces(run_m=8.0)

    def never(*args: object) -> piecewise.Piece:
        raise AssertionError("a short piece was aligned again")

    assert piecewise._split_left_out(local, short, never, 0.5, min_walls=10) == short
