"""A difference that a small local re-fit of the walls around it explains is a wall seen twice
after drift, not a change (mapserver/refit.py)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pytest

from mapserver import explain
from mapserver.grid import nonzero_cells
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, from_states
from mapserver.refit import (
    Band,
    Faces,
    _best_line_through,
    band_in_structure,
    explained_by_refit,
    face_drawn_in_front,
    faces_seen_from_behind,
    faint_strip,
    floor_seen_share,
    ghost_of_wall,
    line_through_wall,
    spread_across_m,
    thin_line_by_wall,
    wall_drawn_elsewhere,
)

if TYPE_CHECKING:
    from mapserver.cluster import Difference
    from mapserver.maps import OccupancyMap
    from mapserver.piecewise import Pieces

RES = 0.05
KW = {"resolution": RES, "tolerance_m": 0.15, "removed_tolerance_m": 0.25}


def room(shift_px: int = 0) -> np.ndarray:
    """A 4 m x 4 m room with a 1.5 m partition inside, walls 1 px, on a 6 m x 6 m grid, moved
    ``shift_px`` to the right."""
    m = np.zeros((120, 120), bool)
    c = 20 + shift_px
    m[20, c : c + 80] = m[99, c : c + 80] = True
    m[20:100, c] = m[20:100, c + 79] = True
    m[40:70, c + 40] = True  # the partition
    return m


def cells(mask: np.ndarray) -> np.ndarray:
    rows, cols = nonzero_cells(mask)
    return np.stack([rows, cols], axis=1)


def test_a_wall_seen_again_off_where_the_walls_around_it_are_off_too_is_explained() -> None:
    glob = room()
    local = room(shift_px=7)  # this corner of the session drifted 0.35 m
    ghost = np.zeros(glob.shape, bool)
    ghost[40:70, 67] = True  # the partition, seen 0.35 m off: beyond the tolerance
    assert explained_by_refit(cells(ghost), "added", glob, local, **KW)


def test_a_new_obstacle_among_walls_that_fit_is_not_explained() -> None:
    glob = room()
    local = room()
    box = np.zeros(glob.shape, bool)
    box[75:85, 40:50] = True  # 0.5 m box in the room, 1 m from every wall
    local |= box
    assert not explained_by_refit(cells(box), "added", glob, local, **KW)


def test_a_wall_gone_stays_gone_and_a_wall_only_moved_is_explained() -> None:
    glob = room()
    partition = np.zeros(glob.shape, bool)
    partition[40:70, 60] = True
    # The partition removed, the rest of the room where it was drawn: seen free, no fit helps.
    local = room() & ~partition
    assert not explained_by_refit(cells(partition), "removed", glob, local, **KW)
    # The whole room seen 0.35 m off: the partition's cells are free in the local map only
    # because its wall was drawn off with the rest.
    assert explained_by_refit(cells(partition), "removed", glob, room(shift_px=7), **KW)


def test_a_gap_in_a_straight_wall_is_not_explained_by_sliding_the_wall_over_it() -> None:
    """A 0.8 m piece of a long straight wall gone, the wall either side seen where it is drawn:
    sliding those walls 0.4 m along themselves fits them as well and would cover the gap, but
    a wall seen where it is drawn has not moved."""
    glob = np.zeros((120, 200), bool)
    glob[60, 10:190] = True
    gap = np.zeros(glob.shape, bool)
    gap[60, 92:108] = True
    local = glob & ~gap
    assert not explained_by_refit(cells(gap), "removed", glob, local, **KW)
    # The same wall seen 0.35 m off across itself: the gap's cells are free only because of
    # that, and the re-fit that moves it back explains them.
    off = np.roll(glob, 7, axis=0) & ~np.roll(gap, 7, axis=0)
    off_gap = gap & ~off
    assert explained_by_refit(cells(off_gap), "removed", glob, off | np.roll(gap, 7, axis=0), **KW)


def test_a_new_wall_beside_a_solid_block_is_not_explained_by_moving_its_face_into_it() -> None:
    """A block drawn solid (rows 30-79), seen from below: its face and the lower ends of its
    sides. A new wall 0.3 m below the face: a move of the local walls 0.3 m up would cost
    nothing on the block's every cell and lay the new wall on it; on the faces it moves the
    face off its own. The whole block seen 0.3 m low is still a fold the re-fit explains."""
    glob = np.zeros((160, 200), bool)
    glob[30:80, 40:160] = True

    def seen_from_below(down_px: int) -> np.ndarray:
        seen = np.zeros(glob.shape, bool)
        seen[79 + down_px, 40:160] = True
        seen[60 + down_px : 80 + down_px, 40] = seen[60 + down_px : 80 + down_px, 159] = True
        return seen

    new = np.zeros(glob.shape, bool)
    new[85:88, 50:150] = True
    assert not explained_by_refit(cells(new), "added", glob, seen_from_below(0) | new, **KW)
    low = seen_from_below(6)
    face_seen_low = low & ~glob
    face_seen_low[:, [40, 159]] = False
    assert explained_by_refit(cells(face_seen_low), "added", glob, low, **KW)


def _corridor() -> tuple[np.ndarray, np.ndarray]:
    """A straight wall 1 px thick across an 8 m x 4 m grid at 0.05 m (row 40), seen in place by
    the local map."""
    glob = np.zeros((80, 160), bool)
    glob[40, 5:155] = True
    return glob, glob.copy()


@pytest.mark.parametrize(("off_px", "turn_deg"), [(7, 1.0), (15, 1.0), (15, 2.5)])
def test_a_wall_drawn_a_second_time_beside_itself_is_a_ghost(off_px: int, turn_deg: float) -> None:
    glob, local = _corridor()
    # A revisit drew 3 m of the wall again 0.35 or 0.75 m off, as sparse hits, 1 or 2.5 degrees
    # turned.
    cols = np.arange(40, 100, 2)
    ghost = np.zeros(glob.shape, bool)
    turned = np.rint((cols - 40) * math.tan(math.radians(turn_deg))).astype(int)
    assert turned.max() >= 1  # really turned: a row or more over its 3 m
    ghost[40 + off_px + turned, cols] = True
    local |= ghost
    piece = ghost.copy()
    piece[:, 70:] = False  # DBSCAN cut the line in pieces; one of them is judged
    assert ghost_of_wall(cells(piece), ghost, glob, local, resolution=RES, tolerance_m=0.15)


def test_a_new_wall_beside_a_wall_occluding_it_is_no_ghost() -> None:
    """A new partition 0.35 m in front of the wall: the robot, on the open side, sees the new
    one and not the old one behind it; nothing the local map shows in place to be a copy of."""
    glob, local = _corridor()
    new = np.zeros(glob.shape, bool)
    new[47, 40:100] = True
    local[40, 35:105] = False  # occluded behind it
    local |= new
    assert not ghost_of_wall(cells(new), new, glob, local, resolution=RES, tolerance_m=0.15)


def test_a_column_beside_a_wall_seen_twice_is_no_ghost() -> None:
    """The wall drawn again 0.35 m off, and a new column 0.4 m wide against that line: the
    line is a ghost, the column has a depth of its own."""
    glob, local = _corridor()
    added = np.zeros(glob.shape, bool)
    added[47, 40:120] = True
    column = np.zeros(glob.shape, bool)
    column[48:56, 70:78] = True
    added |= column
    local |= added
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert not ghost_of_wall(cells(column), added, glob, local, **kw)
    line = added.copy()
    line[48:, :] = False
    line[:, 60:] = False
    assert ghost_of_wall(cells(line), added, glob, local, **kw)


def test_a_short_line_beside_a_wall_is_no_ghost() -> None:
    """A 0.6 m box face seen 0.35 m from a wall: too short to be a stretch of wall seen again."""
    glob, local = _corridor()
    face = np.zeros(glob.shape, bool)
    face[47, 60:72] = True
    local |= face
    assert not ghost_of_wall(cells(face), face, glob, local, resolution=RES, tolerance_m=0.15)


def test_a_new_box_beside_a_wall_seen_twice_is_no_ghost() -> None:
    """A 0.2 x 0.3 m box 0.7 m from a ghost line: the line lands on the wall when moved, the
    box does not (it is near the line, not on it)."""
    glob, local = _corridor()
    ghost = np.zeros(glob.shape, bool)
    ghost[47:49, 20:140] = True
    box = np.zeros(glob.shape, bool)
    box[62:66, 76:82] = True
    added = ghost | box
    local |= added
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert not ghost_of_wall(cells(box), added, glob, local, **kw)
    assert ghost_of_wall(cells(ghost & (np.arange(160) < 80)), added, glob, local, **kw)


def _copy_beside_box(copy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The corridor with its wall drawn again where ``copy`` (bool, its shape) says, and a new
    0.5 m box 0.7-1.2 m below that copy: the global walls, the local map's walls, the added
    cells (copy and box) and the box."""
    glob, local = _corridor()
    box = np.zeros(glob.shape, bool)
    box[64:74, 50:60] = True
    added = copy | box
    local |= added
    return glob, local, added, box


@pytest.mark.parametrize("piece_cols", [(40, 110), (60, 68)])
def test_a_wall_drawn_again_stays_a_ghost_beside_a_new_box(piece_cols: tuple[int, int]) -> None:
    """A revisit drew 3.5 m of the wall again 0.4 m off, and a new 0.5 m box stands 1 m from
    that copy, within reach: the line is the one through the difference (the whole copy, or a
    0.4 m piece of it that DBSCAN cut off) that holds the most added cells, so the box neither
    turns it nor makes it look thick; the box itself is no line."""
    ghost = np.zeros((80, 160), bool)
    ghost[48:50, 40:110] = True
    glob, local, added, box = _copy_beside_box(ghost)
    piece = ghost.copy()
    piece[:, : piece_cols[0]] = piece[:, piece_cols[1] :] = False
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert ghost_of_wall(cells(piece), added, glob, local, **kw)
    assert not ghost_of_wall(cells(box), added, glob, local, **kw)


