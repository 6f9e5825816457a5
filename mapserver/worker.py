"""The daemon's worker processes: their set-up (logging, OpenCV threads, signals, the memory
limit, the watch that ends them with the daemon), the job they run on one bundle, and what they
send back. Workers only read a bundle; the main process (:mod:`mapserver.service`) writes.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mapserver.board import FAULT_ENV, Board, inject_fault, limit_address_space, parse_faults
from mapserver.errors import MapserverError, OutOfMemory, StoreError
from mapserver.faults import is_transient

if TYPE_CHECKING:
    from mapserver.config import Config
    from mapserver.pipeline import Outcome

log = logging.getLogger(__name__)

ProcessFn = Callable[..., "Outcome"]


@dataclass(frozen=True)
class WorkDone:
    """What a worker returns: an outcome, or the stage and reason it failed. ``server_fault``
    names the server's folder (``maps``, ``inbox``) whose fault stopped it: not the bundle's
    fault, so it is processed again when that goes, never failed."""

    outcome: Outcome | None
    stage: str = ""
    reason: str = ""
    seconds: float = 0.0
    server_fault: str = ""


def _exit_with(pid: int) -> None:
    """End this worker when process ``pid`` (the daemon) ends, whatever the way.

    Without it the workers of a daemon killed with -9 wait forever on their task queue: each
    holds both ends of its pipe, so it never sees EOF (and it keeps the fork server alive too).
    """
    try:
        pidfd: int | None = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd (old kernel): look once a second
        pidfd = None

    def watch() -> None:
        if pidfd is not None:
            select.select([pidfd], [], [])
        else:
            while _alive(pid):
                time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="mapserver-watch-daemon", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass
class _Worker:
    """This worker process's part: its slot on the pool's board, its memory limit, the bundle
    in hand and the test faults."""

    board: Board | None = None
    memory_limit_mb: int = 0
    bundle_id: str = ""
    faults: dict[tuple[str, str], str] | None = None


_WORKER = _Worker()


def init_worker(
    setup: Callable[[], None] | None,
    daemon_pid: int,
    threads: int,
    board: Board | None = None,
    memory_limit_mb: int = 0,
) -> None:
    _exit_with(daemon_pid)
    # The pool already keeps every core busy: OpenCV's own threads on top would only contend.
    import cv2

    from mapserver.pipeline import on_stage

    cv2.setNumThreads(threads)
    # Stopping is the parent's business: a Ctrl-C in a terminal reaches the whole process group,
    # and a worker that died of it would look like a crash.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if board is not None:
        board.join()
    _WORKER.board = board
    _WORKER.memory_limit_mb = memory_limit_mb
    _WORKER.faults = parse_faults(os.environ.get(FAULT_ENV, ""))
    on_stage(_entered_stage)
    if setup is not None:
        setup()
    if memory_limit_mb:
        limit_address_space(memory_limit_mb)


def _entered_stage(name: str) -> None:
    """The pipeline's stage listener in a worker: tell the main process."""
    if _WORKER.board is not None:
        _WORKER.board.stage(name)
    fault = (_WORKER.faults or {}).get((_WORKER.bundle_id, name))
    if fault is not None:
        inject_fault(fault, memory_limit_mb=_WORKER.memory_limit_mb)


def process_taken_bundle(bundle_dir: Path, config: Config, *, bundle_id: str) -> Outcome:
    """The workers' default process function: :func:`process_bundle` on a bundle the daemon
    took, whose checksums it verified when it took it (the bundle has been in the daemon's own
    staging folder since), so they are not hashed a second time."""
    from mapserver.pipeline import process_bundle  # workers have it (fork server preload)

    return process_bundle(bundle_dir, config, bundle_id=bundle_id, checksums_verified=True)


def noop() -> None:
    return None


def work(
    process: ProcessFn, bundle_dir: str, config: Config, bundle_id: str, token: int = 0
) -> WorkDone:
    """Run in a worker: process one bundle; bad input becomes a :class:`WorkDone` with a reason.
    ``token`` names the job on the pool's board while it runs."""
    start = time.perf_counter()
    if _WORKER.board is not None:
        _WORKER.board.begin(token)
    _WORKER.bundle_id = bundle_id
    try:
        outcome = process(Path(bundle_dir), config, bundle_id=bundle_id)
    except StoreError as error:
        # The map store, read to link the bundle to its map: busy, damaged, its disk failing.
        # The fault names the store's folder; the reason need not.
        seconds = time.perf_counter() - start
        return WorkDone(None, error.stage, error.problem_line, seconds, "maps")
    except MapserverError as error:
        reason = error.reason
        if isinstance(error, OutOfMemory) and _WORKER.memory_limit_mb:
            reason += f" (worker_memory_mb: {_WORKER.memory_limit_mb})"
        return WorkDone(None, error.stage, reason, time.perf_counter() - start)
    except Exception as error:
        if is_transient(error):  # the bundle's staging folder or the store, failing under it
            server = "maps" if isinstance(error, sqlite3.Error) else "inbox"
            reason = f"{type(error).__name__}: {error}"
            return WorkDone(None, "process", reason, time.perf_counter() - start, server)
        log.exception("%s: internal error", bundle_id)
        reason = f"internal error: {type(error).__name__}: {error}"
        return WorkDone(None, "process", reason, time.perf_counter() - start)
    finally:
        _WORKER.bundle_id = ""
        if _WORKER.board is not None:
            _WORKER.board.end()
    return WorkDone(outcome, seconds=time.perf_counter() - start)
