"""The daemon (``mapserver run``): wires the inbox observer, the stability tracker, a pool of
worker processes and the store; handles signals; talks to systemd.

One thread, the main loop, does everything that changes the filesystem, in this order on every
wake-up: look at the inbox entries that events hinted at, rescan when due, take the bundles the
tracker decided on (:meth:`Store.claim` / :meth:`Store.reject`), publish and archive what the
workers finished, hand queued bundles to free workers, tell systemd it is alive. Workers only read
a bundle and return an :class:`~mapserver.pipeline.Outcome`; they write nothing, so a worker that
crashes (or a daemon killed with -9) leaves nothing half-done behind.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import itertools
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from queue import Empty, SimpleQueue
from types import FrameType
from typing import TYPE_CHECKING, Any

from watchdog.observers.api import BaseObserver
from watchdog.observers.polling import PollingObserver

from mapserver.board import Board, resident_bytes
from mapserver.config import Config, check_paths
from mapserver.faults import Fault, Health, fault_in, fault_of, is_transient
from mapserver.inbox import (
    Decision,
    InboxHandler,
    Rejected,
    StabilityTracker,
    check_entry,
    scan,
    start_observer,
    watch_afresh,
)
from mapserver.lock import daemon_lock, store_lock
from mapserver.notify import notify, watchdog_period
from mapserver.outbox import RESULT, Store, utc_now, within_bundle
from mapserver.retention import Retention
from mapserver.status import STATUS_NAME, write_status
from mapserver.trust import trust_notice
from mapserver.worker import ProcessFn, WorkDone, init_worker, noop, process_taken_bundle, work

if TYPE_CHECKING:
    from mapserver.fleet.store import FleetStore

log = logging.getLogger(__name__)

CRASH_ENV = "MAPSERVER_TEST_CRASH_AT"
"""Test hook: the name of a checkpoint (see :class:`~mapserver.outbox.Store`, plus
``submitted``) at which the daemon kills itself with SIGKILL, to test recovery from each one."""


def env_checkpoint() -> Callable[[str], None]:
    """The checkpoint function that honours ``$MAPSERVER_TEST_CRASH_AT``."""
    point = os.environ.get(CRASH_ENV)

    def checkpoint(name: str) -> None:
        if name == point:
            os.kill(os.getpid(), signal.SIGKILL)

    return checkpoint


# How long watchdog's inotify emitter holds a move out of the inbox, waiting for its pair.
try:
    from watchdog.observers.inotify_move_event_grouper import InotifyMoveEventGrouper

    _INOTIFY_MOVE_DELAY_S = float(InotifyMoveEventGrouper.delay)
except ImportError:  # watchdog < 7 (InotifyBuffer, the same half second), or no inotify
    _INOTIFY_MOVE_DELAY_S = 0.5

# How long one turn of the main loop may spend checking uploads.
_POLL_TURN_S = 0.05
# The inotify watches are set up afresh after this many bundles left the inbox (each left one
# watch behind: see Service._rearm). $MAPSERVER_TEST_REARM_AFTER: a smaller number, for tests.
_REARM_AFTER = int(os.environ.get("MAPSERVER_TEST_REARM_AFTER", "500"))


# Deeper than the folders a path of PATH_MAX bytes can name (see Service.run).
_RECURSION_LIMIT = 5000


def _broke(future: Future[WorkDone]) -> bool:
    """Whether a finished job's worker pool broke under it (a worker process died)."""
    return not future.cancelled() and isinstance(future.exception(), BrokenProcessPool)


# -- the parent side ----------------------------------------------------------------------------


def over_limit(
    stage: str,
    held_s: float,
    resident: int | None,
    *,
    timeout_s: float,
    memory_limit_mb: int,
) -> str | None:
    """Why a worker that has held its bundle ``held_s`` seconds, in ``stage``, with ``resident``
    bytes resident (None: unknown) must be stopped, or None. The memory first: a worker past
    both limits (one that grew slowly on a loaded machine, or was looked at late) is stopped
    for the one that endangers the server, and its error says so."""
    if resident is not None and resident > memory_limit_mb * 2**20:
        return (
            f"over the memory limit: {resident / 2**20:.0f} MiB in stage {stage} after "
            f"{held_s:.1f} s (worker_memory_mb: {memory_limit_mb}); the maps may be too large "
            "for this server"
        )
    if held_s > timeout_s:
        return (
            f"over the time limit: still in stage {stage} after {held_s:.1f} s "
            f"(bundle_timeout_seconds: {timeout_s:g}); the maps may be too large for this "
            "server, or the bundle makes the pipeline hang"
        )
    return None


