"""Watching the inbox and deciding when an upload is a complete bundle.

Three pieces, kept apart:

- :class:`InboxHandler` runs on watchdog's observer thread and only turns events into hints (the
  name of the inbox entry they concern) on a queue. It never raises: an exception in a handler
  stops watchdog's observer thread without a word.
- :class:`StabilityTracker` decides. Events are only hints (the kernel drops them when its queue
  overflows, rsync's final name arrives as a move, a directory can appear with its contents already
  inside), so the tracker looks at the directory itself: a fingerprint of every entry, and
  :func:`check_entry` (contract section 2) once the fingerprint has been still for
  ``settle_seconds``.
- :func:`scan` lists the inbox: at start-up (bundles that arrived while the daemon was down) and
  periodically (events that were lost).
"""

from __future__ import annotations

import logging
import os
import stat
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from queue import SimpleQueue

from watchdog.events import (
    DirCreatedEvent,
    DirDeletedEvent,
    DirModifiedEvent,
    DirMovedEvent,
    FileClosedEvent,
    FileCreatedEvent,
    FileDeletedEvent,
    FileModifiedEvent,
    FileMovedEvent,
    FileSystemEvent,
    FileSystemEventHandler,
)
from watchdog.observers import Observer
from watchdog.observers.api import BaseObserver
from watchdog.observers.polling import PollingObserver

from mapserver import tree
from mapserver.bundle import (
    MANIFEST,
    BundleFiles,
    check_bundle_files,
    is_in_flight,
    is_valid_bundle_id,
    nested_bundles_hint,
)
from mapserver.config import Config, LimitsConfig
from mapserver.errors import BundleError, BundleIncomplete, ChecksumMismatch, ManifestNotYaml

log = logging.getLogger(__name__)
_LIMITS = LimitsConfig()

# Not FileOpenedEvent / FileClosedNoWriteEvent: reading a bundle (the completeness check, the
# workers) would otherwise wake the daemon for nothing.
EVENT_TYPES: list[type[FileSystemEvent]] = [
    FileCreatedEvent,
    DirCreatedEvent,
    FileModifiedEvent,
    DirModifiedEvent,
    FileMovedEvent,
    DirMovedEvent,
    FileDeletedEvent,
    DirDeletedEvent,
    FileClosedEvent,
]


def entry_name(inbox: str, path: str | bytes) -> str | None:
    """The inbox entry (first path component below ``inbox``) that ``path`` belongs to, or None
    for the inbox itself, paths outside it and in-flight names (which include ``.taken``)."""
    rel = os.path.relpath(os.fsdecode(path), inbox)
    if rel == "." or rel == ".." or rel.startswith(".." + os.sep) or os.path.isabs(rel):
        return None
    name = rel.split(os.sep, 1)[0]
    return None if is_in_flight(name) else name


class InboxHandler(FileSystemEventHandler):
    """Puts the inbox entry name of every event on ``hints``; does nothing else."""

    def __init__(self, inbox: Path, hints: SimpleQueue[str | None]) -> None:
        super().__init__()
        self._inbox = os.fspath(inbox)
        self._hints = hints

    def on_any_event(self, event: FileSystemEvent) -> None:
        try:
            for path in (event.src_path, event.dest_path):
                if path:
                    name = entry_name(self._inbox, path)
                    if name is not None:
                        self._hints.put(name)
        except Exception:  # never let it reach watchdog: its thread would die silently
            log.exception("inbox: cannot handle event %r", event)


def scan(inbox: Path) -> list[str]:
    """The inbox entries that may be bundles (in-flight names left out), sorted."""
    with os.scandir(inbox) as entries:
        return sorted(e.name for e in entries if not is_in_flight(e.name))


Fingerprint = tuple[tuple[str, int, int, int, int, int], ...]


