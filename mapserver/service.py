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
import functools
import itertools
import logging
import multiprocessing
import os
import select
import signal
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from queue import Empty, SimpleQueue
from types import FrameType
from typing import TYPE_CHECKING, Any

from watchdog.observers import Observer
from watchdog.observers.api import BaseObserver
from watchdog.observers.polling import PollingObserver

from mapserver.board import (
    FAULT_ENV,
    Board,
    inject_fault,
    limit_address_space,
    parse_faults,
    resident_bytes,
)
from mapserver.config import Config, check_paths
from mapserver.errors import MapserverError, OutOfMemory
from mapserver.inbox import (
    EVENT_TYPES,
    Decision,
    InboxHandler,
    Rejected,
    StabilityTracker,
    check_entry,
    scan,
)
from mapserver.lock import daemon_lock, store_lock
from mapserver.notify import notify, watchdog_period
from mapserver.outbox import RESULT, Store, utc_now
from mapserver.status import write_status
from mapserver.trust import trust_notice

if TYPE_CHECKING:
    from mapserver.fleet.store import FleetStore
    from mapserver.pipeline import Outcome

log = logging.getLogger(__name__)

CRASH_ENV = "MAPSERVER_TEST_CRASH_AT"
"""Test hook: the name of a checkpoint (see :class:`~mapserver.outbox.Store`, plus
``submitted``) at which the daemon kills itself with SIGKILL, to test recovery from each one."""

ProcessFn = Callable[..., "Outcome"]


def env_checkpoint() -> Callable[[str], None]:
    """The checkpoint function that honours ``$MAPSERVER_TEST_CRASH_AT``."""
    point = os.environ.get(CRASH_ENV)

    def checkpoint(name: str) -> None:
        if name == point:
            os.kill(os.getpid(), signal.SIGKILL)

    return checkpoint


# -- the worker side ----------------------------------------------------------------------------


@dataclass(frozen=True)
class WorkDone:
    """What a worker returns: an outcome, or the stage and reason it failed."""

    outcome: Outcome | None
    stage: str = ""
    reason: str = ""
    seconds: float = 0.0


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


