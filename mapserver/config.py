"""The configuration: pydantic models, every key defaulted, unknown keys an error.

This module is the only reader of configuration YAML. The top-level keys of contract section 6
(``inbox`` ... ``max_image_pixels``) are fixed; ``pipeline`` holds the tuning of the image stages.
Relative paths are resolved against the configuration file's directory (or the current directory
for built-in defaults).
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from mapserver.errors import ConfigError, MapserverError, describe_validation, no_such_path

ENV_VAR = "MAPSERVER_CONFIG"
# The file `mapserver demo` leaves in its folder (beside the configuration it writes there):
# the folder is a demo's, which it may clear and whose stopped daemon is no fault.
DEMO_MARKER = ".mapserver-demo"
# What every command's --config says of it (how load_config finds the file).
CONFIG_HELP = (
    "the configuration file (default: $MAPSERVER_CONFIG, else the built-in defaults, with every "
    "folder in the current directory)"
)


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AlignConfig(_Frozen):
    """Alignment of the local map onto the global map."""

    refine: bool = True
    """Refine the pose prior by matching the maps; false keeps the prior as it is."""
    search_xy_m: float = Field(2.5, gt=0)
    """Half-width of the translation search window around the prior."""
    search_theta_deg: float = Field(35.0, gt=0, le=180)
    """Half-width of the rotation search window around the prior."""
    min_score: float = Field(0.6, ge=0, le=1)
    """Below this agreement the alignment is not trusted: a warning, and no differences reported."""
    edge_margin: float = Field(0.1, ge=0, le=1)
    """A whole map's alignment scoring under ``min_score`` by no more than this is trusted
    when it reaches ``min_score`` with the edges of what the global map knows (floor it saw
    beside cells it did not) counted as walls: a map that draws its walls as the end of its
    known floor, few of them dark (willow-2010), scored a right alignment 0.56-0.59 (session 51:
    66 such alignments out of 675 with priors off by up to 8 m and 180 degrees, none wrong;
    without the margin, a piece of 70-95 m2 was trusted 4-6 m off, so never for pieces). 0:
    off."""
    min_gain: float = Field(0.02, ge=0)
    """A refinement that moves the map more than ``jump_m`` from the prior (a distinct solution,
    not a polish) replaces the prior only when it scores at least this much better."""
    jump_m: float = Field(0.5, gt=0)
    deform: bool = True
    """Correct SLAM drift with small per-tile shifts after the rigid alignment."""
    deform_tile_m: float = Field(4.5, gt=0)
    """Size of the smallest neighbourhoods that get their own drift shift (the finest pass)."""
    deform_max_shift_m: float = Field(0.8, ge=0)
    """Largest drift shift of the coarsest pass; each finer pass allows half the one before."""
    deform_passes: int = Field(3, ge=1, le=5)
    """Coarse-to-fine drift passes; each doubles the neighbourhood of the one after it."""
    pieces: bool = True
    """When no rigid transform is trusted for the whole local map, align it in pieces along the
    route (needs a trajectory in bundle.yaml) and compare the trusted ones."""
    piece_m: float = Field(20.0, gt=0)
    """Route length of one piece."""
    fit_check: bool = False
    """After every trusted rigid fit, look for regions whose walls land off the building (a
    bend beyond the drift correction: 9-15 degree kinks were trusted and reported ~30 false
    changes) and align those in pieces or leave them out. Off by default: it costs about 8 ms
    per bundle, and a session without drift does not need it; drifting ones get it anyway
    (``fit_check_drift_m``)."""
    fit_check_drift_m: float = Field(0.2, gt=0)
    """A bundle whose drift correction reaches this, metres, gets the fit check even with
    ``fit_check`` off, and is aligned in pieces too (with ``pieces``), the pieces kept only
    when they find a bend: one beyond the warp leaves a large correction behind."""


class RoiConfig(_Frozen):
    """The region of interest in which differences are looked for."""

    strategy: Literal["observed", "box", "trajectory", "heading"] = "observed"
    box_size_m: float = Field(10.0, gt=0)
    """Side of the square for ``box`` (centred on the robot) and ``heading`` (behind it)."""
    trajectory_radius_m: float = Field(6.0, gt=0)
    """Corridor half-width around the route for ``trajectory``."""


class DiffConfig(_Frozen):
    """Finding and filtering added and removed obstacles."""

    tolerance_m: float = Field(0.15, ge=0)
    """A wall seen this close to where the global map has it is not a change (misalignment)."""
    min_local_cells: int = Field(4, ge=1)
    """Differences smaller than this many local-map cells are noise (scan specks)."""
    min_area_m2: float = Field(0.0, ge=0)
    """An absolute floor on a difference's area, on top of ``min_local_cells``."""
    drifted_min_area_m2: float = Field(0.03, ge=0)
    """The floor on an added obstacle after a drifting session (a drift correction of 0.2 m or
    more, or aligned in pieces): where the local map is known to sit off by decimetres, a speck
    smaller than this (12 cells at 0.05 m: a box's face seen from one side) is more likely the
    scatter of a wall seen twice than a change (0.04 until session 22: 30 more changes found
    for 21 more false positives over 54 generated sets at 0.03; at 0.02 in session 16, 11 for
    20 over 13). Not on a removed one: it must show its removal evidence (cells seen free deep
    inside the structure, or through it) whatever its size, and a small piece of wall gone is
    a common change."""
    max_misfit_tolerance_m: float = Field(0.5, ge=0)
    """Where local walls still sit off the global ones (drift not fully taken out, a wall seen
    doubled on a revisit), the tolerances grow with that misfit: the added one up to this, the
    removed one by as much."""
    misfit_tile_m: float = Field(3.0, gt=0)
    """The misfit is measured over the walls of each tile of this size and its neighbours."""
    unknown_speck_m2: float = Field(0.05, ge=0)
    """A patch the global map left unknown in the open, no larger than this (a speck its
    mapping rays missed, or a pole they hit now and then), hides the local walls within
    ``tolerance_m`` of it, never the misfit's wider tolerance: that one is for walls seen
    displaced, and a speck within 0.5 m of a new box hid the whole box (a site history on a 0.10
    m map: one box seen in 13 sessions was found in none; session 51). A speck drawn as a grey
    wall (the structure mask's) is a wall. 0: every unknown patch takes the misfit's
    tolerance."""
    along_wall_m: float = Field(0.35, ge=0)
    """An added obstacle that never gets further than this from a global wall, and lies all
    on one side of it, is that wall seen displaced (drift left over, a face seen thicker), not
    a new obstacle. 0 turns the rule off."""
    removed_tolerance_m: float = Field(0.25, ge=0)
    """Removed cells must be this far from any wall the local map sees: rays grazing a wall get
    few hits and mark slivers of its face free."""
    removed_end_tolerance_m: float = Field(0.1, ge=0)
    """... but only this far past the end of a wall the robot sees, in line with it, where the
    walls fit: a gap in a wall, not a wall seen off to one side. A lidar draws a wall's end
    within a cell or two; 0.2 m until session 28 left a doorway of 0.57 m cut through a wall
    0.33 m thick 5 cells of removal, not reported (over 66 generated and public sets, 0.1 m
    where the session did not drift: 21 more changes found, 8 more false positives)."""
    drifted_removed_end_tolerance_m: float = Field(0.2, ge=0)
    """The same after a drifting session (as for ``drifted_min_area_m2``): the drift left in
    the map draws a wall's end decimetres short where its tile's walls still fit (at 0.1 m the
    526 drifted bundles of those sets gave 11 changes fewer and 16 false positives more)."""
    min_removed_cells: int = Field(8, ge=1)
    """A removed obstacle must be seen free over at least this many local-map cells (from
    ``min_local_cells`` on when it is a small structure seen gone whole, ``small_structure_m``,
    or cuts a thin wall in two: ``compare._CUT_RULES``)."""
    removed_depth_m: float = Field(0.15, ge=0)
    """A removed obstacle must be seen free this deep inside the structure (at least two cells
    of the local map and one of the global map) ..."""
    see_through_m: float = Field(0.35, ge=0)
    """... or with open space on both sides within this distance: the robot looked through
    where it was. A wall face eroded by grazing rays has neither."""
    both_sides_m: float = Field(1.0, ge=0)
    """... or seen free from both sides of the structure, open space on each within this
    distance, each side seen free past the face's own row, and no wall seen in between (a thick
    wall's piece whose middle no ray reached)."""
    removed_evidence_share: float = Field(0.5, ge=0, le=1)
    """The share of a removed obstacle's cells that must show one of those two ..."""
    removed_evidence_m2: float = Field(0.025, gt=0)
    """... or the area they cover (m2; at least the removed obstacles' floor too) however many
    do not: a piece of a block really gone (10 cells at 0.05 m), joined by the free band of a
    fold or a face eroded by grazing rays that outnumbers it. Reported as its evidence and what
    lies within ``cluster_eps_m`` of it. ``.inf`` turns this off. After a drifting session,
    ``drifted_removed_evidence_m2``.
    Session 23, over 56 generated and public sets and every session, without the floor: 0.05
    found 11 more changes for 4 more false positives (with it, 10 for 4: a removal of a 0.1 m
    local map whose evidence was 5-7 of its cells); 0.1 found 4 for 1; 0.04 14 for 12, 0.025 20
    for 29 (the evidence of a face seen free a few cells deep, most of it in drifted maps).
    Session 47, 0.025 where the session did not drift, over 59 generated sets: 7 more changes
    found (4 of them held out) for 3 more false positives (2 held out), F1 up on the tuning and
    the held-out sets; 0.015: 9 for 4. One of the three, on a 0.1 m global map, is a row of its
    face seen free (2.5 of its cells): asking five cells of the coarser map lost it, and with it
    two changes of the campus sets (coarser maps still) and a held-out one."""
    drifted_removed_evidence_m2: float = Field(0.05, gt=0)
    """The same after a drifting session (as for ``drifted_min_area_m2``): where the map sits
    off by decimetres, a fold's free band or a face seen free a few cells deep shows that much
    evidence."""
    small_structure_m: float = Field(1.0, ge=0)
    """A removed obstacle smaller than ``min_removed_cells`` is reported (from
    ``min_local_cells`` on, with its evidence) when half or more of its cells lie on a small
    structure of the global map seen gone whole: no wider than this either way, three of its
    cells at least, half of them among the removed cells, no local wall within 0.1 m, no part
    of the global map unknown 0.25 m deep within 0.5 m of it (an object the global map draws
    as a few cells, not a dash of a face whose inside the map never saw). Where the session
    did not drift, such a structure (up to 0.5 m, or this if less) is also reported seen gone
    beside a wall, which the removed tolerance hides, or in the open, when every local wall
    within 0.35 m of it lies nearer other structure of the global map
    (``diff.small_structures_beside_walls``). 0 turns both off."""
    cluster_eps_m: float = Field(0.3, gt=0)
    """DBSCAN neighbourhood radius: difference pixels closer than this form one obstacle."""
    cluster_min_samples: int = Field(3, ge=1)
    cluster_engine: Literal["grid", "scikit-learn"] = "grid"
    """The DBSCAN implementation; both give the same labels. ``scikit-learn`` costs about 0.7 s
    and 95 MiB per process to import."""