def fingerprint(path: Path) -> Fingerprint | None:
    """(relative name, type, size, mtime_ns, ctime_ns, inode) of ``path`` and everything below it,
    or None when ``path`` is gone.

    In-flight files (rsync's ``.name.XXXXXX``) are included although they are never read: one
    that still grows means the upload is going on. ctime and inode catch what size and mtime miss
    (``rsync -a`` sets old mtimes; a file replaced by rename keeps its size).
    """

    def item(rel: str, st: os.stat_result) -> tuple[str, int, int, int, int, int]:
        kind = stat.S_IFMT(st.st_mode)
        return (rel, kind, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)

    def unreadable(rel: str, error: OSError) -> tuple[str, int, int, int, int, int]:
        # Type -1: what cannot be looked at (a folder the daemon may not list, a path too
        # long); it stays in the fingerprint, and the check says what is wrong with it.
        return (rel, -1, error.errno or 0, 0, 0, 0)

    try:
        top = os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError as error:
        return (unreadable("", error),)
    items = [item("", top)]
    if stat.S_ISDIR(top.st_mode):

        def cannot_list(folder: str, error: OSError) -> None:
            items.append(unreadable(os.path.relpath(folder, path) + "/", error))

        for full in tree.walk(path, cannot_list):
            rel = os.path.relpath(full, path)
            try:
                items.append(item(rel, os.lstat(full)))
            except FileNotFoundError:
                items.append((rel, 0, -1, 0, 0, 0))
            except OSError as error:
                items.append(unreadable(rel, error))
    return tuple(sorted(items))


def _walk(root: Path) -> Iterator[Path]:
    def cannot_list(folder: str, error: OSError) -> None:
        raise BundleError(
            f"cannot read this folder of the bundle ({error.strerror}): the daemon must be "
            "able to read every file and folder of an upload",
            file=os.path.relpath(folder, root),
        )

    for full in tree.walk(root, cannot_list):
        yield Path(full)


def check_entry(path: Path, *, limits: LimitsConfig = _LIMITS) -> BundleFiles:
    """Contract section 2 for inbox entry ``path``, plus what makes an entry unsafe to read.

    Raises :class:`BundleIncomplete` while the upload may still be going on and
    :class:`BundleError` for an entry that can never be a bundle: not a directory, an invalid id,
    a symlink that is absolute or leaves the bundle, a special file (a FIFO would block a reader).
    """
    name = path.name
    if path.is_symlink():
        raise BundleError("a bundle must be a directory, not a symbolic link", file=name)
    if not path.is_dir():
        raise BundleError("not a directory: a bundle is a directory holding bundle.yaml", file=name)
    if not is_valid_bundle_id(name):
        raise BundleError(
            f"invalid bundle id {name!r}: use 1 to 128 letters, digits, '.', '_' and '-', "
            "starting with a letter or digit"
        )
    if not (path / MANIFEST).exists():
        hint = nested_bundles_hint(path)
        if hint:  # never a bundle, whatever else arrives: the manifest would be one level up
            raise BundleError(
                f"not a bundle: no bundle.yaml in it{hint}; upload each bundle folder directly "
                "into the inbox",
                file=name,
            )
    root = path.resolve()
    for item in _walk(path):
        rel = item.relative_to(path)
        mode = item.lstat().st_mode
        if stat.S_ISLNK(mode):
            target = os.readlink(item)
            try:
                resolved = item.resolve()
            except RuntimeError:  # Python 3.11 on a loop; 3.13 raises OSError (ELOOP)
                raise BundleError("symbolic link loop", file=rel) from None
            if os.path.isabs(target) or not resolved.is_relative_to(root):
                raise BundleError(
                    f"symbolic link to '{target}' points outside the bundle", file=rel
                )
            mode = resolved.stat().st_mode if resolved.exists() else stat.S_IFREG
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            raise BundleError("not a regular file or directory", file=rel)
    # The worker reads the trajectory: here its poses are only counted (a 100,000-pose one
    # held this loop for 4-8 s).
    try:
        return check_bundle_files(path, limits=limits, trajectory=False)
    except ManifestNotYaml as error:
        # Complete only once bundle.yaml parses (contract section 2): an upload that writes it
        # in place (cp, scp) and pauses is not cut off; stale_after_seconds of it is.
        raise BundleIncomplete(error.problem_line, file=error.file) from None