@dataclass
class _Job:
    bundle_id: str
    taken_at: float
    """Monotonic time the bundle was taken as complete (or found in hand at start-up)."""
    attempts: int = 0
    alone: bool = False
    """It was in a worker pool that broke: it now runs with no other bundle beside it."""
    generation: int = 0
    token: int = 0
    """Its name on the worker pool's board."""
    over_limit: tuple[str, str] | None = None
    """(stage, reason): its worker was stopped past the time or memory limit."""
    published: bool = False
    """Its result is in the outbox (a fault stopped the move to archive/ after it)."""
    waits: bool = False
    """It has waited for a fault of the server's folders (:class:`_Waiting`)."""
    again: Fault | None = None
    """The fault that stopped its processing, while it is processed again (the daemon stays
    degraded until it is done)."""


@dataclass
class _Waiting:
    """A bundle whose result, move to archive/ or failure could not be written because the
    server's folders or map store failed (:mod:`mapserver.faults`): it stays taken, and is
    written when the fault goes, not processed again. With neither ``done`` nor ``failure``,
    the fault stopped its processing: it is processed again."""

    job: _Job
    fault: Fault
    done: WorkDone | None = None
    failure: tuple[str, str] | None = None


@dataclass
class _Counts:
    results: int = 0
    failed: int = 0