class RenderConfig(_Frozen):
    margin_m: float = Field(2.0, ge=0)
    """Images cover the ROI plus this margin."""
    max_side_px: int = Field(2000, ge=100)
    """Images are scaled down to at most this many pixels on a side."""


class LimitsConfig(_Frozen):
    """Sanity limits on a bundle's inputs, checked before any heavy work: a bundle past one is
    refused with the limit named, not processed for minutes or until it runs out of memory."""

    min_resolution_m: float = Field(0.005, gt=0)
    """Map cells smaller than this (metres per cell) are refused; 0.005 m is finer than any
    lidar SLAM map."""
    max_resolution_m: float = Field(1.0, gt=0)
    """Map cells larger than this are refused; a 1 m cell cannot hold an indoor obstacle."""
    max_map_extent_m: float = Field(2000.0, gt=0)
    """A map wider or taller than this (metres) is refused, from its image header."""
    max_trajectory_poses: int = Field(100_000, ge=0)
    """A longer ``trajectory`` in bundle.yaml is refused (one pose every 10 cm over 10 km)."""
    max_manifest_bytes: int = Field(16 * 2**20, gt=0)
    """A larger bundle.yaml is refused before it is parsed."""

    @model_validator(mode="after")
    def _ordered(self) -> LimitsConfig:
        if self.min_resolution_m > self.max_resolution_m:
            raise ValueError("min_resolution_m must not be larger than max_resolution_m")
        return self

    @property
    def resolution_range_m(self) -> tuple[float, float]:
        return (self.min_resolution_m, self.max_resolution_m)


