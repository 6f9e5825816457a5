"""The map store: building maps, their versions, the evidence of every bundle and the tracked
changes (contract section 7).

One process writes (the daemon's main process, or one ``mapserver`` command); workers only read
(:func:`lookup`). Applying a bundle is one ``BEGIN IMMEDIATE`` transaction that also records
that the bundle was applied, so a bundle counts once whatever crashes or repeated uploads
happen. Files (versions, ``current.yaml``, the keepout mask, ``changes.yaml``) are written by
rename and derived from the database; :meth:`FleetStore.sync` writes them again from it.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from mapserver.bundle import BUNDLE_ID_RE, map_image_name, sha256_file
from mapserver.config import UpdateConfig
from mapserver.errors import StoreError
from mapserver.fleet import evidence, publish, tracker
from mapserver.fleet.changes import ChangeTracker
from mapserver.fleet.db import connect, connect_readonly, transaction
from mapserver.fleet.lattice import IntArray, Lattice, Window
from mapserver.fleet.model import (
    STATES,
    ChangeInfo,
    MapInfo,
    MapLink,
    Update,
    VersionInfo,
    now_utc,
    utc_stamp,
)
from mapserver.fleet.observe import Observation
from mapserver.fsio import dump_yaml, replace_atomic
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, load_map

log = logging.getLogger(__name__)
WRITER_LOCK = ".writer.lock"


# How far ahead of this server's clock a bundle's stamp may be: ``update.max_clock_ahead_hours``
# (a year by default: recorded sessions replayed on a server whose own clock is behind them, a
# test rig, a benchmark, must count; a year ahead is a clock set wrong).
_EARLIEST_STAMP = "2000-01-01T00:00:00Z"


def _implausible_stamp(stamp: str, ahead_hours: float) -> str | None:
    """Why a bundle's stamp cannot be right (check the robot's clock), or None."""
    if stamp < _EARLIEST_STAMP:
        return f"its stamp {stamp} is before 2000: check the robot's clock"
    limit = datetime.now(timezone.utc) + timedelta(hours=ahead_hours)
    if tracker.parse_stamp(stamp) > limit:
        return (
            f"its stamp {stamp} is more than {ahead_hours:g} hours ahead of this server's clock "
            "(update.max_clock_ahead_hours): check the robot's clock"
        )
    return None


def _named(asked: int, found: int) -> str:
    """A change as an operator named it, and the one it was merged into when that differs."""
    return str(asked) if asked == found else f"{asked} (merged into {found})"


def lookup(root: Path, image_sha256: str) -> MapLink | None:
    """The stored map one of whose versions has this image (sha256), read-only; None if none.

    Run by the workers: they judge a bundle against the map's current version.
    """
    conn = connect_readonly(root)
    if conn is None:
        return None
    try:
        row = conn.execute(
            "SELECT m.id, m.name, m.width, m.height, m.resolution, m.origin_x, m.origin_y, "
            "v.version FROM versions v JOIN maps m ON m.id = v.map_id WHERE v.sha256 = ? "
            "ORDER BY v.version DESC LIMIT 1",
            (image_sha256.lower(),),
        ).fetchone()
        if row is None:
            return None
        map_id, name, width, height, res, ox, oy, version = row
        current, current_yaml = conn.execute(
            "SELECT version, yaml FROM versions WHERE map_id = ? ORDER BY version DESC LIMIT 1",
            (map_id,),
        ).fetchone()
        (first_yaml,) = conn.execute(
            "SELECT yaml FROM versions WHERE map_id = ? ORDER BY version LIMIT 1", (map_id,)
        ).fetchone()
    except sqlite3.DatabaseError as error:
        raise StoreError(f"cannot read the map store: {error}", file=root) from None
    finally:
        conn.close()
    return MapLink(
        name,
        Lattice(width, height, res, ox, oy),
        version,
        current,
        root / name / current_yaml,
        root / name / first_yaml,
    )


class FleetStore:
    """The map store at ``root`` (the configuration's ``maps:``), with the update settings.

    Opening it checks the database (missing while maps exist, unreadable, damaged: a
    :class:`StoreError` that says how to recover).
    """

    def __init__(
        self,
        root: Path,
        settings: UpdateConfig | None = None,
        *,
        create: bool = True,
        check: bool = True,
        checkpoint: Callable[[str], None] | None = None,
        busy_timeout_s: float = 30.0,
    ):
        self.root = Path(root)
        # Test hook: called at named steps ("evidence-applied" inside the bundle's transaction,
        # "bundle-applied" after its commit, "version-written" before a version's commit).
        self._checkpoint = checkpoint or (lambda name: None)
        self.settings = settings or UpdateConfig()
        self._conn = connect(self.root, create=create, check=check, timeout=busy_timeout_s)
        with contextlib.suppress(OSError):  # a read-only store: its readers never take it
            (self.root / WRITER_LOCK).touch(exist_ok=True)
        self.unwritten: OSError | None = None
        """Why the store's files (versions, current.yaml, the keepout mask, changes.yaml) lag
        its database: the error of the last write that failed (a full disk), None once they are
        written again (:meth:`apply` or :meth:`sync`)."""
        self._states: dict[int, tuple[int, NDArray[np.uint8]]] = {}
        # changes.yaml is rewritten after every update: each change's YAML text is kept and
        # made again only when the change was touched (ids in _dirty).
        self._docs: dict[int, dict[int, tuple[str, str, str]]] = {}
        self._dirty: set[int] = set()
        self._writer_depth = 0
        # Another process (an operator's approve, the web) may change the store: SQLite's
        # data_version changes when another connection commits, and the cached lines go.
        self._data_version = self._conn.execute("PRAGMA data_version").fetchone()[0]
        self._changes = ChangeTracker(self._conn, self.settings, self._dirty)

    def close(self) -> None:
        self._conn.close()

    @contextmanager
    def _writer(self) -> Iterator[None]:
        """One publication or review action at a time across processes and threads (the
        daemon, the web's threads, a command): an exclusive flock on ``maps/.writer.lock``
        around reading a change's state, allocating a version, writing its files and
        committing. Reentrant within this store."""
        if self._writer_depth:
            self._writer_depth += 1
            try:
                yield
            finally:
                self._writer_depth -= 1
            return
        fd = os.open(self.root / WRITER_LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o664)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            self._writer_depth = 1
            try:
                yield
            finally:
                self._writer_depth = 0
        finally:
            os.close(fd)

    def __enter__(self) -> FleetStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- maps and versions ------------------------------------------------------------------

    def add_map(self, name: str, map_yaml: Path, *, max_pixels: int = 100_000_000) -> VersionInfo:
        """Register a building map as version 1 of ``name``. The map must load; nothing is
        created otherwise. Its image is kept byte for byte (bundles match it by sha256)."""
        if not BUNDLE_ID_RE.fullmatch(name):
            raise StoreError(
                f"invalid map name {name!r}: use letters, digits, '.', '_' and '-', starting "
                "with a letter or digit"
            )
        if self._map_row(name, missing_ok=True) is not None:
            raise StoreError(
                f"a map named {name!r} is already in the store (see 'mapserver maps show {name}')"
            )
        map_yaml = Path(map_yaml)
        m = load_map(map_yaml, max_pixels=max_pixels)  # MapFileError with the loader's message
        image = map_yaml.parent / map_image_name(map_yaml)
        same = self._conn.execute(
            "SELECT m.name, v.version FROM versions v JOIN maps m ON m.id = v.map_id "
            "WHERE v.sha256 = ? ORDER BY v.version LIMIT 1",
            (sha256_file(image),),
        ).fetchone()
        if same is not None:
            # Bundles find their map by its image's sha256: two maps with one image would
            # feed the evidence of one building into whichever the lookup found first.
            raise StoreError(
                f"the image of {map_yaml} is already version {same[1]} of map {same[0]!r}: a "
                f"map is registered once (see 'mapserver maps show {same[0]}')"
            )
        document = yaml.safe_load(map_yaml.read_text(encoding="utf-8"))
        folder = self.root / name
        folder.mkdir(parents=True, exist_ok=True)
        stem = publish.version_stem(1)
        image_dst = folder / f"{stem}{image.suffix.lower() or '.pgm'}"
        tmp = folder / f".{image_dst.name}.tmp"
        shutil.copyfile(image, tmp)
        replace_atomic(image_dst, tmp.read_bytes())
        tmp.unlink()
        document["image"] = image_dst.name
        yaml_dst = folder / f"{stem}.yaml"
        replace_atomic(yaml_dst, yaml.safe_dump(document, sort_keys=False).encode())
        digest = sha256_file(image_dst)
        now = now_utc()
        lattice = Lattice.of_map(m)
        with transaction(self._conn):
            cur = self._conn.execute(
                "INSERT INTO maps (name, width, height, resolution, origin_x, origin_y, "
                "origin_yaw, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (name, m.width, m.height, m.resolution, m.origin[0], m.origin[1], m.origin[2], now),
            )
            self._conn.execute(
                "INSERT INTO versions (map_id, version, created_at, yaml, image, sha256, note) "
                "VALUES (?, 1, ?, ?, ?, ?, ?)",
                (
                    cur.lastrowid,
                    now,
                    yaml_dst.name,
                    image_dst.name,
                    digest,
                    f"added from {map_yaml}",
                ),
            )
        self._write_derived(name)
        log.info(
            "map %s: version 1 from %s (%dx%d cells at %.3f m)",
            name,
            map_yaml,
            lattice.width,
            lattice.height,
            lattice.resolution,
        )
        return self.versions(name)[0]

    def maps(self) -> list[MapInfo]:
        return [
            self.map_info(row[0])
            for row in self._conn.execute("SELECT name FROM maps ORDER BY name")
        ]

    def map_info(self, name: str) -> MapInfo:
        map_id, lattice, yaw, created = self._map(name)
        counts = dict.fromkeys(STATES, 0)
        for state, n in self._conn.execute(
            "SELECT state, count(*) FROM changes WHERE map_id = ? GROUP BY state", (map_id,)
        ):
            counts[state] = n
        bundles = self._conn.execute(
            "SELECT count(*) FROM bundles WHERE map_id = ?", (map_id,)
        ).fetchone()[0]
        return MapInfo(name, self._current_version(map_id), lattice, yaw, created, counts, bundles)

    def versions(self, name: str) -> list[VersionInfo]:
        map_id = self._map(name)[0]
        published: dict[int, list[int]] = {}
        for cid, version in self._conn.execute(
            "SELECT id, version FROM changes WHERE map_id = ? AND version IS NOT NULL ORDER BY id",
            (map_id,),
        ):
            published.setdefault(version, []).append(cid)
        return [
            VersionInfo(
                name, v, created, self.root / name / y, sha, note, tuple(published.get(v, ()))
            )
            for v, created, y, sha, note in self._conn.execute(
                "SELECT version, created_at, yaml, sha256, note FROM versions WHERE map_id = ? "
                "ORDER BY version",
                (map_id,),
            )
        ]

    def rollback(self, name: str, version: int, *, actor: str = "operator") -> VersionInfo:
        """Publish a NEW version equal to ``version``; history is never rewritten. Published
        changes that ``version`` does not hold are no longer in the map: they become
        ``rejected`` (an operator undid them), so that the same sightings do not publish them
        again. Changes an earlier rollback undid that ``version`` holds are published again."""
        with self._writer():
            self._repaired(name)
            return self._rollback(name, version, actor)

    def _rollback(self, name: str, version: int, actor: str) -> VersionInfo:
        map_id, lattice, yaw, _ = self._map(name)
        source = self._version_yaml(map_id, name, version)
        if source is None:
            known = self._current_version(map_id)
            raise StoreError(f"map {name!r} has no version {version} (versions 1..{known})")
        state = load_map(source).state
        held = self._held_by(map_id, version)
        undone, redone = [], []
        for cid, now in self._conn.execute(
            "SELECT id, state FROM changes WHERE map_id = ? AND version IS NOT NULL "
            "AND state IN ('published', 'rejected')",
            (map_id,),
        ).fetchall():
            if now == "published" and cid not in held:
                undone.append(cid)
            elif now == "rejected" and cid in held:
                redone.append(cid)  # only a rollback rejects a change that has a version
        new = self._publish_state(
            map_id,
            name,
            lattice,
            yaw,
            state,
            f"rollback to version {version} by {actor}",
            undone=undone,
            redone=redone,
            actor=actor,
            copy_of=version,
        )
        self._write_derived(name)
        return next(v for v in self.versions(name) if v.version == new)

    def _held_by(self, map_id: int, version: int) -> set[int]:
        """The changes version ``version`` holds: those published in it and in the versions it
        was made from (the one before it, or for a rollback the version it copied)."""
        parents = dict(
            self._conn.execute(
                "SELECT version, coalesce(copy_of, version - 1) FROM versions WHERE map_id = ?",
                (map_id,),
            ).fetchall()
        )
        lineage = []
        while version >= 1:
            lineage.append(version)
            version = parents.get(version, version - 1)
        return {
            r[0]
            for r in self._conn.execute(
                "SELECT id FROM changes WHERE map_id = ? AND version IN "
                f"({','.join('?' * len(lineage))})",
                (map_id, *lineage),
            )
        }

    # -- changes ----------------------------------------------------------------------------

    def changes(
        self,
        name: str | None = None,
        *,
        state: str | None = None,
        ids: Iterable[int] | None = None,
        before_id: int | None = None,
        limit: int | None = None,
        newest_first: bool = False,
    ) -> list[ChangeInfo]:
        """Tracked changes, oldest first (``newest_first``: the reverse), filtered by map,
        state, ids, and ``id < before_id``; at most ``limit`` (a page, by key)."""
        if state is not None and state not in STATES:
            raise StoreError(f"unknown state {state!r}: use one of {', '.join(STATES)}")
        sql = (
            "SELECT c.id, m.name, c.kind, c.state, c.polygon, c.first_seen, c.last_seen, "
            "c.sessions, c.contradicted, c.version, c.note, c.updated_at FROM changes c "
            "JOIN maps m ON m.id = c.map_id WHERE 1 = 1"
        )
        args: list[Any] = []
        if name is not None:
            sql += " AND c.map_id = ?"
            args.append(self._map(name)[0])
        if state is not None:
            sql += " AND c.state = ?"
            args.append(state)
        if ids is not None:
            wanted = sorted(set(ids))
            if not wanted:
                return []
            sql += f" AND c.id IN ({','.join('?' * len(wanted))})"
            args += wanted
        if before_id is not None:
            sql += " AND c.id < ?"
            args.append(before_id)
        sql += " ORDER BY c.id" + (" DESC" if newest_first else "")
        if limit is not None:
            sql += " LIMIT ?"
            args.append(limit)
        rows = self._conn.execute(sql, args).fetchall()
        sightings: dict[int, list[tuple[str, str, str]]] = {}
        ids = [r[0] for r in rows]
        for chunk in range(0, len(ids), 500):
            part = ids[chunk : chunk + 500]
            q = ",".join("?" * len(part))
            for cid, bundle, robot, stamp in self._conn.execute(
                f"SELECT change_id, bundle_id, robot, stamp FROM sightings WHERE change_id IN ({q})",
                part,
            ):
                sightings.setdefault(cid, []).append((stamp, bundle, robot))
        out = []
        for (
            cid,
            map_name,
            kind,
            st,
            poly,
            first,
            last,
            sessions,
            contra,
            version,
            note,
            upd,
        ) in rows:
            seen = sorted(sightings.get(cid, []))
            out.append(
                ChangeInfo(
                    cid,
                    map_name,
                    kind,
                    st,
                    json.loads(poly),
                    first,
                    last,
                    sessions,
                    contra,
                    sorted({r for _, _, r in seen}),
                    [b for _, b, _ in seen],
                    version,
                    note,
                    upd,
                )
            )
        return out

    def changes_digest(self, name: str) -> tuple[int, str]:
        """(number of changes, their latest update time): what a cached view of a map's changes
        depends on."""
        count, latest = self._conn.execute(
            "SELECT count(*), max(updated_at) FROM changes WHERE map_id = ?", (self._map(name)[0],)
        ).fetchone()
        return int(count), str(latest or "")

    def outlines(self, name: str) -> list[tuple[int, str, list[list[float]]]]:
        """(id, state, polygon) of every change of a map but the expired ones (no sightings
        read: what a picture draws)."""
        return [
            (cid, state, json.loads(polygon))
            for cid, state, polygon in self._conn.execute(
                "SELECT id, state, polygon FROM changes WHERE map_id = ? AND state != 'expired' "
                "ORDER BY id",
                (self._map(name)[0],),
            )
        ]

    def change(self, change_id: int) -> ChangeInfo:
        change_id = self._changes.resolve_merged(change_id)
        row = self._conn.execute(
            "SELECT m.name FROM changes c JOIN maps m ON m.id = c.map_id WHERE c.id = ?",
            (change_id,),
        ).fetchone()
        if row is None:
            raise StoreError(f"no change {change_id} in the store (see 'mapserver changes list')")
        return next(c for c in self.changes(row[0]) if c.id == change_id)

    def approve(self, change_id: int, *, actor: str = "operator") -> VersionInfo:
        """Publish a confirmed change (review mode): a new version with it."""
        with self._writer():
            info = self.change(change_id)
            self._repaired(info.map)
            return self._approve(change_id, info, actor)

    def _approve(self, change_id: int, info: ChangeInfo, actor: str) -> VersionInfo:
        if info.state != "confirmed":
            raise StoreError(
                f"change {_named(change_id, info.id)} is {info.state}, not confirmed: only a "
                "confirmed change "
                "can be approved"
                + (
                    " (it is still pending: more sessions must see it)"
                    if info.state == "pending"
                    else ""
                )
            )
        map_id, lattice, yaw, _ = self._map(info.map)
        version = self._publish_changes(
            map_id,
            info.map,
            lattice,
            yaw,
            [info.id],
            note=f"change {info.id} approved by {actor}",
            actor=actor,
            expect="confirmed",
        )
        self._write_derived(info.map)
        return next(v for v in self.versions(info.map) if v.version == version)

    def reject(self, change_id: int, *, actor: str = "operator") -> ChangeInfo:
        """Reject a pending or confirmed change: it is never published, and later sightings of
        the same thing are counted on it instead of starting a new change."""
        with self._writer():
            info = self.change(change_id)
            self._repaired(info.map)
            return self._reject(change_id, info, actor)

    def _reject(self, change_id: int, info: ChangeInfo, actor: str) -> ChangeInfo:
        if info.state not in ("pending", "confirmed"):
            raise StoreError(
                f"change {_named(change_id, info.id)} is {info.state}: only a pending or "
                "confirmed change can be rejected"
            )
        with transaction(self._conn):
            cur = self._conn.execute(
                "UPDATE changes SET state = 'rejected', note = ?, updated_at = ? "
                "WHERE id = ? AND state IN ('pending', 'confirmed')",
                (f"rejected by {actor}", now_utc(), info.id),
            )
            # The daemon may have expired it since it was read (it does not take the lock).
            self._still_in("pending or confirmed", info.id, cur.rowcount)
            self._event(info.id, actor, "rejected")
            self._dirty.add(info.id)
        self._write_derived(info.map)
        return self.change(change_id)

    def history(self, change_id: int) -> list[dict[str, str]]:
        """Who did what to a change, and when (oldest first): review actions and publications."""
        change_id = self._changes.resolve_merged(change_id)
        return [
            {"at": at, "actor": actor, "action": action, "detail": detail}
            for at, actor, action, detail in self._conn.execute(
                "SELECT at, actor, action, detail FROM change_events WHERE change_id = ? "
                "ORDER BY id",
                (change_id,),
            )
        ]

    def _event(self, change_id: int, actor: str, action: str, detail: str = "") -> None:
        self._conn.execute(
            "INSERT INTO change_events (change_id, at, actor, action, detail) VALUES (?, ?, ?, ?, ?)",
            (change_id, now_utc(), actor, action, detail),
        )

    # -- bundles ----------------------------------------------------------------------------

    def apply(self, obs: Observation) -> Update:
        """Apply one bundle's observation: evidence, tracked changes, the persistence rule, and
        in auto mode the publication of what it confirmed. Once per bundle (fingerprint)."""
        start = time.perf_counter()
        stamp = utc_stamp(obs.stamp)
        map_id, lattice, yaw, _ = self._map(obs.map_name)
        implausible = _implausible_stamp(stamp, self.settings.max_clock_ahead_hours)
        if implausible:
            # A robot with a wrong clock: 1970 or next year would make a cart persist for
            # years, or expire every pending change. Its result is written; the map is not fed.
            return Update(
                obs.map_name,
                obs.bundle_version,
                self._current_version(map_id),
                tuple(None for _ in obs.result_cells),
                warnings=(f"map {obs.map_name}: not applied: {implausible}",),
                seconds=time.perf_counter() - start,
            )
        with transaction(self._conn):
            row = self._conn.execute(
                "SELECT outcome FROM bundles WHERE fingerprint = ?", (obs.fingerprint,)
            ).fetchone()
            if row is not None:
                done = json.loads(row[0])
                return Update(
                    obs.map_name,
                    obs.bundle_version,
                    self._current_version(map_id),
                    tuple(done["changes"]),
                    repeated=True,
                    seconds=time.perf_counter() - start,
                )
            hour = int(tracker.parse_stamp(stamp).timestamp() // 3600)
            evidence.add_deltas(self._conn, map_id, obs.tiles, hour)
            evidence.keep_observation(
                self._conn,
                map_id,
                obs.tiles,
                stamp=stamp,
                bundle_id=obs.bundle_id,
                robot=obs.robot,
            )
            outcome = self._changes.track(
                map_id, lattice, obs, stamp, lambda: self._current_state(map_id, obs.map_name)
            )
            self._checkpoint("evidence-applied")
            self._conn.execute(
                "INSERT INTO bundles (fingerprint, bundle_id, map_id, robot, stamp, applied_at, "
                "judged_version, outcome) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    obs.fingerprint,
                    obs.bundle_id,
                    map_id,
                    obs.robot,
                    stamp,
                    now_utc(),
                    obs.judged_version,
                    json.dumps(outcome),
                ),
            )
        self._checkpoint("bundle-applied")
        unwritten: OSError | None = None
        new_version = None
        published: list[int] = []
        warnings: list[str] = []
        # The bundle is counted (committed): nothing below may fail it. A publication or a file
        # that cannot be written now waits; sync() and the next bundles finish it.
        if self.settings.mode == "auto":
            try:
                with self._writer():
                    published = self._confirmed_ids(map_id)
                    if published:
                        new_version = self._publish_changes(
                            map_id,
                            obs.map_name,
                            lattice,
                            yaw,
                            published,
                            note=f"confirmed by {obs.bundle_id}",
                        )
            except Exception as error:
                published = []
                if isinstance(error, OSError):
                    unwritten = error
                warnings.append(
                    f"map {obs.map_name}: cannot publish a new version now ({error}); the confirmed changes wait"
                )
                log.error(
                    "%s: cannot publish a new version of %s: %s", obs.bundle_id, obs.map_name, error
                )
        try:
            with self._writer():
                self._write_derived(obs.map_name)
        except Exception as error:
            if isinstance(error, OSError):
                unwritten = error
            warnings.append(f"map {obs.map_name}: cannot rewrite changes.yaml / keepout ({error})")
            log.error(
                "%s: cannot write the files of map %s: %s", obs.bundle_id, obs.map_name, error
            )
        self.unwritten = unwritten
        return Update(
            obs.map_name,
            obs.bundle_version,
            self._current_version(map_id),
            tuple(outcome["changes"]),
            created=tuple(outcome["created"]),
            supported=tuple(outcome["supported"]),
            expired=tuple(outcome["expired"]),
            confirmed=tuple(outcome["confirmed"]),
            published=tuple(published),
            new_version=new_version,
            warnings=tuple(warnings),
            seconds=time.perf_counter() - start,
        )

    def bundles_under_review(self) -> set[str]:
        """The ids of the bundles a change not yet decided (pending or confirmed) was seen in:
        the ones whose files (result, archived bundle) a person reviewing it may look at."""
        return {
            row[0]
            for row in self._conn.execute(
                "SELECT DISTINCT s.bundle_id FROM sightings s JOIN changes c "
                "ON c.id = s.change_id WHERE c.state IN ('pending', 'confirmed')"
            )
        }

    def fold_evidence(self, *, max_tiles: int = 16) -> int:
        """Fold the pending evidence of up to ``max_tiles`` tiles into their counters (the
        daemon calls it when idle). Returns the deltas folded; 0 when nothing waits."""
        tiles = evidence.pending_tiles(self._conn, max_tiles)
        if not tiles:
            return 0
        folded = 0
        with transaction(self._conn):
            for map_id, tr, tc in tiles:
                folded += evidence.fold(self._conn, map_id, [(tr, tc)])
        return folded

    def sync(self) -> None:
        """Bring the files in line with the database (after a crash between a commit and the
        files, or a publication that failed on a full disk): publish what auto mode has
        confirmed, then write current.yaml, the keepout mask and changes.yaml of every map."""
        try:
            for (name,) in self._conn.execute("SELECT name FROM maps").fetchall():
                map_id, lattice, yaw, _ = self._map(name)
                with self._writer():
                    self._tidy(map_id, name)
                    if self.settings.mode == "auto":
                        ids = self._confirmed_ids(map_id)
                        if ids:
                            note = "confirmed earlier"
                            self._publish_changes(map_id, name, lattice, yaw, ids, note=note)
                    self._write_derived(name, force=True)
        except OSError as error:
            self.unwritten = error
            raise
        self.unwritten = None

    def _tidy(self, map_id: int, name: str) -> None:
        """The map's folder tidied (:func:`publish.set_aside`), each step logged."""
        known = {
            f
            for row in self._conn.execute(
                "SELECT yaml, image FROM versions WHERE map_id = ?", (map_id,)
            )
            for f in row
        }
        for line in publish.set_aside(self.root / name, known):
            log.warning("map %s: %s", name, line)

    def _repaired(self, name: str) -> None:
        """Before an operator's action: current.yaml, the keepout mask and changes.yaml brought
        in line with the database, should an earlier action have been killed between its commit
        and its files (a retried approve is refused as published; nothing else would mend them
        until the daemon's next bundle for that map)."""
        self._write_derived(name)

    # -- publishing -------------------------------------------------------------------------

    def _confirmed_ids(self, map_id: int) -> list[int]:
        return [
            r[0]
            for r in self._conn.execute(
                "SELECT id FROM changes WHERE map_id = ? AND state = 'confirmed' ORDER BY id",
                (map_id,),
            )
        ]

    def _paint_cells(self, cid: int) -> tuple[str, IntArray]:
        kind = self._conn.execute("SELECT kind FROM changes WHERE id = ?", (cid,)).fetchone()[0]
        most = self._conn.execute(
            "SELECT max(hits) FROM change_cells WHERE change_id = ?", (cid,)
        ).fetchone()[0]
        # Cells that enough of its sessions saw changed (or all of them, when fewer did).
        need = min(self.settings.paint_min_sessions, most or 1)
        cells = np.array(
            [
                r[0]
                for r in self._conn.execute(
                    "SELECT cell FROM change_cells WHERE change_id = ? AND hits >= ?", (cid, need)
                )
            ],
            np.int64,
        )
        return kind, cells

    def _seen_free_inside(
        self, map_id: int, lattice: Lattice, cid: int, cells: IntArray, state: NDArray[np.uint8]
    ) -> tuple[IntArray, IntArray]:
        """(rows, cols) of the cells inside removed change ``cid`` that ``state`` (the version
        being made, its outline painted) leaves unknown, in a patch of unknown enclosed within
        the convex hull of its painted ``cells`` (touching nothing outside it, nor the map's
        edge), that the fleet saw free: in at least as many sessions as a cell of it must have
        seen changed to be painted (``paint_min_sessions``, or all of its sessions when fewer),
        and more often free than occupied. A map draws a block or a column as its outline round
        an inside no lidar saw; gone, its outline painted free would leave that inside an island
        of unknown in the middle of floor the robots drove round (a planner that keeps out of
        unknown space would still go round it). Unknown that reaches past the change (a room
        beyond a removed wall that the map never saw) is no part of it: that stays unknown."""
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        if len(cells) < 3:
            return empty
        import cv2  # as Lattice.outline: the main process needs it only to publish

        rows, cols = lattice.unflat(cells)
        # The change's box and a cell round it (within the map): what lies past the hull.
        r0, c0 = max(int(rows.min()) - 1, 0), max(int(cols.min()) - 1, 0)
        r1 = min(int(rows.max()) + 2, lattice.height)
        c1 = min(int(cols.max()) + 2, lattice.width)
        window = Window(r0, c0, r1 - r0, c1 - c0)
        hull = cv2.convexHull(np.stack([cols - c0, rows - r0], axis=1).astype(np.int32))
        inside = np.zeros((window.rows, window.cols), np.uint8)
        cv2.fillConvexPoly(inside, hull, 1)
        unknown = (state[r0:r1, c0:c1] == UNKNOWN).view(np.uint8)
        n, labels = cv2.connectedComponents(unknown, connectivity=4)
        # A patch with a cell outside the hull, or on the window's edge (the map's, where the
        # window reaches it), is not enclosed.
        open_ = np.zeros(n, bool)
        open_[np.unique(labels[(inside == 0) & (unknown == 1)])] = True
        edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
        open_[np.unique(edge[edge > 0])] = True
        enclosed = (labels > 0) & ~open_[labels]
        if not enclosed.any():
            return empty
        sessions = self._conn.execute(
            "SELECT sessions FROM changes WHERE id = ?", (cid,)
        ).fetchone()[0]
        need = max(1, min(self.settings.paint_min_sessions, int(sessions)))
        seen = evidence.read_window(self._conn, map_id, window)
        free = enclosed & (seen.free >= need) & (seen.free > seen.occupied)
        fr, fc = np.nonzero(free)
        return fr + r0, fc + c0

    def _current_state(self, map_id: int, name: str) -> NDArray[np.uint8]:
        version = self._current_version(map_id)
        cached = self._states.get(map_id)
        if cached is not None and cached[0] == version:
            return cached[1]
        source = self._version_yaml(map_id, name, version)
        assert source is not None  # the current version has a row
        state = load_map(source).state
        state.flags.writeable = False
        self._states[map_id] = (version, state)
        return state

    def _publish_changes(
        self,
        map_id: int,
        name: str,
        lattice: Lattice,
        yaw: float,
        ids: list[int],
        *,
        note: str,
        actor: str = "mapserver",
        expect: str | None = None,
    ) -> int:
        """A new version: the current one with the changes painted (an added change's cells
        occupied, a removed one's free), only the cells their sessions saw changed. With
        ``expect``, each change must still be in that state when the version is committed
        (the daemon may expire it meanwhile: it does not take the writer lock), or nothing is
        published (:class:`StoreError`)."""
        state = self._current_state(map_id, name).copy()
        for cid in ids:
            kind, cells = self._paint_cells(cid)
            rows, cols = lattice.unflat(cells)
            if kind == "added":
                state[rows, cols] = OCCUPIED
            else:
                was = state[rows, cols] == OCCUPIED
                state[rows[was], cols[was]] = FREE
                inside = self._seen_free_inside(map_id, lattice, cid, cells, state)
                state[inside] = FREE
        if np.array_equal(state, self._current_state(map_id, name)):
            # The current version already shows them (another change painted the same cells):
            # no new version, the changes are in the current one.
            version = self._current_version(map_id)
            with transaction(self._conn):
                for cid in ids:
                    cur = self._conn.execute(
                        "UPDATE changes SET state = 'published', version = ?, updated_at = ? "
                        "WHERE id = ? AND (? IS NULL OR state = ?)",
                        (version, now_utc(), cid, expect, expect),
                    )
                    self._still_in(expect, cid, cur.rowcount)
                    self._event(cid, actor, "published", f"already in version {version}")
            self._dirty.update(ids)
            return version
        return self._publish_state(
            map_id, name, lattice, yaw, state, note, published=ids, actor=actor, expect=expect
        )

    def _still_in(self, expect: str | None, cid: int, updated: int) -> None:
        """Inside a publication's transaction: raise (rolling it back) when change ``cid`` was
        not updated because it is no longer in state ``expect``."""
        if expect is None or updated == 1:
            return
        row = self._conn.execute("SELECT state FROM changes WHERE id = ?", (cid,)).fetchone()
        raise StoreError(
            f"change {cid} is {row[0] if row else 'gone'} now, not {expect}: the daemon updated "
            "it while this was being done; nothing was published"
        )

    def _publish_state(
        self,
        map_id: int,
        name: str,
        lattice: Lattice,
        yaw: float,
        state: NDArray[np.uint8],
        note: str,
        *,
        published: Sequence[int] = (),
        undone: Sequence[int] = (),
        redone: Sequence[int] = (),
        actor: str = "mapserver",
        expect: str | None = None,
        copy_of: int | None = None,
    ) -> int:
        folder = self.root / name
        # Past every number on disk too: a file the database does not know (a restored backup)
        # may have been published, and is never overwritten with other contents.
        version = max(self._current_version(map_id), publish.highest_on_disk(folder)) + 1
        yaml_path, image = publish.write_version(folder, version, state, lattice, yaw)
        digest = sha256_file(image)
        now = now_utc()
        self._checkpoint("version-written")
        try:
            self._commit_version(
                map_id,
                version,
                now,
                (yaml_path, image, digest, note, copy_of),
                published,
                undone,
                redone,
                actor,
                expect,
            )
        except StoreError:
            # Never published: its files go (they would be written again by the next version).
            for path in (yaml_path, image):
                path.unlink(missing_ok=True)
            raise
        self._dirty.update(published, undone, redone)
        frozen = state.copy()
        frozen.flags.writeable = False
        self._states[map_id] = (version, frozen)
        publish.write_current(folder, yaml_path)
        log.info("map %s: published version %d (%s)", name, version, note)
        return version

    def _commit_version(
        self,
        map_id: int,
        version: int,
        now: str,
        files: tuple[Path, Path, str, str, int | None],
        published: Sequence[int],
        undone: Sequence[int],
        redone: Sequence[int],
        actor: str,
        expect: str | None,
    ) -> None:
        yaml_path, image, digest, note, copy_of = files
        with transaction(self._conn):
            self._conn.execute(
                "INSERT INTO versions (map_id, version, created_at, yaml, image, sha256, note, "
                "copy_of) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (map_id, version, now, yaml_path.name, image.name, digest, note, copy_of),
            )
            for cid in published:
                cur = self._conn.execute(
                    "UPDATE changes SET state = 'published', version = ?, updated_at = ? "
                    "WHERE id = ? AND (? IS NULL OR state = ?)",
                    (version, now, cid, expect, expect),
                )
                self._still_in(expect, cid, cur.rowcount)
                action = "approved" if actor != "mapserver" else "published"
                self._event(cid, actor, action, f"in version {version}")
            for cid in undone:
                self._conn.execute(
                    "UPDATE changes SET state = 'rejected', note = ?, updated_at = ? WHERE id = ?",
                    (f"undone by {note}", now, cid),
                )
                self._event(cid, actor, "rolled back", f"version {version}: {note}")
            for cid in redone:
                self._conn.execute(
                    "UPDATE changes SET state = 'published', note = ?, updated_at = ? WHERE id = ?",
                    (f"in the map again: {note}", now, cid),
                )
                self._event(cid, actor, "published", f"in version {version} again: {note}")

    def _write_derived(self, name: str, *, force: bool = False) -> None:
        """current.yaml (force), the keepout mask (when its cells changed) and changes.yaml."""
        map_id, lattice, yaw, _ = self._map(name)
        folder = self.root / name
        version = self._current_version(map_id)
        current_yaml = folder / publish.CURRENT
        wanted = self._version_yaml(map_id, name, version)
        assert wanted is not None  # the current version has a row
        # A process that died between a version's commit and current.yaml's rename left it
        # behind: every update compares the two (tiny) files.
        stale = not current_yaml.exists() or current_yaml.read_bytes() != wanted.read_bytes()
        if force or stale:
            publish.write_current(folder, wanted)
        keep = [self._paint_cells(cid) for cid in self._confirmed_ids(map_id)]
        cells = np.unique(
            np.concatenate([c for k, c in keep if k == "added"] or [np.zeros(0, np.int64)])
        )
        sig = hashlib.sha256(cells.astype("<i8").tobytes()).hexdigest()
        old = self._conn.execute("SELECT keepout_sig FROM maps WHERE id = ?", (map_id,)).fetchone()[
            0
        ]
        if force or sig != old or not (folder / f"{publish.KEEPOUT}.yaml").exists():
            publish.write_keepout(folder, cells, lattice, yaw)
            self._conn.execute("UPDATE maps SET keepout_sig = ? WHERE id = ?", (sig, map_id))
        self._write_changes(map_id, name, folder, version, force=force)

    def _write_changes(
        self, map_id: int, name: str, folder: Path, version: int, *, force: bool
    ) -> None:
        """changes.yaml: every tracked change, except expired ones that ended more than
        ``update.expired_listed_days`` ago (the database keeps them all: 'mapserver changes
        list --state expired')."""
        version_now = self._conn.execute("PRAGMA data_version").fetchone()[0]
        if version_now != self._data_version:
            self._docs.clear()
            self._data_version = version_now
        docs = self._docs.get(map_id)
        # The dirty ids of the other maps stay dirty until their own changes.yaml is written.
        others = set()
        if self._dirty:
            q = ",".join("?" * len(self._dirty))
            others = {
                r[0]
                for r in self._conn.execute(
                    f"SELECT id FROM changes WHERE map_id != ? AND id IN ({q})",
                    (map_id, *self._dirty),
                )
            }
        if docs is None or force:
            docs = self._docs[map_id] = {}
            fresh = self.changes(name)
        else:
            fresh = self.changes(name, ids=self._dirty - others)
            for cid in self._dirty - others:
                docs.pop(cid, None)  # merged away, or about to be made again
        self._dirty.intersection_update(others)
        # Until the file is written, the cached lines may be ahead of it: a failed write makes
        # the next one start from the database.
        del self._docs[map_id]
        for c in fresh:
            docs[c.id] = (c.state, c.updated_at, dump_yaml([c.document()]).decode("utf-8"))
        cutoff = utc_stamp(
            (
                tracker.parse_stamp(now_utc()) - timedelta(days=self.settings.expired_listed_days)
            ).isoformat()
        )
        for cid in [k for k, (st, upd, _) in docs.items() if st == "expired" and upd < cutoff]:
            del docs[cid]
        # Block style, as a person reads it; the name through the dumper, which quotes a name
        # YAML would read as something else (0042, 1.10, null, on, a date: session 59's review).
        head = yaml.safe_dump(
            {"format": 1, "map": name, "current_version": version},
            sort_keys=False,
            default_flow_style=False,
        ).encode("utf-8")
        body = "".join(docs[cid][2] for cid in sorted(docs))
        publish.write_changes_text(
            folder, head + (b"changes:\n" + body.encode("utf-8") if body else b"changes: []\n")
        )
        self._docs[map_id] = docs

    # -- rows -------------------------------------------------------------------------------

    def _map_row(self, name: str, *, missing_ok: bool = False) -> tuple[Any, ...] | None:
        row = self._conn.execute(
            "SELECT id, width, height, resolution, origin_x, origin_y, origin_yaw, created_at "
            "FROM maps WHERE name = ?",
            (name,),
        ).fetchone()
        if row is None and not missing_ok:
            known = [r[0] for r in self._conn.execute("SELECT name FROM maps ORDER BY name")]
            raise StoreError(
                f"no map named {name!r} in the store"
                + (
                    f" (maps: {', '.join(known)})"
                    if known
                    else " (add one with 'mapserver maps add')"
                )
            )
        return row  # type: ignore[no-any-return]

    def _map(self, name: str) -> tuple[int, Lattice, float, str]:
        row = self._map_row(name)
        assert row is not None
        map_id, w, h, res, ox, oy, yaw, created = row
        return map_id, Lattice(w, h, res, ox, oy), yaw, created

    def _version_yaml(self, map_id: int, name: str, version: int) -> Path | None:
        """The YAML of a version of a map, or None when it has no such version."""
        row = self._conn.execute(
            "SELECT yaml FROM versions WHERE map_id = ? AND version = ?", (map_id, version)
        ).fetchone()
        return None if row is None else self.root / name / row[0]

    def _current_version(self, map_id: int) -> int:
        return int(
            self._conn.execute(
                "SELECT max(version) FROM versions WHERE map_id = ?", (map_id,)
            ).fetchone()[0]
        )
