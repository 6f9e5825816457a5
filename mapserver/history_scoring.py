"""Scoring a fleet map's final version against a site history's ground truth (contract section 7).

The inputs are the reference map (version 1, as the history's bundles saw it before any change),
the final published map (``current.yaml`` after every bundle was processed, in auto mode) and
the parsed ``history.yaml``. Nothing here runs the server; ``benchmarks/bench_history.py`` does.

Cells and polygons. Both maps must share one grid (size, resolution, origin). A cell belongs to
a polygon when its CENTRE lies in the closed polygon (boundary included, even-odd rule, the same
rule as :func:`mapserver.scoring.point_in_polygon`). "Grown by one cell" is a dilation of those
cells by one cell, diagonals included (a 3 x 3 square); "grown by 0.3 m" is every cell whose
centre lies within 0.3 m of the polygon, measured exactly from the centre to the polygon (the
Euclidean distance transform of the polygon itself, not of its raster, which would be up to
half a cell off).

The rules (section 7), and the choices made where it is silent:

- A change is EXPECTED when it is permanent (``added`` or ``removed``), still there at the end
  (``until: null``), and seen in at least ``confirm_sessions`` sessions whose stamps span at
  least ``confirm_span_hours`` (``seen_until - seen_from``; both thresholds inclusive).
- An added (or temporary) change is HELD when at least :data:`ADDED_MIN_CELLS` cells of its
  polygon grown by one cell are occupied in the final map and not in the reference. A removed
  change is held when, of the cells it erased that are occupied in the reference, at least
  :data:`REMOVED_MIN_PERCENT` % or at least :data:`REMOVED_MIN_CELLS` are not occupied in the
  final map (free or unknown). Erased cells that the reference does not show occupied are not
  counted; a removed change with none is never held.
- Update recall = expected changes held / expected changes; 1.0 when none is expected ("nothing
  was missed", as :func:`mapserver.scoring.recall_from_counts` has it). Totals over histories
  are micro averages from the summed counts, so that convention never weighs in a total.
- Temporaries are the changes of kind ``temporary`` (whatever their ``until``) and the permanent
  ones gone before the end (``until`` not null); "the map holds anything, by the same rules"
  is read as the held rule above, per kind (a removed structure that came back is held when the
  map still shows its cells erased). The cell counts behind each verdict are kept, so a
  one-cell trace stays visible.
- False edits are the cells whose state (free, occupied, unknown: any change of state) differs
  from the reference outside every change's polygon grown by 0.3 m, ALL changes counted,
  temporary and unexpected ones included; the area is their number times the cell area.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from mapserver.bundle import BUNDLE_ID_RE
from mapserver.maps import OCCUPIED, OccupancyMap
from mapserver.scoring import (
    CHANGE_KINDS,
    ON_EDGE_M,
    STRUCTURAL_KINDS,
    ChangeId,
    as_mapping,
    as_polygon,
    check_format,
    field_of,
    kinded_items,
    parse_polygon,
    recall_from_counts,
)

ADDED_MIN_CELLS = 3
"""An added (or temporary) change is held when at least this many cells turned occupied."""
REMOVED_MIN_PERCENT = 30
"""A removed change is held when at least this share (percent) of its erased cells is gone ..."""
REMOVED_MIN_CELLS = 10
"""... or at least this many of them."""
GROW_CELLS = 1
"""Added changes are looked for in their polygon grown by this many cells."""
FALSE_EDIT_MARGIN_M = 0.3
"""Cells this close to some change's polygon are never false edits."""

Role = Literal["expected", "temporary", "unconfirmable"]
BoolArray = NDArray[np.bool_]


# --------------------------------------------------------------------------------------------
# Plain data