class RetentionConfig(_Frozen):
    """How long the daemon keeps what it is done with; null (the default): for ever."""

    archive_days: float | None = Field(None, gt=0)
    """Processed bundles in archive/ older than this are deleted."""
    failed_days: float | None = Field(None, gt=0)
    """Rejected bundles in failed/ (with their error.yaml) older than this are deleted."""
    outbox_days: float | None = Field(None, gt=0)
    """Results in the outbox older than this are deleted."""
    every_hours: float = Field(1.0, gt=0)
    """How often the daemon looks (each look is spread over many turns of its main loop)."""


class PipelineConfig(_Frozen):
    align: AlignConfig = AlignConfig()
    roi: RoiConfig = RoiConfig()
    diff: DiffConfig = DiffConfig()
    render: RenderConfig = RenderConfig()


class UpdateConfig(_Frozen):
    """The fleet map's update (contract section 7)."""

    mode: Literal["review", "auto"] = "review"
    """review: confirmed changes wait for ``mapserver changes approve``; auto: published at once."""
    confirm_sessions: int = Field(3, ge=1)
    """A change is confirmed when this many sessions (bundles) saw it ..."""
    confirm_span_hours: float = Field(12.0, ge=0)
    """... spread over at least this many hours (a cart parked for an afternoon is not a wall)."""
    expire_unseen_days: float = Field(30.0, gt=0)
    """A pending change that no bundle has observed for this long (by bundle stamps) expires."""
    expired_listed_days: float = Field(7.0, ge=0)
    """changes.yaml lists expired changes for this long after they expired (a person seen once
    is an expired change: a year of them would make the file huge); the database keeps all."""
    paint_min_sessions: int = Field(2, ge=1)
    """A published version paints a cell of a change only when at least this many of its
    sessions saw that cell changed (or all of them, when fewer)."""
    max_clock_ahead_hours: float = Field(8784.0, gt=0)
    """A bundle stamped more than this ahead of the server's clock feeds nothing (its result
    says to check the robot's clock). A year (366 days) by default, so that recorded sessions
    replayed on a server whose clock is behind them still count; within it, a robot clock a
    day ahead stretches the spans it takes part in by that day (a temporary change could then
    pass ``confirm_span_hours``). A live fleet whose robots keep time (NTP) can set 1."""


