"""A fixed-rate cycle on the monotonic clock (host-side): real-time settings, deadlines, overruns, timing statistics.

Cycle ``k``'s deadline is ``t0 + k T``.  The runner sleeps until ``SPIN`` before it (the kernel's
timer slack on a non-RT kernel is tens of microseconds), runs the optional ``prepare(k)`` (work
that readies the cycle, such as warming the caches for its step), and spins the rest.  A deadline is
*missed* when a cycle's work ends after the next deadline.  Overrun policy: when a cycle would
start after the next deadline has passed, the runner skips to the
next deadline in the future (it never runs cycles back to back to catch up), counts the skipped
cycles, and hands the count to the cycle function, which decides (the bridge faults after
``max_consecutive_misses``).  Garbage collection is frozen and disabled for the run.
"""

from __future__ import annotations

import ctypes
import gc
import os
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

SPIN = 200e-6  # s spent spinning before each deadline


@dataclass
class RealtimeReport:
    """What the OS granted: each setting with 'granted' or the reason it was refused."""

    settings: dict = field(default_factory=dict)
    previous: tuple = ()  # (policy, priority, affinity) before the setup
    latency_fd: int | None = None  # /dev/cpu_dma_latency, held open while the request stands
    helpers: dict = field(default_factory=dict)  # the other threads given SCHED_FIFO: tid -> (policy, priority) before

    def lines(self) -> list[str]:
        return [f"{k}: {v}" for k, v in self.settings.items()]

    def restore(self) -> None:
        """Back to the scheduling and CPUs the process had, and the CPUs' idle states released (the memory stays
        locked)."""
        if self.latency_fd is not None:
            os.close(self.latency_fd)
            self.latency_fd = None
        for tid, (policy, priority) in self.helpers.items():
            try:
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
            except OSError:  # a thread that ended meanwhile
                pass
        self.helpers = {}
        if not self.previous:
            return
        policy, priority, cpus = self.previous
        try:
            os.sched_setscheduler(0, policy, os.sched_param(priority))
            _set_affinity(cpus)
        except OSError:
            pass


def realtime_setup(priority: int = 80, cpu: int | None = None) -> RealtimeReport:
    """Every thread of the process on ``cpu`` (default: the last CPU), ``mlockall``, SCHED_FIFO at ``priority`` for the
    calling thread and at ``priority - 1`` for the process's other threads (:func:`_helpers_fifo`), and a CPU latency
    request of 0 us (idle CPUs poll instead of halting), where allowed; :meth:`RealtimeReport.restore` undoes all but
    the memory lock.

    In this order: ``mlockall`` walks every page of the process (15-55 ms measured here in a process that has
    loaded JAX), so it runs on ``cpu`` and at the priority the process had: done at real-time priority before the
    move, it could hold whichever CPU the process was on, over the other real-time process there (the simulated
    robot's, on loopback).
    """
    rep = RealtimeReport()
    try:
        rep.previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0))
    except (OSError, AttributeError):
        pass
    try:
        cpus = sorted(os.sched_getaffinity(0))
        target = cpus[-1] if cpu is None else cpu
        threads = _set_affinity({target})
        rep.settings["affinity"] = f"granted (CPU {target} of {len(cpus)}, {threads} threads)"
    except (OSError, AttributeError) as e:
        rep.settings["affinity"] = f"refused ({e})"
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
            raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
        rep.settings["mlockall"] = "granted"
    except (OSError, AttributeError) as e:
        rep.settings["mlockall"] = f"refused ({getattr(e, 'strerror', None) or e}); pages may fault in the loop"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        below = max(priority - 1, 1)
        rep.helpers = _helpers_fifo(below)
        rep.settings["SCHED_FIFO"] = (
            f"granted (priority {priority}; the process's {len(rep.helpers)} other threads at {below})"
        )
    except (OSError, AttributeError) as e:
        rep.settings["SCHED_FIFO"] = f"refused ({getattr(e, 'strerror', None) or e}); running SCHED_OTHER"
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
        os.write(fd, struct.pack("<i", 0))
        rep.latency_fd = fd
        rep.settings["cpu_dma_latency"] = "granted (0 us: idle CPUs poll instead of halting)"
    except OSError as e:
        rep.settings["cpu_dma_latency"] = f"refused ({e.strerror or e}); an idle CPU may halt and wake late"
    return rep