class Service:
    """The daemon. ``run()`` blocks until :meth:`request_stop` (or SIGTERM/SIGINT when run in the
    main thread) and returns the exit code.

    Parameters
    ----------
    config
        The validated configuration; read once, plain values passed down.
    process
        The function a worker calls (a module-level function, so it can be pickled):
        ``process(bundle_dir, config, bundle_id=...) -> Outcome``.
    worker_setup
        Called once in each worker process (the CLI passes its logging set-up).
    stop_timeout
        After a stop request, how long bundles in hand may take to finish before their workers
        are killed (they are processed again at the next start).
    """

    def __init__(
        self,
        config: Config,
        *,
        process: ProcessFn = process_taken_bundle,
        worker_setup: Callable[[], None] | None = None,
        stop_timeout: float = 60.0,
    ) -> None:
        self._config = config
        self._process = process
        self._worker_setup = worker_setup
        self._stop_timeout = stop_timeout
        self._checkpoint = env_checkpoint()
        self._store = Store.from_config(config, checkpoint=self._stepped)
        self._moved_out_at = float("-inf")
        """When a bundle last left the inbox's tree (to archive/ or failed/), monotonic."""
        self._moved_since_arm = 0
        """Bundles moved out of the inbox's tree since the inotify watches were last set up."""
        self._handler: InboxHandler | None = None
        self._started_at = utc_now()
        self._status_written: tuple[object, float] = ((), float("-inf"))
        self._status_unwritable = False
        """Whether the last write of the status file failed (said once, at WARNING)."""
        self._workers = config.worker_count()
        self._tracker = StabilityTracker(
            config.inbox,
            settle_seconds=config.settle_seconds,
            stale_after_seconds=config.stale_after_seconds,
            check=functools.partial(check_entry, limits=config.limits),
        )
        self._hints: SimpleQueue[str | None] = SimpleQueue()
        self._queue: deque[_Job] = deque()
        self._running: dict[Future[WorkDone], _Job] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._board: Board | None = None
        self._tokens = itertools.count(1)
        self._timeout_s = config.bundle_timeout_seconds
        self._memory_limit_mb = config.worker_memory_limit_mb()
        self._stopped_in: set[int] = set()
        """Pool generations in which a worker was stopped past a limit."""
        self._generation = 0
        self._pool_broken = False
        self._counts = _Counts()
        self._fleet: FleetStore | None = None
        self._health = Health()
        self._waiting: deque[_Waiting] = deque()
        self._retake: dict[str, Fault] = {}
        """Inbox entries that could not be taken (or rejected) because of a fault."""
        self._locked: set[str] = set()
        """Inbox entries whose own folder the server may not write (each said once)."""
        self._store_fault: Fault | None = None
        """The map store's files lag its database, or it could not be used (a fault)."""
        self._folders = {
            "inbox": config.inbox,
            "outbox": config.outbox,
            "archive": config.archive,
            "failed": config.failed,
        }
        if config.maps is not None:
            self._folders["maps"] = config.maps
        self._retention = Retention(config.retention, self._folders, keep=self._under_review)
        self._stopping = False
        self._abort = False
        self.ready = threading.Event()
        """Set once the start-up scan is done (when systemd gets READY=1)."""
        self._next_rescan = 0.0
        self._inbox_id: tuple[int, int] | None = None
        self._last_ping = float("-inf")
        period = watchdog_period()
        self._ping_every = min(1.0, period / 3) if period else 1.0

    # -- control --------------------------------------------------------------------------

    @property
    def stopping(self) -> bool:
        return self._stopping

    @property
    def health(self) -> Health:
        """Whether the daemon is degraded (``health.degraded``), by which faults
        (``health.faults``: folder, path, reason, free bytes), since when and how many bundles
        wait: for the metrics. Read-only; the main loop keeps it."""
        return self._health

    def request_stop(self) -> None:
        """Stop taking bundles, finish the ones in hand, return from :meth:`run`. A second call
        stops at once (bundles in hand are processed again at the next start). Safe to call from
        a signal handler or another thread."""
        if self._stopping:
            self._abort = True
        self._stopping = True
        self._hints.put(None)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.request_stop()

    def run(self) -> int:
        """Run until stopped; 0 after a requested stop, 1 when the inbox cannot be watched.

        Raises :class:`~mapserver.lock.AlreadyRunning` at once when another daemon serves the
        same inbox (nothing is touched then).
        """
        # watchdog walks a folder moved into the inbox with os.walk, which recurses on Python
        # 3.11: an upload nested a thousand folders deep (a path still under PATH_MAX, 4096
        # bytes, holds about 2000) would raise RecursionError in its thread and stop the watch.
        sys.setrecursionlimit(max(sys.getrecursionlimit(), _RECURSION_LIMIT))
        previous: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGTERM, signal.SIGINT):
                previous[signum] = signal.signal(signum, self._on_signal)
        try:
            check_paths(self._config)
            folders = {
                "inbox": self._config.inbox,
                "outbox": self._config.outbox,
                "archive": self._config.archive,
                "failed": self._config.failed,
            }
            if self._config.maps is not None:
                folders["maps"] = self._config.maps
            missing = [f"{name} {path}" for name, path in folders.items() if not path.exists()]
            with daemon_lock(self._config), contextlib.ExitStack() as self._exits:
                if missing:  # a misspelt path in the configuration must not pass unseen
                    log.warning(
                        "created %s: not there before; if robots upload elsewhere, correct the "
                        "configuration",
                        ", ".join(missing),
                    )
                return self._run()
        finally:
            for number, handler in previous.items():
                signal.signal(number, handler)

    def _run(self) -> int:
        config = self._config
        self._store.prepare()
        self._inbox_id = _identity(config.inbox)
        if config.maps is not None:
            # One process feeds the store (held until exit: the kernel drops it on a crash).
            self._exits.enter_context(store_lock(config.maps))
            # Refuses to start on a damaged or missing database, saying how to recover.
            from mapserver.fleet.store import FleetStore

            self._fleet = FleetStore(
                config.maps, config.update, checkpoint=self._checkpoint, busy_timeout_s=2.0
            )
            self._sync_store()
        now = time.monotonic()
        recovered = self._store.recover()
        self._queue.extend(_Job(bundle_id, now) for bundle_id in recovered)
        self._pool = self._new_pool()
        try:
            self._warm_up()
            observer = self._start_observer()
            try:
                self._rescan()
                # The status file first: once the daemon says it is ready, `mapserver status`
                # can read it, and a disk that fills right after still has its block to rewrite
                # in place (a first write on a full disk has none).
                self._write_status()
                log.info(
                    "ready: watching %s with the %s observer, %d workers; %d inbox entries "
                    "waiting, %d bundles in hand from before",
                    config.inbox,
                    "polling" if isinstance(observer, PollingObserver) else "native",
                    self._workers,
                    len(self._tracker),
                    len(recovered),
                )
                notify("READY=1", self._status())
                self.ready.set()
                code = self._loop(observer)
            finally:
                notify("STOPPING=1", "STATUS=stopping: finishing the bundles in hand")
                self._let_the_observer_pair_its_moves(observer)
                observer.stop()
                observer.join()
        finally:
            self._finish_running()
            if self._fleet is not None:
                self._fleet.close()
        log.info(
            "stopped: %d results, %d failed; %d bundles taken and not started (processed at the "
            "next start)",
            self._counts.results,
            self._counts.failed,
            len(self._queue) + len(self._waiting),  # those that waited for a fault too
        )
        return code

    # -- the main loop ----------------------------------------------------------------------

    def _loop(self, observer: BaseObserver) -> int:
        while not self._stopping:
            names = self._wait(self._timeout())
            if self._stopping:
                break
            for name in names:
                self._tracker.touch(name)
            if time.monotonic() >= self._next_rescan:
                self._rescan()
            # Finished bundles first: their workers get the next bundle in the queue before
            # anything else here runs (publishing, hashing new uploads).
            self._collect()
            self._enforce_limits()
            if self._health.due():
                self._retry_waiting()
            # Bounded, so that a large backlog (checksums to hash) keeps neither the watchdog nor
            # the workers waiting: what is taken goes out below, the rest is looked at on the
            # next turn, a moment later.
            for decision in self._tracker.poll(budget_s=min(_POLL_TURN_S, self._ping_every)):
                _guarded(decision.name, self._take, decision)
            self._dispatch()
            if self._fleet is not None and not (self._running or self._queue or self._waiting):
                # Idle: fold waiting evidence into its counters, a few tiles a turn.
                _guarded("fleet", self._fold_evidence)
            self._health.update(self._faults(), self._waiting_count())
            _guarded("retention", self._retention.step)  # a few entries a turn, hourly
            if self._moved_since_arm >= _REARM_AFTER:
                _guarded("inbox", self._rearm, observer)
            if not _observer_alive(observer):
                log.error("inbox: the observer stopped watching %s; exiting", self._config.inbox)
                return 1
            # Looked at here, not left to the observer: the lock file held open inside the inbox
            # keeps the kernel from reporting the inbox's removal (IN_DELETE_SELF) while it is
            # open, and a replaced inbox is never reported at all.
            if _identity(self._config.inbox) != self._inbox_id:
                log.error("inbox: %s was removed or replaced; exiting", self._config.inbox)
                return 1
            self._heartbeat()
        log.info("stopping: no more bundles are taken")
        return 0

    def _timeout(self) -> float:
        now = time.monotonic()
        timeout = min(self._next_rescan - now, self._ping_every)
        deadline = self._tracker.next_deadline()
        if deadline is not None:
            timeout = min(timeout, deadline - now)
        retry = self._health.seconds_to_retry()
        if retry is not None:
            timeout = min(timeout, retry)
        if self._running and self._board is not None:
            for activity in self._board.activities():
                timeout = min(timeout, activity.started + self._timeout_s - now)
        return max(timeout, 0.01)

    def _wait(self, timeout: float) -> set[str]:
        """Block until a hint arrives (or ``timeout``), then drain the queue: the inbox entry
        names hinted at. Many events about one upload become one look at it."""
        names: set[str] = set()
        try:
            item = self._hints.get(timeout=timeout)
        except Empty:
            return names
        while True:
            if item is not None:
                names.add(item)
            try:
                item = self._hints.get_nowait()
            except Empty:
                return names

    def _rescan(self) -> None:
        self._next_rescan = time.monotonic() + self._config.rescan_seconds
        try:
            names = scan(self._config.inbox)
        except OSError as error:
            log.error("inbox: cannot list %s: %s", self._config.inbox, error.strerror)
            return
        for name in names:
            self._tracker.touch(name)
        self._tracker.forget_missing(set(names))

    # -- taking bundles -----------------------------------------------------------------------

    def _take(self, decision: Decision) -> None:
        name = decision.name
        try:
            # A rejected upload goes to failed/ whatever it repeats: no search for its twin.
            allocation = self._store.allocate(
                name, find_duplicate=not isinstance(decision, Rejected)
            )
            bundle_id = allocation.bundle_id
            if isinstance(decision, Rejected):
                self._reject(name, bundle_id, decision.stage, decision.reason)
                return
            if allocation.duplicate_of is not None:
                reason = (
                    f"a repeated upload: identical to {allocation.duplicate_of}, taken already; "
                    "upload new maps under a new bundle id"
                )
                self._reject(name, bundle_id, "bundle", reason)
                return
            self._store.claim(name, bundle_id)
        except FileNotFoundError:
            self._retake.pop(name, None)
            self._locked.discard(name)
            log.warning("%s: left the inbox before it was taken", name)
            return
        except OSError as error:
            entry = self._config.inbox / name
            if locked_folder(error, entry):
                # The bundle's own fault, not the inbox's: no degraded state, one line for
                # the operator, and the rescans try it again until it can be moved.
                self._retake.pop(name, None)
                if name not in self._locked:
                    self._locked.add(name)
                    log.error(
                        "%s: cannot take it: the server may not write its folder %s, and a "
                        "folder moves only with write permission on itself (a copy of a "
                        "read-only folder?); it stays in the inbox, taken once it may "
                        "(chmod -R u+w, or the group write permission the documented uploads "
                        "give)",
                        name,
                        entry,
                    )
                return
            if is_transient(error):  # it stays in the inbox, looked at again after a pause
                self._retake[name] = fault_of(error, self._folders, "inbox")
                log.info("%s: cannot take it now (%s); it stays in the inbox", name, error)
                return
            log.error("%s: cannot take it from the inbox: %s", name, error)
            return
        self._retake.pop(name, None)
        if name in self._locked:
            self._locked.discard(name)
            log.info("%s: its folder may be written now: taken", name)
        if bundle_id != name:
            log.info("%s: id already in use, taken as %s", name, bundle_id)
        log.info("%s: upload %.1f ms", bundle_id, decision.waited_s * 1000.0)
        self._queue.append(_Job(bundle_id, time.monotonic()))

    def _reject(self, name: str, bundle_id: str, stage: str, reason: str) -> None:
        path = self._store.reject(name, bundle_id, stage, reason)
        self._retake.pop(name, None)
        self._counts.failed += 1
        # The files named as error.yaml names them, in the folder the line ends with (session
        # 58's review: the line named them in inbox/.taken/, where they no longer are).
        shown = within_bundle(reason, self._config.inbox / name)
        log.warning("%s: done: failed at stage %s: %s -> %s", bundle_id, stage, shown, path)

    # -- workers ----------------------------------------------------------------------------

    def _new_pool(self) -> ProcessPoolExecutor:
        # forkserver, not fork: a pool replaced after a crash is forked while the observer thread
        # runs, and fork() with threads can copy a held lock into the child. The server imports
        # the pipeline once; every worker (also those replacing a crashed pool) forks from it.
        context = multiprocessing.get_context("forkserver")
        preload = ["mapserver.pipeline"]
        if self._config.pipeline.diff.cluster_engine == "scikit-learn":
            preload.append("sklearn.cluster")
        context.set_forkserver_preload(preload)
        threads = max(1, (os.cpu_count() or 1) // self._workers)
        self._board = Board(context, self._workers)
        # The fork server reads these when it imports numpy: a BLAS's threads spin on every
        # core, and beside a second worker they cost each a third of its speed (measured).
        for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(name, str(threads))
        return ProcessPoolExecutor(
            max_workers=self._workers,
            mp_context=context,
            initializer=init_worker,
            initargs=(
                self._worker_setup,
                os.getpid(),
                threads,
                self._board,
                self._memory_limit_mb,
            ),
        )

    def _warm_up(self) -> None:
        """Start the worker processes now, not on the first bundle (the first start waits for the
        fork server to import the pipeline). Not waited for beyond that: a broken pool shows on
        first use and is replaced then."""
        assert self._pool is not None
        for _ in range(self._workers):
            self._pool.submit(noop)

    def _replace_pool(self) -> None:
        if self._pool is not None:
            # A broken pool asks its other workers to stop with SIGTERM, which they ignore (see
            # _init_worker), and waits for them: its thread, and the daemon's exit, would hang.
            self._kill_workers()
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()
        self._generation += 1
        self._pool_broken = False

    def _dispatch(self) -> None:
        # While finished bundles wait for a fault to clear, more results would only wait too.
        if self._stopping or self._waiting:
            return
        while self._queue and len(self._running) < self._workers:
            if any(job.alone for job in self._running.values()):
                return
            job = self._queue[0]
            if job.alone and self._running:
                return
            self._queue.popleft()
            self._submit(job)
            if job.alone:
                return

    def _submit(self, job: _Job) -> None:
        if self._pool_broken:
            self._replace_pool()
        assert self._pool is not None
        path = str(self._store.taken_path(job.bundle_id))
        job.token = next(self._tokens)
        args = (self._process, path, self._config, job.bundle_id, job.token)
        try:
            future = self._pool.submit(work, *args)
        except (BrokenProcessPool, RuntimeError):
            self._replace_pool()
            future = self._pool.submit(work, *args)
        if job.attempts == 0:
            log.info("%s: queue %.1f ms", job.bundle_id, (time.monotonic() - job.taken_at) * 1e3)
        job.attempts += 1
        job.generation = self._generation
        self._running[future] = job
        future.add_done_callback(self._wake)
        self._checkpoint("submitted")

    def _wake(self, future: Future[WorkDone]) -> None:
        self._hints.put(None)

    def _collect(self) -> None:
        finished = [(f, self._running.pop(f)) for f in [f for f in self._running if f.done()]]
        if not any(_broke(f) for f, _ in finished):
            # Refill the freed workers before publishing (fsyncs): they would idle meanwhile.
            # Not after a crash: the pool is replaced first, below.
            self._dispatch()
        for future, job in finished:
            try:
                done = future.result()
            except BrokenProcessPool:
                _guarded(job.bundle_id, self._crashed, job)
                continue
            except Exception as error:  # the outcome could not be sent back, for instance
                reason = f"internal error: {type(error).__name__}: {error}"
                _guarded(job.bundle_id, self._fail, job, "process", reason)
                continue
            _guarded(job.bundle_id, self._finish, job, done)
        if self._pool_broken and not self._stopping:
            self._replace_pool()

    def _crashed(self, job: _Job) -> None:
        if job.generation == self._generation:
            self._pool_broken = True
        if job.over_limit is not None:  # the bundle's own fault: failed at once, not retried
            self._fail(job, *job.over_limit)
            return
        if self._stopping:
            log.warning(
                "%s: its worker died while stopping; processed again at the next start",
                job.bundle_id,
            )
            return
        if job.alone:
            self._fail(
                job,
                "process",
                "the worker process died while processing this bundle, twice, with no other "
                "bundle beside it (out of memory, or a crash in the image code)",
            )
            return
        if job.generation in self._stopped_in:
            # The pool broke because another bundle's worker was stopped past a limit.
            log.info(
                "%s: started again: its worker pool was replaced after another bundle went past "
                "a limit",
                job.bundle_id,
            )
            self._queue.appendleft(job)
            return
        log.warning(
            "%s: a worker process died while this bundle was in hand; retrying it alone",
            job.bundle_id,
        )
        job.alone = True
        self._queue.appendleft(job)

    def _enforce_limits(self) -> None:
        """Stop (SIGKILL) each worker past ``bundle_timeout_seconds`` or ``worker_memory_mb``;
        its bundle is failed with the stage it was in when the pool reports the worker dead
        (:meth:`_crashed`), and the other bundles of the pool are started again."""
        if self._board is None or not self._running:
            return
        jobs = {j.token: j for j in self._running.values() if j.generation == self._generation}
        processes = getattr(self._pool, "_processes", None) or {}
        now = time.monotonic()
        for activity in self._board.activities():
            job = jobs.get(activity.token)
            if job is None or job.over_limit is not None or activity.pid not in processes:
                continue
            stage = activity.stage
            reason = over_limit(
                stage,
                now - activity.started,
                resident_bytes(activity.pid),
                timeout_s=self._timeout_s,
                memory_limit_mb=self._memory_limit_mb,
            )
            if reason is None:
                continue
            job.over_limit = (stage, reason)
            self._stopped_in.add(job.generation)
            log.warning("%s: %s; stopping its worker (pid %d)", job.bundle_id, reason, activity.pid)
            with contextlib.suppress(ProcessLookupError):
                os.kill(activity.pid, signal.SIGKILL)

    def _finish(self, job: _Job, done: WorkDone, *, retry: bool = False) -> None:
        """Apply a finished bundle to the map store, publish its result, archive it (or fail
        it). A fault of the server's folders or store makes it wait (:meth:`_hold`); ``retry``
        is the attempt after one."""
        bundle_id = job.bundle_id
        outcome = done.outcome
        if outcome is None and done.server_fault:
            self._hold(job, fault_in(done.server_fault, self._folders, done.reason))
            return
        if outcome is None:
            self._fail(job, done.stage, done.reason, retry=retry)
            return
        if self._waiting and not retry:  # behind the ones that wait already
            self._hold(job, self._waiting[-1].fault, done=done)
            return
        if outcome.bundle_id != bundle_id:
            reason = f"internal error: the result is for bundle {outcome.bundle_id!r}"
            self._fail(job, "process", reason)
            return
        if outcome.observation is not None and self._fleet is not None:
            try:
                # Once per bundle (a fingerprint): a retry after a fault re-applies as a no-op.
                update = self._fleet.apply(outcome.observation)
            except Exception as error:  # a damaged database, a full disk under it
                if is_transient(error):
                    self._hold(job, fault_of(error, self._folders, "maps"), done=done)
                    return
                log.exception("%s: cannot apply it to the fleet map", bundle_id)
                self._fail(job, "update", f"cannot apply it to the fleet map: {error}")
                return
            self._note_store_files()
            update.annotate(outcome.result)
            log.info("%s: update %.1f ms: %s", bundle_id, update.seconds * 1000.0, update.summary())
        start = time.perf_counter()
        result_dir = self._store.outbox / bundle_id
        if not job.published:
            try:
                result_dir = self._store.publish(outcome)
            except Exception as error:  # a full disk, or a result YAML cannot hold
                if is_transient(error):
                    self._hold(job, fault_of(error, self._folders, "outbox"), done=done)
                    return
                self._fail(job, "write", f"cannot write the result: {error}")
                return
            job.published = True
        published = time.perf_counter()
        log.info("%s: publish %.1f ms", bundle_id, (published - start) * 1000.0)
        try:
            self._store.archive(bundle_id)
        except OSError as error:
            if is_transient(error):
                self._hold(job, fault_of(error, self._folders, "archive"), done=done)
                return
            log.error("%s: result written, but cannot archive the bundle: %s", bundle_id, error)
            return
        log.info("%s: archive %.1f ms", bundle_id, (time.perf_counter() - published) * 1000.0)
        self._counts.results += 1
        notice = trust_notice(outcome.result.get("alignment") or {})
        if notice:
            log.warning("%s: %s", bundle_id, notice)
        log.info(
            "%s: done: ok, %d differences, %.2f s from complete to result (processing %.2f s) "
            "-> %s",
            bundle_id,
            len(outcome.result.get("differences") or []),
            time.monotonic() - job.taken_at,
            done.seconds,
            result_dir / RESULT,
        )

    def _fail(self, job: _Job, stage: str, reason: str, *, retry: bool = False) -> None:
        if self._waiting and not retry:
            self._hold(job, self._waiting[-1].fault, failure=(stage, reason))
            return
        try:
            path = self._store.fail(job.bundle_id, stage, reason)
        except OSError as error:
            if is_transient(error):
                fault = fault_of(error, self._folders, "failed")
                self._hold(job, fault, failure=(stage, reason))
                return
            log.error(
                "%s: failed at stage %s (%s), and cannot move it to failed/: %s; it stays in hand "
                "until the next start",
                job.bundle_id,
                stage,
                reason,
                error,
            )
            return
        self._counts.failed += 1
        shown = within_bundle(reason, self._store.taken / job.bundle_id)
        log.warning("%s: done: failed at stage %s: %s -> %s", job.bundle_id, stage, shown, path)

    # -- faults of the server's folders (mapserver.faults) ----------------------------------

    def _hold(
        self,
        job: _Job,
        fault: Fault,
        *,
        done: WorkDone | None = None,
        failure: tuple[str, str] | None = None,
    ) -> None:
        """Keep a finished bundle until the fault goes; nothing of it is visible meanwhile."""
        self._waiting.append(_Waiting(job, fault, done, failure))
        if job.waits:  # said already; the health warning repeats once a minute
            return
        job.waits = True
        log.info(
            "%s: waits: %s %s: %s (the bundle stays in %s)",
            job.bundle_id,
            fault.folder,
            fault.path,
            fault.reason,
            self._store.taken_path(job.bundle_id),
        )

    def _retry_waiting(self) -> None:
        """One retry of what waits for a fault: the inbox entries not taken (looked at again),
        the map store's files, then the finished bundles in order until one fails again."""
        for name in list(self._retake):
            self._tracker.touch(name)
            if name not in self._tracker:  # gone from the inbox
                del self._retake[name]
        if self._store_fault is not None:
            self._sync_store()
        while self._waiting:
            item = self._waiting.popleft()
            before = len(self._waiting)
            if item.done is not None:
                retry = functools.partial(self._finish, retry=True)
                _guarded(item.job.bundle_id, retry, item.job, item.done)
            elif item.failure is not None:
                retry = functools.partial(self._fail, retry=True)
                _guarded(item.job.bundle_id, retry, item.job, *item.failure)
            else:
                log.info("%s: processed again after: %s", item.job.bundle_id, item.fault.reason)
                item.job.again = item.fault
                self._queue.appendleft(item.job)
                continue
            if len(self._waiting) > before:  # it waits again, first in line: try later
                self._waiting.rotate(1)
                break
        self._health.retried()

    def _sync_store(self) -> None:
        """Write the map store's files from its database (at start, and to retry a publication
        a fault stopped); a fault leaves the daemon degraded, not stopped."""
        assert self._fleet is not None
        try:
            self._fleet.sync()
        except Exception as error:
            if not is_transient(error):
                raise
            self._store_fault = fault_of(error, self._folders, "maps")
            return
        self._store_fault = None

    def _note_store_files(self) -> None:
        """After a bundle was applied: whether the store's files could be written."""
        assert self._fleet is not None
        error = self._fleet.unwritten
        self._store_fault = None if error is None else fault_of(error, self._folders, "maps")

    def _fold_evidence(self) -> None:
        assert self._fleet is not None
        if self._store_fault is not None:
            return
        try:
            self._fleet.fold_evidence()
        except Exception as error:
            if not is_transient(error):
                raise
            self._store_fault = fault_of(error, self._folders, "maps")

    def _under_review(self) -> set[str]:
        """Bundles whose files retention keeps: seen in a change not yet decided."""
        return set() if self._fleet is None else self._fleet.bundles_under_review()

    def _faults(self) -> list[Fault]:
        faults = [item.fault for item in self._waiting]
        faults += [job.again for job in (*self._queue, *self._running.values()) if job.again]
        faults += self._retake.values()
        if self._store_fault is not None:
            faults.append(self._store_fault)
        return faults

    def _waiting_count(self) -> int:
        """Bundles that wait for a fault: finished ones, inbox entries not taken, and, while
        finished ones wait, those taken and not started."""
        return len(self._waiting) + len(self._retake) + (len(self._queue) if self._waiting else 0)

    def _finish_running(self) -> None:
        """Let the bundles in hand finish (bounded by ``stop_timeout``), then stop the pool."""
        if self._running:
            log.info("stopping: finishing %d bundles in hand", len(self._running))
        deadline = time.monotonic() + self._stop_timeout
        while self._running and not self._abort and time.monotonic() < deadline:
            self._wait(min(self._ping_every, max(deadline - time.monotonic(), 0.0)))
            self._collect()
            self._enforce_limits()
            if time.monotonic() - self._last_ping >= self._ping_every:
                notify("WATCHDOG=1")
                self._last_ping = time.monotonic()
        if self._running:
            log.warning(
                "stopping: %d bundles unfinished; they are processed again at the next start",
                len(self._running),
            )
        # Idle workers hold nothing; killing them beats waiting for one still starting up.
        self._kill_workers()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def _kill_workers(self) -> None:
        # No public API before Python 3.14 (kill_workers()); workers ignore SIGTERM.
        processes = getattr(self._pool, "_processes", None) or {}
        for process in list(processes.values()):
            process.kill()

    def _workers_alive(self) -> bool:
        if self._pool is None or self._pool_broken:
            return False
        processes = getattr(self._pool, "_processes", None) or {}
        return all(p.is_alive() for p in list(processes.values()))

    # -- systemd --------------------------------------------------------------------------

    def _status(self) -> str:
        degraded = self._health.summary()
        return (
            f"STATUS={degraded + '; ' if degraded else ''}{len(self._tracker)} uploading, "
            f"{len(self._queue) + len(self._waiting)} queued, {len(self._running)} processing; "
            f"{self._counts.results} results, {self._counts.failed} failed"
        )

    def _heartbeat(self) -> None:
        """WATCHDOG=1 (with STATUS) from the main loop, only while the workers are alive (the
        loop has exited already if the observer died): systemd restarts a daemon that hangs or
        has lost either."""
        now = time.monotonic()
        if now - self._last_ping < self._ping_every:
            return
        self._last_ping = now
        if self._workers_alive():
            notify("WATCHDOG=1", self._status())
        else:
            notify(self._status())
        self._write_status()

    def _write_status(self) -> None:
        """``inbox/.mapserver.status`` for ``mapserver status``: when the counts change, and
        every 30 s (its age tells a hung daemon)."""
        counts = (
            len(self._tracker),
            len(self._queue) + len(self._waiting),
            len(self._running),
            self._counts.results,
            self._counts.failed,
        )
        now = time.monotonic()
        state = (counts, self._health.faults, self._health.waiting)
        if state == self._status_written[0] and now - self._status_written[1] < 30.0:
            return
        document = {
            "format": 1,
            "pid": os.getpid(),
            "started_at": self._started_at,
            "updated_at": utc_now(),
            "uploading": counts[0],
            "queued": counts[1],
            "processing": counts[2],
            "results": counts[3],
            "failed": counts[4],
            "degraded": self._health.document(),
        }
        try:
            write_status(self._config.inbox, document)
        except OSError as error:  # never worth stopping for, but `mapserver status` goes stale
            if not self._status_unwritable:
                log.warning(
                    "cannot write the status file %s: %s (tried again every %g s)",
                    self._config.inbox / STATUS_NAME,
                    error,
                    self._ping_every,
                )
            self._status_unwritable = True
            return
        if self._status_unwritable:
            log.info("the status file is written again")
        self._status_unwritable = False
        self._status_written = (state, now)

    # -- the observer ------------------------------------------------------------------------

    def _stepped(self, step: str) -> None:
        """The store's checkpoint: note moves out of the inbox, then the test hook."""
        if step in ("archived", "failed-moved"):
            self._moved_out_at = time.monotonic()
            self._moved_since_arm += 1
        self._checkpoint(step)

    def _rearm(self, observer: BaseObserver) -> None:
        """Set the inotify watches up afresh. watchdog never drops the watch of a directory
        moved out of its tree: each archived bundle kept one, and a daemon running for months
        would reach the kernel's limit (fs.inotify.max_user_watches) and stop seeing uploads.
        Done between bundles' moves (no event of a move is lost half-paired); the rescan right
        after catches anything that arrived meanwhile."""
        if isinstance(observer, PollingObserver) or self._handler is None:
            self._moved_since_arm = 0  # polling holds no watches
            return
        if time.monotonic() - self._moved_out_at < _INOTIFY_MOVE_DELAY_S + 0.1:
            return  # a move out may still be waiting for its pair: next turn
        watch_afresh(observer, self._handler, self._config.inbox)
        log.info("inbox: watches set up afresh after %d bundles left it", self._moved_since_arm)
        self._moved_since_arm = 0
        self._rescan()

    def _let_the_observer_pair_its_moves(self, observer: BaseObserver) -> None:
        """Wait, before stopping the inotify observer, until it has let go of the last bundle
        moved out of the inbox (at most half a second after it).

        watchdog holds an IN_MOVED_FROM without its IN_MOVED_TO (a rename out of the watched
        tree) for ``_INOTIFY_MOVE_DELAY_S``, waiting for its pair; an emitter stopped meanwhile
        still returns it from its closed queue and logs "InotifyEmitter.queue_events() called
        when the thread is inactive" at ERROR (watchdog 7, ``DelayedQueue.get`` after
        ``close()``): every stop right after a bundle was archived did.
        """
        if isinstance(observer, PollingObserver):
            return
        wait_s = self._moved_out_at + _INOTIFY_MOVE_DELAY_S + 0.2 - time.monotonic()
        if wait_s > 0:
            time.sleep(wait_s)

    def _start_observer(self) -> BaseObserver:
        self._handler = InboxHandler(self._config.inbox, self._hints)
        return start_observer(self._config, self._handler)


def may_write(path: Path) -> bool:
    """Whether this process may write ``path`` (a module-level name, so that a test run as root,
    which may write anything, can say otherwise)."""
    return os.access(path, os.W_OK)


def locked_folder(error: OSError, entry: Path) -> bool:
    """Whether ``error``, from moving inbox entry ``entry``, is the entry's own folder refusing
    the server: a directory moves to another folder only with write permission on itself (its
    ``..`` changes), which a copy of a read-only folder (``cp -a``, ``rsync -a``) lacks, while
    the inbox itself may be written."""
    if error.errno not in (errno.EACCES, errno.EPERM):
        return False
    if entry.is_symlink() or not entry.is_dir():
        return False
    return not may_write(entry) and may_write(entry.parent)


def _guarded(bundle_id: str, handle: Callable[..., object], *args: Any) -> None:
    """A bug met while handling one bundle is logged; it never stops the daemon (the bundle stays
    where it is, and the next start takes it up again)."""
    try:
        handle(*args)
    except Exception:
        log.exception("%s: internal error while handling it; left where it is", bundle_id)


def _identity(path: Path) -> tuple[int, int] | None:
    """(device, inode) of ``path``, None when it is gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def _observer_alive(observer: BaseObserver) -> bool:
    return observer.is_alive() and all(e.is_alive() for e in observer.emitters)
