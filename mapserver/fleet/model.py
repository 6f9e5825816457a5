"""Plain data of the map store: what its commands and :meth:`FleetStore.apply` return, and the
stamps it keeps (UTC, sortable as text)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timezone
from pathlib import Path
from typing import Any

from mapserver.fleet import tracker
from mapserver.fleet.lattice import Lattice

STATES = ("pending", "confirmed", "published", "rejected", "expired")


def utc_stamp(stamp: str) -> str:
    """A stamp normalised to UTC ``YYYY-MM-DDTHH:MM:SSZ``, sortable as text: a part of a second
    is dropped (kept, ``...00.500Z`` sorted before ``...00Z``, and a bundle half a second later
    was taken for an earlier one; session 54's review). The fleet tells bundles apart to the
    second."""
    value = tracker.parse_stamp(stamp).astimezone(timezone.utc).replace(microsecond=0)
    return value.isoformat(timespec="seconds").replace("+00:00", "Z")


def now_utc() -> str:
    from mapserver.outbox import utc_now

    return utc_now()


@dataclass(frozen=True)
class VersionInfo:
    map: str
    version: int
    created_at: str
    yaml: Path
    sha256: str
    note: str
    changes: tuple[int, ...] = ()


@dataclass(frozen=True)
class MapInfo:
    name: str
    current_version: int
    lattice: Lattice
    origin_yaw: float
    created_at: str
    counts: dict[str, int]
    bundles: int


@dataclass(frozen=True)
class ChangeInfo:
    """One tracked change as ``changes.yaml`` shows it."""

    id: int
    map: str
    kind: str
    state: str
    polygon: list[list[float]]
    first_seen: str
    last_seen: str
    sessions: int
    contradicted: int
    robots: list[str]
    bundles: list[str]
    version: int | None
    note: str
    updated_at: str = ""

    def document(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "state": self.state,
            "polygon": self.polygon,
            "first_seen": self.first_seen,
            "last_seen": self.last_seen,
            "sessions": self.sessions,
            "contradicted": self.contradicted,
            "robots": self.robots,
            "bundles": self.bundles,
            "version": self.version,
        }


@dataclass(frozen=True)
class Update:
    """What applying one bundle did to the store (plain data, for result.yaml and the logs)."""

    map: str
    bundle_version: int
    current_version: int
    changes: tuple[int | None, ...]
    """The tracked change of each difference of the bundle's result, in its order."""
    repeated: bool = False
    """The bundle had been applied before: nothing was counted again."""
    created: tuple[int, ...] = ()
    supported: tuple[int, ...] = ()
    expired: tuple[int, ...] = ()
    confirmed: tuple[int, ...] = ()
    published: tuple[int, ...] = ()
    new_version: int | None = None
    warnings: tuple[str, ...] = ()
    seconds: float = 0.0

    def annotate(self, result: dict[str, Any]) -> None:
        """Add what the store made of the bundle to its ``result.yaml`` document: the map's name
        and version (the one the robot navigated on) and the current version, each difference's
        tracked change, the update's time, and its warnings."""
        result.setdefault("map", {}).update(
            {
                "name": self.map,
                "version": self.bundle_version,
                "current_version": self.current_version,
            }
        )
        for difference, change in zip(result.get("differences") or [], self.changes, strict=False):
            difference["change"] = change
        result.setdefault("timings_ms", {})["update"] = round(self.seconds * 1000.0, 1)
        if self.warnings:
            result.setdefault("warnings", []).extend(self.warnings)

    def summary(self) -> str:
        parts = [f"map {self.map} v{self.current_version}"]
        if self.repeated:
            parts.append("already applied")
        for name in ("created", "supported", "expired", "confirmed", "published"):
            ids = getattr(self, name)
            if ids:
                parts.append(f"{name} {', '.join(str(i) for i in ids)}")
        if self.new_version is not None:
            parts.append(f"published version {self.new_version}")
        return "; ".join(parts)


@dataclass(frozen=True)
class MapLink:
    """What a worker needs to judge a bundle against the current version of its stored map."""

    name: str
    lattice: Lattice
    bundle_version: int
    current_version: int
    current_yaml: Path
    first_yaml: Path
    """Version 1: the building map as registered, byte for byte (a floor-plan drawing keeps its
    grey lines there; later versions are written by map_saver's rules, states only)."""