def _thread_ids() -> list[int]:
    """The ids of the process's threads (Linux: the tasks of ``/proc/self/task``; elsewhere none)."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def _helpers_fifo(priority: int) -> dict:
    """The process's threads other than the calling one at SCHED_FIFO ``priority``; ``{tid: (policy, priority)}``
    before, of those changed.  The calling thread may hand them work and wait: XLA's CPU runtime can run parts of a
    compiled step on its pool (the simulated robot's drive step woke two 'tf_XLAEigen' threads and waited for them,
    2.4 times per call, until :class:`~pusupu_jax.hw_bridge.compiled.FlatStep` closed over its constants), and
    python-can's
    notifier thread runs the CANopen robot's whole period.  Left at SCHED_OTHER, that work waits behind any ordinary
    task on the CPU while the real-time thread waits for it; one step below the calling thread, it runs before
    ordinary tasks and never preempts the thread that waits for it."""
    me = threading.get_native_id()
    before = {}
    for tid in _thread_ids():
        if tid == me:
            continue
        try:
            was = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            before[tid] = was
        except OSError:  # a thread that ended meanwhile
            pass
    return before


def _set_affinity(cpus) -> int:
    """Every thread of the process on ``cpus`` (Linux: each task of ``/proc/self/task``; elsewhere the calling
    thread); returns how many.  Every thread, not only the calling one: XLA's CPU runtime hands parts of a compiled
    step to its thread pool, and a pool thread left on the other CPU waited there behind the other process's real-time
    thread while this one waited for it (seen in a scheduler trace of the simulated robot: its 'tf_XLAEigen' threads
    woken on the bridge's CPU in each step)."""
    tids = _thread_ids() or [0]
    for tid in tids:
        try:
            os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:  # a thread that ended meanwhile
            pass
    return len(tids)


def steal_seconds() -> np.ndarray | None:
    """Per CPU (index: its number), the time [s] since boot that the hypervisor ran something else while the CPU had
    work (Linux ``/proc/stat``, 'steal', in clock ticks: 10 ms); None where the kernel does not count it.  A stall
    of a real-time thread that no setting inside a virtual machine prevents."""
    try:
        with open("/proc/stat") as f:
            rows = {int(r[0][3:]): int(r[8]) for r in (line.split() for line in f) if r[0][3:].isdigit()}
        ticks = np.zeros(max(rows) + 1)
        ticks[list(rows)] = list(rows.values())
        return ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


@dataclass
class CycleStats:
    """Per-cycle timing [s] in preallocated arrays: wake-up lateness and the cycle function's own time."""

    period: float
    wake_late: np.ndarray
    busy: np.ndarray
    skipped: int = 0
    cycles: int = 0

    @property
    def missed(self) -> int:
        """Deadlines missed: cycles whose work ended after the next deadline, plus the cycles skipped."""
        return int(np.count_nonzero(self.wake_late + self.busy > self.period)) + self.skipped

    @classmethod
    def allocate(cls, period: float, n: int) -> "CycleStats":
        return cls(period, np.zeros(n), np.zeros(n))


def percentiles(x) -> dict | None:
    """p50, p99, p99.9 and max of ``x`` (in its own unit), or None when it is empty."""
    x = np.asarray(x)
    if not len(x):
        return None
    return {f"p{p}": float(np.percentile(x, p)) for p in (50, 99, 99.9)} | {"max": float(x.max())}


OVERRUN = ("skip", "rephase")


class CycleRunner:
    """Calls ``fn(k, skipped) -> bool`` once per cycle at ``rate`` [Hz] until it returns False or ``n`` cycles ran.

    ``overrun``: 'skip' (real time: a late cycle skips to the next deadline ahead, counted) or 'rephase' (every
    cycle runs, and a late one moves the deadlines after it: for lock-step runs whose timing is not the point,
    such as tests on a loaded machine).
    """

    def __init__(self, rate: float, overrun: str = "skip"):
        if not (rate > 0):
            raise ValueError(f"rate: expected a positive number of Hz, got {rate!r}")
        if overrun not in OVERRUN:
            raise ValueError(f"overrun: expected one of {OVERRUN}, got {overrun!r}")
        self.period = 1.0 / rate
        self.overrun = overrun

    def run(self, fn, n: int, prepare=None) -> CycleStats:
        """``prepare(k)``, if given, runs after the sleep before cycle ``k``'s deadline, inside the spin window (work
        that readies the cycle without being part of it: warming the caches)."""
        stats = CycleStats.allocate(self.period, n)
        T = self.period
        gc.collect()
        gc.freeze()
        was_enabled = gc.isenabled()
        gc.disable()
        try:
            t0 = time.monotonic() + 2 * T
            k = 0
            skipped = 0
            while k < n:
                deadline = t0 + k * T
                now = time.monotonic()
                if now < deadline - SPIN:
                    time.sleep(deadline - SPIN - now)
                    if prepare is not None:
                        prepare(k)
                while (now := time.monotonic()) < deadline:
                    pass
                late = now - deadline
                if late > T and self.overrun == "rephase":
                    t0 += late
                elif late > T:  # the next deadline has passed too: skip to the next one ahead
                    behind = int(late // T)
                    stats.skipped += behind
                    skipped += behind
                    k += behind
                    if k >= n:
                        break
                    continue
                stats.wake_late[stats.cycles] = late
                go_on = fn(k, skipped)
                stats.busy[stats.cycles] = time.monotonic() - now
                stats.cycles += 1
                skipped = 0
                k += 1
                if not go_on:
                    break
        finally:
            if was_enabled:
                gc.enable()
            gc.unfreeze()
        stats.wake_late = stats.wake_late[: stats.cycles]
        stats.busy = stats.busy[: stats.cycles]
        return stats