class WebConfig(_Frozen):
    """The operator's web pages, HTTP API and metrics (``mapserver web``)."""

    listen: str = Field("127.0.0.1:8350", pattern=r"^[^\s:]+:\d{1,5}$|^\[[0-9a-fA-F:]+\]:\d{1,5}$")
    """HOST:PORT to serve on. Any address but the loopback needs ``token_file``."""
    token_file: Path | None = None
    """A file holding the review token (approve, reject, rollback need it; read-only pages
    don't). Without it the review actions are off."""
    with_daemon: bool = True
    """``mapserver run`` serves the pages too (a systemd deployment runs ``mapserver web`` in its
    own unit instead, and starts the daemon with ``--no-web``)."""
    page_size: int = Field(50, ge=5, le=1000)
    """Rows per page of every list."""


class Config(_Frozen):
    """The whole configuration. The first keys are contract section 6."""

    inbox: Path = Path("./inbox")
    outbox: Path = Path("./outbox")
    archive: Path = Path("./archive")
    failed: Path = Path("./failed")
    reference_map: Path | None = None
    settle_seconds: float = Field(2.0, ge=0)
    stale_after_seconds: float = Field(600.0, gt=0)
    rescan_seconds: float = Field(60.0, gt=0)
    workers: int = Field(0, ge=0)
    observer: Literal["native", "polling"] = "native"
    max_image_pixels: int = Field(100_000_000, gt=0)
    bundle_timeout_seconds: float = Field(300.0, gt=0)
    """A bundle still in a worker after this long is stopped (its worker killed) and failed."""
    worker_memory_mb: int | None = Field(None, gt=0)
    """A worker using more memory than this (MiB) is stopped and its bundle failed. None: a share
    of the machine, see :meth:`worker_memory_limit_mb`."""
    limits: LimitsConfig = LimitsConfig()
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    maps: Path | None = None
    """The map store (contract section 7); null turns the fleet map's update off."""
    update: UpdateConfig = UpdateConfig()
    retention: RetentionConfig = RetentionConfig()
    web: WebConfig | None = None
    """The web pages and API; null (the default) turns them off for ``mapserver run``
    (``mapserver web`` then serves with the defaults)."""
    pipeline: PipelineConfig = PipelineConfig()

    def resolved(self, base_dir: Path) -> Config:
        """A copy with every relative path made absolute against ``base_dir``."""
        updates: dict[str, Path | None] = {}
        for key in ("inbox", "outbox", "archive", "failed", "reference_map", "maps"):
            value = getattr(self, key)
            if value is not None:
                updates[key] = (base_dir / value).resolve() if not value.is_absolute() else value
        resolved = self.model_copy(update=updates)
        if self.web is not None and self.web.token_file is not None:
            token = self.web.token_file
            if not token.is_absolute():
                token = (base_dir / token).resolve()
            resolved = resolved.model_copy(
                update={"web": self.web.model_copy(update={"token_file": token})}
            )
        return resolved

    def worker_count(self) -> int:
        """``workers``, with 0 meaning the number of cores."""
        return self.workers or (os.cpu_count() or 1)

    def worker_memory_limit_mb(self) -> int:
        """``worker_memory_mb``, by default the memory available to the daemon (the machine's,
        or the service's cgroup ``memory.max`` when lower, as systemd's ``MemoryMax=`` sets it)
        divided by workers + 1: the workers at their limits leave one share to the main process
        and the rest of the machine."""
        if self.worker_memory_mb is not None:
            return self.worker_memory_mb
        return max(64, available_memory_mb() // (self.worker_count() + 1))


def available_memory_mb() -> int:
    """The machine's memory, or the lowest cgroup (v2) ``memory.max`` above this process when
    lower (systemd's ``MemoryMax=`` of the service or its slice), in MiB."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        with open("/proc/self/cgroup", encoding="ascii") as cgroups:
            groups = [line.strip()[3:] for line in cgroups if line.startswith("0::/")]
    except OSError:
        groups = []  # no cgroup v2: the machine's memory
    if groups:
        group = Path("/sys/fs/cgroup", groups[0].lstrip("/"))
        for level in (group, *group.parents):
            if level == Path("/sys/fs"):
                break
            try:
                limit = (level / "memory.max").read_text().strip()
            except OSError:
                continue
            if limit.isdigit():
                total = min(total, int(limit))
    return total // 2**20


def check_paths(config: Config) -> None:
    """Raise :class:`ConfigError` for a configured file that is not there (a misspelt
    ``reference_map``): found at start-up, not on the first bundle that needs it."""
    ref = config.reference_map
    if ref is not None and not ref.is_file():
        problem = no_such_path(ref) if not ref.exists() else "not a file"
        raise ConfigError(f"reference_map: {problem}", file=ref)
    if ref is not None:
        # Its YAML and its image's header, as a bundle that names no nav2_map will read them
        # (a map YAML whose image is gone, a PGM given for the YAML: every such bundle failed).
        from mapserver.maps import load_map

        try:
            load_map(
                ref,
                max_pixels=config.max_image_pixels,
                resolution_range_m=config.limits.resolution_range_m,
                max_extent_m=config.limits.max_map_extent_m,
            )
        except MapserverError as error:
            where = "" if error.file in (None, ref) else f" ({error.file})"
            raise ConfigError(f"reference_map: {error.problem_line}{where}", file=ref) from None


def parse_config(data: object, *, base_dir: Path, source: Path | None = None) -> Config:
    """Validate configuration data (a mapping) and resolve its paths against ``base_dir``."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError("the configuration must be a mapping of keys to values", file=source)
    try:
        config = Config.model_validate(data)
    except ValidationError as error:
        raise ConfigError(describe_validation(error), file=source) from None
    config = config.resolved(base_dir)
    _refuse_nested_folders(config, source)
    return config


def _refuse_nested_folders(config: Config, source: Path | None) -> None:
    """The server's folders (and the map store) must be apart, none inside another: the
    daemon lists every entry of its inbox as an upload, and retention deletes every old entry of
    outbox/, archive/ and failed/ (session 53's review: with ``maps: data/maps`` and ``outbox:
    data``, retention deleted the map store)."""
    folders = {
        "inbox": config.inbox,
        "outbox": config.outbox,
        "archive": config.archive,
        "failed": config.failed,
        "maps": config.maps,
    }
    real = {key: path.resolve() for key, path in folders.items() if path is not None}
    for a, b in itertools.combinations(real, 2):
        if real[a] == real[b]:
            problem = f"{a} and {b} are one folder ({real[a]})"
        elif real[a] in real[b].parents or real[b] in real[a].parents:
            outer, inner = (a, b) if real[a] in real[b].parents else (b, a)
            problem = f"{inner} ({real[inner]}) lies inside {outer} ({real[outer]})"
        else:
            continue
        raise ConfigError(
            f"{problem}: the server's folders must be apart, none inside another (the daemon "
            "takes every entry of the inbox as an upload, and retention deletes old entries of "
            "outbox, archive and failed)",
            file=source,
        )


def load_config(path: str | Path | None = None) -> Config:
    """Load the configuration.

    ``path`` if given, else ``$MAPSERVER_CONFIG`` if set, else the built-in defaults with paths
    relative to the current directory.
    """
    if path is None:
        env = os.environ.get(ENV_VAR)
        path = Path(env) if env else None
    if path is None:
        return Config().resolved(Path.cwd())
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"cannot read the configuration: {error.strerror}", file=path) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"not valid YAML: {error}", file=path) from None
    return parse_config(data, base_dir=path.resolve().parent, source=path)


def dump_config(config: Config) -> str:
    """The effective settings as YAML (what ``check-config`` prints)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
