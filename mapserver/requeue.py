"""``mapserver requeue``: send failed bundles back to the inbox, to be processed again once the
cause is fixed (a missing reference map, a limit raised, an upgrade).

Each bundle moves by one rename, ``failed/<id>`` -> ``inbox/<id>``, so the daemon (running or
not) sees a complete upload appear at once and takes it like any other. Before that, the
daemon's error document of the attempt that failed (``error.yaml``, or ``mapserver-error.yaml``
when the bundle brought its own error.yaml) moves into the bundle as
``.mapserver-history/error-<n>.yaml``, n = 1, 2, ... one per failed attempt: a dot-name, which
the server never reads, kept with the bundle wherever it goes next (archive/, or failed/ again).
A crash between the two renames leaves the bundle in failed/ without error.yaml; requeueing it
again finishes the move.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from itertools import count
from pathlib import Path

import yaml

from mapserver.bundle import MANIFEST, is_valid_bundle_id
from mapserver.config import Config
from mapserver.errors import MapserverError
from mapserver.fsio import rename_durable
from mapserver.outbox import HISTORY, daemon_error


@dataclass(frozen=True)
class Requeued:
    """A bundle sent back to the inbox, and the failure it had."""

    bundle_id: str
    failed_at: str
    stage: str
    reason: str
    path: Path
    """Where it is now (``inbox/<id>``)."""
    history: Path | None
    """Where its error document went (inside the bundle), None when it had none."""


def failed_since(config: Config, since: datetime) -> list[str]:
    """The ids in failed/ that failed at or after ``since`` (their error document's
    ``failed_at``; the folder's time when it has none), oldest first."""
    found = []
    try:
        names = [e.name for e in os.scandir(config.failed) if not e.name.startswith(".")]
    except FileNotFoundError:
        return []
    for name in names:
        when = _failed_at(config.failed / name)
        if when is not None and when >= since:
            found.append((when, name))
    return [name for _, name in sorted(found)]


def requeue(config: Config, ids: Sequence[str]) -> list[Requeued]:
    """Send failed bundles ``ids`` back to the inbox. Every id is checked first: when one is not
    a bundle in failed/ (or its name is taken in the inbox), :class:`MapserverError` says which,
    and nothing is moved."""
    problems = []
    wanted = list(dict.fromkeys(ids))
    for bundle_id in wanted:
        source = config.failed / bundle_id
        if not is_valid_bundle_id(bundle_id) or not source.is_dir() or source.is_symlink():
            problems.append(f"{bundle_id}: not in {config.failed}")
        elif _not_a_bundle(source, bundle_id):
            problems.append(f"{bundle_id}: a file or link was uploaded, not a bundle folder")
        elif os.path.lexists(config.inbox / bundle_id):
            problems.append(f"{bundle_id}: {config.inbox / bundle_id} exists already")
    if wanted and not config.inbox.is_dir():
        problems.append(f"the inbox {config.inbox} is not there (the daemon makes it at start)")
    if problems:
        raise MapserverError("; ".join(problems) + " (nothing was requeued)", stage="requeue")
    done: list[Requeued] = []
    for bundle_id in wanted:
        try:
            done.append(_requeue_one(config, bundle_id))
        except OSError as error:
            before = f"; requeued before it: {', '.join(d.bundle_id for d in done)}" if done else ""
            raise MapserverError(
                f"{bundle_id}: cannot move it: {error.strerror or error} ({error.filename}); it "
                f"stays in {config.failed} as it was (run requeue as the daemon's user){before}",
                stage="requeue",
            ) from None
    return done


def _requeue_one(config: Config, bundle_id: str) -> Requeued:
    """One bundle back to the inbox; on an OSError (a folder it may not write), everything as
    it was before."""
    source = config.failed / bundle_id
    document: dict[str, object] = {}
    error = daemon_error(source)
    history = None
    made = False
    if error is not None:
        document = _read(error)
        folder = source / HISTORY
        if not folder.is_dir():
            folder.mkdir()
            made = True
        history = next(
            folder / f"error-{n}.yaml"
            for n in count(1)
            if not (folder / f"error-{n}.yaml").exists()
        )
        try:
            rename_durable(error, history)
        except OSError:
            if made:
                folder.rmdir()
            raise
    target = config.inbox / bundle_id
    try:
        rename_durable(source, target)
    except OSError:
        if error is not None and history is not None:  # the error document back in its place
            rename_durable(history, error)
            if made:
                history.parent.rmdir()
        raise
    return Requeued(
        bundle_id,
        str(document.get("failed_at", "?")),
        str(document.get("stage", "?")),
        str(document.get("reason", "?")),
        target,
        None if history is None else target / HISTORY / history.name,
    )


def _not_a_bundle(source: Path, bundle_id: str) -> bool:
    """A file or symlink that was uploaded in place of a bundle sits in ``failed/<id>/<id>``."""
    inner = source / bundle_id
    return not (source / MANIFEST).exists() and (inner.is_symlink() or inner.is_file())


def _read(path: Path) -> dict[str, object]:
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    return document if isinstance(document, dict) else {}


def _failed_at(folder: Path) -> datetime | None:
    error = daemon_error(folder)
    if error is not None:
        stamp = _read(error).get("failed_at")
        try:
            return parse_time(str(stamp))
        except ValueError:
            pass
    try:
        return datetime.fromtimestamp(folder.stat().st_mtime, timezone.utc)
    except OSError:
        return None


def parse_time(text: str) -> datetime:
    """``2026-11-21``, ``2026-11-21T10:15``, ``2026-11-21T10:15:00Z`` ... as an aware datetime;
    without a zone, UTC (the zone of every time the server writes)."""
    value = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    return value if value.tzinfo is not None else value.replace(tzinfo=timezone.utc)