@dataclass(frozen=True, eq=False)
class HistoryChange:
    """One true change of ``history.yaml``.

    Attributes
    ----------
    polygon_xy
        (N, 2) float64, N >= 3, vertices in the nav2 frame, metres; the closing edge is implied.
    since, until
        When it was in the world (``from`` and ``until`` of the file); ``until`` is ``None``
        when it is still there at the end, ``since`` is ``None`` when the file has no ``from``.
    sessions, seen_from, seen_until
        How many bundles showed it, and the first and last of their stamps (``None`` when none
        did).
    erase
        (M,) int64 flat indices ``row * width + col`` (row 0 the image's top row) of the
        reference cells a removed change erased; empty for other kinds.
    shape
        The generator's word for it (``wall``, ``box``, ``cart`` ...) when the file has one.
    """

    id: ChangeId
    kind: str
    polygon_xy: NDArray[np.float64]
    until: datetime | None
    sessions: int
    seen_from: datetime | None
    seen_until: datetime | None
    erase: NDArray[np.int64]
    since: datetime | None = None
    shape: str | None = None

    @property
    def permanent(self) -> bool:
        """Whether it is an ``added`` or ``removed`` change (not ``temporary``)."""
        return self.kind in STRUCTURAL_KINDS

    @property
    def gone(self) -> bool:
        """Whether it left the world before the end of the history."""
        return self.until is not None

    @property
    def span_hours(self) -> float | None:
        """``seen_until - seen_from`` in hours; ``None`` when no session saw it."""
        if self.seen_from is None or self.seen_until is None:
            return None
        return (self.seen_until - self.seen_from).total_seconds() / 3600.0


@dataclass(frozen=True)
class History:
    """``history.yaml``: the name the map is registered under, and the true changes."""

    map: str
    changes: tuple[HistoryChange, ...]


@dataclass(frozen=True)
class ChangeScore:
    """How the final map fares on one true change.

    ``cells`` / ``of_cells``: for an added or temporary change, the cells of its polygon grown
    by one cell that are occupied in the final map and not in the reference / the cells of that
    region not occupied in the reference; for a removed change, the erased cells no longer
    occupied / the erased cells occupied in the reference.
    """

    id: ChangeId
    kind: str
    role: Role
    """``expected``; ``temporary`` (kind temporary, or gone before the end: must not be held);
    ``unconfirmable`` (permanent and still there, but seen too little: counted nowhere)."""
    held: bool
    cells: int
    of_cells: int

    @property
    def expected(self) -> bool:
        return self.role == "expected"


@dataclass(frozen=True)
class HistoryScore:
    """The score of one history's final map."""

    map: str
    changes: tuple[ChangeScore, ...]
    false_edit_cells: int
    false_edit_m2: float

    @property
    def n_expected(self) -> int:
        return sum(c.role == "expected" for c in self.changes)

    @property
    def n_expected_held(self) -> int:
        return sum(c.role == "expected" and c.held for c in self.changes)

    @property
    def n_temporaries(self) -> int:
        return sum(c.role == "temporary" for c in self.changes)

    @property
    def n_temporaries_in_map(self) -> int:
        """Temporaries the map holds (must be 0)."""
        return sum(c.role == "temporary" and c.held for c in self.changes)

    @property
    def update_recall(self) -> float:
        """Expected changes held / expected changes; 1.0 when none is expected."""
        return recall_from_counts(self.n_expected_held, self.n_expected)


@dataclass(frozen=True)
class HistoryTotals:
    """Sums over histories; the recall is from the summed counts (a micro average)."""

    n_histories: int
    n_expected: int
    n_expected_held: int
    n_temporaries: int
    n_temporaries_in_map: int
    false_edit_cells: int
    false_edit_m2: float
    false_edit_m2_max: float
    """The largest false-edit area of one history (0.0 with no history)."""

    @property
    def update_recall(self) -> float:
        return recall_from_counts(self.n_expected_held, self.n_expected)


# --------------------------------------------------------------------------------------------
# Parsing


def _time(value: Any, where: str) -> datetime:
    """An ISO 8601 time with a zone: a string, or the datetime YAML makes of an unquoted one."""
    if isinstance(value, str):
        text = value.strip()
        try:
            # Python 3.10's fromisoformat does not know the suffix Z.
            value = datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
        except ValueError:
            raise ValueError(f"{where} must be an ISO 8601 time, got {text!r}") from None
    if not isinstance(value, datetime):
        raise ValueError(f"{where} must be an ISO 8601 time, got {value!r}")
    if value.tzinfo is None or value.utcoffset() is None:
        raise ValueError(f"{where} must have a zone (e.g. 2026-11-21T10:15:00Z), got {value}")
    return value


def _optional_time(item: Mapping[str, Any], key: str, where: str) -> datetime | None:
    value = item.get(key)
    return None if value is None else _time(value, f"{where}.{key}")


