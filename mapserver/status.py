"""What ``mapserver status`` reports: is the daemon running (and its pid), its queue, the results
and failures of the last 24 hours, and the free space of each folder.

The running daemon writes its own counts to ``inbox/.mapserver.status`` (a dot-name, never read
as an upload) whenever they change, at most once a second; the rest is read from the folders,
so the report also works when no daemon runs.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from mapserver.config import Config
from mapserver.faults import format_size
from mapserver.lock import daemon_pid
from mapserver.outbox import RESULT, TAKEN, daemon_error

STATUS_NAME = ".mapserver.status"
DAY_S = 24 * 3600.0
# Failures listed with their reason (the most recent first); the rest are counted.
_LISTED_FAILURES = 5


def write_status(inbox: Path, document: dict[str, Any]) -> None:
    """Replace ``inbox/.mapserver.status`` with ``document`` (a reader never sees half of it).
    Not fsynced: after a crash the lock, not this file, says whether a daemon runs.

    On a full disk (no block for a new file) the existing file is rewritten in place instead,
    in the block it has: a full disk is what the status must then tell. A reader may catch
    that write half done; :func:`read_status` reads again.
    """
    path = inbox / STATUS_NAME
    data = (yaml.safe_dump(document, sort_keys=False) + _END).encode("utf-8")
    partial = path.with_name(path.name + ".tmp")
    try:
        partial.write_bytes(data)
        os.replace(partial, path)
    except OSError as error:
        with contextlib.suppress(OSError):
            partial.unlink()
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        fd = os.open(path, os.O_WRONLY)
        try:
            os.pwrite(fd, data, 0)
            os.ftruncate(fd, len(data))
        finally:
            os.close(fd)


# The status file's last line: a file read while rewritten in place lacks it.
_END = "# end\n"


def read_status(inbox: Path) -> dict[str, Any] | None:
    for _ in range(5):
        try:
            text = (inbox / STATUS_NAME).read_text(encoding="utf-8")
        except OSError:
            return None
        except UnicodeDecodeError:
            text = ""
        if text.endswith(_END):
            try:
                document = yaml.safe_load(text)
            except yaml.YAMLError:
                document = None
            if isinstance(document, dict):
                return document
        time.sleep(0.02)  # caught while the daemon rewrote it in place
    return None


@dataclass(frozen=True)
class Failure:
    bundle_id: str
    failed_at: str
    stage: str
    reason: str


@dataclass(frozen=True)
class Space:
    name: str
    path: Path
    free_bytes: int | None
    total_bytes: int | None
    device: int | None


@dataclass
class Report:
    pid: int | None
    """The running daemon's pid; None when none runs."""
    daemon: dict[str, Any] | None
    """The running daemon's own status document, when it has written one."""
    uploading: int = 0
    queued: int = 0
    processing: int = 0
    results_24h: int = 0
    failed_24h: int = 0
    failures: list[Failure] = field(default_factory=list)
    space: list[Space] = field(default_factory=list)
    degraded: dict[str, Any] | None = None
    """The running daemon's faults (its status file's ``degraded``); None when it has none."""

    @property
    def running(self) -> bool:
        return self.pid is not None

    def lines(self, config: Config, *, now: float | None = None) -> list[str]:
        """The report for a person, one fact per line."""
        now = time.time() if now is None else now
        out = []
        if self.running:
            since = (self.daemon or {}).get("started_at", "?")
            out.append(f"daemon:    running, pid {self.pid or 'unknown'}, since {since}")
            out += _health_lines(self.degraded)
        else:
            out.append(f"daemon:    not running (no mapserver run holds {config.inbox})")
        # Without a daemon nothing tells an upload still going on from a complete one: the
        # entries are counted as waiting in the inbox (session 58's review: after a kill -9,
        # eight complete uploads read "8 uploading").
        waiting = "uploading" if self.running else "in the inbox (judged when it starts)"
        queue = (
            f"queue:     {self.uploading} {waiting}, {self.queued} queued, "
            f"{self.processing} processing"
        )
        if self.running and self.daemon is not None:
            queue += f" (the daemon's count, {_age(self.daemon.get('updated_at'), now)})"
        elif self.queued:
            queue += " (taken before the daemon stopped: processed at its next start)"
        out.append(queue)
        out.append(f"last 24 h: {self.results_24h} results, {self.failed_24h} failed")
        for failure in self.failures:
            out.append(
                f"  failed {failure.bundle_id} at {failure.failed_at}, stage {failure.stage}: "
                f"{failure.reason}"
            )
        if self.failed_24h > len(self.failures):
            out.append(f"  ... and {self.failed_24h - len(self.failures)} more in {config.failed}")
        out.append("free space:")
        width = max(len(str(s.path)) for s in self.space)
        seen: set[int | None] = set()
        for s in self.space:
            if s.free_bytes is None or s.total_bytes is None:
                out.append(f"  {s.name:<8} {s.path!s:<{width}}  not there")
                continue
            line = (
                f"  {s.name:<8} {s.path!s:<{width}}  {format_size(s.free_bytes)} free of "
                f"{format_size(s.total_bytes)} ({100 * s.free_bytes / max(s.total_bytes, 1):.0f}%)"
            )
            if s.device in seen:
                line += ", the same filesystem"
            seen.add(s.device)
            out.append(line)
        return out


