"""Where results and bundles go: atomic result directories, moves into ``archive/`` and
``failed/``, and the recovery that lets a restart after a crash finish every bundle exactly once.

The layout (contract section 3, plus two places of the daemon's own)::

    inbox/<name>/                    uploads: robots write here, the daemon only renames out of it
    inbox/.taken/<id>/               bundles the daemon has taken and not yet archived or failed
    inbox/.taken/.<id>.error.yaml    the error document of a bundle on its way to failed/
    outbox/.tmp-*                    results being written (partial; deleted at start-up)
    outbox/<id>/                     results; the directory appears whole, result.yaml written last
    archive/<id>/                    processed bundles, exactly as they arrived
    failed/<id>/                     rejected bundles, exactly as they arrived, plus error.yaml

Every step that changes where a bundle is is one ``rename`` (so inbox, outbox, archive and failed
must be on one filesystem), fsynced before the next step starts. Taking a bundle renames it into
``.taken`` under the id it will keep (``run-7``, or ``run-7.2`` when ``run-7`` is in use), so a
robot re-uploading the same name cannot write into a bundle being processed, and a restart knows
exactly which bundles are in hand. :meth:`Store.recover` holds the recovery rules; the README lists
them.
"""

from __future__ import annotations

import errno
import logging
import os
import secrets
import shutil
import stat
import string
import time
from collections.abc import Callable, Iterator
from contextlib import suppress
from dataclasses import dataclass
from datetime import datetime, timezone
from itertools import count
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapserver import tree
from mapserver.bundle import MANIFEST, is_valid_bundle_id
from mapserver.errors import ConfigError, MapserverError
from mapserver.fsio import dump_yaml as _dump
from mapserver.fsio import fsync_dir as _fsync_dir
from mapserver.fsio import rename_durable as _rename
from mapserver.fsio import write_new as _write

if TYPE_CHECKING:
    from mapserver.config import Config
    from mapserver.pipeline import Outcome

log = logging.getLogger(__name__)

RESULT = "result.yaml"
ERROR = "error.yaml"
TAKEN = ".taken"
TMP_PREFIX = ".tmp-"
_PROBE = ".mapserver-probe"
_ID_CHARS = frozenset(string.ascii_letters + string.digits + "._-")
_MAX_ID = 128


class OutboxError(MapserverError):
    """A result that cannot be written where it was asked to go."""

    default_stage = "outbox"


def utc_now() -> str:
    """The current time as ISO 8601 UTC with milliseconds (``2026-11-21T10:15:03.512Z``)."""
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _text(value: str) -> str:
    """A str that YAML can hold: undecodable bytes of file names become U+FFFD."""
    return value.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def error_document(bundle_id: str, stage: str, reason: str) -> dict[str, Any]:
    """The ``error.yaml`` document (contract section 3), ``reason`` on one line."""
    return {
        "format": 1,
        "bundle": _text(bundle_id),
        "failed_at": utc_now(),
        "stage": stage,
        "reason": " ".join(_text(reason).split()),
    }


def sanitize_id(name: str) -> str:
    """A valid bundle id made from a name that is not one (for ``failed/``): characters outside
    ``[A-Za-z0-9._-]`` become ``_``, leading ``._-`` are dropped, at most 128 characters."""
    text = "".join(c if c in _ID_CHARS else "_" for c in name).lstrip("._-")
    return text[:_MAX_ID] or "bundle"


def suffixed(bundle_id: str, n: int) -> str:
    """``run-7`` -> ``run-7.2`` (still a valid id: the base is shortened when needed)."""
    suffix = f".{n}"
    return bundle_id[: _MAX_ID - len(suffix)] + suffix


HISTORY = ".mapserver-history"
"""The folder ``mapserver requeue`` keeps a bundle's earlier error documents in (requeue.py)."""