def _count(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{where} must be an integer >= 0, got {value!r}")
    return value


def _erase(value: Any, where: str) -> NDArray[np.int64]:
    if not isinstance(value, list) or not value:
        raise ValueError(f"{where} must be a non-empty list of flat cell indices")
    for i, index in enumerate(value):
        _count(index, f"{where}[{i}]")
    return np.asarray(value, dtype=np.int64)


def _change(i: int, where: str, item: Mapping[str, Any], kind: str) -> HistoryChange:
    until = field_of(item, "until", where)
    until = None if until is None else _time(until, f"{where}.until")
    since = _optional_time(item, "from", where)
    if since is not None and until is not None and until < since:
        raise ValueError(f"{where}: until ({until}) is before from ({since})")
    sessions = _count(field_of(item, "sessions", where), f"{where}.sessions")
    seen_from = _optional_time(item, "seen_from", where)
    seen_until = _optional_time(item, "seen_until", where)
    if sessions and (seen_from is None or seen_until is None):
        raise ValueError(f"{where}: seen_from and seen_until are required when sessions > 0")
    if seen_from is not None and seen_until is not None and seen_until < seen_from:
        raise ValueError(f"{where}: seen_until ({seen_until}) is before seen_from ({seen_from})")
    if kind == "removed":
        erase = _erase(field_of(item, "erase", where), f"{where}.erase")
    else:
        erase = np.empty(0, np.int64)
    shape = item.get("shape")
    return HistoryChange(
        id=item.get("id", i + 1),
        kind=kind,
        polygon_xy=parse_polygon(field_of(item, "polygon", where), f"{where}.polygon"),
        until=until,
        sessions=sessions,
        seen_from=seen_from,
        seen_until=seen_until,
        erase=erase,
        since=since,
        shape=None if shape is None else str(shape),
    )


def parse_history(doc: Any) -> History:
    """A :class:`History` from a parsed ``history.yaml`` document.

    Every change needs ``kind``, ``polygon``, ``until`` (null when still there) and
    ``sessions``; ``seen_from`` and ``seen_until`` when ``sessions`` > 0; ``erase`` when it is
    removed. ``id`` defaults to its position from 1; ``from`` and ``shape`` are optional; other
    keys are ignored. Raises ``ValueError`` naming the bad field.
    """
    doc = as_mapping(doc, "history")
    check_format(doc, "history")
    name = field_of(doc, "map", "history")
    if not isinstance(name, str) or not BUNDLE_ID_RE.fullmatch(name):
        raise ValueError(f"history.map must be a map name ({BUNDLE_ID_RE.pattern}), got {name!r}")
    changes = [
        _change(i, where, item, kind)
        for i, where, item, kind in kinded_items(
            doc.get("changes") or [], "history.changes", CHANGE_KINDS
        )
    ]
    seen: set[ChangeId] = set()
    for change in changes:
        if change.id in seen:
            raise ValueError(f"history.changes: id {change.id!r} is used twice")
        seen.add(change.id)
    return History(name, tuple(changes))


def read_history(path: str | Path) -> History:
    """:func:`parse_history` of a ``history.yaml`` file; a ``ValueError`` names the file."""
    path = Path(path)
    try:
        return parse_history(yaml.safe_load(path.read_text(encoding="utf-8")))
    except (OSError, yaml.YAMLError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None


# --------------------------------------------------------------------------------------------
# Cells of polygons


def polygon_mask(
    grid_map: OccupancyMap, polygon_xy: ArrayLike, *, grow_m: float = 0.0
) -> BoolArray:
    """The cells of a map whose centre lies within ``grow_m`` of a closed polygon.

    Parameters
    ----------
    grid_map
        Only its grid is used (size, resolution, origin).
    polygon_xy
        (N, 2) vertices, metres, N >= 3; the closing edge is implied. Even-odd rule.
    grow_m
        Metres, >= 0; 0 gives the cells whose centre is in the polygon or on its boundary.

    Returns
    -------
    (H, W) bool, indexed [row, col], row 0 at the top.
    """
    polygon = as_polygon(polygon_xy)
    if not (grow_m >= 0 and math.isfinite(grow_m)):
        raise ValueError(f"grow_m must be a finite number >= 0, got {grow_m}")
    height, width = grid_map.state.shape
    mask = np.zeros((height, width), bool)
    reach = grow_m + ON_EDGE_M
    lo = polygon.min(axis=0) - reach
    hi = polygon.max(axis=0) + reach
    cols, rows = grid_map.world_to_pixel([lo[0], hi[0]], [hi[1], lo[1]])
    # One cell of slack on each side; the exact test below decides.
    c0, c1 = max(math.floor(cols[0]), 0), min(math.ceil(cols[1]), width - 1)
    r0, r1 = max(math.floor(rows[0]), 0), min(math.ceil(rows[1]), height - 1)
    if c0 > c1 or r0 > r1:
        return mask
    x, y = grid_map.pixel_to_world(np.arange(c0, c1 + 1), np.arange(r0, r1 + 1))
    xx, yy = x[None, :], y[:, None]
    inside = np.zeros((y.size, x.size), bool)
    distance2 = np.full((y.size, x.size), np.inf)
    for (x0, y0), (x1, y1) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        # Even-odd crossings of a ray towards +x, half-open in y as in scoring.point_in_polygon.
        straddles = (y0 > y) != (y1 > y)
        if straddles.any():
            x_cross = x0 + (y[straddles] - y0) * (x1 - x0) / (y1 - y0)
            inside[straddles] ^= x_cross[:, None] > xx
        dx, dy = x1 - x0, y1 - y0
        length2 = dx * dx + dy * dy
        t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / length2, 0.0, 1.0) if length2 else 0.0
        np.minimum(distance2, (xx - x0 - t * dx) ** 2 + (yy - y0 - t * dy) ** 2, out=distance2)
    mask[r0 : r1 + 1, c0 : c1 + 1] = inside | (distance2 <= reach * reach)
    return mask


def _check_same_grid(reference: OccupancyMap, final: OccupancyMap) -> None:
    if reference.state.shape != final.state.shape:
        raise ValueError(
            f"the final map is {final.width} x {final.height} cells, the reference "
            f"{reference.width} x {reference.height}: they must share one grid"
        )
    if not math.isclose(reference.resolution, final.resolution, rel_tol=1e-9):
        raise ValueError(
            f"the final map's resolution is {final.resolution}, the reference's "
            f"{reference.resolution}: they must share one grid"
        )
    gap = max(
        abs(reference.origin[0] - final.origin[0]), abs(reference.origin[1] - final.origin[1])
    )
    if gap > 1e-6 * reference.resolution:
        raise ValueError(
            f"the final map's origin is {final.origin[:2]}, the reference's "
            f"{reference.origin[:2]}: they must share one grid"
        )


def added_cells(
    reference: OccupancyMap, final: OccupancyMap, polygon_xy: ArrayLike
) -> tuple[int, int]:
    """``(turned, candidates)``: the cells of the polygon grown by :data:`GROW_CELLS` cells that
    are occupied in ``final`` and not in ``reference``, and those not occupied in ``reference``.
    """
    _check_same_grid(reference, final)
    size = 2 * GROW_CELLS + 1
    region = polygon_mask(reference, polygon_xy).view(np.uint8)
    grown = cv2.dilate(region, np.ones((size, size), np.uint8)).view(bool)
    candidates = grown & (reference.state != OCCUPIED)
    turned = candidates & (final.state == OCCUPIED)
    return int(np.count_nonzero(turned)), int(np.count_nonzero(candidates))


def removed_cells(
    reference: OccupancyMap, final: OccupancyMap, erase: ArrayLike
) -> tuple[int, int]:
    """``(gone, erased)``: of the cells of ``erase`` (flat indices ``row * width + col``) that
    are occupied in ``reference``, those not occupied in ``final``, and all of them."""
    _check_same_grid(reference, final)
    flat = np.asarray(erase, dtype=np.int64).reshape(-1)
    if flat.size and (flat.min() < 0 or flat.max() >= reference.state.size):
        raise ValueError(
            f"erase holds a cell index outside the map's {reference.state.size} cells "
            f"({int(flat.min())} .. {int(flat.max())})"
        )
    flat = np.unique(flat)
    erased = flat[reference.state.reshape(-1)[flat] == OCCUPIED]
    gone = np.count_nonzero(final.state.reshape(-1)[erased] != OCCUPIED)
    return int(gone), int(erased.size)


def false_edit_mask(
    reference: OccupancyMap,
    final: OccupancyMap,
    polygons_xy: Iterable[ArrayLike],
    *,
    margin_m: float = FALSE_EDIT_MARGIN_M,
) -> BoolArray:
    """(H, W) bool: the cells whose state differs between the maps, outside every polygon
    grown by ``margin_m`` metres (see :func:`polygon_mask`)."""
    _check_same_grid(reference, final)
    edits: BoolArray = final.state != reference.state
    for polygon in polygons_xy:
        edits &= ~polygon_mask(reference, polygon, grow_m=margin_m)
    return edits


# --------------------------------------------------------------------------------------------
# Scoring


def is_expected(change: HistoryChange, *, confirm_sessions: int, confirm_span_hours: float) -> bool:
    """Whether the final map should hold the change: permanent, still there at the end, seen in
    at least ``confirm_sessions`` sessions spread over at least ``confirm_span_hours``."""
    span = change.span_hours
    return (
        change.permanent
        and not change.gone
        and change.sessions >= confirm_sessions
        and span is not None
        and span >= confirm_span_hours
    )


def _role(change: HistoryChange, *, confirm_sessions: int, confirm_span_hours: float) -> Role:
    if not change.permanent or change.gone:
        return "temporary"
    if is_expected(
        change, confirm_sessions=confirm_sessions, confirm_span_hours=confirm_span_hours
    ):
        return "expected"
    return "unconfirmable"


def score_change(
    reference: OccupancyMap,
    final: OccupancyMap,
    change: HistoryChange,
    *,
    confirm_sessions: int = 3,
    confirm_span_hours: float = 12.0,
) -> ChangeScore:
    """Whether ``final`` holds one change, and the cell counts behind the verdict."""
    role = _role(change, confirm_sessions=confirm_sessions, confirm_span_hours=confirm_span_hours)
    try:
        if change.kind == "removed":
            cells, of_cells = removed_cells(reference, final, change.erase)
            held = cells > 0 and (
                cells >= REMOVED_MIN_CELLS or 100 * cells >= REMOVED_MIN_PERCENT * of_cells
            )
        else:
            cells, of_cells = added_cells(reference, final, change.polygon_xy)
            held = cells >= ADDED_MIN_CELLS
    except ValueError as error:
        raise ValueError(f"change {change.id!r}: {error}") from None
    return ChangeScore(change.id, change.kind, role, held, cells, of_cells)


def score_history(
    reference: OccupancyMap,
    final: OccupancyMap,
    history: History,
    *,
    confirm_sessions: int = 3,
    confirm_span_hours: float = 12.0,
) -> HistoryScore:
    """Score a history's final map against its reference map (contract section 7).

    Parameters
    ----------
    reference
        The map as registered (version 1).
    final
        The last published version (``current.yaml``); same grid as ``reference``.
    history
        The history's truth.
    confirm_sessions, confirm_span_hours
        The server's ``update`` settings, which decide which changes are expected.

    Raises ``ValueError`` when the maps do not share one grid or an erased cell lies outside it.
    """
    if isinstance(confirm_sessions, bool) or not (
        isinstance(confirm_sessions, int) and confirm_sessions >= 1
    ):
        raise ValueError(f"confirm_sessions must be an integer >= 1, got {confirm_sessions!r}")
    if not (confirm_span_hours >= 0 and math.isfinite(confirm_span_hours)):
        raise ValueError(
            f"confirm_span_hours must be a finite number >= 0, got {confirm_span_hours}"
        )
    _check_same_grid(reference, final)
    scores = tuple(
        score_change(
            reference,
            final,
            change,
            confirm_sessions=confirm_sessions,
            confirm_span_hours=confirm_span_hours,
        )
        for change in history.changes
    )
    false_cells = int(
        np.count_nonzero(false_edit_mask(reference, final, (c.polygon_xy for c in history.changes)))
    )
    return HistoryScore(history.map, scores, false_cells, false_cells * reference.resolution**2)


def summarize_histories(scores: Iterable[HistoryScore]) -> HistoryTotals:
    """Totals over history scores (see :class:`HistoryTotals`)."""
    scores = list(scores)
    return HistoryTotals(
        n_histories=len(scores),
        n_expected=sum(s.n_expected for s in scores),
        n_expected_held=sum(s.n_expected_held for s in scores),
        n_temporaries=sum(s.n_temporaries for s in scores),
        n_temporaries_in_map=sum(s.n_temporaries_in_map for s in scores),
        false_edit_cells=sum(s.false_edit_cells for s in scores),
        false_edit_m2=sum(s.false_edit_m2 for s in scores),
        false_edit_m2_max=max((s.false_edit_m2 for s in scores), default=0.0),
    )