@dataclass(frozen=True)
class Ready:
    """Inbox entry ``name`` is a complete bundle; ``waited_s`` since the tracker first saw it."""

    name: str
    waited_s: float


@dataclass(frozen=True)
class Rejected:
    """Inbox entry ``name`` can never be a bundle (or never completed)."""

    name: str
    stage: str
    reason: str


Decision = Ready | Rejected


@dataclass
class _Entry:
    fingerprint: Fingerprint
    first_seen: float
    last_change: float
    incomplete: str | None = None
    """Why the current fingerprint is not a complete bundle (None: not checked yet)."""
    mismatch: bool = False
    """``incomplete`` is a checksum that does not match, with every file there."""


class StabilityTracker:
    """Decides when inbox entries are complete bundles (contract section 2).

    Per entry it keeps a fingerprint (:func:`fingerprint`), when it was first seen and when the
    fingerprint last changed. An entry whose fingerprint has been still for ``settle_seconds`` is
    checked once (:func:`check_entry`); the check is trusted only if the fingerprint is the same
    after it. A complete bundle becomes :class:`Ready`, an entry that can never be a bundle
    :class:`Rejected`; one that stays incomplete with nothing changing for
    ``stale_after_seconds`` is rejected with the last reason it was incomplete (an upload that is
    still making progress is never cut off). A checksum that does not match while every file is
    there is rejected sooner, after ``mismatch_after_seconds`` without a change (default: 10 x
    ``settle_seconds``, at most 60 s and at most ``stale_after_seconds``): waiting ten minutes
    for a file that is not being written is waiting for nothing. Each decision is returned once,
    after which the entry is forgotten: a new upload under the same name is a new entry.

    Not thread-safe: the service's main loop is its only user.
    """

    def __init__(
        self,
        inbox: Path,
        *,
        settle_seconds: float,
        stale_after_seconds: float,
        mismatch_after_seconds: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        check: Callable[[Path], object] = check_entry,
    ) -> None:
        self._inbox = Path(inbox)
        self._settle = settle_seconds
        self._stale = stale_after_seconds
        if mismatch_after_seconds is None:
            mismatch_after_seconds = min(10 * settle_seconds, 60.0)
        self._mismatch = max(settle_seconds, min(mismatch_after_seconds, stale_after_seconds))
        self._clock = clock
        self._check = check
        self._entries: dict[str, _Entry] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def touch(self, name: str) -> None:
        """Look at entry ``name`` now (an event hinted at it, or a scan listed it)."""
        if is_in_flight(name):
            return
        current = fingerprint(self._inbox / name)
        if current is None:
            self._entries.pop(name, None)
            return
        now = self._clock()
        entry = self._entries.get(name)
        if entry is None:
            self._entries[name] = _Entry(current, now, now)
        elif entry.fingerprint != current:
            entry.fingerprint, entry.last_change, entry.incomplete = current, now, None
            entry.mismatch = False

    def forget_missing(self, present: set[str]) -> None:
        """Drop entries not in ``present`` (a scan's listing)."""
        for name in [n for n in self._entries if n not in present]:
            del self._entries[name]

    def next_deadline(self) -> float | None:
        """The clock time at which :meth:`poll` may next decide something, None with no entries."""
        return min((self._deadline(e) for e in self._entries.values()), default=None)

    def _deadline(self, entry: _Entry) -> float:
        if entry.incomplete is None:
            return entry.last_change + self._settle
        return entry.last_change + (self._mismatch if entry.mismatch else self._stale)

    def poll(self, *, budget_s: float | None = None) -> list[Decision]:
        """The decisions that are due now. With ``budget_s``, stop deciding once that much time
        has gone (checksums of a large backlog take a while); the rest stay due for the next
        call."""
        decisions: list[Decision] = []
        start = self._clock()
        for name in list(self._entries):
            if budget_s is not None and self._clock() - start >= budget_s:
                break
            decision = self._decide(name, self._entries[name])
            if decision is not None:
                del self._entries[name]
                decisions.append(decision)
        return decisions

    def _decide(self, name: str, entry: _Entry) -> Decision | None:
        now = self._clock()
        if now - entry.last_change < self._settle:
            return None
        path = self._inbox / name
        if entry.incomplete is not None:
            if now < self._deadline(entry) or not self._still(name, entry, path, now):
                return None
            if entry.mismatch:
                return Rejected(
                    name,
                    "upload",
                    f"{entry.incomplete} (every file there, nothing changed for "
                    f"{now - entry.last_change:.0f} s)",
                )
            return Rejected(
                name,
                "upload",
                f"still incomplete after {now - entry.last_change:.0f} s without a change: "
                f"{entry.incomplete}",
            )
        if not self._still(name, entry, path, now):
            return None
        decision: Decision | None
        try:
            self._check(path)
        except BundleIncomplete as error:
            entry.incomplete = error.reason
            entry.mismatch = isinstance(error, ChecksumMismatch)
            decision = None
        except BundleError as error:
            decision = Rejected(name, error.stage, error.reason)
        except OSError as error:
            entry.incomplete = f"{path}: {error.strerror}"
            decision = None
        except Exception as error:  # a bug must not stop the daemon, nor retry forever
            log.exception("%s: cannot check it", name)
            reason = f"cannot check the bundle: {type(error).__name__}: {error}"
            decision = Rejected(name, "bundle", reason)
        else:
            decision = Ready(name, now - entry.first_seen)
        # The check read the files: trust it only if nothing changed meanwhile.
        if not self._still(name, entry, path, self._clock()):
            return None
        return decision

    def _still(self, name: str, entry: _Entry, path: Path, now: float) -> bool:
        """Whether the entry is unchanged since the stored fingerprint (updating it if not)."""
        current = fingerprint(path)
        if current is None:
            self._entries.pop(name, None)
            return False
        if current != entry.fingerprint:
            entry.fingerprint, entry.last_change, entry.incomplete = current, now, None
            entry.mismatch = False
            return False
        return True


