"""Scoring results against benchmark ground truth (contract section 4), as pure functions.

The inputs are plain data: the parsed ``truth.yaml`` and ``result.yaml`` documents (mappings, as
``yaml.safe_load`` returns them) and, for the alignment error, the centre of the local map's
observed area. Nothing here reads files or runs the pipeline; ``benchmarks/bench_public.py`` does.

Matching (section 4): a reported difference MATCHES a change when

(a) its bbox, grown by :data:`BBOX_GROWTH_M` on every side, intersects the change's polygon;
(b) its centroid lies within :data:`CENTROID_DISTANCE_M` of the polygon (0 when inside);
(c) its bbox diagonal is at most the polygon's bbox diagonal + :data:`DIAGONAL_SLACK_M`.

All three comparisons are inclusive (touching counts). Polygons are closed regions (boundary
included) under the even-odd rule, given in the nav2 frame in metres; they need not be convex.

Choices where section 4 is silent, made once here:

- A difference that matches several structural changes is assigned to ONE of them for kind
  accuracy and fragments: a change of the difference's own kind first, then an observed one,
  then the one nearest to the difference's centroid, then the first listed. Recall does not use
  the assignment: every observed structural change matched by any difference counts as found.
- Fragments count, per structural change, the correct differences assigned to it beyond the
  first. Temporary changes have no fragments (their differences are neutral anyway).
- A bundle without a result, or whose result has ``status`` other than ``ok``, is a failure: it
  contributes its observed changes, unmatched, and no differences.
- A ratio with a zero denominator takes its value "nothing was wrong": precision 1.0 with no
  (non-neutral) differences, recall 1.0 with no observed structural changes. Kind accuracy
  with no correct differences is undefined (``None``). Totals over bundles are micro averages
  from the summed counts, so those conventions never weigh in a total.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapserver.geometry import Transform2D, wrap_angle
from mapserver.maps import UNKNOWN, OccupancyMap

BBOX_GROWTH_M = 0.25
"""Rule (a): the reported bbox is grown by this much on every side."""
CENTROID_DISTANCE_M = 0.5
"""Rule (b): the reported centroid must lie at most this far from the polygon."""
DIAGONAL_SLACK_M = 1.0
"""Rule (c): the reported bbox diagonal may exceed the polygon's bbox diagonal by this much."""

STRUCTURAL_KINDS = ("added", "removed")
CHANGE_KINDS = ("added", "removed", "temporary")

# Points closer than this to a polygon's boundary are on it. Far below any map resolution; it only
# absorbs the rounding of the point-segment projection.
ON_EDGE_M = 1e-9

Label = Literal["correct", "neutral", "false_positive"]
ChangeId = int | str


# --------------------------------------------------------------------------------------------
# Plain data


@dataclass(frozen=True, eq=False)
class Change:
    """One true change of ``truth.yaml``.

    Attributes
    ----------
    polygon_xy
        (N, 2) float64, N >= 3, vertices in the nav2 frame, metres; the closing edge is implied.
    """

    id: ChangeId
    kind: str
    polygon_xy: NDArray[np.float64]
    observed: bool

    @property
    def structural(self) -> bool:
        return self.kind in STRUCTURAL_KINDS


@dataclass(frozen=True)
class Truth:
    """``truth.yaml``: the true slam -> nav2 transform and the changes."""

    nav2_from_slam: Transform2D
    changes: tuple[Change, ...]


@dataclass(frozen=True)
class Difference:
    """One reported difference of ``result.yaml`` (nav2 frame, metres)."""

    id: ChangeId
    kind: str
    centroid_xy: tuple[float, float]
    bbox_m: tuple[float, float, float, float]
    """``(min_x, min_y, max_x, max_y)``."""


