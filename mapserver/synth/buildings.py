"""Generated buildings: airport terminals and office or hospital floors, and roughening a map
to look SLAM-built (:func:`make_airport_map`, :func:`make_office_map`, :func:`roughen_map`)."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from mapserver.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, from_states
from mapserver.synth._common import Seed, _as_rng, _positive

_Box = Callable[[float, float, float, float, int], None]


def _box(
    img: NDArray[np.uint8], res: float, x0: float, y0: float, x1: float, y1: float, value: int
) -> None:
    """Set the axis-aligned rectangle between corners (x0, y0) and (x1, y1) (metres from the
    image's lower-left corner) to ``value``; at least one pixel wide."""
    h = img.shape[0]
    xa, xb = sorted((x0, x1))
    ya, yb = sorted((y0, y1))
    c0 = round(xa / res)
    c1 = max(c0 + 1, round(xb / res))
    r0 = h - round(yb / res)
    r1 = max(r0 + 1, h - round(ya / res))
    img[max(r0, 0) : max(r1, 0), max(c0, 0) : max(c1, 0)] = value


def _all(
    img: NDArray[np.uint8], res: float, x0: float, y0: float, x1: float, y1: float, value: int
) -> bool:
    h, w = img.shape
    c0, c1 = max(0, round(min(x0, x1) / res)), min(w, round(max(x0, x1) / res))
    r0, r1 = max(0, h - round(max(y0, y1) / res)), min(h, h - round(min(y0, y1) / res))
    region = img[r0:r1, c0:c1]
    return bool(region.size) and bool(np.all(region == value))


def _finish(
    img: NDArray[np.uint8],
    rng: np.random.Generator,
    res: float,
    origin: tuple[float, float, float] | None,
    transpose: bool,
) -> OccupancyMap:
    """Mirror the drawing at random (the layouts are drawn long side along x) and give it an
    origin: a random one, as a real map's, unless one is given."""
    if transpose:
        img = img.T
    if rng.random() < 0.5:
        img = img[::-1]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    img = np.ascontiguousarray(img)
    if origin is None:
        h, w = img.shape
        origin = (round(-rng.uniform(0, w * res), 3), round(-rng.uniform(0, h * res), 3), 0.0)
    return from_states(img, res, origin)


def _lounges(
    img: NDArray[np.uint8],
    reserved: NDArray[np.uint8],
    res: float,
    rng: np.random.Generator,
    *,
    axis: str,
    wall_at: float,
    inward: int,
    along: tuple[float, float],
    depth: float,
) -> None:
    """Gate lounges along a wall: a partition wall between gates, a gate counter by the wall and
    rows of seats parallel to it. ``axis`` is the direction the wall runs ("x" or "y")."""

    def rect(
        a0: float, a1: float, b0: float, b1: float, value: int, target: NDArray[np.uint8] = img
    ) -> None:
        p0, p1 = wall_at + inward * b0, wall_at + inward * b1
        if axis == "y":
            _box(target, res, p0, a0, p1, a1, value)
        else:
            _box(target, res, a0, p0, a1, p1, value)

    a = along[0] + rng.uniform(0, 3)
    while a + 8 < along[1] - 2:
        gs = min(rng.uniform(15, 25), along[1] - 2 - a)
        rect(a, a + gs, 0, depth, 1, reserved)
        rect(a, a + 0.2, 0, depth * rng.uniform(0.4, 0.7), OCCUPIED)
        centre = a + gs / 2
        rect(centre - 1.0, centre + 1.0, 0.8, 1.5, OCCUPIED)
        b = 2.6
        mid = centre + rng.uniform(-2, 2)
        while b + 0.55 < depth - 1.2:
            rect(a + 2, mid - 0.6, b, b + 0.55, OCCUPIED)
            rect(mid + 0.6, a + gs - 2, b, b + 0.55, OCCUPIED)
            b += 1.9
        a += gs


def _shops(
    img: NDArray[np.uint8],
    reserved: NDArray[np.uint8],
    res: float,
    rng: np.random.Generator,
    x0: float,
    x1: float,
    front_y: float,
    back_y: float,
) -> None:
    """A row of shops against the back wall: open fronts, shelves inside, sometimes a gap."""
    t = rng.uniform(0.15, 0.2)
    x = x0 + rng.uniform(0, 6)
    depth = back_y - front_y
    while x + 4 < x1:
        sw = min(rng.uniform(5, 12), x1 - x)
        if rng.random() < 0.2:
            x += rng.uniform(4, 10)
            continue
        _box(reserved, res, x - 1, front_y - 1.5, x + sw + 1, back_y, 1)
        _box(img, res, x, front_y, x + t, back_y, OCCUPIED)
        _box(img, res, x + sw - t, front_y, x + sw, back_y, OCCUPIED)
        _box(img, res, x, front_y, x + sw, front_y + t, OCCUPIED)
        open_w = sw * rng.uniform(0.4, 0.9)
        oa = x + t + rng.uniform(0, max(0.0, sw - 2 * t - open_w))
        _box(img, res, oa, front_y, min(oa + open_w, x + sw - t), front_y + t, FREE)
        if sw >= 4 and depth >= 4:
            for _ in range(int(rng.integers(1, 3))):
                sx = x + rng.uniform(1.0, sw - 1.6)
                _box(img, res, sx, front_y + 1.5, sx + 0.5, back_y - 0.8, OCCUPIED)
        x += sw


def make_airport_map(
    *,
    width_px: int,
    height_px: int,
    resolution: float = 0.05,
    origin: tuple[float, float, float] | None = None,
    rng: Seed,
) -> OccupancyMap:
    """A generated airport terminal.

    A main hall (with piers of gates when the map is deep enough), outer walls 0.25-0.45 m thick,
    a regular grid of IDENTICAL columns (spacing 7-12 m, 0.45-0.9 m, all round or all square;
    the hard case for alignment: repeated structure), shops with open fronts along the back
    wall, check-in islands, gate lounges (partitions, counters, rows of seats), service rooms
    with doors and some clutter. Everything inside is known free, outside unknown. Large
    furniture is sometimes an outline with unknown inside, as in SLAM-built maps.

    Parameters
    ----------
    width_px, height_px
        Map size in pixels (200 to 20000 each; 8000 x 8000 draws in about a second).
    resolution
        Metres per pixel.
    origin
        Map origin ``(x, y, yaw)``; default random, like a real map's.
    rng
        Generator or seed.

    Returns
    -------
    OccupancyMap
    """
    for name, value in (("width_px", width_px), ("height_px", height_px)):
        if not 200 <= value <= 20000:
            raise ValueError(f"{name} must be in [200, 20000], got {value}")
    _positive("resolution", resolution)
    rng = _as_rng(rng)
    res = resolution
    img = np.full((min(width_px, height_px), max(width_px, height_px)), UNKNOWN, np.uint8)
    lx, ly = img.shape[1] * res, img.shape[0] * res
    m = float(np.clip(0.03 * ly, 1.0, 8.0))
    wall = rng.uniform(0.25, 0.45)
    has_piers = ly >= 60 and rng.random() < 0.8
    hall_y0 = ly * rng.uniform(0.4, 0.55) if has_piers else m
    interior = np.zeros_like(img)
    _box(interior, res, m, hall_y0, lx - m, ly - m, 1)
    piers = []
    if has_piers:
        n = int(np.clip((lx - 2 * m) // rng.uniform(45, 80), 1, 6))
        slot = (lx - 2 * m) / n
        for i in range(n):
            pw = min(rng.uniform(18, 28), 0.6 * slot)
            cx = m + (i + 0.5) * slot + rng.uniform(-0.15, 0.15) * (slot - pw)
            piers.append((cx - pw / 2, m, cx + pw / 2, hall_y0 + wall + res))
            _box(interior, res, *piers[-1], 1)
    wp = max(1, round(wall / res))
    inner = cv2.erode(interior, np.ones((2 * wp + 1, 2 * wp + 1), np.uint8))
    img[interior > 0] = OCCUPIED
    img[inner > 0] = FREE
    reserved = np.zeros_like(img)  # where the columns are left out
    hx0, hx1, hy0, hy1 = m + wall, lx - m - wall, hall_y0 + wall, ly - m - wall
    hall_w, hall_h = hx1 - hx0, hy1 - hy0

    # The column grid: one stamp, integer pixel steps, so every column is the same pixels.
    sx = min(rng.uniform(7, 12), max(3.0, hall_w / 4))
    sy = min(rng.uniform(7, 12), max(3.0, hall_h / 3))
    size_px = max(2, round(rng.uniform(0.45, 0.9) / res))
    if rng.random() < 0.5:
        yy, xx = np.mgrid[:size_px, :size_px] - (size_px - 1) / 2
        stamp = xx**2 + yy**2 <= (size_px / 2) ** 2
    else:
        stamp = np.ones((size_px, size_px), bool)
    step_x, step_y = round(sx / res), round(sy / res)
    first_x = round((hx0 + rng.uniform(2.0, max(2.0, min(sx, hall_w / 2)))) / res)
    first_y = round((hy0 + rng.uniform(2.0, max(2.0, min(sy, hall_h / 2)))) / res)
    col_x = list(range(first_x, round((hx1 - 1.5) / res), step_x))
    col_y = list(range(first_y, round((hy1 - 1.5) / res), step_y))

    # A big hall is split into halls by inner walls with wide openings.
    for lo, hi, along_x in ((hx0, hx1, True), (hy0, hy1, False)):
        at = lo + rng.uniform(60, 120)
        while hi - at > 40:
            a0, a1 = (hy0, hy1) if along_x else (hx0, hx1)
            parts = [(a0, a1, OCCUPIED)]
            for _ in range(int(rng.integers(2, 5))):
                centre, width = rng.uniform(a0 + 8, a1 - 8), rng.uniform(6, 15)
                parts.append((centre - width / 2, centre + width / 2, FREE))
            for a, b, value in parts:
                if along_x:
                    _box(img, res, at, a, at + wall, b, value)
                else:
                    _box(img, res, a, at, b, at + wall, value)
            if along_x:
                _box(reserved, res, at - 1.5, a0, at + wall + 1.5, a1, 1)
            else:
                _box(reserved, res, a0, at - 1.5, a1, at + wall + 1.5, 1)
            at += rng.uniform(60, 120)

    shop_depth = min(rng.uniform(5, 9), 0.3 * hall_h)
    if shop_depth >= 3.0 and hall_w >= 12:
        _shops(img, reserved, res, rng, hx0, hx1, hy1 - shop_depth, hy1)
    else:
        shop_depth = 0.0

    # Check-in islands in the middle of bays between column rows.
    depth = rng.uniform(0.8, 1.6)
    bays = [(a + b) / 2 * res for a, b in itertools.pairwise(col_y)]
    bays = [y for y in bays if y < hy1 - shop_depth - 3 and (not has_piers or y > hy0 + 6)]
    if bays and sy * 1.0 - size_px * res - 3 >= depth:
        for yc in rng.permutation(bays)[: int(rng.integers(1, 3))]:
            x = hx0 + rng.uniform(4, 10)
            while x + 10 < hx1 - 4:
                length = min(rng.uniform(10, 20), hx1 - 4 - x)
                _box(
                    reserved, res, x - 1, yc - depth / 2 - 1, x + length + 1, yc + depth / 2 + 1, 1
                )
                _box(img, res, x, yc - depth / 2, x + length, yc + depth / 2, OCCUPIED)
                if rng.random() < 0.5:  # an outline with unknown inside
                    _box(
                        img,
                        res,
                        x + 2 * res,
                        yc - depth / 2 + 2 * res,
                        x + length - 2 * res,
                        yc + depth / 2 - 2 * res,
                        UNKNOWN,
                    )
                x += length + rng.uniform(3, 6)

    # Gates: lounges along the piers' sides, or along the hall's front wall.
    pier_axes = []
    if has_piers:
        for px0, _py0, px1, py1 in piers:
            ix0, ix1 = px0 + wall, px1 - wall
            walk = rng.uniform(5, 8)
            ld = (ix1 - ix0 - walk) / 2
            pier_axes.append(((ix0 + ix1) / 2, m + wall, py1))
            if ld >= 3:
                for wall_x, inward in ((ix0, 1), (ix1, -1)):
                    _lounges(
                        img,
                        reserved,
                        res,
                        rng,
                        axis="y",
                        wall_at=wall_x,
                        inward=inward,
                        along=(m + wall, hall_y0),
                        depth=ld,
                    )
    elif hall_h >= 20:
        ld = min(rng.uniform(6, 10), 0.3 * hall_h)
        _lounges(
            img, reserved, res, rng, axis="x", wall_at=hy0, inward=1, along=(hx0, hx1), depth=ld
        )

    # Service rooms with a door and a partition.
    for _ in range(int(rng.integers(0, 3))):
        rw, rh = rng.uniform(6, 10), rng.uniform(4, 6)
        if hall_w < rw + 6 or hall_h < rh + 6:
            break
        x, y = rng.uniform(hx0 + 3, hx1 - rw - 3), rng.uniform(hy0 + 3, hy1 - rh - 3)
        if not _all(reserved, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, 0):
            continue
        if not _all(img, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, FREE):
            continue
        _box(reserved, res, x - 1.5, y - 1.5, x + rw + 1.5, y + rh + 1.5, 1)
        _box(img, res, x, y, x + rw, y + rh, OCCUPIED)
        _box(img, res, x + 0.2, y + 0.2, x + rw - 0.2, y + rh - 0.2, FREE)
        door = x + rng.uniform(0.5, rw - 1.7)
        _box(img, res, door, y, door + 1.2, y + 0.2, FREE)
        _box(img, res, x + rw / 2, y + 1.4, x + rw / 2 + 0.15, y + rh, OCCUPIED)

    # Columns, where nothing else stands.
    h = img.shape[0]
    half = size_px // 2
    gap = round(1.0 / res)

    def column(cx_px: int, cy_px: int) -> None:
        r, c = h - cy_px - half, cx_px - half
        if r - gap < 0 or c - gap < 0 or r + size_px + gap > h or c + size_px + gap > img.shape[1]:
            return
        if reserved[r - gap : r + size_px + gap, c - gap : c + size_px + gap].any():
            return
        if np.any(img[r - gap : r + size_px + gap, c - gap : c + size_px + gap] != FREE):
            return
        img[r : r + size_px, c : c + size_px][stamp] = OCCUPIED

    for cy in col_y:
        for cx in col_x:
            column(cx, cy)
    for axis_x, y_end, y_hall in pier_axes:
        for cy in range(round((y_end + 3) / res), round((y_hall - 1) / res), step_y):
            column(round(axis_x / res), cy)

    # Clutter: bins, benches, signs.
    for _ in range(int(hall_w * hall_h / rng.uniform(120, 250))):
        s = rng.uniform(0.3, 0.6)
        x, y = rng.uniform(hx0 + 1, hx1 - 1), rng.uniform(hy0 + 1, hy1 - 1)
        if _all(img, res, x - 1, y - 1, x + s + 1, y + s + 1, FREE) and _all(
            reserved, res, x - 1, y - 1, x + s + 1, y + s + 1, 0
        ):
            _box(img, res, x, y, x + s, y + s, OCCUPIED)
    return _finish(img, rng, res, origin, height_px > width_px)


def _furnish(
    rect: _Box,
    rng: np.random.Generator,
    x0: float,
    x1: float,
    b0: float,
    b1: float,
    door: tuple[float, float],
    hospital: bool,
) -> None:
    """Furniture in a room ``[x0, x1] x [b0, b1]`` (b from the corridor), clear of the door."""
    keep_out = [(door[0] - 0.3, 0.0, door[1] + 0.3, b0 + 1.6)]
    placed: list[tuple[float, float, float, float]] = []

    def fits(r: tuple[float, float, float, float]) -> bool:
        if r[0] < x0 or r[2] > x1 or r[1] < b0 or r[3] > b1:
            return False
        for k in keep_out:
            if r[0] < k[2] and k[0] < r[2] and r[1] < k[3] and k[1] < r[3]:
                return False
        return not any(
            r[0] < p[2] + 0.8 and p[0] - 0.8 < r[2] and r[1] < p[3] + 0.8 and p[1] - 0.8 < r[3]
            for p in placed
        )

    items = int(rng.integers(1, 3)) if hospital else int(rng.integers(1, 4))
    for _ in range(items):
        for _ in range(20):
            if hospital:
                x = rng.uniform(x0, max(x0, x1 - 0.95))
                r = (x, b1 - 2.0, x + 0.95, b1)
            elif rng.random() < 0.6:
                length, d = rng.uniform(1.2, 1.8), rng.uniform(0.6, 0.8)
                x = rng.uniform(x0, max(x0, x1 - length))
                r = (x, b1 - d, x + length, b1)
            else:
                length, d = rng.uniform(1.2, 1.8), rng.uniform(0.6, 0.8)
                b = rng.uniform(b0 + 1.7, max(b0 + 1.7, b1 - length))
                x = x0 if rng.random() < 0.5 else x1 - d
                r = (x, b, x + d, b + length)
            if fits(r):
                placed.append(r)
                rect(*r, OCCUPIED)
                break


def _office_block(
    box: _Box,
    rng: np.random.Generator,
    xa: float,
    xb: float,
    y_edge: float,
    y_far: float,
    wt: float,
    hospital: bool,
) -> None:
    """Rooms along one side of a corridor, from the corridor edge ``y_edge`` towards ``y_far``;
    when the block is deep, an open-plan area behind them reached through a passage."""
    sgn = 1 if y_far > y_edge else -1
    depth = abs(y_far - y_edge)

    def rect(x0: float, b0: float, x1: float, b1: float, value: int) -> None:
        box(x0, y_edge + sgn * b0, x1, y_edge + sgn * b1, value)

    rd = rng.uniform(5, 7) if hospital else rng.uniform(4, 7)
    if depth - rd < 3.5:
        rd = depth
    open_area = rd < depth
    rooms = []
    x = xa
    while x < xb - 1e-6:
        rw = rng.uniform(4, 7) if hospital else rng.uniform(3, 6)
        if xb - (x + rw) < 2.5:
            rw = xb - x
        rooms.append((x, x + rw))
        x += rw
    passage = int(rng.integers(len(rooms))) if open_area else -1
    rect(xa, 0, xb, wt, OCCUPIED)
    if open_area:
        rect(xa, rd - wt, xb, rd, OCCUPIED)
    for x0, _x1 in rooms:
        rect(x0, 0, x0 + wt, rd, OCCUPIED)
    rect(xb - wt, 0, xb, rd, OCCUPIED)
    for i, (x0, x1) in enumerate(rooms):
        right = x1 if i < len(rooms) - 1 else xb - wt
        if i == passage:
            rect(x0 + wt, 0, right, wt, FREE)
            rect(x0 + wt, rd - wt, right, rd, FREE)
            continue
        inner = right - x0 - wt
        dw = rng.uniform(1.2, 1.6) if hospital else rng.uniform(0.9, 1.2)
        dw = min(dw, max(0.8, inner - 0.4))
        dx = x0 + wt + rng.uniform(0.2, max(0.2, inner - dw - 0.2))
        rect(dx, 0, dx + dw, wt, FREE)
        far = rd - wt if open_area else depth
        _furnish(rect, rng, x0 + wt, right, wt, far, (dx, dx + dw), hospital)
    if open_area and passage >= 0:
        px0, px1 = rooms[passage]
        b = rd + 1.5
        while b + 1.6 < depth - 1.0:
            x = xa + 1.5
            while x + 2.8 < xb - 1.5:
                k = int(rng.integers(2, 5))
                width = min(k * 1.4, xb - 1.5 - x)
                clear_of_passage = x + width < px0 - 0.5 or x > px1 + 0.5 or b > rd + 2.5
                if clear_of_passage and rng.random() < 0.8:
                    rect(x, b, x + width, b + 1.6, OCCUPIED)
                x += width + 1.5
            b += 1.6 + 1.6


def make_office_map(
    *,
    width_m: float | None = None,
    height_m: float | None = None,
    resolution: float = 0.05,
    style: str | None = None,
    origin: tuple[float, float, float] | None = None,
    rng: Seed,
) -> OccupancyMap:
    """A generated office or hospital floor: corridors, rooms with doors, furniture.

    A main corridor (1.6-2.2 m wide; hospital 2.2-3.0 m) along the long side, often a cross
    corridor, rows of rooms 3-6 m wide (hospital 4-7 m) with a door (0.9-1.2 m; hospital
    1.2-1.6 m) onto the corridor, desks or beds inside, and behind the rooms of a deep block an
    open-plan area with desk clusters, reached through a passage. Inside known free, outside
    unknown, a 1 m unknown margin around the building.

    Parameters
    ----------
    width_m, height_m
        Building size in metres; default random in 20-40 m. At least 8 m each.
    resolution
        Metres per pixel.
    style
        ``office`` or ``hospital``; default random.
    origin
        Map origin ``(x, y, yaw)``; default random, like a real map's.
    rng
        Generator or seed.

    Returns
    -------
    OccupancyMap
    """
    _positive("resolution", resolution)
    rng = _as_rng(rng)
    if style is None:
        style = "office" if rng.random() < 0.6 else "hospital"
    if style not in ("office", "hospital"):
        raise ValueError(f"style must be 'office' or 'hospital', got {style!r}")
    wm = float(width_m) if width_m is not None else rng.uniform(20, 40)
    hm = float(height_m) if height_m is not None else rng.uniform(20, 40)
    if min(wm, hm) < 8:
        raise ValueError(f"width_m and height_m must be >= 8, got {wm} and {hm}")
    hospital = style == "hospital"
    res = resolution
    lx, ly = max(wm, hm), min(wm, hm)
    m = 1.0
    img = np.full((round((ly + 2 * m) / res), round((lx + 2 * m) / res)), UNKNOWN, np.uint8)

    def box(x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        _box(img, res, x0 + m, y0 + m, x1 + m, y1 + m, value)

    wt = rng.uniform(0.15, 0.25) if hospital else rng.uniform(0.1, 0.2)
    cw = rng.uniform(2.2, 3.0) if hospital else rng.uniform(1.6, 2.2)
    box(0, 0, lx, ly, OCCUPIED)
    box(wt, wt, lx - wt, ly - wt, FREE)
    yc = rng.uniform(0.35, 0.65) * ly
    cy0, cy1 = yc - cw / 2, yc + cw / 2
    spans = [(wt, lx - wt)]
    if lx >= 22 and rng.random() < 0.7:
        xc = rng.uniform(0.3, 0.7) * lx
        spans = [(wt, xc - cw / 2), (xc + cw / 2, lx - wt)]
    for xa, xb in spans:
        if xb - xa < 3:
            continue
        _office_block(box, rng, xa, xb, cy0, wt, wt, hospital)
        _office_block(box, rng, xa, xb, cy1, ly - wt, wt, hospital)
    # Cabinets and benches against the corridor walls, never in front of a door.
    for _ in range(int(rng.integers(0, 5))):
        length, d = rng.uniform(0.8, 2.0), rng.uniform(0.35, 0.5)
        x = rng.uniform(1.0, lx - 1.0 - length)
        if rng.random() < 0.5:
            behind, y0, y1 = cy0 - wt / 2, cy0, cy0 + d
        else:
            behind, y0, y1 = cy1 + wt / 2, cy1 - d, cy1
        wall_ok = _all(
            img,
            res,
            x - 0.5 + m,
            behind + m - res / 2,
            x + length + 0.5 + m,
            behind + m + res / 2,
            OCCUPIED,
        )
        if wall_ok and _all(img, res, x + m, y0 + m, x + length + m, y1 + m, FREE):
            box(x, y0, x + length, y1, OCCUPIED)
    return _finish(img, rng, res, origin, hm > wm)


def roughen_map(
    world: OccupancyMap,
    *,
    rng: Seed,
    edge_rate: float = 0.15,
    speckles_per_100m2: float = 1.0,
) -> OccupancyMap:
    """A generated map made to look SLAM-built: ragged wall faces and a few lone speckles.

    Parameters
    ----------
    world
        The map (not modified).
    rng
        Generator or seed.
    edge_rate
        Share of the free cells touching an occupied cell that become occupied.
    speckles_per_100m2
        Lone occupied cells per 100 m2 of free space.

    Returns
    -------
    OccupancyMap
        Same size, resolution and origin.
    """
    if not 0 <= edge_rate <= 1:
        raise ValueError(f"edge_rate must be in [0, 1], got {edge_rate}")
    if speckles_per_100m2 < 0:
        raise ValueError(f"speckles_per_100m2 must be >= 0, got {speckles_per_100m2}")
    rng = _as_rng(rng)
    state = world.state.copy()
    free = state == FREE
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
    touching = free & (cv2.dilate((state == OCCUPIED).astype(np.uint8), cross) > 0)
    edge = np.flatnonzero(touching)
    grown = edge[rng.random(edge.size) < edge_rate]
    n_free = int(np.count_nonzero(free))
    count = int(rng.poisson(speckles_per_100m2 * n_free * world.resolution**2 / 100))
    flat = state.reshape(-1)
    flat[grown] = OCCUPIED
    if count and n_free:
        # Uniform over the free cells, by rejection: no index array as big as the map.
        draws = rng.integers(0, flat.size, max(64, 4 * count * flat.size // n_free))
        flat[draws[free.reshape(-1)[draws]][:count]] = OCCUPIED
    return from_states(state, world.resolution, world.origin)