def report(config: Config, *, now: float | None = None, recent: bool = True) -> Report:
    """Gather the report for ``config``'s folders (reads only). ``recent=False`` leaves out the
    last 24 hours' results and failures (a stat per bundle: the web pages count them from their
    own index)."""
    now = time.time() if now is None else now
    pid = daemon_pid(config)
    daemon = read_status(config.inbox) if pid is not None else None
    if daemon is not None and daemon.get("pid") != pid:
        daemon = None  # left by an earlier daemon
    out = Report(pid, daemon)
    if daemon is not None:
        out.uploading = int(daemon.get("uploading", 0))
        out.queued = int(daemon.get("queued", 0))
        out.processing = int(daemon.get("processing", 0))
        degraded = daemon.get("degraded")
        out.degraded = degraded if isinstance(degraded, dict) else None
    else:
        out.uploading = len(_visible(config.inbox))
        out.queued = len(_visible(config.inbox / TAKEN))
    if recent:
        since = now - DAY_S
        out.results_24h = sum(1 for _ in _recent(config.outbox, lambda d: d / RESULT, since))
        # The daemon's error document: mapserver-error.yaml when the bundle brought an
        # error.yaml of its own, whose time may be a robot's (rsync -a keeps it).
        failed = sorted(_recent(config.failed, daemon_error, since), key=lambda item: -item[1])
        out.failed_24h = len(failed)
        out.failures = [_failure(path) for path, _ in failed[:_LISTED_FAILURES]]
    folders = {name: getattr(config, name) for name in ("inbox", "outbox", "archive", "failed")}
    if config.maps is not None:
        folders["maps"] = config.maps
    for name, path in folders.items():
        try:
            usage = shutil.disk_usage(path)
            device: int | None = os.stat(path).st_dev
        except OSError:
            out.space.append(Space(name, path, None, None, None))
            continue
        out.space.append(Space(name, path, usage.free, usage.total, device))
    return out


def _health_lines(degraded: dict[str, Any] | None) -> list[str]:
    """``health: ok``, or ``health: DEGRADED ...`` with a line per fault."""
    if degraded is None:
        return ["health:    ok"]
    waiting = degraded.get("waiting", 0)
    wait = f"{waiting} bundle waits" if waiting == 1 else f"{waiting} bundles wait"
    out = [
        f"health:    DEGRADED since {degraded.get('since', '?')}: {wait} (not "
        "failed: they are done once the cause goes)"
    ]
    for fault in degraded.get("faults") or []:
        free = fault.get("free_bytes")
        space = f"{format_size(free)} free" if isinstance(free, int) else "free space unknown"
        out.append(
            f"  {fault.get('folder', '?')} {fault.get('path', '?')}: {fault.get('reason', '?')} "
            f"({space})"
        )
    return out


def _visible(path: Path) -> list[str]:
    try:
        with os.scandir(path) as entries:
            return [e.name for e in entries if not e.name.startswith(".")]
    except OSError:
        return []


def _recent(
    folder: Path, document: Callable[[Path], Path | None], since: float
) -> list[tuple[Path, float]]:
    """The ``document`` of each ``folder/<id>/`` written since ``since`` (epoch seconds), with
    that time."""
    found = []
    for bundle_id in _visible(folder):
        path = document(folder / bundle_id)
        if path is None:
            continue
        with contextlib.suppress(OSError):
            mtime = path.stat().st_mtime
            if mtime >= since:
                found.append((path, mtime))
    return found


def _failure(error_yaml: Path) -> Failure:
    try:
        document = yaml.safe_load(error_yaml.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        document = None
    if not isinstance(document, dict):
        document = {}
    return Failure(
        error_yaml.parent.name,
        str(document.get("failed_at", "?")),
        str(document.get("stage", "?")),
        str(document.get("reason", f"(unreadable {error_yaml.name})")),
    )


def _age(stamp: object, now: float) -> str:
    try:
        then = datetime.fromisoformat(str(stamp).replace("Z", "+00:00"))
    except ValueError:
        return "age unknown"
    seconds = max(0.0, now - then.replace(tzinfo=then.tzinfo or timezone.utc).timestamp())
    return f"{seconds:.0f} s ago"