@dataclass(frozen=True)
class Result:
    """The parts of ``result.yaml`` that scoring reads."""

    status: str
    differences: tuple[Difference, ...] = ()
    nav2_from_slam: Transform2D | None = None
    timings_ms: Mapping[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class DifferenceScore:
    """How one reported difference was judged."""

    difference_id: ChangeId
    kind: str
    label: Label
    matched_change_ids: tuple[ChangeId, ...]
    """Every change (of any kind) the difference matches, in truth order."""
    assigned_change_id: ChangeId | None = None
    """The structural change it is counted on (``None`` unless ``label == "correct"``)."""
    kind_correct: bool | None = None
    """Whether its kind equals the assigned change's (``None`` unless correct)."""


def precision_from_counts(n_correct: int, n_false_positive: int) -> float:
    """``correct / (correct + false positives)``; 1.0 when there is nothing to judge."""
    total = n_correct + n_false_positive
    return n_correct / total if total else 1.0


def recall_from_counts(n_matched: int, n_observed: int) -> float:
    """``matched / observed``; 1.0 when nothing was there to find."""
    return n_matched / n_observed if n_observed else 1.0


def f1_from(precision: float, recall: float) -> float:
    """Harmonic mean of precision and recall; 0.0 when both are 0."""
    total = precision + recall
    return 2.0 * precision * recall / total if total > 0 else 0.0


@dataclass(frozen=True)
class _Counts:
    """What a score counts, and the ratios derived from the counts (one bundle or a total)."""

    n_differences: int
    n_correct: int
    n_neutral: int
    n_false_positive: int
    n_observed: int
    n_matched: int
    n_fragments: int
    n_kind_correct: int

    @property
    def precision(self) -> float:
        return precision_from_counts(self.n_correct, self.n_false_positive)

    @property
    def recall(self) -> float:
        return recall_from_counts(self.n_matched, self.n_observed)

    @property
    def f1(self) -> float:
        return f1_from(self.precision, self.recall)

    @property
    def kind_accuracy(self) -> float | None:
        return self.n_kind_correct / self.n_correct if self.n_correct else None


@dataclass(frozen=True)
class BundleScore(_Counts):
    """The score of one bundle. Counts are over differences, except ``n_observed`` and
    ``n_matched`` (observed structural changes, and those matched by at least one difference).

    ``n_correct + n_neutral + n_false_positive == n_differences``.
    """

    status: str
    """The result's ``status``, or ``"missing"`` when there was no result."""
    alignment_error_m: float | None = None
    alignment_error_rad: float | None = None
    differences: tuple[DifferenceScore, ...] = ()
    unmatched_change_ids: tuple[ChangeId, ...] = ()
    """Observed structural changes that no difference matched."""

    @property
    def failed(self) -> bool:
        return self.status != "ok"


# --------------------------------------------------------------------------------------------
# Parsing (the helpers history_scoring.py's parser shares are public)


def as_mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{where} must be a mapping, got {type(value).__name__}")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def field_of(doc: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in doc:
        raise ValueError(f"{where}: missing key '{key}'")
    return doc[key]


def _numbers(value: Any, where: str, keys: tuple[str, ...]) -> tuple[float, ...]:
    """The finite numbers under ``keys`` of mapping ``value`` (found at ``where``)."""
    doc = as_mapping(value, where)
    return tuple(_number(field_of(doc, k, where), f"{where}.{k}") for k in keys)


def kinded_items(
    raw: Any, where: str, kinds: tuple[str, ...]
) -> Iterator[tuple[int, str, Mapping[str, Any], str]]:
    """``(index, where, item, kind)`` of each mapping of list ``raw``, whose ``kind`` must be
    one of ``kinds``."""
    if not isinstance(raw, list):
        raise ValueError(f"{where} must be a list")
    for i, value in enumerate(raw):
        at = f"{where}[{i}]"
        item = as_mapping(value, at)
        kind = field_of(item, "kind", at)
        if kind not in kinds:
            raise ValueError(f"{at}.kind must be one of {kinds}, got {kind!r}")
        yield i, at, item, kind


def parse_polygon(value: Any, where: str) -> NDArray[np.float64]:
    """A polygon of a truth document (at ``where``): at least 3 finite [x, y] points."""
    try:
        polygon = as_polygon(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be a list of at least 3 [x, y] points") from None
    if not np.isfinite(polygon).all():
        raise ValueError(f"{where} must hold finite numbers")
    return polygon


def _transform(value: Any, where: str) -> Transform2D:
    theta, tx, ty = _numbers(value, where, ("theta", "tx", "ty"))
    return Transform2D(theta, tx, ty)


def check_format(doc: Mapping[str, Any], what: str) -> None:
    version = doc.get("format", 1)
    if version != 1:
        raise ValueError(f"{what}: unsupported format {version!r}; this scorer reads format 1")


def parse_truth(doc: Any) -> Truth:
    """A :class:`Truth` from a parsed ``truth.yaml`` document.

    Raises ``ValueError`` naming the bad field.
    """
    doc = as_mapping(doc, "truth")
    check_format(doc, "truth")
    transform = _transform(field_of(doc, "transform", "truth"), "truth.transform")
    changes = []
    for i, where, item, kind in kinded_items(
        doc.get("changes") or [], "truth.changes", CHANGE_KINDS
    ):
        polygon = parse_polygon(field_of(item, "polygon", where), f"{where}.polygon")
        observed = field_of(item, "observed", where)
        if not isinstance(observed, bool):
            raise ValueError(f"{where}.observed must be true or false, got {observed!r}")
        changes.append(Change(item.get("id", i + 1), kind, polygon, observed))
    return Truth(transform, tuple(changes))


def parse_result(doc: Any) -> Result:
    """A :class:`Result` from a parsed ``result.yaml`` document.

    Only the fields scoring needs are read: ``status``, and for an ``ok`` result ``differences``
    (each ``kind``, ``centroid``, ``bbox``; ``id`` defaults to its position from 1),
    ``alignment`` (``theta``, ``tx``, ``ty``; optional) and ``timings_ms`` (optional).
    Raises ``ValueError`` naming the bad field.
    """
    doc = as_mapping(doc, "result")
    check_format(doc, "result")
    status = field_of(doc, "status", "result")
    if not isinstance(status, str):
        raise ValueError(f"result.status must be a string, got {status!r}")
    timings = {
        str(k): _number(v, f"result.timings_ms.{k}")
        for k, v in as_mapping(doc.get("timings_ms") or {}, "result.timings_ms").items()
    }
    if status != "ok":
        return Result(status, timings_ms=timings)
    differences = []
    for i, where, item, kind in kinded_items(
        field_of(doc, "differences", "result") or [], "result.differences", STRUCTURAL_KINDS
    ):
        x, y = _numbers(field_of(item, "centroid", where), f"{where}.centroid", ("x", "y"))
        centroid = (x, y)
        min_x, min_y, max_x, max_y = _numbers(
            field_of(item, "bbox", where), f"{where}.bbox", ("min_x", "min_y", "max_x", "max_y")
        )
        bbox = (min_x, min_y, max_x, max_y)
        if bbox[0] > bbox[2] or bbox[1] > bbox[3]:
            raise ValueError(f"{where}.bbox must have min <= max, got {bbox}")
        differences.append(Difference(item.get("id", i + 1), kind, centroid, bbox))
    alignment = doc.get("alignment")
    transform = None if alignment is None else _transform(alignment, "result.alignment")
    return Result(status, tuple(differences), transform, timings)


# --------------------------------------------------------------------------------------------
# Geometry (closed polygons, even-odd rule)


def as_polygon(polygon_xy: ArrayLike) -> NDArray[np.float64]:
    polygon = np.asarray(polygon_xy, dtype=float)
    if polygon.ndim != 2 or polygon.shape[0] < 3 or polygon.shape[1] != 2:
        raise ValueError(f"polygon_xy must have shape (N >= 3, 2), got {polygon.shape}")
    return polygon


def _distance_to_boundary_m(point_xy: ArrayLike, polygon: NDArray[np.float64]) -> float:
    p = np.asarray(point_xy, dtype=float)
    a = polygon
    ab = np.roll(polygon, -1, axis=0) - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.divide(
        np.einsum("ij,ij->i", p - a, ab), length2, out=np.zeros_like(length2), where=length2 > 0
    )
    closest = a + np.clip(t, 0.0, 1.0)[:, None] * ab
    return float(np.min(np.hypot(*(p - closest).T)))


def point_in_polygon(point_xy: ArrayLike, polygon_xy: ArrayLike) -> bool:
    """Whether a point lies in a closed polygon (boundary included; even-odd rule).

    Parameters
    ----------
    point_xy
        (2,) metres.
    polygon_xy
        (N, 2) vertices, metres, N >= 3; the closing edge is implied.
    """
    polygon = as_polygon(polygon_xy)
    x, y = (float(v) for v in np.asarray(point_xy, dtype=float))
    if _distance_to_boundary_m((x, y), polygon) <= ON_EDGE_M:
        return True
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    # Half-open in y so that a ray through a vertex counts the crossing once.
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return bool(np.count_nonzero(straddles & (x_cross > x)) % 2)


def point_polygon_distance_m(point_xy: ArrayLike, polygon_xy: ArrayLike) -> float:
    """Distance (metres) from a point to a closed polygon: 0 inside or on it, else to its boundary."""
    polygon = as_polygon(polygon_xy)
    if point_in_polygon(point_xy, polygon):
        return 0.0
    return _distance_to_boundary_m(point_xy, polygon)


def rect_intersects_polygon(
    bbox_m: tuple[float, float, float, float] | Sequence[float], polygon_xy: ArrayLike
) -> bool:
    """Whether an axis-aligned rectangle and a closed polygon share at least one point.

    Parameters
    ----------
    bbox_m
        ``(min_x, min_y, max_x, max_y)`` metres, closed (touching counts).
    polygon_xy
        (N, 2) vertices, metres.
    """
    polygon = as_polygon(polygon_xy)
    min_x, min_y, max_x, max_y = (float(v) for v in bbox_m)
    if min_x > max_x or min_y > max_y:
        raise ValueError(f"bbox_m must have min <= max, got {tuple(bbox_m)}")
    # Some polygon edge meets the rectangle (Liang-Barsky clipping of every edge at once)...
    start = polygon
    delta = np.roll(polygon, -1, axis=0) - start
    p = np.stack([-delta[:, 0], delta[:, 0], -delta[:, 1], delta[:, 1]], axis=1)
    q = np.stack(
        [start[:, 0] - min_x, max_x - start[:, 0], start[:, 1] - min_y, max_y - start[:, 1]], axis=1
    )
    parallel = p == 0
    outside_parallel = (parallel & (q < 0)).any(axis=1)
    t = q / np.where(parallel, 1.0, p)
    t_enter = np.max(np.where(p < 0, t, 0.0), axis=1)
    t_leave = np.min(np.where(p > 0, t, 1.0), axis=1)
    if np.any(~outside_parallel & (t_enter <= t_leave)):
        return True
    # ... or else the whole rectangle is inside the polygon, or they are apart.
    return point_in_polygon((min_x, min_y), polygon)


def bbox_diagonal_m(bbox_m: Sequence[float]) -> float:
    """Diagonal length (metres) of ``(min_x, min_y, max_x, max_y)``."""
    return math.hypot(bbox_m[2] - bbox_m[0], bbox_m[3] - bbox_m[1])


def polygon_bbox_m(polygon_xy: ArrayLike) -> tuple[float, float, float, float]:
    """``(min_x, min_y, max_x, max_y)`` of a polygon's vertices."""
    polygon = as_polygon(polygon_xy)
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def matches(difference: Difference, change: Change) -> bool:
    """Whether a reported difference matches a true change (rules (a), (b), (c) of section 4)."""
    min_x, min_y, max_x, max_y = difference.bbox_m
    g = BBOX_GROWTH_M
    polygon = change.polygon_xy
    if bbox_diagonal_m(difference.bbox_m) > bbox_diagonal_m(polygon_bbox_m(polygon)) + (
        DIAGONAL_SLACK_M
    ):
        return False
    if not rect_intersects_polygon((min_x - g, min_y - g, max_x + g, max_y + g), polygon):
        return False
    return point_polygon_distance_m(difference.centroid_xy, polygon) <= CENTROID_DISTANCE_M


# --------------------------------------------------------------------------------------------
# Alignment


def observed_centroid_xy(local_map: OccupancyMap) -> tuple[float, float]:
    """Centre (slam frame, metres) of the local map's observed area: the mean of the centres of
    its known (free or occupied) cells. A map with no known cell gives the centre of its extent.
    """
    rows, cols = np.nonzero(local_map.state != UNKNOWN)
    if rows.size == 0:
        min_x, min_y, max_x, max_y = local_map.extent()
        return (0.5 * (min_x + max_x), 0.5 * (min_y + max_y))
    x, y = local_map.pixel_to_world(cols, rows)
    return (float(np.mean(x)), float(np.mean(y)))


# A session "without drift", for issue 12's alignment target there (0.03 m at p90): its true
# local map bends less than this from one rigid transform (the simulator's record of how far a
# route pose lies from where the best rigid fit puts it), a cell of a 0.05 m map. Every
# simulated session drifts a little; a bend under a cell leaves the transform's error to the
# alignment itself.
RIGID_BEND_M = 0.05


def alignment_error(
    reported: Transform2D, true: Transform2D, centre_slam_xy: ArrayLike
) -> tuple[float, float]:
    """Error of a reported slam -> nav2 transform against the true one.

    Parameters
    ----------
    reported, true
        ``nav2_from_slam`` transforms.
    centre_slam_xy
        (2,) metres, slam frame: where to evaluate the error (the observed area's centre).

    Returns
    -------
    error_m
        Distance in the nav2 frame between the images of ``centre_slam_xy`` under both.
    error_rad
        ``|wrap(theta_reported - theta_true)|``, in [0, pi].
    """
    centre = np.asarray(centre_slam_xy, dtype=float).reshape(2)
    gap = reported.apply(centre) - true.apply(centre)
    return (float(np.hypot(gap[0], gap[1])), abs(wrap_angle(reported.theta - true.theta)))


# --------------------------------------------------------------------------------------------
# Scoring


def _failure(status: str, truth: Truth) -> BundleScore:
    observed = [c.id for c in truth.changes if c.structural and c.observed]
    return BundleScore(
        status=status,
        n_differences=0,
        n_correct=0,
        n_neutral=0,
        n_false_positive=0,
        n_observed=len(observed),
        n_matched=0,
        n_fragments=0,
        n_kind_correct=0,
        unmatched_change_ids=tuple(observed),
    )


def score_bundle(
    truth: Truth, result: Result | None, *, centre_slam_xy: ArrayLike | None = None
) -> BundleScore:
    """Score one bundle's result against its truth (contract section 4).

    Parameters
    ----------
    truth
        The bundle's ground truth.
    result
        Its result; ``None`` when there is none. Either that or a ``status`` other than ``ok``
        is a failure: every observed structural change unmatched, no differences.
    centre_slam_xy
        (2,) metres, slam frame: the centre of the local map's observed area (see
        :func:`observed_centroid_xy`). Without it, or without an ``alignment`` in the result, the
        alignment error is ``None``.
    """
    if result is None:
        return _failure("missing", truth)
    if not result.ok:
        return _failure(result.status, truth)

    changes = truth.changes
    scored = []
    matched_ids: set[ChangeId] = set()
    assigned_count: dict[int, int] = {}
    for difference in result.differences:
        hits = [i for i, change in enumerate(changes) if matches(difference, change)]
        matched_ids.update(changes[i].id for i in hits)
        structural = [i for i in hits if changes[i].structural]
        hit_ids = tuple(changes[i].id for i in hits)
        if not structural:
            label: Label = "neutral" if hits else "false_positive"
            scored.append(DifferenceScore(difference.id, difference.kind, label, hit_ids))
            continue
        best = min(
            structural,
            key=lambda i: (
                changes[i].kind != difference.kind,
                not changes[i].observed,
                point_polygon_distance_m(difference.centroid_xy, changes[i].polygon_xy),
                i,
            ),
        )
        assigned_count[best] = assigned_count.get(best, 0) + 1
        scored.append(
            DifferenceScore(
                difference.id,
                difference.kind,
                "correct",
                hit_ids,
                assigned_change_id=changes[best].id,
                kind_correct=changes[best].kind == difference.kind,
            )
        )

    observed = [c for c in changes if c.structural and c.observed]
    unmatched = tuple(c.id for c in observed if c.id not in matched_ids)
    error_m = error_rad = None
    if centre_slam_xy is not None and result.nav2_from_slam is not None:
        error_m, error_rad = alignment_error(
            result.nav2_from_slam, truth.nav2_from_slam, centre_slam_xy
        )
    return BundleScore(
        status=result.status,
        n_differences=len(scored),
        n_correct=sum(s.label == "correct" for s in scored),
        n_neutral=sum(s.label == "neutral" for s in scored),
        n_false_positive=sum(s.label == "false_positive" for s in scored),
        n_observed=len(observed),
        n_matched=len(observed) - len(unmatched),
        n_fragments=sum(n - 1 for n in assigned_count.values()),
        n_kind_correct=sum(bool(s.kind_correct) for s in scored),
        alignment_error_m=error_m,
        alignment_error_rad=error_rad,
        differences=tuple(scored),
        unmatched_change_ids=unmatched,
    )


@dataclass(frozen=True)
class Summary(_Counts):
    """Totals over bundles: counts summed, ratios from the sums (micro averages).

    Alignment statistics are over the bundles that have an alignment error (not failures);
    ``None`` when there is none.
    """

    n_bundles: int
    n_failures: int
    alignment_error_median_m: float | None
    alignment_error_p90_m: float | None
    alignment_error_median_rad: float | None
    alignment_error_p90_rad: float | None


def _percentile(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def summarize(scores: Iterable[BundleScore]) -> Summary:
    """Totals over bundle scores (see :class:`Summary`)."""
    scores = list(scores)
    errors_m = [s.alignment_error_m for s in scores if s.alignment_error_m is not None]
    errors_rad = [s.alignment_error_rad for s in scores if s.alignment_error_rad is not None]
    return Summary(
        n_bundles=len(scores),
        n_failures=sum(s.failed for s in scores),
        n_differences=sum(s.n_differences for s in scores),
        n_correct=sum(s.n_correct for s in scores),
        n_neutral=sum(s.n_neutral for s in scores),
        n_false_positive=sum(s.n_false_positive for s in scores),
        n_observed=sum(s.n_observed for s in scores),
        n_matched=sum(s.n_matched for s in scores),
        n_fragments=sum(s.n_fragments for s in scores),
        n_kind_correct=sum(s.n_kind_correct for s in scores),
        alignment_error_median_m=_percentile(errors_m, 50),
        alignment_error_p90_m=_percentile(errors_m, 90),
        alignment_error_median_rad=_percentile(errors_rad, 50),
        alignment_error_p90_rad=_percentile(errors_rad, 90),
    )