def start_observer(config: Config, handler: InboxHandler) -> BaseObserver:
    """Watch ``config.inbox`` (and everything under it) with inotify, or by polling when
    ``observer: polling`` or inotify is not to be had; started."""
    # A bundle moved back into the inbox (a failed one, to be tried again) still carries the
    # inotify watch it had before it left: watchdog keeps the watches of directories moved
    # out of its tree, finds that one again and warns that it "will be Overwritten". It is
    # harmless (the watch follows the directory to its new name), and a bare warning on
    # stderr is not for an operator.
    warnings.filterwarnings(
        "ignore",
        message=r"Callback with id .* already exists for watch",
        category=RuntimeWarning,
    )
    kinds = ["native", "polling"] if config.observer == "native" else ["polling"]
    for kind in kinds:
        observer: BaseObserver
        if kind == "polling":
            observer = PollingObserver(timeout=min(1.0, max(0.1, config.settle_seconds / 2)))
        else:
            observer = Observer()
        observer.schedule(handler, str(config.inbox), recursive=True, event_filter=EVENT_TYPES)
        try:
            observer.start()
        except OSError as error:
            if kind == "polling":
                raise
            log.warning("inbox: cannot watch with inotify (%s); polling instead", error)
            continue
        return observer
    raise AssertionError("unreachable")  # pragma: no cover


def watch_afresh(observer: BaseObserver, handler: InboxHandler, inbox: Path) -> None:
    """Drop every watch of ``observer`` and watch ``inbox`` again (the watches of directories
    that left the tree go with them)."""
    observer.unschedule_all()
    observer.schedule(handler, str(inbox), recursive=True, event_filter=EVENT_TYPES)