def test_a_piece_of_a_copy_drawn_as_sparse_hits_stays_a_ghost_beside_a_new_box() -> None:
    """The copy drawn as a hit every other cell, the box as before: a 0.4 m piece of it is a
    row of 5 cells, elongated, and the line follows it (the box holds more cells than any line
    through the piece along the copy)."""
    ghost = np.zeros((80, 160), bool)
    ghost[48, 40:110:2] = True
    glob, local, added, _ = _copy_beside_box(ghost)
    piece = ghost.copy()
    piece[:, :60] = piece[:, 69:] = False
    assert np.count_nonzero(piece) == 5
    assert ghost_of_wall(cells(piece), added, glob, local, resolution=RES, tolerance_m=0.15)


def test_a_compact_piece_of_a_thick_copy_lies_on_the_line_that_holds_most_cells() -> None:
    """A copy three cells thick, and a piece of it three cells across and two along: too
    compact for a direction of its own (its main axis runs across the copy); the line through
    it that holds the most added cells is the copy's."""
    glob, local = _corridor()
    ghost = np.zeros(glob.shape, bool)
    ghost[47:50, 40:110] = True
    local |= ghost
    piece = np.zeros(glob.shape, bool)
    piece[47:50, 60:62] = True
    assert ghost_of_wall(cells(piece), ghost, glob, local, resolution=RES, tolerance_m=0.15)


def test_the_line_through_a_point_that_holds_the_most_points() -> None:
    """A row of 40 points 30 degrees off the row axis through the origin, and a block of 100
    points off it: the line through the origin along the row holds the row, not the block."""
    t = np.arange(-20, 20, dtype=float)
    angle = math.radians(30.0)
    row = np.stack([t * math.cos(angle), t * math.sin(angle)], axis=1)
    block = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0)), axis=-1).reshape(-1, 2)
    block += (30.0, -30.0)
    held = _best_line_through(np.concatenate([row, block]), np.zeros(2), half_width=1.0)
    assert held[:40].all() and not held[40:].any()


def test_a_slanted_wall_drawn_again_stays_a_ghost_beside_a_new_box() -> None:
    """The same along a wall 20 degrees off the grid's axes: the copy 0.4 m across it, the box
    1 m from the copy."""

    def rows_of(c: np.ndarray, down: int) -> np.ndarray:
        return np.rint(20 + (c - 10) * math.tan(math.radians(20.0))).astype(int) + down

    glob = np.zeros((100, 160), bool)
    c = np.arange(10, 150)
    glob[rows_of(c, 0), c] = True
    local = glob.copy()
    ghost = np.zeros(glob.shape, bool)
    cg = np.arange(40, 110)
    ghost[rows_of(cg, 8), cg] = True  # 8 rows down: 0.4 m x cos 20 degrees across
    box = np.zeros(glob.shape, bool)
    box[62:72, 40:50] = True
    added = ghost | box
    local |= added
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert ghost_of_wall(cells(ghost), added, glob, local, **kw)
    assert not ghost_of_wall(cells(box), added, glob, local, **kw)


def _column_hall() -> tuple[np.ndarray, np.ndarray]:
    """A 6 m hall (global states) with a 0.5 m column in it; and the column's cells."""
    glob = np.full((120, 120), FREE, np.uint8)
    column = np.zeros(glob.shape, bool)
    column[50:60, 50:60] = True
    glob[column] = OCCUPIED
    return glob, column


def test_a_column_gone_has_its_floor_seen_all_round() -> None:
    glob, column = _column_hall()
    local = np.full(glob.shape, FREE, np.uint8)  # the robot drove round where it stood
    assert floor_seen_share(cells(column), glob, local, resolution=RES) == 1.0


def test_free_cells_inside_a_column_whose_floor_went_unseen_were_laid_there_by_a_fold() -> None:
    glob, column = _column_hall()
    # A revisit's part of the map, its drift different, laid open space over the column; the
    # column's faces and the floor 0.15 m around them were never seen (grey in the slam map).
    local = np.full(glob.shape, FREE, np.uint8)
    local[47:63, 47:63] = UNKNOWN
    local[column] = FREE
    assert floor_seen_share(cells(column), glob, local, resolution=RES) == 0.0
    # Half of the floor around seen: half the share.
    local[47:63, 55:63] = FREE
    share = floor_seen_share(cells(column), glob, local, resolution=RES)
    assert 0.4 < share < 0.6


def _band() -> tuple[np.ndarray, np.ndarray]:
    """A building with a solid wall 1.25 m thick (rows 20-44 at 0.05 m) across an 80 x 80
    grid, and a local map that saw the floor on both sides of it."""
    walls = np.zeros((80, 80), bool)
    walls[20:45] = True
    local = np.full((80, 80), UNKNOWN, np.uint8)
    local[:20], local[45:] = FREE, FREE
    return walls, local


def _cells(rows: slice, cols: slice) -> np.ndarray:
    mask = np.zeros((80, 80), bool)
    mask[rows, cols] = True
    return np.stack(nonzero_cells(mask), axis=1)


def test_free_cells_in_a_solid_wall_between_faces_seen_from_both_sides_are_a_fold() -> None:
    """Drift drew the wall's top face on its bottom one (row 44): one line, floor seen free
    below it, and above it the top pass's floor laid inside the solid wall."""
    walls, local = _band()
    local[20:44] = FREE
    local[44] = OCCUPIED
    faces = faces_seen_from_behind(
        _cells(slice(26, 41), slice(10, 70)), walls, local, resolution=0.05
    )
    assert faces.walls >= 60 and faces.behind_share > 0.95
    assert faces.depth_m == pytest.approx(0.6, abs=0.06)  # row 32: 12-13 cells from a face


def test_a_cut_into_a_solid_wall_ends_on_a_face_with_the_solid_behind_it() -> None:
    """The top 0.65 m of the wall removed over 3 m: the robot above saw into the cut, down to
    its new face (row 33), and nothing behind that face."""
    walls, local = _band()
    local[20:33, 20:60] = FREE
    local[33, 20:60] = OCCUPIED
    local[20:34, 19] = OCCUPIED
    local[20:34, 60] = OCCUPIED
    faces = faces_seen_from_behind(
        _cells(slice(20, 31), slice(22, 58)), walls, local, resolution=0.05
    )
    assert faces.walls >= 40 and faces.behind_share < 0.2
    assert faces.depth_m >= 0.4


def test_a_thin_wall_removed_lies_no_depth_into_the_structure() -> None:
    """A 0.15 m wall between two rooms, 1 m of it gone: its ends are seen from both rooms,
    yet the removed cells lie within a cell or two of the floor."""
    walls = np.zeros((80, 80), bool)
    walls[40:43] = True
    local = np.full((80, 80), FREE, np.uint8)
    local[40:43, :30], local[40:43, 50:] = OCCUPIED, OCCUPIED
    faces = faces_seen_from_behind(
        _cells(slice(40, 43), slice(30, 50)), walls, local, resolution=0.05
    )
    assert faces.depth_m <= 0.1
    # Nor are its walls seen from behind: the wall goes on along its line behind its ends.
    assert faces.behind_share < 0.1