def _tree(root: Path) -> dict[str, tuple[int, int, str]]:
    """Relative path -> (file type, size, symlink target) of everything under ``root``, but the
    error documents requeue kept in it (a requeued repeat is the same upload)."""
    out: dict[str, tuple[int, int, str]] = {}
    for path in tree.walk(root):
        rel = os.path.relpath(path, root)
        if rel == HISTORY or rel.startswith(HISTORY + os.sep):
            continue
        st = os.lstat(path)
        kind = stat.S_IFMT(st.st_mode)
        target = os.readlink(path) if stat.S_ISLNK(st.st_mode) else ""
        size = st.st_size if stat.S_ISREG(st.st_mode) else 0
        out[rel] = (kind, size, target)
    return out


def _same_bytes(a: Path, b: Path) -> bool:
    with a.open("rb") as fa, b.open("rb") as fb:
        while True:
            block = fa.read(1 << 20)
            if block != fb.read(1 << 20):
                return False
            if not block:
                return True


def _plain_tree(root: Path) -> dict[str, tuple[int, int, str]] | None:
    """``_tree(root)`` of a real directory (not a symlink); None for anything else, or when it
    cannot be listed."""
    try:
        if not root.is_dir() or root.is_symlink():
            return None
        return _tree(root)
    except OSError:
        return None


def _same_tree(a: Path, listing: dict[str, tuple[int, int, str]], b: Path) -> bool:
    """Whether directory ``b`` holds the same names, types and bytes as directory ``a``, whose
    :func:`_plain_tree` is ``listing``."""
    try:
        if listing != _plain_tree(b):
            return False
        return all(
            _same_bytes(a / rel, b / rel)
            for rel, (kind, _, _) in listing.items()
            if kind == stat.S_IFREG
        )
    except OSError:
        return False


def _make_tmp_dir(outbox: Path, bundle_id: str) -> Path:
    # Not tempfile.mkdtemp: its 0700 mode would follow the directory into the outbox.
    while True:
        path = outbox / f"{TMP_PREFIX}{bundle_id}-{secrets.token_hex(4)}"
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path


