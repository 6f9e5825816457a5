"""Floor-plan maps: walls drawn as 1-pixel grey anti-aliased lines (an architectural plan turned
into a map), which the trinary thresholds read as unknown or free. They must align as scanned
maps do, and a wall drawn and then seen gone is a removed one (issue 12, item 2).

The real drawing is a crop of the RMF airport terminal floor plan (tests/data/maps/SOURCES.md).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from worlds import cut_local, offset, write_bundle

from mapserver.align import drawn_walls, make_view, structure_mask
from mapserver.bundle import sha256_file
from mapserver.config import Config, UpdateConfig
from mapserver.fleet.store import FleetStore
from mapserver.geometry import Transform2D
from mapserver.grid import Grid
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states, load_map, save_map
from mapserver.pipeline import process_bundle

CROP = Path(__file__).parent / "data" / "maps" / "rmf_terminal_crop" / "terminal_crop.yaml"
RES = 0.05


def drawing(grey: np.ndarray, resolution: float = RES) -> OccupancyMap:
    """A map read from a grey drawing (paper 254) as the loader reads it."""
    p = (255 - grey.astype(np.float64)) / 255
    state = np.full(grey.shape, UNKNOWN, np.uint8)
    state[p < 0.196] = FREE
    state[p > 0.65] = OCCUPIED
    m = from_states(state, resolution, (0.0, 0.0, 0.0))
    return OccupancyMap(state, np.rint(p * 255).astype(np.uint8), resolution, m.origin)


def plan() -> np.ndarray:
    """Paper with a 4 m outline drawn 1 px wide in mid grey (anti-aliased into the next row), a
    grey label box, a faint guide line (read as free) and a small cross mark."""
    g = np.full((120, 200), 254, np.uint8)
    g[40, 20:100] = 150  # the outline ...
    g[41, 20:100] = 215  # ... and its anti-aliasing
    g[70:90, 120:160] = 128  # a label box: the commonest unknown grey
    g[100, 10:190] = 228  # a guide line, read as free
    g[60, 170:175] = 140  # a cross mark, 0.25 m
    g[58:63, 172] = 140
    return g


def test_a_drawn_outline_is_a_wall_as_thick_as_a_lidar_sees_it() -> None:
    m = drawing(plan())
    walls = drawn_walls(m)
    # The outline, grown by 0.08 m (2 px at 0.05 m) each side, along its whole length.
    assert walls[38:43, 20:100].all()
    assert not walls[35, 20:100].any() and not walls[45, 20:100].any()
    # Not the label box's inside (the unknown grey), not the faint guide line.
    assert not walls[75:85, 125:155].any()
    assert not walls[100, 30:180].any()
    # The trinary rule reads none of it as occupied: the alignment's walls come from here.
    assert not (m.state == OCCUPIED).any()
    assert structure_mask(m)[40, 20:100].all()


def test_a_faint_slanted_line_split_over_two_pixels_is_a_drawn_wall() -> None:
    # A pastel fill read as free (p 0.18: the lightest grey a free cell has is near the free
    # threshold), and on the paper beside it an outline drawn at 30 degrees whose ink the
    # anti-aliasing splits over two pixels, each only a little darker than the fill (p 0.21,
    # read as unknown): a wall in the building, its pixels lighter than the line.
    g = np.full((120, 200), 254, np.uint8)
    g[10:40, 10:190] = 209  # the fill
    g[48:50, 10:190] = 150  # an outline drawn darker: the map is a drawing
    g[70:100, 160:195] = 128  # a label box: the commonest unknown grey
    rows = 60 + np.arange(0, 100) * math.tan(math.radians(30))
    for col, row in zip(range(50, 150), rows, strict=True):
        g[int(row), col] = g[int(row) + 1, col] = 201
    m = drawing(g)
    assert (m.state[10:40, 10:190] == FREE).all()
    assert (m.state[g == 201] == UNKNOWN).all()
    walls = drawn_walls(m)
    line = g == 201
    assert walls[line].mean() > 0.95
    assert not walls[15:35, 15:185].any()  # the fill is floor


def test_a_scan_s_grey_rims_and_unknown_are_no_drawn_walls() -> None:
    # A scan: black walls with a grey rim, unknown (205) around, a strip of unknown in free.
    g = np.full((120, 200), 205, np.uint8)
    g[20:100, 20:180] = 254
    g[50, 20:180] = 0
    g[49, 20:180] = g[51, 20:180] = 150  # the rim: cells barely seen
    g[80, 40:120] = 205  # a strip never seen
    assert not drawn_walls(drawing(g)).any()


def test_the_view_of_a_drawing_has_its_long_lines_as_walls_not_its_marks() -> None:
    m = drawing(plan())
    local = from_states(np.full((40, 40), FREE, np.uint8), RES, (4.0, 1.0, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)
    grid = view.grid
    (c, r), (cc, rc) = np.rint(grid.to_pixel([[2.5, 3.975], [8.625, 2.975]])).astype(int)
    assert view.state[r, c] == OCCUPIED  # on the outline
    assert view.state[rc, cc] != OCCUPIED  # the cross: a mark, no wall
    assert view.structure[rc, cc]  # though the search may use it


def test_a_drawing_s_grey_boxes_are_grown_as_its_lines_are_not_a_scan_s_unknown() -> None:
    # A label box drawn in the drawing's own unknown grey, anti-aliased into a row each side
    # that the thresholds read as free: what stands there (the box, as thick as its lines'
    # walls) reaches over its rim, so a face seen there is the box, not a new obstacle. The
    # view marks the cells within half a thin wall of the box unknown (0.08 m: two cells at
    # 0.05 m), never a difference.
    g = plan()
    g[69, 120:160] = g[90, 120:160] = 215  # the box's anti-aliased rims (read as free)
    m = drawing(g)
    assert (m.state[69, 120:160] == FREE).all()
    local = from_states(np.full((40, 40), FREE, np.uint8), RES, (6.0, 0.5, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)

    def at(x: float, row: int) -> tuple[int, int]:
        ((c, r),) = np.rint(view.grid.to_pixel([[x, 6.0 - RES * (row + 0.5)]])).astype(int)
        return r, c

    for row in (68, 69, 90, 91):  # the rims, and the cell beyond each
        assert view.state[at(7.0, row)] == UNKNOWN
    for row in (67, 92):  # floor
        assert view.state[at(7.0, row)] == FREE
    # A scan (map_saver's unknown grey): its unknown is where no ray went, and the free cells
    # beside it are floor seen free.
    g = np.full((120, 200), 205, np.uint8)
    g[20:100, 20:180] = 254
    g[40, 20:180] = g[80, 20:180] = 150  # grey walls: the map passes for a drawing
    g[55:65, 60:140] = 205  # a patch never seen
    m = drawing(g)
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)
    assert view.raw_state is not None  # its grey walls are walls: it passed for a drawing
    assert view.state[at(5.0, 54)] == FREE and view.state[at(5.0, 65)] == FREE


def floorplan_world(m: OccupancyMap) -> OccupancyMap:
    """What stands in a building drawn as ``m``: its outlines (not the faint guide lines the
    thresholds read as free) and its dark boxes, walls a few pixels thick."""
    occ = m.occupancy
    hat = cv2.morphologyEx(occ, cv2.MORPH_TOPHAT, np.ones((5, 5), np.uint8))
    drawn = (occ >= 89) | ((hat >= 30) & (m.state != FREE))
    walls = cv2.dilate(drawn.view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return from_states(np.where(walls, OCCUPIED, FREE).astype(np.uint8), m.resolution, m.origin)


def edit(world: OccupancyMap, op: str, box: tuple[float, float, float, float]) -> OccupancyMap:
    state = world.state.copy()
    grid = Grid.of_map(world)
    (c0, r1), (c1, r0) = np.rint(grid.to_pixel([box[:2], box[2:]])).astype(int)
    state[r0 : r1 + 1, c0 : c1 + 1] = OCCUPIED if op == "add" else FREE
    return from_states(state, world.resolution, world.origin)


TRUE = Transform2D(0.6, 120.0, -30.0)
CENTRE = (124.0, -39.5)  # the concourse between the shops, nav2 metres
BOX = (126.5, -38.9, 127.3, -38.1)  # a new 0.8 m box in the concourse
GONE = (114.5, -41.95, 117.0, -41.25)  # 2.5 m of a shop front's outline


def bundle(tmp_path: Path, prior: Transform2D, global_yaml: Path = CROP) -> Path:
    """A session in the terminal with the box added and the shop front gone, carrying
    ``global_yaml`` (and the image it names) as the map it navigated on."""
    plan_map = load_map(CROP)
    now = edit(edit(floorplan_world(plan_map), "add", BOX), "clear", GONE)
    cut = cut_local(now, centre_xy=CENTRE, radius_m=12.0, nav2_from_slam=TRUE, resolution=RES)
    d = tmp_path / "plan-run"
    d.mkdir()
    image = yaml.safe_load(global_yaml.read_text())["image"]
    shutil.copyfile(global_yaml, d / global_yaml.name)
    shutil.copyfile(global_yaml.parent / image, d / image)
    save_map(d / "slam_map.yaml", cut.local.state, cut.local.resolution, cut.local.origin)
    slam = TRUE.inverse().apply(np.array(CENTRE))
    nav2 = prior.apply(slam)
    names = ["slam_map.yaml", "slam_map.pgm", global_yaml.name, image]
    manifest = {
        "format": 1,
        "robot": "test-01",
        "stamp": "2026-11-21T10:15:00Z",
        "slam_map": "slam_map.yaml",
        "nav2_map": global_yaml.name,
        "pose": {
            "nav2": {"x": float(nav2[0]), "y": float(nav2[1]), "yaw": prior.theta},
            "slam": {"x": float(slam[0]), "y": float(slam[1]), "yaw": 0.0},
        },
        "checksums": {n: sha256_file(d / n) for n in names},
    }
    (d / "bundle.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return d


def inside(d: dict, box: tuple[float, float, float, float], grow: float) -> bool:
    x, y = d["centroid"]["x"], d["centroid"]["y"]
    return box[0] - grow <= x <= box[2] + grow and box[1] - grow <= y <= box[3] + grow


@pytest.mark.parametrize("error_deg", [0.0, 20.0])
def test_a_floor_plan_bundle_aligns_and_finds_a_new_box_and_a_wall_gone(
    tmp_path: Path, error_deg: float
) -> None:
    prior = offset(TRUE, 0.8, -0.5, error_deg, CENTRE) if error_deg else TRUE
    r = process_bundle(bundle(tmp_path, prior), Config()).result
    a = r["alignment"]
    assert a["trusted"] is True and a["score"] >= 0.6
    assert math.degrees(abs(a["theta"] - TRUE.theta)) < 0.5
    assert math.hypot(a["tx"] - TRUE.tx, a["ty"] - TRUE.ty) < 0.5
    kinds = sorted(d["kind"] for d in r["differences"])
    assert kinds == ["added", "removed"], r["differences"]
    added = next(d for d in r["differences"] if d["kind"] == "added")
    removed = next(d for d in r["differences"] if d["kind"] == "removed")
    assert inside(added, BOX, 0.3) and inside(removed, GONE, 0.3)


def test_a_drawing_s_lines_darker_than_its_label_boxes_are_walls_for_the_differences() -> None:
    # A drawing (paper, label boxes of its own grey, never through map_saver) at the RMF
    # terminal's 0.082 m whose outline is drawn 2 px wide and darker than that grey: ink, a
    # wall to see gone like its lighter lines (too thin for the core a grey wall keeps).
    g = plan()
    g[20, 20:100] = 119  # an outline darker than the label box (128) ...
    g[21, 20:100] = 117  # ... two pixels wide
    m = drawing(g, 0.0821)
    assert not (m.state == OCCUPIED).any()
    local = from_states(np.full((40, 40), FREE, np.uint8), 0.0821, (4.0, 1.0, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)
    top = 120 * 0.0821
    (c, r), (c2, r2) = np.rint(
        view.grid.to_pixel([[4.0, top - 20.5 * 0.0821], [4.0, top - 40.5 * 0.0821]])
    ).astype(int)
    assert view.state[r, c] == OCCUPIED  # the dark outline
    assert view.state[r2, c2] == OCCUPIED  # the light one, as before


def test_a_scan_is_told_by_its_whole_map_not_by_a_crop_without_its_unknown_grey() -> None:
    # A scan whose grey walls (darker than map_saver's 205, noisy, few black cells) pass for a
    # drawing, its unknown all east of x = 20 m: a view of its west part holds none of that
    # grey, and its commonest unknown grey there is the walls' own. Still no wall to see gone.
    rng = np.random.default_rng(0)
    g = np.full((120, 600), 254, np.uint8)
    g[:, 400:] = 205
    for row in (40, 80):
        g[row, 10:190] = rng.integers(110, 170, 180)
    m = drawing(g)
    local = from_states(np.full((40, 40), FREE, np.uint8), RES, (4.0, 1.0, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)
    assert view.grid.x0 + view.grid.width * RES < 400 * RES  # the crop: none of the 205
    assert view.structure.any()  # the search has the grey walls
    assert not (view.state == OCCUPIED).any()  # the differences do not


def test_a_scan_s_grey_wall_is_a_wall_along_its_darkest_line_not_its_blurred_rims() -> None:
    # A scan whose walls came out grey (darker than its unknown grey, few black cells),
    # blurred: a dark middle row and a lighter row each side, both read as walls by the search.
    # The middle row is where the wall stands; the rims are blur, not walls to see gone.
    g = np.full((120, 200), 205, np.uint8)
    g[20:100, 20:180] = 254
    g[40, 20:180] = 120  # the wall's darkest line, 1 px ...
    g[39, 20:180] = g[41, 20:180] = 160  # ... and its blurred rims
    g[80, 20:180] = 120  # a thinner wall: only its line reads as one
    g[79, 20:180] = g[81, 20:180] = 220
    g[60, 50:58] = 120  # a grey mark 0.4 m long: no wall
    g[30, 100:180] = 0  # a black wall with a grey rim: not a wall ...
    g[31, 100:180] = 140
    g[28, 100:180] = 120  # ... nor its second trace, two cells off (a wall seen doubled)
    g[29, 100:180] = 235
    m = drawing(g)
    local = from_states(np.full((40, 40), FREE, np.uint8), RES, (4.0, 1.0, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)

    def at(x: float, row: int) -> tuple[int, int]:
        ((c, r),) = np.rint(view.grid.to_pixel([[x, 6.0 - 0.05 * (row + 0.5)]])).astype(int)
        return r, c

    for row in (40, 80):
        assert view.structure[at(5.0, row)] and view.state[at(5.0, row)] == OCCUPIED
    for row in (39, 41):
        assert view.structure[at(5.0, row)] and view.state[at(5.0, row)] != OCCUPIED
    assert view.structure[at(2.7, 60)] and view.state[at(2.7, 60)] != OCCUPIED  # the mark
    assert view.state[at(7.0, 30)] == OCCUPIED
    assert view.state[at(7.0, 31)] != OCCUPIED and view.state[at(7.0, 28)] != OCCUPIED


def grey_hall(tmp_path: Path, gone_x: tuple[float, float]) -> Path:
    """A bundle in a 15 x 9 m hall whose global map draws its walls grey (map_saver's unknown
    grey outside): a 0.5 m thick outer wall, and across the hall a thin inner wall drawn 2 px
    wide, anti-aliased into the rows beside it, as a thin wall comes out of a blurred grey
    rendering (too thin for the core a thick grey wall keeps after an erosion). The robot, at
    the hall's middle, sees the inner wall gone between ``gone_x`` (metres)."""
    res, h, w = RES, 280, 400
    g = np.full((h, w), 205, np.uint8)  # unknown beyond the building, 2 m all round
    g[40:240, 40:360] = 120  # the outer wall, 0.5 m of grey ink
    g[50:230, 50:350] = 254
    g[139:141, 50:350] = 130  # the thin wall, 2 px ...
    g[138, 50:350] = g[141, 50:350] = 230  # ... and its anti-aliasing
    pgm = tmp_path / "grey_hall.pgm"
    cv2.imwrite(str(pgm), g)
    (tmp_path / "grey_hall.yaml").write_text(
        "image: grey_hall.pgm\nmode: trinary\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    drawn = load_map(tmp_path / "grey_hall.yaml")
    assert not (drawn.state == OCCUPIED).any()  # every wall reads as unknown
    state = np.full((h, w), FREE, np.uint8)
    state[(g <= 130)] = OCCUPIED
    state[138:142, 50:350] = OCCUPIED  # the thin wall stands 0.2 m thick
    c0, c1 = round(gone_x[0] / res), round(gone_x[1] / res)
    state[138:142, c0:c1] = FREE
    world = from_states(state, res, (0.0, 0.0, 0.0))
    truth = Transform2D(0.3, 2.0, -1.0)
    cut = cut_local(world, centre_xy=(10.0, 7.0), radius_m=7.0, nav2_from_slam=truth)
    d = tmp_path / "bundle"
    write_bundle(d, world, cut, slam_pose=(0.0, 0.0, 0.0))
    for name in ("nav2_map.yaml", "nav2_map.pgm"):
        (d / name).unlink()
    shutil.copyfile(tmp_path / "grey_hall.yaml", d / "nav2_map.yaml")
    shutil.copyfile(pgm, d / "grey_hall.pgm")
    manifest = yaml.safe_load((d / "bundle.yaml").read_text())
    names = ["slam_map.yaml", "slam_map.pgm", "nav2_map.yaml", "grey_hall.pgm"]
    manifest["checksums"] = {n: sha256_file(d / n) for n in names}
    (d / "bundle.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return d


def test_a_thin_wall_drawn_grey_and_seen_gone_is_a_removed_difference(tmp_path: Path) -> None:
    r = process_bundle(grey_hall(tmp_path, (8.0, 10.0)), Config()).result
    assert r["alignment"]["trusted"] is True, r["warnings"]
    removed = [d for d in r["differences"] if d["kind"] == "removed"]
    assert len(removed) == 1, r["differences"]
    centre = removed[0]["centroid"]
    assert abs(centre["x"] - 9.0) < 0.3 and abs(centre["y"] - 7.0) < 0.15, centre
    assert [d for d in r["differences"] if d["kind"] == "added"] == []


def test_the_core_of_a_wall_drawn_grey_is_a_wall_for_the_differences_not_its_rim() -> None:
    # A map whose walls are drawn grey, darker than its unknown grey (205 outside): a 0.5 m
    # thick wall of flat grey ink, anti-aliased one pixel each side.
    g = np.full((120, 200), 205, np.uint8)
    g[20:100, 20:180] = 254
    g[50:60, 20:180] = 110
    g[49, 20:180] = g[60, 20:180] = 180
    m = drawing(g)
    assert not (m.state == OCCUPIED).any()  # the trinary rule reads the wall as unknown
    local = from_states(np.full((40, 40), FREE, np.uint8), RES, (4.0, 1.0, 0.0))
    view = make_view(m, local, Transform2D(0.0, 0.0, 0.0), search_xy_m=3.0, margin_m=5.0)

    def at(y: float) -> tuple[int, int]:
        ((c, r),) = np.rint(view.grid.to_pixel([[5.0, y]])).astype(int)
        return r, c

    assert view.state[at(6.0 - 0.05 * 55)] == OCCUPIED  # the wall's middle
    edge = at(6.0 - 0.05 * 50.5)  # its outer row of ink: not a line of its own
    assert view.structure[edge] and view.state[edge] != OCCUPIED  # the search's, no more
    assert view.state[at(6.0 - 0.05 * 49.5)] != OCCUPIED  # its anti-aliased rim


def test_a_bundle_on_a_later_version_of_a_stored_drawing_aligns_on_the_drawing_s_lines(
    tmp_path: Path,
) -> None:
    # Versions after the first are written by map_saver's rules: cell states only, the grey
    # lines gone (205 like the label boxes, or free). A robot navigating on version 2 must
    # still be aligned on the drawing, which the store keeps as version 1.
    store = FleetStore(tmp_path / "maps", UpdateConfig(mode="auto"))
    store.add_map("terminal", CROP)
    store.rollback("terminal", 1)  # version 2: version 1's states, written by map_saver
    v2 = tmp_path / "maps" / "terminal" / "v0002.yaml"
    assert drawn_walls(load_map(v2)).sum() == 0 < drawn_walls(load_map(CROP)).sum()
    config = Config(maps=tmp_path / "maps")
    prior = offset(TRUE, 0.8, -0.5, 20.0, CENTRE)
    outcome = process_bundle(bundle(tmp_path, prior, v2), config)
    r = outcome.result
    assert r["alignment"]["trusted"] is True, r["warnings"]
    assert r["map"]["name"] == "terminal" and r["map"]["version"] == 2
    assert sorted(d["kind"] for d in r["differences"]) == ["added", "removed"]
    # The fleet's observation is judged against the current version (2) with the drawing's
    # walls where no change touched them: the same two differences.
    assert outcome.observation is not None
    assert sorted(f.kind for f in outcome.observation.found) == ["added", "removed"]


def test_a_bundle_on_the_drawing_is_judged_against_a_later_version_with_its_lines(
    tmp_path: Path,
) -> None:
    store = FleetStore(tmp_path / "maps", UpdateConfig(mode="auto"))
    store.add_map("terminal", CROP)
    store.rollback("terminal", 1)
    outcome = process_bundle(bundle(tmp_path, TRUE), Config(maps=tmp_path / "maps"))
    assert outcome.result["map"]["version"] == 1
    assert outcome.observation is not None and outcome.observation.judged_version == 2
    assert sorted(f.kind for f in outcome.observation.found) == ["added", "removed"]