def _init_worker(
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


# How long watchdog's inotify emitter holds a move out of the inbox, waiting for its pair.
try:
    from watchdog.observers.inotify_move_event_grouper import InotifyMoveEventGrouper

    _INOTIFY_MOVE_DELAY_S = float(InotifyMoveEventGrouper.delay)
except ImportError:  # watchdog < 7 (InotifyBuffer, the same half second), or no inotify
    _INOTIFY_MOVE_DELAY_S = 0.5

# How long one turn of the main loop may spend checking uploads.
_POLL_TURN_S = 0.05


def process_taken_bundle(bundle_dir: Path, config: Config, *, bundle_id: str) -> Outcome:
    """The workers' default process function: :func:`process_bundle` on a bundle the daemon
    took, whose checksums it verified when it took it (the bundle has been in the daemon's own
    staging folder since), so they are not hashed a second time."""
    from mapserver.pipeline import process_bundle  # workers have it (fork server preload)

    return process_bundle(bundle_dir, config, bundle_id=bundle_id, checksums_verified=True)


def _broke(future: Future[WorkDone]) -> bool:
    """Whether a finished job's worker pool broke under it (a worker process died)."""
    return not future.cancelled() and isinstance(future.exception(), BrokenProcessPool)


def _noop() -> None:
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
    except MapserverError as error:
        reason = error.reason
        if isinstance(error, OutOfMemory) and _WORKER.memory_limit_mb:
            reason += f" (worker_memory_mb: {_WORKER.memory_limit_mb})"
        return WorkDone(None, error.stage, reason, time.perf_counter() - start)
    except Exception as error:
        log.exception("%s: internal error", bundle_id)
        reason = f"internal error: {type(error).__name__}: {error}"
        return WorkDone(None, "process", reason, time.perf_counter() - start)
    finally:
        _WORKER.bundle_id = ""
        if _WORKER.board is not None:
            _WORKER.board.end()
    return WorkDone(outcome, seconds=time.perf_counter() - start)


# -- the parent side ----------------------------------------------------------------------------


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
        self._started_at = utc_now()
        self._status_written: tuple[tuple[int, ...], float] = ((), float("-inf"))
        """When a bundle last left the inbox's tree (to archive/ or failed/), monotonic."""
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

            self._fleet = FleetStore(config.maps, config.update, checkpoint=self._checkpoint)
            self._fleet.sync()
        now = time.monotonic()
        recovered = self._store.recover()
        self._queue.extend(_Job(bundle_id, now) for bundle_id in recovered)
        self._pool = self._new_pool()
        try:
            self._warm_up()
            observer = self._start_observer()
            try:
                self._rescan()
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
                self._write_status()
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
            len(self._queue),
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
            # Bounded, so that a large backlog (checksums to hash) keeps neither the watchdog nor
            # the workers waiting: what is taken goes out below, the rest is looked at on the
            # next turn, a moment later.
            for decision in self._tracker.poll(budget_s=min(_POLL_TURN_S, self._ping_every)):
                _guarded(decision.name, self._take, decision)
            self._dispatch()
            if self._fleet is not None and not self._running and not self._queue:
                # Idle: fold waiting evidence into its counters, a few tiles a turn.
                _guarded("fleet", self._fleet.fold_evidence)
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
            log.warning("%s: left the inbox before it was taken", name)
            return
        except OSError as error:
            log.error("%s: cannot take it from the inbox: %s", name, error)
            return
        if bundle_id != name:
            log.info("%s: id already in use, taken as %s", name, bundle_id)
        log.info("%s: upload %.1f ms", bundle_id, decision.waited_s * 1000.0)
        self._queue.append(_Job(bundle_id, time.monotonic()))

    def _reject(self, name: str, bundle_id: str, stage: str, reason: str) -> None:
        path = self._store.reject(name, bundle_id, stage, reason)
        self._counts.failed += 1
        log.warning("%s: done: failed at stage %s: %s -> %s", bundle_id, stage, reason, path)

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
            initializer=_init_worker,
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
            self._pool.submit(_noop)

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
        if self._stopping:
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
            held_s = now - activity.started
            stage = activity.stage
            if held_s > self._timeout_s:
                reason = (
                    f"over the time limit: still in stage {stage} after {held_s:.1f} s "
                    f"(bundle_timeout_seconds: {self._timeout_s:g}); the maps may be too large "
                    "for this server, or the bundle makes the pipeline hang"
                )
            else:
                resident = resident_bytes(activity.pid)
                if resident is None or resident <= self._memory_limit_mb * 2**20:
                    continue
                reason = (
                    f"over the memory limit: {resident / 2**20:.0f} MiB in stage {stage} after "
                    f"{held_s:.1f} s (worker_memory_mb: {self._memory_limit_mb}); the maps may "
                    "be too large for this server"
                )
            job.over_limit = (stage, reason)
            self._stopped_in.add(job.generation)
            log.warning("%s: %s; stopping its worker (pid %d)", job.bundle_id, reason, activity.pid)
            with contextlib.suppress(ProcessLookupError):
                os.kill(activity.pid, signal.SIGKILL)

    def _finish(self, job: _Job, done: WorkDone) -> None:
        bundle_id = job.bundle_id
        outcome = done.outcome
        if outcome is None:
            self._fail(job, done.stage, done.reason)
            return
        if outcome.bundle_id != bundle_id:
            reason = f"internal error: the result is for bundle {outcome.bundle_id!r}"
            self._fail(job, "process", reason)
            return
        if outcome.observation is not None and self._fleet is not None:
            try:
                update = self._fleet.apply(outcome.observation)
            except Exception as error:  # a damaged database, a full disk under it
                log.exception("%s: cannot apply it to the fleet map", bundle_id)
                self._fail(job, "update", f"cannot apply it to the fleet map: {error}")
                return
            update.annotate(outcome.result)
            log.info("%s: update %.1f ms: %s", bundle_id, update.seconds * 1000.0, update.summary())
        start = time.perf_counter()
        try:
            result_dir = self._store.publish(outcome)
        except Exception as error:  # a full disk, or a result YAML cannot hold
            self._fail(job, "write", f"cannot write the result: {error}")
            return
        published = time.perf_counter()
        log.info("%s: publish %.1f ms", bundle_id, (published - start) * 1000.0)
        try:
            self._store.archive(bundle_id)
        except OSError as error:
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

    def _fail(self, job: _Job, stage: str, reason: str) -> None:
        try:
            path = self._store.fail(job.bundle_id, stage, reason)
        except OSError as error:
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
        log.warning("%s: done: failed at stage %s: %s -> %s", job.bundle_id, stage, reason, path)

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
        return (
            f"STATUS={len(self._tracker)} uploading, {len(self._queue)} queued, "
            f"{len(self._running)} processing; {self._counts.results} results, "
            f"{self._counts.failed} failed"
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
            len(self._queue),
            len(self._running),
            self._counts.results,
            self._counts.failed,
        )
        now = time.monotonic()
        if counts == self._status_written[0] and now - self._status_written[1] < 30.0:
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
        }
        try:
            write_status(self._config.inbox, document)
        except OSError as error:  # never worth stopping for
            log.debug("cannot write the status file: %s", error)
            return
        self._status_written = (counts, now)

    # -- the observer ------------------------------------------------------------------------

    def _stepped(self, step: str) -> None:
        """The store's checkpoint: note moves out of the inbox, then the test hook."""
        if step in ("archived", "failed-moved"):
            self._moved_out_at = time.monotonic()
        self._checkpoint(step)

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
        config = self._config
        handler = InboxHandler(config.inbox, self._hints)
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