def _write_tmp_result(outbox: Path, outcome: Outcome) -> Path:
    """``outbox/.tmp-<id>-<random>/`` with the images, then result.yaml, all fsynced."""
    tmp = _make_tmp_dir(outbox, outcome.bundle_id)
    try:
        start = time.perf_counter()
        for name, data in outcome.images.items():
            if Path(name).name != name or name.startswith(".") or name == RESULT:
                raise ValueError(f"image name must be a plain file name, got {name!r}")
            _write(tmp / name, data)
        timings = outcome.result.get("timings_ms")
        if isinstance(timings, dict):
            # The images' writing (contract section 3's `write`); result.yaml, written last,
            # cannot hold its own time.
            timings["write"] = round((time.perf_counter() - start) * 1000.0, 1)
        _write(tmp / RESULT, _dump(outcome.result))
        _fsync_dir(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp


def write_result(outbox: Path, outcome: Outcome) -> Path:
    """Write ``outbox/<bundle_id>/`` atomically (temp dir, fsync, rename; result.yaml last).

    Returns the result directory. An existing result directory for the id is replaced (what
    ``mapserver process`` wants; the daemon uses :meth:`Store.publish`, which never replaces).
    """
    outbox.mkdir(parents=True, exist_ok=True)
    final = outbox / outcome.bundle_id
    if os.path.isdir(final) and not os.path.islink(final) and _holds_input(final):
        # ``mapserver process --outbox .`` in the folder that holds the bundle: the "earlier
        # result" would be the bundle itself, and replacing it would delete the input.
        raise OutboxError(
            f"{final} is not an earlier result but a bundle (it holds {MANIFEST}): choose an "
            "outbox that is not the folder the bundle is in; nothing was written",
            file=final,
        )
    tmp = _write_tmp_result(outbox, outcome)
    if os.path.lexists(final):
        old = outbox / f"{TMP_PREFIX}old-{outcome.bundle_id}-{secrets.token_hex(4)}"
        os.rename(final, old)
        _rename(tmp, final)
        shutil.rmtree(old)
    else:
        _rename(tmp, final)
    return final


def _earlier_ids(bundle_id: str) -> list[str]:
    """The ids ``bundle_id`` is a suffixed form of (``run-7.3``: ``run-7``, ``run-7.2``)."""
    root, dot, number = bundle_id.rpartition(".")
    if not dot or not number.isdigit() or not number.isascii() or int(number) < 2:
        return []
    n = int(number)
    if not root or suffixed(root, n) != bundle_id:
        return []
    # Bounded: an id such as "a.999999999" must not cost a billion looks.
    return [root, *(suffixed(root, k) for k in range(2, min(n, _EARLIER_IDS_MAX)))]


_EARLIER_IDS_MAX = 100


def _holds_input(folder: Path) -> bool:
    """Whether ``folder`` holds a bundle (its manifest) rather than a result."""
    return os.path.lexists(folder / MANIFEST)


@dataclass(frozen=True)
class Allocation:
    """The id a bundle will keep, and the bundle (archived, or in hand) it is a byte-identical
    copy of, if any (``archive/run-7``, ``inbox/.taken/run-7``)."""

    bundle_id: str
    duplicate_of: str | None = None


def check_one_filesystem(inbox: Path, outbox: Path, archive: Path, failed: Path) -> None:
    """A :class:`ConfigError` when the four folders (for one not made yet, the nearest folder
    above it that is) lie on different filesystems: bundles move between them by rename, which
    fails across filesystems. Made nothing, and read nothing but their devices: what
    ``check-config`` asks before ``run`` makes the folders and tries a rename between them
    (:meth:`Store.prepare`; under systemd, different ``ReadWritePaths=`` bind mounts of one
    filesystem fail the same way, and only that rename shows it)."""

    def device(path: Path) -> tuple[int, Path]:
        there = Path(path)
        while not there.exists() and there != there.parent:
            there = there.parent
        return os.stat(there).st_dev, there

    first, first_at = device(inbox)
    for name, path in (("outbox", outbox), ("archive", archive), ("failed", failed)):
        dev, at = device(path)
        if dev != first:
            raise ConfigError(
                f"{name} {path} is on another filesystem than inbox {inbox} ({at} and "
                f"{first_at}): inbox, outbox, archive and failed must be on one filesystem "
                "(bundles move between them by rename)"
            )


def _no_checkpoint(point: str) -> None:
    """The default checkpoint: nothing (see ``MAPSERVER_TEST_CRASH_AT`` in :mod:`service`)."""


class Store:
    """The four directories and every move between them.

    ``checkpoint(name)`` is called right after each durable step (``claimed``,
    ``result-written``, ``published``, ``archived``, ``error-staged``, ``failed-moved``); the
    crash tests use it to kill the daemon at each of them.
    """

    def __init__(
        self,
        inbox: Path,
        outbox: Path,
        archive: Path,
        failed: Path,
        *,
        checkpoint: Callable[[str], None] = _no_checkpoint,
    ) -> None:
        self.inbox = Path(inbox)
        self.outbox = Path(outbox)
        self.archive_dir = Path(archive)
        self.failed_dir = Path(failed)
        self.taken = self.inbox / TAKEN
        self._checkpoint = checkpoint

    @classmethod
    def from_config(
        cls, config: Config, *, checkpoint: Callable[[str], None] = _no_checkpoint
    ) -> Store:
        return cls(
            config.inbox, config.outbox, config.archive, config.failed, checkpoint=checkpoint
        )

    # -- start-up ---------------------------------------------------------------------------

    def prepare(self) -> None:
        """Create the directories and check that a bundle can move between them by rename.

        Raises :class:`ConfigError` when it cannot: different filesystems, or (under systemd)
        different ``ReadWritePaths=`` bind mounts, where rename fails with EXDEV.
        """
        for path in (self.inbox, self.outbox, self.archive_dir, self.failed_dir, self.taken):
            try:
                path.mkdir(parents=True, exist_ok=True)
            except OSError as error:
                raise ConfigError(
                    f"cannot create the directory: {error.strerror}", file=path
                ) from None
        hops = [self.taken, self.archive_dir, self.failed_dir, self.taken]
        for path in hops:  # a probe a crash left behind
            with suppress(FileNotFoundError):
                (path / _PROBE).rmdir()
        current = self.taken / _PROBE
        try:
            current.mkdir()
        except OSError as error:
            if error.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            # A full disk is no reason not to start (the daemon waits for space, degraded).
            log.warning("cannot check that bundles can move by rename now: %s", error.strerror)
            return
        try:
            for nxt in hops[1:]:
                try:
                    os.rename(current, nxt / _PROBE)
                except OSError as error:
                    hint = (
                        " (different filesystems, or under systemd different ReadWritePaths= "
                        "entries: give them one common parent)"
                        if error.errno == errno.EXDEV
                        else ""
                    )
                    raise ConfigError(
                        f"cannot move a bundle from {current.parent} to {nxt} by rename: "
                        f"{error.strerror}{hint}; inbox, outbox, archive and failed must be on "
                        "one filesystem"
                    ) from None
                current = nxt / _PROBE
        finally:
            with suppress(FileNotFoundError):
                current.rmdir()

    def recover(self) -> list[str]:
        """Finish what a crash interrupted; return the ids still to be processed (in ``.taken``).

        The rules, each safe at every crash point because every step is one rename:

        1. ``outbox/.tmp-*`` and ``.taken/*.tmp`` are the daemon's own partial writes: deleted.
        2. A staged error ``.taken/.<id>.error.yaml`` is finished: the bundle moves to
           ``failed/<id>/`` (if it had not yet) and the error joins it. If the bundle is in
           neither place it is still in the inbox (the crash came before it was taken): the
           staged error is dropped and the bundle is judged again like any upload.
        3. A bundle in ``.taken/<id>/`` whose ``outbox/<id>/result.yaml`` exists was published:
           it moves to ``archive/`` without being processed again. Any other one is processed
           again (the crashed attempt left nothing visible).
        """
        for entry in _scandir(self.outbox):
            if entry.name.startswith(TMP_PREFIX):
                log.info("recovery: removing partial result %s", entry.path)
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(entry.path)
                else:
                    os.unlink(entry.path)
        for entry in _scandir(self.taken):
            if entry.name.endswith(".tmp"):
                os.unlink(entry.path)
        for staged in sorted(self.taken.glob(".*.error.yaml")):
            bundle_id = staged.name[1 : -len(".error.yaml")]
            if os.path.lexists(self.taken / bundle_id):
                log.info("%s: recovery: finishing the move to failed/", bundle_id)
                self._finish_fail(bundle_id, staged)
            elif os.path.lexists(self.failed_dir / bundle_id):
                log.info("%s: recovery: adding error.yaml to failed/%s", bundle_id, bundle_id)
                self._place_error(staged, self.failed_dir / bundle_id)
            else:
                staged.unlink()
        todo = []
        for entry in sorted(_scandir(self.taken), key=lambda e: e.name):
            if entry.name.startswith("."):
                continue
            if (self.outbox / entry.name / RESULT).is_file():
                log.info("%s: recovery: result already published, archiving", entry.name)
                self.archive(entry.name)
            else:
                log.info("%s: recovery: taken but not finished, processing again", entry.name)
                todo.append(entry.name)
        return todo

    # -- taking bundles ---------------------------------------------------------------------

    def allocate(self, name: str, *, find_duplicate: bool = True) -> Allocation:
        """The id for inbox entry ``name``: the name itself when it is a valid id not yet in use in
        archive/, failed/, outbox/ or in hand; else the first free ``<id>.2``, ``<id>.3``, ...
        (contract section 3). With ``find_duplicate``, also reports a bundle, archived or in
        hand, that the upload is byte-identical to (a repeated upload)."""
        entry = self.inbox / name
        base = name if is_valid_bundle_id(name) else sanitize_id(name)
        listing = _plain_tree(entry) if find_duplicate else None  # listed once, compared often

        def copied(candidate: str) -> str | None:
            """The archived or in-hand bundle ``candidate`` when the upload is a copy of it."""
            if listing is None:
                return None
            for place, label in (
                (self.archive_dir, self.archive_dir.name),
                (self.taken, f"{self.inbox.name}/{TAKEN}"),
            ):
                earlier = place / candidate
                if earlier.is_dir() and _same_tree(entry, listing, earlier):
                    return f"{label}/{candidate}"
            return None

        # A requeued repeat (run-7.2) is a copy of run-7 or of an id between them.
        duplicate = next(filter(None, map(copied, _earlier_ids(base))), None)
        for n in count(1):
            candidate = base if n == 1 else suffixed(base, n)
            duplicate = duplicate or copied(candidate)
            if not self._in_use(candidate):
                return Allocation(candidate, duplicate)
        raise AssertionError("unreachable")  # pragma: no cover

    def _in_use(self, bundle_id: str) -> bool:
        places = (
            self.archive_dir / bundle_id,
            self.failed_dir / bundle_id,
            self.outbox / bundle_id,
            self.taken / bundle_id,
            self._staged(bundle_id),
        )
        return any(os.path.lexists(p) for p in places)

    def claim(self, name: str, bundle_id: str) -> Path:
        """Take inbox entry ``name``: rename it to ``.taken/<bundle_id>``."""
        path = self._take(name, bundle_id)
        self._checkpoint("claimed")
        return path

    def _take(self, name: str, bundle_id: str) -> Path:
        self.taken.mkdir(exist_ok=True)
        target = self.taken / bundle_id
        if os.path.lexists(target):
            raise FileExistsError(errno.EEXIST, "already in hand", str(target))
        _rename(self.inbox / name, target)
        return target

    def taken_path(self, bundle_id: str) -> Path:
        return self.taken / bundle_id

    # -- results ----------------------------------------------------------------------------

    def publish(self, outcome: Outcome) -> Path:
        """Write ``outbox/<id>/`` atomically; never replaces an existing result."""
        final = self.outbox / outcome.bundle_id
        if os.path.lexists(final):
            raise FileExistsError(errno.EEXIST, "a result directory already exists", str(final))
        tmp = _write_tmp_result(self.outbox, outcome)
        self._checkpoint("result-written")
        _rename(tmp, final)
        self._checkpoint("published")
        return final

    def archive(self, bundle_id: str) -> Path:
        """Move ``.taken/<id>`` to ``archive/<id>``."""
        target = self.archive_dir / bundle_id
        if os.path.lexists(target):
            raise FileExistsError(errno.EEXIST, "already archived", str(target))
        _rename(self.taken / bundle_id, target)
        self._checkpoint("archived")
        return target

    # -- failures ---------------------------------------------------------------------------

    def reject(self, name: str, bundle_id: str, stage: str, reason: str) -> Path:
        """Move inbox entry ``name`` to ``failed/<bundle_id>/`` with error.yaml (via .taken)."""
        reason = within_bundle(reason, self.inbox / name)
        staged = self._stage_error(bundle_id, stage, reason)
        try:
            self._take(name, bundle_id)
        except OSError:
            staged.unlink()
            raise
        return self._finish_fail(bundle_id, staged)

    def fail(self, bundle_id: str, stage: str, reason: str) -> Path:
        """Move ``.taken/<bundle_id>`` to ``failed/<bundle_id>/`` with error.yaml (also when a
        fault stopped an earlier call after the move: then only error.yaml is added)."""
        reason = within_bundle(reason, self.taken / bundle_id)
        staged = self._stage_error(bundle_id, stage, reason)
        target = self.failed_dir / bundle_id
        if not os.path.lexists(self.taken / bundle_id) and os.path.lexists(target):
            self._place_error(staged, target)
            return target
        return self._finish_fail(bundle_id, staged)

    def _staged(self, bundle_id: str) -> Path:
        return self.taken / f".{bundle_id}.error.yaml"

    def _stage_error(self, bundle_id: str, stage: str, reason: str) -> Path:
        self.taken.mkdir(exist_ok=True)
        staged = self._staged(bundle_id)
        partial = staged.with_name(staged.name + ".tmp")
        with suppress(FileNotFoundError):
            partial.unlink()
        try:
            _write(partial, _dump(error_document(bundle_id, stage, reason)))
            _rename(partial, staged)
        except OSError:  # a full disk: leave no partial error document behind
            with suppress(OSError):
                partial.unlink()
            raise
        self._checkpoint("error-staged")
        return staged

    def _finish_fail(self, bundle_id: str, staged: Path) -> Path:
        source = self.taken / bundle_id
        target = self.failed_dir / bundle_id
        if source.is_dir() and not source.is_symlink():
            _rename(source, target)
        else:
            # A file or symlink (not a bundle at all) gets a directory, so error.yaml has a place.
            target.mkdir(exist_ok=True)
            _rename(source, target / bundle_id)
        self._checkpoint("failed-moved")
        self._place_error(staged, target)
        return target

    def _place_error(self, staged: Path, target: Path) -> None:
        # Never overwrite an input: a bundle that holds files named like the daemon's error
        # document keeps them, and the daemon's takes the name after the last of them, so that
        # the last name is always the daemon's (daemon_error).
        after = _last_error_index(target)
        for n in count(after + 1):
            if not os.path.lexists(target / _error_name(n)):
                _rename(staged, target / _error_name(n))
                return


def _error_name(n: int) -> str:
    """The n-th name (from 1) the daemon's error document may take in ``failed/<id>/``:
    ``error.yaml``, then ``mapserver-error.yaml``, ``mapserver-error2.yaml`` ..."""
    return ERROR if n == 1 else f"mapserver-error{'' if n == 2 else n - 1}.yaml"


def _error_index(name: str) -> int:
    """Where ``name`` stands among :func:`_error_name`'s names (from 1), 0 when it is none."""
    if name == ERROR:
        return 1
    digits = name.removeprefix("mapserver-error").removesuffix(".yaml")
    if name != f"mapserver-error{digits}.yaml":
        return 0
    if digits == "":
        return 2
    n = int(digits) + 1 if digits.isdigit() and digits.isascii() else 0
    return n if n >= 3 and _error_name(n) == name else 0


def _last_error_index(folder: Path) -> int:
    """The last of :func:`_error_name`'s names present in ``folder``, as its index (0: none)."""
    return max((_error_index(e.name) for e in _scandir(folder)), default=0)


def daemon_error(failed_bundle: Path) -> Path | None:
    """The daemon's error document in ``failed/<id>/``: the last of :func:`_error_name`'s names
    there (the daemon names its own after every file of the bundle so named), None when there is
    none."""
    last = _last_error_index(failed_bundle)
    return failed_bundle / _error_name(last) if last else None


def within_bundle(reason: str, bundle: Path) -> str:
    """``reason`` with the bundle's path left out of the file names it gives: error.yaml sits in
    the bundle's folder, and the folder has moved since."""
    for form in dict.fromkeys((str(bundle), str(bundle.resolve()))):
        reason = reason.replace(form + os.sep, "")
    return reason


def _scandir(path: Path) -> Iterator[os.DirEntry[str]]:
    try:
        with os.scandir(path) as entries:
            yield from list(entries)
    except FileNotFoundError:
        return
