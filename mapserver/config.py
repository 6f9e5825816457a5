"""The configuration: pydantic models, every key defaulted, unknown keys an error.

This module is the only reader of configuration YAML. The top-level keys of contract section 6
(``inbox`` ... ``max_image_pixels``) are fixed; ``pipeline`` holds the tuning of the image stages.
Relative paths are resolved against the configuration file's directory (or the current directory
for built-in defaults).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mapserver.errors import ConfigError, describe_validation

ENV_VAR = "MAPSERVER_CONFIG"


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
    max_misfit_tolerance_m: float = Field(0.5, ge=0)
    """Where local walls still sit off the global ones (drift not fully taken out, a wall seen
    doubled on a revisit), the tolerances grow with that misfit: the added one up to this, the
    removed one by as much."""
    misfit_tile_m: float = Field(3.0, gt=0)
    """The misfit is measured over the walls of each tile of this size and its neighbours."""
    removed_tolerance_m: float = Field(0.25, ge=0)
    """Removed cells must be this far from any wall the local map sees: rays grazing a wall get
    few hits and mark slivers of its face free."""
    min_removed_cells: int = Field(8, ge=1)
    """A removed obstacle must be seen free over at least this many local-map cells."""
    removed_depth_m: float = Field(0.15, ge=0)
    """A removed obstacle must be seen free this deep inside the structure (at least two cells
    of the coarser map) ..."""
    see_through_m: float = Field(0.35, ge=0)
    """... or with open space on both sides within this distance: the robot looked through
    where it was. A wall face eroded by grazing rays has neither."""
    removed_evidence_share: float = Field(0.5, ge=0, le=1)
    """The share of a removed obstacle's cells that must show one of those two."""
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
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    maps: Path | None = None
    """The map store (contract section 7); null turns the fleet map's update off."""
    update: UpdateConfig = UpdateConfig()
    pipeline: PipelineConfig = PipelineConfig()

    def resolved(self, base_dir: Path) -> Config:
        """A copy with every relative path made absolute against ``base_dir``."""
        updates: dict[str, Path | None] = {}
        for key in ("inbox", "outbox", "archive", "failed", "reference_map", "maps"):
            value = getattr(self, key)
            if value is not None:
                updates[key] = (base_dir / value).resolve() if not value.is_absolute() else value
        return self.model_copy(update=updates)

    def worker_count(self) -> int:
        """``workers``, with 0 meaning the number of cores."""
        return self.workers or (os.cpu_count() or 1)


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
    return config.resolved(base_dir)


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
