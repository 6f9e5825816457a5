"""What each worker process is doing, in memory shared with the daemon's main process; the
worker's own memory limit; and the test hook that makes a worker go past the limits.

Each worker of a pool owns one slot of a :class:`Board`: its pid, the bundle it works on (a token
the main process gave the job), since when, and the pipeline stage it is in. Workers only write
their own slot, with plain stores (no lock, no message); the main process reads every slot on
each turn of its loop to stop a worker that is past ``bundle_timeout_seconds`` or
``worker_memory_mb``, and to name the stage the bundle was in when it failed.

A torn read is harmless: the main process acts only on a slot whose token it reads the same
before and after the rest of the slot.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import time
from dataclasses import dataclass
from multiprocessing.context import BaseContext
from typing import Any

log = logging.getLogger(__name__)

_STAGE_BYTES = 16

FAULT_ENV = "MAPSERVER_TEST_FAULT"
"""Test hook: ``<bundle id>@<stage>=<fault>``, comma-separated. A worker entering that stage of
that bundle hangs (``hang``), grows its resident memory past ``worker_memory_mb`` and holds it
(``hog``, the worker's address-space limit lifted: the main process's watch tested), or asks
for twice ``worker_memory_mb`` at once (``alloc``): the time and memory limits, tested on a
real daemon."""


class _Slot(ctypes.Structure):
    _fields_ = [
        ("pid", ctypes.c_int64),
        ("token", ctypes.c_int64),
        ("started", ctypes.c_double),
        ("stage", ctypes.c_char * _STAGE_BYTES),
    ]


@dataclass(frozen=True)
class Activity:
    """One worker busy with a bundle: ``started`` is ``time.monotonic()`` when it began (the
    clock is the system's, the same in every process)."""

    pid: int
    token: int
    started: float
    stage: str


class Board:
    """The slots of one worker pool (``size`` workers). Made in the main process and handed to
    each worker when it starts (``initargs``), where :meth:`join` gives it its slot."""

    def __init__(self, context: BaseContext, size: int) -> None:
        self._slots: Any = context.RawArray(_Slot, size)
        self._next: Any = context.Value(ctypes.c_int64, 0)
        self._mine: int | None = None

    # -- in a worker -------------------------------------------------------------------------

    def join(self) -> None:
        """Take the next free slot for this process (once, when the worker starts)."""
        with self._next.get_lock():
            index = int(self._next.value)
            self._next.value = index + 1
        if index < len(self._slots):  # a pool never starts more workers than its size
            self._mine = index
            self._slots[index].pid = os.getpid()

    def begin(self, token: int) -> None:
        """This worker starts on the job ``token`` (> 0)."""
        slot = self._slot()
        if slot is not None:
            slot.token = 0
            slot.started = time.monotonic()
            slot.stage = b"process"
            slot.token = token

    def stage(self, name: str) -> None:
        """The job in hand has entered stage ``name``."""
        slot = self._slot()
        if slot is not None:
            slot.stage = name.encode("ascii", "replace")[:_STAGE_BYTES]

    def end(self) -> None:
        slot = self._slot()
        if slot is not None:
            slot.token = 0

    def _slot(self) -> Any:
        return None if self._mine is None else self._slots[self._mine]

    # -- in the main process -----------------------------------------------------------------

    def activities(self) -> list[Activity]:
        """The workers busy with a job now."""
        out = []
        for slot in self._slots:
            token = int(slot.token)
            if token == 0:
                continue
            activity = Activity(
                int(slot.pid), token, float(slot.started), slot.stage.decode("ascii", "replace")
            )
            if int(slot.token) == token:  # not rewritten while it was read
                out.append(activity)
        return out


_PAGE = os.sysconf("SC_PAGE_SIZE")


def resident_bytes(pid: int) -> int | None:
    """The resident memory of process ``pid`` (``/proc/<pid>/statm``), None when unknown."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as statm:
            return int(statm.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        return None


def mapped_bytes() -> int | None:
    """This process's address space (``VmSize``), None when unknown."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            return int(statm.read().split()[0]) * _PAGE
    except (OSError, IndexError, ValueError):
        return None


# -- in a worker: its limit, and the test faults ----------------------------------------------


def limit_address_space(limit_mb: int) -> None:
    """RLIMIT_AS at the worker's size now plus ``limit_mb``: an allocation that would take it
    further fails at once with MemoryError (the stage's out-of-memory failure), before the
    main process, which watches resident memory about once a second, could see it, and before
    the kernel's OOM killer picks a process."""
    import resource

    mapped = mapped_bytes()
    if mapped is None:
        return
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = mapped + limit_mb * 2**20
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    try:
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    except OSError as error:  # a seccomp filter without prlimit64, say: the watch remains
        log.warning("worker %d: cannot limit its address space: %s", os.getpid(), error)


def parse_faults(text: str) -> dict[tuple[str, str], str]:
    """``FAULT_ENV``'s value as {(bundle id, stage): fault}."""
    faults = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        where, _, fault = item.partition("=")
        bundle_id, _, stage = where.partition("@")
        faults[(bundle_id, stage)] = fault
    return faults


def inject_fault(fault: str, *, memory_limit_mb: int) -> None:
    """Do ``fault`` (``hang``, ``hog``, ``alloc``; see ``FAULT_ENV``) in this worker."""
    import numpy as np

    limit = memory_limit_mb * 2**20
    if fault == "alloc":
        np.ones(2 * limit, np.uint8)
    held = []
    if fault == "hog":
        # The main process's watch of resident memory is what a hog tests: the address-space
        # limit lifted, as where it cannot be set. Under it, the hog's room depended on how much
        # the worker had mapped before the stage (the main process's heap it was forked with
        # among it): some runs failed with MemoryError before they were seen.
        import resource

        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        with contextlib.suppress(OSError):  # not set either, where it cannot be
            resource.setrlimit(resource.RLIMIT_AS, (hard, hard))
        while (resident_bytes(os.getpid()) or 0) < limit + 32 * 2**20:
            held.append(np.ones(8 * 2**20, np.uint8))  # written: resident, not just mapped
    while True:  # hang (and hold what it took) until the main process stops this worker
        time.sleep(60)