def _band_or_cut(*, cut: bool, edge: int = OCCUPIED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The wall of ``_band`` (rows 20-44), the robot below it (rows 45 on seen free), and
    removed cells at its bottom face, bounded above by the local map's ``edge`` state: its
    bottom face drawn 0.3 m inside it over 3 m (rows 39-44 seen free, row 38 a wall: drift left
    in the pass below), or, with ``cut``, a half disc 1.2 m across cut out of it, its curved
    new face drawn. The global walls, the local states and the removed cells."""
    walls, local = _band()
    gone = np.zeros(walls.shape, bool)
    if cut:
        rr, cc = np.mgrid[:80, :80]
        gone = walls & ((rr - 44) ** 2 + (cc - 40) ** 2 <= 12**2)
        face = walls & ~gone & ((rr - 44) ** 2 + (cc - 40) ** 2 <= 13**2)
    else:
        gone[39:45, 10:70] = True
        face = np.zeros(walls.shape, bool)
        face[38, 10:70] = True
    local[gone], local[face] = FREE, edge
    return walls, local, cells(gone)


def test_a_face_drawn_inside_its_structure_leaves_a_long_shallow_walled_band() -> None:
    walls, local, gone = _band_or_cut(cut=False)
    band = band_in_structure(gone, walls, local, resolution=RES)
    # Row 39, six cells from the floor: 6 x 0.955 (the 3x3 chamfer's step) x 0.05 m.
    assert band.depth_m == pytest.approx(0.2865, abs=0.001)
    assert band.length_m == pytest.approx(3.0, abs=0.01)  # 60 cells
    assert band.inner == 62 and band.walled_share == 1.0  # row 38, 60 cells and two corners
    assert explain._face_displaced(band, RES)


def test_a_band_whose_inner_edge_went_unseen_is_no_face() -> None:
    walls, local, gone = _band_or_cut(cut=False, edge=UNKNOWN)
    band = band_in_structure(gone, walls, local, resolution=RES)
    assert band.inner == 62 and band.walled == 0
    assert not explain._face_displaced(band, RES)


def test_a_half_disc_cut_out_of_a_structure_is_twice_as_long_as_it_is_deep() -> None:
    walls, local, gone = _band_or_cut(cut=True)
    band = band_in_structure(gone, walls, local, resolution=RES)
    assert band.depth_m == pytest.approx(0.6, abs=0.06)
    assert band.length_m == pytest.approx(1.25, abs=0.01)  # 25 cells along the face
    assert band.walled_share > 0.9  # its new face drawn all round
    assert not explain._face_displaced(band, RES)


def test_a_gap_through_a_thin_wall_has_no_inner_edge() -> None:
    """The 0.15 m wall of a corridor, 1 m of it gone: floor on both sides, nothing of the
    structure deeper than the gap beside it (its ends lie as deep as it)."""
    walls = np.zeros((80, 80), bool)
    walls[40:43] = True
    local = np.full((80, 80), FREE, np.uint8)
    local[40:43, :30], local[40:43, 50:] = OCCUPIED, OCCUPIED
    band = band_in_structure(_cells(slice(40, 43), slice(30, 50)), walls, local, resolution=RES)
    assert band.inner == 0 and band.walled_share == 0.0


def test_a_cut_through_a_wall_beside_a_junction_has_a_few_inner_cells_not_a_row() -> None:
    """A 0.3 m wall (rows 37-42) with another joining it from below (cols 60-65), cut
    through by a disc 1.2 m across next to the junction: the junction's cells beside the cut
    lie deeper than it, two of them, not an edge along it. Long, shallow and walled there, it
    is still a gap."""

    walls = np.zeros((80, 80), bool)
    walls[37:43] = True
    walls[43:, 60:66] = True
    rr, cc = np.mgrid[:80, :80]
    gone = walls & ((rr - 40) ** 2 + (cc - 52) ** 2 <= 12**2)
    local = np.full((80, 80), FREE, np.uint8)
    local[walls & ~gone] = OCCUPIED
    band = band_in_structure(cells(gone), walls, local, resolution=RES)
    assert band.length_m >= explain._BAND_LENGTH_RATIO * band.depth_m
    assert band.inner == 2 and band.walled_share == 1.0
    assert not explain._face_displaced(band, RES)


@pytest.mark.parametrize(
    ("length_m", "depth_m", "inner", "walled", "displaced"),
    [
        (1.0, 0.4, 10, 8, True),  # 2.5 times as long as deep, its inner edge walled
        (1.0, 0.41, 10, 8, False),  # deeper: a piece cut out
        (1.0, 0.4, 100, 80, True),  # 80 % walled
        (1.0, 0.4, 100, 79, False),
        (1.0, 0.4, 9, 9, False),  # an inner edge along under half of it
    ],
)
def test_a_displaced_face_is_long_shallow_and_walled(
    length_m: float, depth_m: float, inner: int, walled: int, displaced: bool
) -> None:

    assert explain._face_displaced(Band(depth_m, length_m, inner, walled), 0.05) is displaced


@pytest.mark.parametrize(
    ("cut", "in_pieces", "kept"),
    [
        (False, True, 0),  # a face seen displaced, after an alignment in pieces
        (False, False, 1),  # a map the warp fits whole: not asked
        (True, True, 1),  # a half disc cut out
    ],
)
def test_the_re_fit_drops_a_displaced_face_and_keeps_a_cut(
    cut: bool, in_pieces: bool, kept: int
) -> None:
    """Also what is lost with the displaced faces: a band 0.3 m deep and 3 m long really gone
    from a wall's face (a shelf removed from against it, drawn joined to it) is the first case
    too, and after an alignment in pieces is not reported."""
    from mapserver.cluster import cluster_mask
    from mapserver.grid import Grid

    walls, local, gone = _band_or_cut(cut=cut)
    glob = np.where(walls, OCCUPIED, FREE).astype(np.uint8)
    mask = np.zeros(walls.shape, bool)
    mask[gone[:, 0], gone[:, 1]] = True
    (found,) = cluster_mask(mask, Grid(0.0, 0.0, RES, 80, 80), "removed", eps_m=0.1, min_samples=1)
    slam_map = from_states(local, RES, (0.0, 0.0, 0.0))
    assert len(_refit(found, glob, local, RES, slam_map, None, in_pieces=in_pieces)) == kept


def test_a_removed_piece_with_no_floor_near_it_has_nothing_to_miss() -> None:
    glob = np.full((120, 120), OCCUPIED, np.uint8)  # inside a thick structure
    piece = np.zeros(glob.shape, bool)
    piece[50:60, 50:60] = True
    local = np.full(glob.shape, UNKNOWN, np.uint8)
    local[piece] = FREE
    assert floor_seen_share(cells(piece), glob, local, resolution=RES) == 1.0


def _column_seen_through_a_band(*, in_pieces: bool) -> list[Difference]:
    """The pipeline's re-fit of a removed column seen free through a band of rays, the floor
    on either side of the band in shadow (unknown), after a drift correction of 0.3 m; the
    differences it keeps."""
    from mapserver.cluster import Difference

    glob, column = _column_hall()
    local = np.full(glob.shape, UNKNOWN, np.uint8)
    local[:, 52:58] = FREE  # the band the robot looked along, 0.3 m wide, through the column
    seen = column & (local == FREE)
    gone = Difference("removed", (2.75, 3.25), (2.6, 3.0, 2.9, 3.5), 0.15, 60, cells(seen))
    slam_map = from_states(local, RES, (0.0, 0.0, 0.0))
    return _refit(gone, glob, local, RES, slam_map, None, in_pieces=in_pieces)


def _refit(
    found: Difference,
    glob: np.ndarray,
    local_state: np.ndarray,
    res: float,
    slam_map: OccupancyMap,
    pieces: Pieces | None,
    *,
    in_pieces: bool,
) -> list[Difference]:
    """The re-fit (``explain.unexplained``) of difference ``found`` of a local map aligned onto
    the global states ``glob`` (local states ``local_state`` on the same grid at ``res``, its
    origin at 0, 0), compared in ``pieces`` when ``in_pieces`` (in none that holds its cells
    when those are None), else whole; the differences it keeps."""
    from mapserver import piecewise
    from mapserver.align import GlobalView
    from mapserver.config import Config
    from mapserver.grid import Grid

    view = GlobalView(Grid(0.0, 0.0, res, glob.shape[1], glob.shape[0]), glob, glob == OCCUPIED)
    compared = None
    if in_pieces:
        compared = pieces if pieces is not None else piecewise.Pieces((), 0.0)
    no_added = np.zeros(glob.shape, bool)

    def reach_m() -> float:
        # As the pipeline's: how far from the route (the pieces' runs joined) the map saw.
        if pieces is None:
            return 0.0
        route = np.concatenate([piece.run for piece in pieces.pieces])
        return piecewise.seen_reach_m(slam_map, route)

    return explain.unexplained(
        [found], view, local_state, compared, no_added, Config(), slam_map, reach_m
    )


def test_a_removal_seen_through_a_narrow_band_is_kept_when_the_map_fits_whole() -> None:
    # Its floor beside the band unseen (share 0.6): a fold only where a map was aligned
    # in pieces, a narrow view where the smooth warp fitted the map whole.
    assert len(_column_seen_through_a_band(in_pieces=False)) == 1
    assert _column_seen_through_a_band(in_pieces=True) == []


def _wall_seen_free(*, folded: bool, behind: int = FREE) -> list[Difference]:
    """The pipeline's re-fit of free cells in a wall 0.6 m thick (rows 30-41 at 0.05 m) across
    a 4 m hall, with corridors seen free on both sides. ``folded``: the wall drawn as one line
    on its south face (row 41), its inside unseen but for its northern 0.3 m seen free over 3 m
    (the north pass's floor laid inside it: a shallow fold, 0.3 m deep at most); ``behind``: the
    map's state south of that line, the corridor. Else a real gap: 1 m of the wall gone through
    its whole thickness, the wall either side drawn as its two faces."""
    from mapserver.cluster import cluster_mask
    from mapserver.grid import Grid

    glob = np.full((80, 80), FREE, np.uint8)
    glob[30:42] = OCCUPIED
    local = np.full(glob.shape, FREE, np.uint8)
    local[30:42] = UNKNOWN
    gone = np.zeros(glob.shape, bool)
    if folded:
        local[41] = OCCUPIED
        local[42:46] = behind
        gone[30:36, 10:70] = True
    else:
        local[[30, 41]] = OCCUPIED
        gone[30:42, 30:50] = True
    local[gone] = FREE
    (found,) = cluster_mask(gone, Grid(0.0, 0.0, RES, 80, 80), "removed", eps_m=0.1, min_samples=1)
    slam_map = from_states(local, RES, (0.0, 0.0, 0.0))
    return _refit(found, glob, local, RES, slam_map, None, in_pieces=False)


def test_a_wall_drawn_on_one_face_with_its_other_part_seen_free_is_a_fold() -> None:
    """Shallower than the depth floor (0.4 m), but the line's far side seen free all along it:
    two faces drawn on one line. This gap through the wall is kept: the wall's faces either
    side of it go on along their lines, the wall behind the cells next to the gap."""
    assert _wall_seen_free(folded=True) == []
    assert len(_wall_seen_free(folded=False)) == 1
    # The line's far side unseen: nothing says a second face was drawn on it.
    assert len(_wall_seen_free(folded=True, behind=UNKNOWN)) == 1


@pytest.mark.parametrize(
    ("walls", "seen_behind", "depth_m", "fold"),
    [
        (20, 18, 0.1, True),  # 1 m of wall, 90 % seen behind: at any depth
        (20, 17, 0.1, False),  # 85 %, shallow
        (19, 19, 0.1, False),  # 0.95 m of wall: too little to say
        (20, 12, 0.4, True),  # 60 %, deep inside the structure
        (20, 11, 0.4, False),
        (19, 19, 0.5, False),
    ],
)
def test_the_fold_asks_more_of_the_faces_the_shallower_it_lies(
    walls: int, seen_behind: int, depth_m: float, fold: bool
) -> None:

    assert explain._folded(Faces(walls, seen_behind, depth_m), 0.05) is fold


def test_a_line_spreads_less_across_itself_than_a_block_or_a_corner() -> None:
    def spread(mask: np.ndarray) -> float:
        return spread_across_m(cells(mask), resolution=RES)

    grid = np.zeros((40, 40), bool)
    along = grid.copy()
    along[10, 5:35] = True  # one cell wide, along a grid axis
    assert spread(along) == pytest.approx(0.0)
    slanted = grid.copy()
    for i in range(30):
        slanted[5 + round(i * 0.4), 5 + i] = True  # 22 degrees: a staircase
    assert 0.0 < spread(slanted) < 0.5 * RES
    stairs = grid.copy()
    for i in range(15):
        stairs[5 + i, 5 + i] = stairs[5 + i, 6 + i] = True  # 45 degrees, 4-connected
    assert 0.0 < spread(stairs) < 0.5 * RES
    two = grid.copy()
    two[10:12, 5:35] = True  # two cells wide: half a cell
    assert spread(two) == pytest.approx(np.std(np.repeat([0, 1], 30), ddof=1) * RES)
    block = grid.copy()
    block[10:20, 10:20] = True  # 0.5 m x 0.5 m: the spread of rows 0..9, either way
    assert spread(block) == pytest.approx(np.std(np.repeat(np.arange(10), 10), ddof=1) * RES)
    corner = grid.copy()
    corner[10, 10:30] = corner[10:30, 10] = True  # an L of 1 m arms: a box seen from a corner
    assert spread(corner) > 0.1
    assert spread_across_m(np.array([[3, 4]]), resolution=RES) == 0.0
    held = cells(corner)
    kept = held.copy()
    spread_across_m(held, resolution=RES)
    assert np.array_equal(held, kept)  # a pure function: its input untouched


def _refit_in_pieces(
    kind: str,
    other_run_x: tuple[float, float],
    *,
    other_drew: int = OCCUPIED,
    wall_beside: bool = False,
    seen_north_m: float = 0.0,
    own_run_x: tuple[float, float] = (0.0, 10.0),
    added_rows: tuple[int, int] = (49, 51),
    wall_rows: tuple[int, int] = (39, 41),
    removed_wall_rows: tuple[int, int] | None = None,
) -> list[Difference]:
    """The pipeline's re-fit, in a 20 m x 10 m hall aligned in two pieces, of one difference at
    x 7.5..8.5 m, y 5 m (a block 0.4 m deep in the building there; a wall along y = 6 m
    for the added kind, none for the removed), of the west piece (identity). An added one
    holds rows ``added_rows`` (y 4.9..5.1 by default; row r is y = 10 - (r + 0.5) * 0.1), the
    wall rows ``wall_rows`` (for the removed kind, ``removed_wall_rows``: none by default). The
    other piece
    (third on the route) puts everything 1 m north; its run lies along y = 5 m over
    ``other_run_x``. ``other_drew``: the local map's state where that pass would have drawn
    the block (1 m south, y 4 m in the slam frame): OCCUPIED, it saw it standing; FREE, it saw
    the place open too; UNKNOWN, it did not see it. ``wall_beside``: a local wall 0.1-0.2 m south
    of the place back (within ``tolerance_m``, 0.15 m, of half of it). ``seen_north_m``:
    the slam map also saw that far north of the hall (seen free; a sensor that reaches
    further than the hall's 5 m). ``own_run_x``: the west piece's run, two points along
    y = 5 m (by default 2 m from the difference's centre, at x = 10 m)."""
    from mapserver import piecewise
    from mapserver.cluster import Difference
    from mapserver.geometry import Transform2D

    res = 0.1
    glob = np.full((100, 200), FREE, np.uint8)  # row r: y = 10 - (r + 0.5) * 0.1
    glob[48:52, 70:90] = OCCUPIED  # the block, y 4.8..5.2
    if kind == "added":
        glob[48:52, 70:90] = FREE
        glob[slice(*wall_rows), :] = OCCUPIED  # the wall, by default y 5.9..6.1
    elif removed_wall_rows is not None:
        glob[slice(*removed_wall_rows), :] = OCCUPIED
    drawn = np.full((100, 200), FREE, np.uint8)
    drawn[58:62, 70:90] = other_drew  # y 3.8..4.2
    if wall_beside:
        drawn[61, 70:90] = OCCUPIED  # y 3.85
    # Rows put north of the hall keep every row's y (the map's origin is its south-west corner).
    north = round(seen_north_m / res)
    drawn = np.concatenate([np.full((north, 200), FREE, np.uint8), drawn])
    local = from_states(drawn, res, (0.0, 0.0, 0.0))
    west = np.zeros(drawn.shape, bool)
    west[:, :100] = True
    pieces = piecewise.Pieces(
        (
            piecewise.Piece(
                0,
                west,
                Transform2D(0.0, 0.0, 0.0),
                0.9,
                True,
                50.0,
                (0.0, 5.0),
                np.array([[own_run_x[0], 5.0], [own_run_x[1], 5.0]]),
                aligned=True,
            ),
            piecewise.Piece(
                2,
                ~west,
                Transform2D(0.0, 0.0, 1.0),
                0.9,
                True,
                50.0,
                (other_run_x[0], 5.0),
                np.array([[other_run_x[0], 5.0], [other_run_x[1], 5.0]]),
                aligned=True,
            ),
        ),
        100.0,
    )
    state = np.full(glob.shape, FREE, np.uint8)
    where = np.zeros(glob.shape, bool)
    where[slice(*added_rows) if kind == "added" else slice(49, 51), 75:85] = True
    if kind == "added":
        state[where] = OCCUPIED
    n = int(np.count_nonzero(where))
    found = Difference(kind, (8.0, 5.0), (7.5, 4.9, 8.5, 5.1), n * res**2, n, cells(where))
    return _refit(found, glob, state, res, local, pieces, in_pieces=True)


@pytest.mark.parametrize("kind", ["added", "removed"])
def test_a_difference_another_pass_saw_as_the_building_is_a_fold(kind: str) -> None:
    # The other pass came within 2 m: through its transform the added cells lie on the wall
    # at y = 6, the removed ones' floor on open floor. That pass's view, drawn here by slam.
    assert _refit_in_pieces(kind, (10.0, 20.0)) == []
    # Its run 17 m away and more, where the map shows nothing seen further than 5 m from the
    # route: no lidar of it saw the place; the difference stands.
    assert len(_refit_in_pieces(kind, (25.0, 40.0))) == 1


@pytest.mark.parametrize("kind", ["added", "removed"])
def test_the_other_pass_counts_as_far_as_the_sensor_saw(kind: str) -> None:
    """The other pass's run 17 m from the difference: a lidar that saw 25 m from the route
    (the map seen 20 m north of the hall; the route is the runs joined in order, x 0..40 m
    along y = 5) saw the place from there, and that pass explains it; one whose map reaches
    10 m did not. The map's reach is a lower bound of the sensor's (walls close in): a pass
    11 m off counts whatever it says, a common lidar's 12 m."""
    # The robot's own run 5 m from the difference (x 0..3 m): that pass, 17 m off, is not
    # more than four times as far (see the next test).
    own = (0.0, 3.0)
    assert _refit_in_pieces(kind, (25.0, 40.0), seen_north_m=20.0, own_run_x=own) == []
    assert len(_refit_in_pieces(kind, (25.0, 40.0), seen_north_m=5.0, own_run_x=own)) == 1
    assert _refit_in_pieces(kind, (19.0, 30.0), own_run_x=own) == []


def test_an_obstacle_the_robot_saw_from_near_is_not_a_far_pass_fold() -> None:
    """The other pass's run 17 m from the difference, a lidar that saw 25 m: past half its
    reach. The robot's own run came to 2 m from it: an added one there is what the robot saw
    from near (a pass more than four times as far drew nothing over it) and stays."""
    own = (0.0, 6.0)  # the run's end 2 m from it (distances are to the run's points)
    assert len(_refit_in_pieces("added", (25.0, 40.0), seen_north_m=20.0, own_run_x=own)) == 1
    # That pass 11 m off (x from 19 m), more than four times 2 m but within half the 24.9 m
    # reach: it saw the place as well.
    assert _refit_in_pieces("added", (19.0, 30.0), seen_north_m=20.0, own_run_x=own) == []


def test_a_removal_seen_from_beside_it_across_open_floor_is_not_a_far_pass_fold() -> None:
    """As above, removed: the block stood alone (no local wall within 0.5 m of it; where the
    other pass would have drawn it, 0.8 m south, it did) and the robot's own run came to 2 m of
    it across cells seen free: no pass more than four times as far explains it, however near
    within the reach (piecewise.PlainSight, session 56). The robot's run 3 m from it: its free
    cells may be drawn by rays from afar, and the far pass explains it, as before."""
    own = (0.0, 6.0)
    assert len(_refit_in_pieces("removed", (25.0, 40.0), seen_north_m=20.0, own_run_x=own)) == 1
    assert len(_refit_in_pieces("removed", (19.0, 30.0), seen_north_m=20.0, own_run_x=own)) == 1
    # A pass 8 m off (x from 16 m), four times the robot's run: it explains it.
    assert _refit_in_pieces("removed", (16.0, 30.0), seen_north_m=20.0, own_run_x=own) == []
    farther = (0.0, 5.0)  # the run's end 3 m from it
    assert _refit_in_pieces("removed", (25.0, 40.0), seen_north_m=20.0, own_run_x=farther) == []
    assert len(_refit_in_pieces("added", (25.0, 40.0), seen_north_m=20.0, own_run_x=farther)) == 1


def test_a_pass_lays_a_line_on_a_wall_looser_than_an_obstacle_with_a_depth() -> None:
    """The other pass's transform lays the added cells 0.2-0.3 m from the wall (it stands at
    y 6.2..6.3 m, row 37). A line of them (y 4.9..5.0, landing 0.3 m off) is that pass's wall
    with the drift of its piece left in: a fold. A block 0.4 m deep (y 4.9..5.3, landing 0-0.3
    m off, half of it beyond the 0.15 m tolerance, one cell at 0.1 m) is not what a pass draws
    of a wall, and laid that near one only by coincidence: it stays."""
    line = _refit_in_pieces("added", (10.0, 20.0), added_rows=(50, 51), wall_rows=(37, 38))
    assert line == []
    block = _refit_in_pieces("added", (10.0, 20.0), added_rows=(47, 51), wall_rows=(37, 38))
    assert len(block) == 1
    # The same block laid within the tolerance (a wall y 6.0..6.2 m, rows 38-39) is a fold.
    assert _refit_in_pieces("added", (10.0, 20.0), added_rows=(47, 51), wall_rows=(38, 40)) == []


def test_a_line_a_far_pass_drew_lands_off_the_wall_by_its_range_times_a_degree() -> None:
    """A line (y 4.9..5.0, row 50) that the other pass's transform lays 5 cells (0.5 m,
    centre to centre) south of a wall (y 6.4..6.5 m, row 35). That pass's run 2 m from it:
    0.3 m and 2 m times sin(1 degree) allowed, 3 cells: not a fold. Its run 17 m away (a lidar
    that saw 25 m, the robot's own run 5 m off): what it drew there is off by its heading error
    over 17 m, 0.3 m more (6 cells), and the line is that pass's wall. A wall 8 cells off is
    beyond that too. A block 0.4 m deep (rows 47-50, landing 2-5 cells from a wall at row 36)
    lands within the tolerance or not at all, however far the pass: no allowance for its range."""
    far = {"seen_north_m": 20.0, "own_run_x": (0.0, 3.0)}
    line, block = (50, 51), (47, 51)
    assert len(_refit_in_pieces("added", (10.0, 20.0), added_rows=line, wall_rows=(35, 36))) == 1
    assert _refit_in_pieces("added", (25.0, 40.0), added_rows=line, wall_rows=(35, 36), **far) == []
    beyond = _refit_in_pieces("added", (25.0, 40.0), added_rows=line, wall_rows=(32, 33), **far)
    assert len(beyond) == 1
    deep = _refit_in_pieces("added", (25.0, 40.0), added_rows=block, wall_rows=(36, 37), **far)
    assert len(deep) == 1


def test_a_removal_a_far_pass_lays_on_open_floor_gets_no_allowance_for_its_range() -> None:
    """A removed difference's floor must land off every wall by twice the tolerance, however
    far the pass: the other pass's run 17 m away lays it (rows 49-50) 4 cells (0.4 m) from a
    wall at row 35, on open floor, and it is a fold. Its range widens what counts as on a wall
    for an added line only; here it would put the floor on the wall and keep the removal."""
    far = {"seen_north_m": 20.0, "own_run_x": (0.0, 3.0)}
    assert _refit_in_pieces("removed", (25.0, 40.0), removed_wall_rows=(34, 36), **far) == []
    # The same wall 2 cells off: the floor lands on it, and no pass explains the removal.
    assert len(_refit_in_pieces("removed", (25.0, 40.0), removed_wall_rows=(36, 38), **far)) == 1


def test_a_structure_the_other_pass_drew_open_too_stays_removed() -> None:
    """The other pass's transform lays the removed cells on open floor, as a fold's, but where
    that pass would have drawn the block had it seen it standing (1 m south in the slam frame),
    the local map is open as well: both passes saw it gone, and it is a removal."""
    assert len(_refit_in_pieces("removed", (10.0, 20.0), other_drew=FREE)) == 1
    assert _refit_in_pieces("removed", (10.0, 20.0), other_drew=OCCUPIED) == []
    # Unknown there is not open: nothing says that pass saw it gone; still a fold.
    assert _refit_in_pieces("removed", (10.0, 20.0), other_drew=UNKNOWN) == []
    # A wall seen open a few centimetres from the place is not open there either.
    assert _refit_in_pieces("removed", (10.0, 20.0), other_drew=FREE, wall_beside=True) == []


def test_an_obstacle_the_other_pass_drew_on_open_floor_is_still_a_fold() -> None:
    """Only a removed difference asks what the other pass drew at the building's place: an
    added one's place back open is what any pass shows of open floor, fold or not."""
    assert _refit_in_pieces("added", (10.0, 20.0), other_drew=FREE) == []


def test_open_is_read_in_a_crop_as_over_the_whole_map() -> None:
    """The fold check reads "open" (seen free, no wall within the tolerance) in a box around
    the points asked about; it must read what the whole map says, the map's edges included."""
    import cv2

    from mapserver.grid import Grid

    rng = np.random.default_rng(5)
    state = rng.choice(np.array([FREE, OCCUPIED, UNKNOWN], np.uint8), (60, 90), p=[0.88, 0.02, 0.1])
    local = from_states(state, 0.05, (-1.0, 2.0, 0.0))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))  # 0.15 m at 0.05 m
    walls = cv2.dilate((state == OCCUPIED).view(np.uint8), disk).view(bool)
    whole = (state == FREE) & ~walls
    xy = rng.uniform([-1.5, 1.5], [4.0, 5.5], (400, 2))  # some off the map
    expected = Grid.of_map(local).sample(whole, xy, False)
    assert expected.any() and not expected.all()
    for chunk in np.array_split(np.arange(len(xy)), 40):
        got = explain._open_in(local, xy[chunk], wall_m=0.15)
        assert np.array_equal(got, expected[chunk])


def _rooms() -> tuple[np.ndarray, np.ndarray]:
    """Two rooms side by side, 1 px walls, split by a wall at column 100 (a 10 m x 6 m grid
    at 0.05 m), every wall seen in place by the local map."""
    glob = np.zeros((120, 200), bool)
    glob[10, 10:190] = glob[110, 10:190] = True
    glob[10:111, 10] = glob[10:111, 190] = glob[10:111, 100] = True
    return glob, glob.copy()


def _drawn_line(
    shape: tuple[int, int], start: tuple[float, float], deg: float, n: int
) -> np.ndarray:
    """Cells of a straight line from ``start`` (row, col), ``deg`` from the column axis, ``n``
    cells long."""
    line = np.zeros(shape, bool)
    t = np.arange(n)
    rows = np.rint(start[0] - t * math.sin(math.radians(deg))).astype(int)
    cols = np.rint(start[1] + t * math.cos(math.radians(deg))).astype(int)
    line[rows, cols] = True
    return line


@pytest.mark.parametrize("judged", ["first room", "second room"])
@pytest.mark.parametrize("pad", [0, 37])
def test_a_wall_drawn_turned_through_a_wall_standing_is_a_heading_error(
    judged: str, pad: int
) -> None:
    """A pass whose heading drifted 15 degrees drew a wall across both rooms, through the wall
    between them, which the local map shows standing: no new wall goes through a wall. Either
    part judged, the rooms anywhere on a larger map."""
    glob, local = _rooms()
    copy = _drawn_line(glob.shape, (90, 40), 15.0, 120)
    glob, local, copy = (np.pad(m, ((pad, pad + 11), (pad + 5, pad))) for m in (glob, local, copy))
    local |= copy
    cols = np.arange(copy.shape[1]) - pad - 5
    piece = copy & ((cols < 80) if judged == "first room" else (cols > 120))
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert line_through_wall(cells(piece), local, glob, **kw)
    # The same line, where the local map does not show the wall between them standing (a
    # wall really gone there, or never seen): nothing says the line is not new.
    local[:, (cols >= 98) & (cols < 103)] = False
    local |= copy
    assert not line_through_wall(cells(piece), local, glob, **kw)


def test_a_new_wall_across_the_free_end_of_a_wall_is_not_a_heading_error() -> None:
    """A partition that ends in the open, and a new wall built across its end (a T): the
    partition lies on one side of the new wall only, so the new wall does not run through it."""
    glob = np.zeros((120, 200), bool)
    glob[60:110, 100] = True  # the partition, its free end at row 60
    local = glob.copy()
    new = np.zeros(glob.shape, bool)
    new[60, 20:180] = True
    local |= new
    kw = {"resolution": RES, "tolerance_m": 0.15}
    for judged in (new & (np.arange(200) < 90), new & (np.arange(200) > 110)):
        assert not line_through_wall(cells(judged), local, glob, **kw)
    # Carried on through it, the partition on both sides: a copy through a wall.
    glob[10:60, 100] = True
    local[10:60, 100] = True
    assert line_through_wall(cells(new & (np.arange(200) < 90)), local, glob, **kw)


def test_a_line_through_a_wall_is_one_line_only_across_short_gaps() -> None:
    """A new wall that ends at the wall between the rooms, and in line with it, 0.6 m past
    that wall, a cabinet's face: the gap between them is too wide for one line. At 0.4 m it
    is one line through the wall."""
    glob, local = _rooms()
    new = np.zeros(glob.shape, bool)
    new[60, 30:100] = True
    local |= new
    kw = {"resolution": RES, "tolerance_m": 0.15}
    face = np.zeros(glob.shape, bool)
    face[60, 112:150] = True  # 0.6 m of gap from the wall's column (100) to the face
    assert not line_through_wall(cells(new), local | face, glob, **kw)
    face = np.zeros(glob.shape, bool)
    face[60, 108:150] = True
    assert line_through_wall(cells(new), local | face, glob, **kw)


def test_a_new_wall_that_ends_at_the_walls_it_meets_is_not_a_heading_error() -> None:
    """A new partition across the first room, from its bottom wall up to the wall between the
    rooms, 15 degrees turned: it ends there."""
    glob, local = _rooms()
    new = _drawn_line(glob.shape, (105, 40), 15.0, 62)
    assert new[:, 100:].sum() == 0  # it stops at the wall
    local |= new
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert not line_through_wall(cells(new), local, glob, **kw)


def test_a_new_wall_along_a_wall_stub_between_two_gaps_is_not_a_heading_error() -> None:
    """Two doorways either side of a wall's pier closed by one new wall along the wall's
    line: the pier lies under the line, but along it, not across it."""
    glob = np.zeros((80, 200), bool)
    glob[40, 10:60] = glob[40, 90:110] = glob[40, 140:190] = True
    local = glob.copy()
    new = np.zeros(glob.shape, bool)
    new[40, 60:90] = new[40, 110:140] = True
    local |= new
    kw = {"resolution": RES, "tolerance_m": 0.15}
    assert not line_through_wall(cells(new & (np.arange(200) < 100)), local, glob, **kw)


def _line_before_wall(
    cols: slice, unknown: slice | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, object]]:
    """The corridor with a line 0.35 m in front of its wall over ``cols``, the floor between
    them seen free but over ``unknown``: the global walls, the local walls, the line and the
    keywords asking that floor seen (and the pipeline's 0.6 m)."""
    glob, walls = _corridor()
    line = np.zeros(glob.shape, bool)
    line[47, cols] = True
    walls |= line
    state = np.full(glob.shape, FREE, np.uint8)
    state[walls] = OCCUPIED
    if unknown is not None:
        state[41:47, unknown] = UNKNOWN
    kw = {"resolution": RES, "tolerance_m": 0.15, "local_state": state, "min_length_m": 0.6}
    return glob, walls, line, kw


@pytest.mark.parametrize("between", [UNKNOWN, FREE])
def test_a_line_beside_a_wall_is_a_ghost_only_where_the_floor_between_them_was_seen(
    between: int,
) -> None:
    """A 0.8 m line 0.35 m in front of the wall, the wall seen in place everywhere: where the strip
    between them is unknown the line hid it (a new wall in front of an old one, the old one
    seen past its ends and on a revisit); where the strip was seen free, the robot looked
    through it at the wall: the line is that wall drawn again."""
    glob, walls, new, kw = _line_before_wall(
        slice(40, 56), slice(40, 56) if between == UNKNOWN else None
    )
    assert ghost_of_wall(cells(new), new, glob, walls, **kw) == (between == FREE)


def test_the_floor_asked_seen_free_is_the_one_behind_the_difference_itself() -> None:
    """A 4 m line 0.35 m in front of the wall: the floor between them seen free behind its
    first half (a copy there), unknown behind its second (a new wall hides it). The half that
    hides its floor is no ghost, whatever the other half lets the robot see."""
    glob, walls, line, kw = _line_before_wall(slice(20, 100), slice(60, 100))
    first, second = line & (np.arange(160) < 60), line & (np.arange(160) >= 60)
    assert ghost_of_wall(cells(first), line, glob, walls, **kw)
    assert not ghost_of_wall(cells(second), line, glob, walls, **kw)


def _wall_drawn_off(
    off_px: int, wall_seen: int, between: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corridor's wall (row 40, 7.5 m), a pass that drew 3 m of it (cols 40-99) ``off_px``
    rows off, 1 degree turned, as sparse hits; where the wall stands the local map shows
    ``wall_seen`` over those 3 m (FREE: seen gone; OCCUPIED: drawn in place too; UNKNOWN) and
    the strip between the two ``between``; the floor all round seen free. The global walls,
    the local states and the line's cells."""
    glob, _ = _corridor()
    state = np.full(glob.shape, FREE, np.uint8)
    state[glob] = OCCUPIED
    state[40, 40:100] = wall_seen
    lo, hi = sorted((40, 40 + off_px))
    state[lo + 1 : hi, 40:100] = between
    cols = np.arange(40, 100, 2)
    line = np.zeros(glob.shape, bool)
    line[40 + off_px + np.rint((cols - 40) * math.tan(math.radians(1.0))).astype(int), cols] = True
    state[line] = OCCUPIED
    return glob, state, line


@pytest.mark.parametrize("off_px", [-8, 12, 28])
def test_a_wall_seen_gone_beside_its_line_drawn_off_it_is_that_wall_drawn_elsewhere(
    off_px: int,
) -> None:
    """Drift left in a pass drew 3 m of a wall 0.4, 0.6 or 1.4 m off where it stands, and the
    robot saw the floor where it stands open: one wall drawn displaced (session 57's false
    additions), whichever side; a piece of the line as the clustering cut it is judged the
    same."""
    glob, state, line = _wall_drawn_off(off_px, FREE, FREE)
    piece = line & (np.arange(160) < 60)
    kw = {"resolution": RES, "tolerance_m": 0.15, "clear_m": 0.25}
    assert wall_drawn_elsewhere(cells(line), line, glob, state == OCCUPIED, state, **kw)
    assert wall_drawn_elsewhere(cells(piece), line, glob, state == OCCUPIED, state, **kw)
    # The ghost (the wall drawn in place too) is the other twin: not this one.
    assert not ghost_of_wall(
        cells(line),
        line,
        glob,
        state == OCCUPIED,
        resolution=RES,
        tolerance_m=0.15,
        local_state=state,
    )


@pytest.mark.parametrize(
    ("off_px", "wall_seen", "between", "why"),
    [
        (12, OCCUPIED, FREE, "the wall drawn in place too: a ghost's case, not this one"),
        (12, UNKNOWN, UNKNOWN, "a new wall in front of the old one hides it and the floor"),
        (12, FREE, UNKNOWN, "the floor between unseen: the line hid it"),
        (36, FREE, FREE, "1.8 m off: farther than drift leaves a wall"),
    ],
)
def test_a_line_beside_a_wall_is_drawn_elsewhere_only_with_the_wall_and_the_floor_seen_open(
    off_px: int, wall_seen: int, between: int, why: str
) -> None:
    glob, state, line = _wall_drawn_off(off_px, wall_seen, between)
    kw = {"resolution": RES, "tolerance_m": 0.15, "clear_m": 0.25}
    assert not wall_drawn_elsewhere(cells(line), line, glob, state == OCCUPIED, state, **kw), why


def test_a_short_line_or_a_box_beside_a_wall_seen_gone_is_no_wall_drawn_elsewhere() -> None:
    """A real new box 0.3 m across in front of a piece of wall really removed: a line under
    0.4 m (the pipeline's) or cells with a depth of their own are not a wall's line."""
    glob, state, _ = _wall_drawn_off(12, FREE, FREE)
    state[52, :] = FREE  # no line drawn
    short = np.zeros(glob.shape, bool)
    short[52, 60:66] = True  # 0.3 m
    box = np.zeros(glob.shape, bool)
    box[50:58, 60:68] = True  # 0.4 m x 0.4 m
    kw = {"resolution": RES, "tolerance_m": 0.15, "clear_m": 0.25}
    for added in (short, box):
        s = state.copy()
        s[added] = OCCUPIED
        assert not wall_drawn_elsewhere(cells(added), added, glob, s == OCCUPIED, s, **kw)
    # The same line 0.5 m long is a stretch of the wall.
    line = np.zeros(glob.shape, bool)
    line[52, 60:70] = True
    state[line] = OCCUPIED
    assert wall_drawn_elsewhere(cells(line), line, glob, state == OCCUPIED, state, **kw)


@pytest.mark.parametrize("drawn_off_px", [2, 4])
def test_a_line_beside_a_wall_drawn_a_few_cells_off_its_place_is_no_wall_drawn_elsewhere(
    drawn_off_px: int,
) -> None:
    """A real box's face 0.6 m in front of a wall that the local map draws 0.1 or 0.2 m off
    its place (drift left in the map): the wall's own cells are seen free, but the wall is
    there, drawn within the removed tolerance (wander11's gen-08: a box lost until the wall
    drawn in place was asked for beyond the added tolerance)."""
    glob, state, line = _wall_drawn_off(12, FREE, FREE)
    state[40 - drawn_off_px, 5:155] = OCCUPIED
    kw = {"resolution": RES, "tolerance_m": 0.15, "clear_m": 0.25}
    assert not wall_drawn_elsewhere(cells(line), line, glob, state == OCCUPIED, state, **kw)
    # Drawn farther off than that, 0.35 m, it is no longer the wall in place.
    state[40 - drawn_off_px, 5:155] = FREE
    state[33, 5:155] = OCCUPIED
    assert wall_drawn_elsewhere(cells(line), line, glob, state == OCCUPIED, state, **kw)


@pytest.mark.parametrize("between", [FREE, UNKNOWN])
def test_the_re_fit_drops_a_wall_drawn_elsewhere_and_keeps_a_line_that_hid_its_floor(
    between: int,
) -> None:
    """The pipeline's re-fit (explain.unexplained, a map compared whole after a drift
    correction) of the line drawn 0.6 m off its wall seen gone: dropped where the floor between
    was seen, kept where the line hid it (what a new wall in front of a wall gone does)."""
    from mapserver.align import GlobalView
    from mapserver.cluster import Difference
    from mapserver.config import Config
    from mapserver.grid import Grid

    glob, state, line = _wall_drawn_off(12, FREE, between)
    glob_state = np.where(glob, OCCUPIED, FREE).astype(np.uint8)
    grid = Grid(0.0, 0.0, RES, glob.shape[1], glob.shape[0])
    view = GlobalView(grid, glob_state, glob)
    found = Difference("added", (3.5, 5.4), (2.0, 5.3, 5.0, 5.5), 0.075, 30, cells(line))
    slam_map = from_states(state, RES, (0.0, 0.0, 0.0))
    kept = explain.unexplained([found], view, state, None, line, Config(), slam_map, lambda: 0.0)
    assert len(kept) == (0 if between == FREE else 1)


def _corridor_strip(
    drawn: bool, res: float = RES, wall_off_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A corridor 1 m wide and 4 m long between two thin walls (y = 2 and 3 m of a 5 m x 5 m
    grid of ``res`` cells, a cell thick), a local map that saw its floor, and a strip of 0.5 m
    of the upper wall seen free: with ``drawn``, the local map draws both walls round the strip
    (``wall_off_m`` into the corridor), else neither (the floor seen, the walls too faintly to
    be drawn). The global and local states, and the strip's cells."""
    n = round(5.0 / res)

    def at(metres: float) -> int:
        return round(metres / res)

    upper, lower, x0, x1 = at(2.0), at(3.0), at(0.5), at(4.5)
    global_state = np.full((n, n), UNKNOWN, np.uint8)
    global_state[upper + 1 : lower, x0:x1] = FREE
    global_state[upper, x0:x1] = OCCUPIED
    global_state[lower, x0:x1] = OCCUPIED
    local_state = np.full_like(global_state, UNKNOWN)
    local_state[upper : lower + 1, x0:x1] = FREE
    if drawn:
        off = at(wall_off_m)
        local_state[upper + off, x0:x1] = OCCUPIED
        local_state[lower - off, x0:x1] = OCCUPIED
    s0, s1 = at(2.25), at(2.75)
    local_state[upper, s0:s1] = FREE
    cells = np.array([[upper, c] for c in range(s0, s1)])
    return global_state, local_state, cells


@pytest.mark.parametrize("res", [0.025, 0.05, 0.1])
def test_a_strip_of_a_wall_seen_free_between_walls_drawn_in_place_is_no_faint_strip(
    res: float,
) -> None:
    global_state, local_state, cells = _corridor_strip(drawn=True, res=res)
    strip = faint_strip(cells, global_state, local_state, resolution=res)
    # The upper wall either side of the strip, the lower one under it: all drawn.
    assert strip.faces >= 10 and strip.drawn == strip.faces
    assert strip.spread_m == 0.0
    assert math.sqrt(12) * strip.along_m == pytest.approx(0.5, abs=2 * res)  # 0.5 m long
    assert not explain._faint_strip(strip, res)


@pytest.mark.parametrize("res", [0.025, 0.05, 0.1])
def test_a_strip_of_a_wall_seen_free_where_no_wall_around_is_drawn_is_a_faint_strip(
    res: float,
) -> None:
    global_state, local_state, cells = _corridor_strip(drawn=False, res=res)
    strip = faint_strip(cells, global_state, local_state, resolution=res)
    assert strip.faces >= 10 and strip.drawn == 0 and strip.drawn_share == 0.0
    assert explain._faint_strip(strip, res)


@pytest.mark.parametrize(("off_m", "drawn"), [(0.1, True), (0.15, False)])
def test_a_face_counts_as_drawn_with_a_local_wall_within_a_tenth_of_a_metre(
    off_m: float, drawn: bool
) -> None:
    global_state, local_state, cells = _corridor_strip(drawn=True, wall_off_m=off_m)
    strip = faint_strip(cells, global_state, local_state, resolution=RES)
    assert (strip.drawn_share == 1.0) is drawn and (strip.drawn == 0) is not drawn
    assert explain._faint_strip(strip, RES) is not drawn


def test_the_back_of_a_wall_the_robot_never_looked_at_is_not_counted() -> None:
    # The upper wall 0.3 m thick, the room behind it never seen: only its front face, drawn,
    # counts (its back, facing unknown space, would make the strip look faint).
    global_state, local_state, cells = _corridor_strip(drawn=True)
    global_state[34:40, 10:90] = OCCUPIED
    strip = faint_strip(cells, global_state, local_state, resolution=RES)
    assert strip.faces >= 10 and strip.drawn_share == 1.0
    # Seen from behind too (the room behind it free in the local map), the back counts.
    local_state[:34, 10:90] = FREE
    behind = faint_strip(cells, global_state, local_state, resolution=RES)
    assert behind.faces > strip.faces and behind.drawn_share < 0.5


def test_a_block_gone_is_no_strip_however_faint_the_walls_around_it() -> None:
    # A 0.3 m x 0.3 m block in the corridor seen gone spreads across itself; a 0.15 m one
    # (3 x 3 cells) spreads less than a line may, but is no longer than it is wide.
    for side in (6, 3):
        global_state, local_state, _ = _corridor_strip(drawn=False)
        global_state[48 : 48 + side, 30 : 30 + side] = OCCUPIED
        block = np.argwhere(global_state[48 : 48 + side, 30 : 30 + side] == OCCUPIED) + np.array(
            [48, 30]
        )
        strip = faint_strip(block, global_state, local_state, resolution=RES)
        assert strip.drawn_share < 0.5
        assert not explain._faint_strip(strip, RES)


def test_a_strip_with_no_faces_around_it_keeps_its_evidence() -> None:
    # A free-standing wall 0.5 m long, nothing else within 1 m: no faces to judge it by.
    global_state = np.full((60, 60), FREE, np.uint8)
    global_state[30, 25:35] = OCCUPIED
    local_state = np.full_like(global_state, FREE)
    cells = np.array([[30, c] for c in range(25, 35)])
    strip = faint_strip(cells, global_state, local_state, resolution=RES)
    assert strip.faces == 0 and strip.drawn_share == 1.0
    assert not explain._faint_strip(strip, RES)


def _face_in_front(offset_px: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A block 1 m x 2.5 m at 0.05 m (rows 40-60, cols 30-80) whose bottom face the local map
    draws ``offset_px`` cells below it (drift left over), the block's inside unseen, its top
    face and sides drawn where they stand (the sides run on to the face drawn low); floor
    around it. The added difference: the face drawn low."""
    g = np.full((120, 120), FREE, np.uint8)
    g[40:61, 30:81] = OCCUPIED
    loc = np.full_like(g, FREE)
    low = 60 + offset_px
    loc[40:low, 30:81] = UNKNOWN
    loc[40, 30:81] = OCCUPIED
    loc[40 : low + 1, 30] = OCCUPIED
    loc[40 : low + 1, 80] = OCCUPIED
    loc[low, 30:81] = OCCUPIED
    return g, loc, np.column_stack(np.nonzero(_row(g.shape, low, 30, 81)))


def _row(shape: tuple[int, ...], row: int, start: int, stop: int) -> np.ndarray:
    out = np.zeros(shape, bool)
    out[row, start:stop] = True
    return out


def _in_front(g: np.ndarray, loc: np.ndarray, cells: np.ndarray) -> bool:
    return face_drawn_in_front(
        cells, g == OCCUPIED, loc, resolution=RES, tolerance_m=KW["tolerance_m"]
    )


@pytest.mark.parametrize("offset_px", [4, 6, 10, 24])
def test_a_face_drawn_in_front_of_a_block_with_nothing_seen_behind_is_explained(
    offset_px: int,
) -> None:
    """The block's bottom face drawn 0.2, 0.3, 0.5 or 1.2 m low, its inside unseen: explained,
    also with a cell behind every third of the face's cells seen free (rays through its gaps),
    and a fragment of it; the inputs not modified."""
    g, loc, cells = _face_in_front(offset_px)
    g0, loc0 = g.copy(), loc.copy()
    assert _in_front(g, loc, cells)
    assert (g == g0).all() and (loc == loc0).all()
    loc[59 + offset_px, 30:81:3] = FREE
    assert _in_front(g, loc, cells)
    # A fragment of it, its ends short of the corners (the sides drawn cross the face's line).
    assert _in_front(g, loc, cells[(cells[:, 1] >= 40) & (cells[:, 1] <= 70)])


def test_an_obstacle_in_front_of_a_wall_seen_past_its_ends_is_not_a_face_drawn_in_front() -> None:
    """Not: a box's face 1 m long 0.3 m in front of a long wall, the wall behind it hidden and
    seen where it stands past both its ends (past one end is enough); the face drawn low with
    the floor between seen free (a copy: ghost_of_wall's case); too far from the face (1.6 m);
    too short (0.4 m); a depth of its own (0.3 m deep, drawn so); the face drawn where it stands
    too; a line over the face for 0.6 of it only."""
    g = np.full((120, 120), FREE, np.uint8)
    g[55:61, :] = OCCUPIED
    loc = g.copy()
    loc[55:66, 38:63] = UNKNOWN  # behind the box
    loc[66, 40:61] = OCCUPIED
    box = np.column_stack(np.nonzero(_row(g.shape, 66, 40, 61)))
    assert not _in_front(g, loc, box)
    loc[55:66, 63:] = UNKNOWN  # past its right end unseen too, past the left one seen
    assert not _in_front(g, loc, box)
    g, loc, cells = _face_in_front()
    loc[61:66, 30:81] = FREE
    loc[60, 31:80] = FREE  # seen through where the face stands
    assert not _in_front(g, loc, cells)
    g, loc, cells = _face_in_front(32)
    assert not _in_front(g, loc, cells)
    g, loc, cells = _face_in_front()
    assert not _in_front(g, loc, cells[(cells[:, 1] >= 45) & (cells[:, 1] < 53)])
    deep = np.column_stack(np.nonzero(np.pad(np.ones((6, 40), bool), ((66, 48), (36, 44)))))
    loc[66:72, 36:76] = OCCUPIED  # drawn as deep as it is
    assert not _in_front(g, loc, deep)
    g, loc, cells = _face_in_front()
    loc[60, 30:81] = OCCUPIED  # the face drawn where it stands too: something in front of it
    assert not _in_front(g, loc, cells)
    g, loc, cells = _face_in_front()
    longer = np.column_stack(np.nonzero(_row(g.shape, 66, 30, 110)))  # 0.6 of it over the face
    assert not _in_front(g, loc, longer)


def test_an_obstacle_turned_in_front_of_a_wall_seen_past_its_ends_is_not_explained() -> None:
    """A box's face 2 m long, turned 3 or 5 degrees, 0.3 m in front of a thin wall seen where
    it stands past both its ends (only the strip behind the box unseen): no face drawn in
    front, though past its ends the wall lies more than a cell off the line at the face's
    median offset."""
    for deg in (3, 5):
        g = np.full((200, 200), FREE, np.uint8)
        g[60, :] = OCCUPIED
        loc = g.copy()
        loc[:60] = UNKNOWN  # the wall's far side unseen
        cols = np.arange(80, 120)
        rows = np.rint(67 + (cols - 100) * math.tan(math.radians(deg))).astype(int)
        for r, c in zip(rows, cols, strict=True):
            loc[60:r, c - 1 : c + 2] = UNKNOWN  # the box's shadow
        loc[rows, cols] = OCCUPIED
        assert not _in_front(g, loc, np.column_stack((rows, cols)))


def _beside_wall(
    offset_px: int = 8, thick_px: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A corridor at 0.05 m: a wall along row 40 (cols 10-110), floor below it. The local map
    draws the wall in place, the floor seen free beyond 0.6 m of it, and a line ``thick_px``
    cells thick and 2 m long (cols 30-70) ``offset_px`` cells below the wall, the floor between
    them and 0.25 m below the line unseen (seen from one side, from afar). The added
    difference: that line."""
    g = np.full((120, 140), FREE, np.uint8)
    g[40, 10:111] = OCCUPIED
    g[:40] = UNKNOWN
    loc = np.full_like(g, FREE)
    loc[:40] = UNKNOWN
    loc[40, 10:111] = OCCUPIED
    top = 40 + offset_px
    loc[41 : top + thick_px + 5, 25:76] = UNKNOWN
    loc[top : top + thick_px, 30:71] = OCCUPIED
    cells = np.column_stack(np.nonzero(loc[:, :] == OCCUPIED))
    cells = cells[cells[:, 0] >= top]
    return g, loc, cells


def _thin(g: np.ndarray, loc: np.ndarray, cells: np.ndarray) -> bool:
    return thin_line_by_wall(cells, g, g == OCCUPIED, loc, resolution=RES)


def test_a_thin_line_by_a_wall_its_floor_unseen_is_the_face_drawn_again() -> None:
    g, loc, cells = _beside_wall()
    g0, loc0 = g.copy(), loc.copy()
    assert _thin(g, loc, cells)
    assert (g == g0).all() and (loc == loc0).all()
    # Dotted (every other cell): thinner still.
    assert _thin(g, loc, cells[cells[:, 1] % 2 == 0])
    # Slanted by a cell every 20 (1.4 degrees), as a pass with its heading off draws it.
    slanted = cells.copy()
    slanted[:, 0] += (slanted[:, 1] - 30) // 20
    assert _thin(g, loc, slanted)


def test_a_line_seen_thick_far_off_or_with_its_floor_is_not_a_face_drawn_again() -> None:
    # A new wall 0.15 m thick (3 cells), the same place.
    g, loc, cells = _beside_wall(thick_px=3)
    assert len(cells) == 3 * 41 and not _thin(g, loc, cells)
    # 2 cells thick: over the 1.6 cells asked on average.
    g, loc, cells = _beside_wall(thick_px=2)
    assert not _thin(g, loc, cells)
    # The line 0.75 m from the wall (15 cells): farther than a face drawn again lands.
    g, loc, cells = _beside_wall(offset_px=15)
    assert not _thin(g, loc, cells)
    # The floor around it seen free (a line seen from its own side, near): a change.
    g, loc, cells = _beside_wall()
    loc[41:60, 20:80] = FREE
    loc[48, 30:71] = OCCUPIED
    assert not _thin(g, loc, cells)
    # A single cell, or nothing but a point: no line to measure.
    assert not _thin(g, loc, cells[:1])


def test_a_thin_line_is_measured_against_the_floor_the_building_has_and_up_to_its_reach() -> None:
    # 0.15 m below the wall, the floor below it seen free: what lies behind the wall (unknown
    # in both maps, never floor) does not make the floor around it unseen.
    g, loc, cells = _beside_wall(offset_px=3)
    loc[41:60, 20:80] = FREE
    loc[43, 30:71] = OCCUPIED
    assert not _thin(g, loc, cells)
    # 0.6 m (12 cells) off the wall, the reach asked, is within it; 13 cells is not.
    assert _thin(*_beside_wall(offset_px=12))
    assert not _thin(*_beside_wall(offset_px=13))


def test_a_corner_of_two_faces_is_no_line_drawn_again() -> None:
    # An L of two thin arms (a box seen from one side at its corner), by the wall, the floor
    # around it unseen: as thin as a line, but it spreads across itself.
    g, loc, cells = _beside_wall()
    arm = np.column_stack([np.arange(48, 60), np.full(12, 30)])
    corner = np.concatenate([cells, arm])
    loc[arm[:, 0], arm[:, 1]] = OCCUPIED
    assert len(corner) / 41 < 1.6 and spread_across_m(corner, resolution=RES) >= 0.05
    assert not _thin(g, loc, corner)


@pytest.mark.parametrize(
    ("drawn", "walls", "seen_behind", "explained"),
    [
        (False, 20, 15, True),  # neither wall drawn, 75 % of the local walls seen from behind
        (False, 20, 12, True),  # 60 %: the fold check's own share
        (False, 20, 10, False),  # 50 %: not folded enough
        (True, 20, 15, False),  # the walls around drawn in place: not faint
        (False, 0, 0, False),  # no local wall around it at all
        (False, 2, 2, False),  # two cells of local wall (0.1 m), both seen from behind
    ],
)
def test_a_removal_where_the_map_is_both_faint_and_folded_is_explained(
    drawn: bool, walls: int, seen_behind: int, explained: bool
) -> None:
    """A removed difference after a drifting session whose surroundings the local map both
    drew faintly (under 70 % of the faces around it in place) and folded (60 % of its walls
    around it seen free behind): a part drawn twice, neither copy in place."""
    from mapserver.cluster import Difference

    global_state, local_state, cells = _corridor_strip(drawn=drawn)
    strip = faint_strip(cells, global_state, local_state, resolution=RES)
    assert strip.drawn_share == (1.0 if drawn else 0.0)
    diff = Difference("removed", (2.5, 3.0), (2.25, 2.95, 2.75, 3.05), 0.0, len(cells), cells)
    faces = Faces(walls=walls, seen_behind=seen_behind, depth_m=0.05)
    folded = explain._faint_and_folded(diff, faces, global_state, local_state, RES)
    assert folded is explained


def test_a_removal_among_few_faces_the_robot_looked_at_is_not_faint_and_folded() -> None:
    """The local map saw only the strip itself free, nothing around it: too few faces looked
    at (under 10) to call the place faint, however folded its walls."""
    from mapserver.cluster import Difference

    global_state, _, cells = _corridor_strip(drawn=False)
    local_state = np.full_like(global_state, UNKNOWN)
    local_state[cells[:, 0], cells[:, 1]] = FREE
    # The floor next to six cells of the wall beside the strip seen, that wall not drawn.
    upper, end = int(cells[0, 0]), int(cells[:, 1].max()) + 1
    local_state[upper + 1, end + 3 : end + 9] = FREE
    strip = faint_strip(cells, global_state, local_state, resolution=RES)
    assert 0 < strip.faces < 10 and strip.drawn_share < 0.7
    diff = Difference("removed", (2.5, 3.0), (2.25, 2.95, 2.75, 3.05), 0.0, len(cells), cells)
    faces = Faces(walls=20, seen_behind=20, depth_m=0.05)
    assert not explain._faint_and_folded(diff, faces, global_state, local_state, RES)
