"""Operating-system scheduling of worker processes: flowrt priority -> SCHED_FIFO or nice.

flowrt priorities run 1..99, higher = more important (CAMBADA uses 15..45). In a worker the
priority becomes a real-time SCHED_FIFO priority when the process may have one, so that the
kernel preempts a low-priority tracker the instant a high-priority one becomes runnable, and a
nice level otherwise. What was actually granted is reported as a string, because an operator
must see when "priority 45" quietly meant "nice 0".

Nice levels only weight the fair scheduler's shares, so they are assigned by *rank*
(:class:`FairShare`): the loop process takes the lowest nice it is permitted, the graph's
highest priority a little above it, and each lower distinct priority three levels (half the
CPU weight) further, so that a priority-40 tracker clearly outweighs a priority-35 one however
close the numbers. How low "lowest permitted" is depends on the user: -20 with CAP_SYS_NICE
(root), ``20 - RLIMIT_NICE`` with a nice limit (``@robot - nice -20`` in limits.conf), else the
current level — then every rank sits at or above the nice of the machine's other programs.

Real-time priorities are capped at :data:`MAX_WORKER_RT_PRIORITY` so that the event-loop
process (which may itself run SCHED_FIFO to keep its timers precise) stays above every worker:
a busy worker must never starve the scheduler that detects its deadline miss. The kernel's RT
throttling (sched_rt_runtime_us, 95 % by default) still leaves other tasks a slice of a CPU
that a runaway SCHED_FIFO worker occupies.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import platform
import resource
import sys
from collections.abc import Iterable
from dataclasses import dataclass

__all__ = [
    "MAX_WORKER_RT_PRIORITY",
    "FairShare",
    "WorkerScheduling",
    "apply_os_priority",
    "apply_scheduling",
    "lowest_nice",
    "nice_for",
    "rt_priority_for",
]

MAX_WORKER_RT_PRIORITY = 89


def rt_priority_for(priority: int) -> int:
    """SCHED_FIFO priority of a worker: the flowrt number itself, capped below the loop's."""
    return max(1, min(int(priority), MAX_WORKER_RT_PRIORITY))


def nice_for(priority: int) -> int:
    """Nice level of a worker: priority 1 -> 19, 50 -> 0, 99 -> -20 (linear)."""
    p = max(1, min(int(priority), 99))
    return max(-20, min(19, round(19 - (p - 1) * 39 / 98)))


_CAP_SYS_NICE = 23


def lowest_nice() -> int:
    """The lowest nice level this process may set (-20 .. its current level)."""
    current = os.getpriority(os.PRIO_PROCESS, 0)
    with contextlib.suppress(OSError, ValueError), open("/proc/self/status") as f:
        for line in f:
            if line.startswith("CapEff:") and int(line.split()[1], 16) >> _CAP_SYS_NICE & 1:
                return -20
    try:
        soft = resource.getrlimit(resource.RLIMIT_NICE)[0]
    except (AttributeError, OSError, ValueError):
        return current
    if soft == resource.RLIM_INFINITY:
        return -20
    return max(-20, min(current, 20 - soft))


class FairShare:
    """Nice levels by rank of priority, for when the workers do not get SCHED_FIFO.

    ``floor`` is the loop process's own nice (the lowest permitted). The highest of
    ``priorities`` gets ``floor + 3`` (but never above 0 when ``floor`` allows less): the loop
    must outweigh the trackers it dispatches. Each lower distinct priority adds ``step``. A
    priority outside the list (set at run time) ranks where it would fall among them.
    """

    def __init__(self, priorities: Iterable[int], floor: int, step: int = 3) -> None:
        self.levels = sorted(set(priorities), reverse=True)
        self.step = step
        self.top = max(floor, min(floor + 3, 0))

    def nice(self, priority: int) -> int:
        rank = sum(1 for p in self.levels if p > priority)
        return min(19, self.top + rank * self.step)


@dataclass(frozen=True)
class WorkerScheduling:
    """What a worker applies to itself before running a node.

    ``nice`` is used when SCHED_FIFO is not (None: :func:`nice_for`); ``cpus`` pins the
    process (None: the CPUs the worker started with); ``spin`` is how long, in seconds, the
    worker busy-polls for the node's next call around the instant it expects it (0: it sleeps).
    """

    priority: int
    realtime: bool = False
    nice: int | None = None
    cpus: tuple[int, ...] | None = None
    spin: float = 0.0


_START_CPUS: set[int] | None = None


def apply_scheduling(s: WorkerScheduling) -> str:
    """Apply priority and CPU affinity to the calling process; return what was granted."""
    global _START_CPUS
    granted = apply_os_priority(s.priority, realtime=s.realtime, nice=s.nice)
    if not hasattr(os, "sched_setaffinity"):
        return granted if s.cpus is None else f"{granted}, cpus not supported"
    if _START_CPUS is None:
        _START_CPUS = os.sched_getaffinity(0)
    want = set(s.cpus) if s.cpus is not None else _START_CPUS
    try:
        os.sched_setaffinity(0, want)
    except OSError:
        return f"{granted}, cpus {_cpus(want)} not available"
    if s.cpus is None:
        return granted
    got = os.sched_getaffinity(0)  # the kernel keeps the CPUs that exist
    return f"{granted}, cpus {_cpus(got)}" + ("" if got == want else f" (asked {_cpus(want)})")


def _cpus(cpus: Iterable[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus))


def apply_os_priority(priority: int, *, realtime: bool = True, nice: int | None = None) -> str:
    """Give the calling process the OS priority of ``priority``; return what was granted.

    Tries SCHED_FIFO (when ``realtime``), then the nice level (``nice``, or
    :func:`nice_for`); if lowering nice is refused, keeps the current nice. Never raises: a
    refused request is reported, not fatal.
    """
    refused = ""
    if realtime and hasattr(os, "sched_setscheduler"):
        rt = rt_priority_for(priority)
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt))
            return f"SCHED_FIFO {rt}"
        except OSError:
            refused = " (SCHED_FIFO not permitted)"
    elif hasattr(os, "sched_setscheduler"):
        # Leave any inherited real-time policy: a worker must not outrank what it was asked for.
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass
    want = nice_for(priority) if nice is None else max(-20, min(19, nice))
    try:
        current = os.getpriority(os.PRIO_PROCESS, 0)
    except OSError:
        return f"SCHED_OTHER (unknown nice){refused}"
    if want != current:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, want)
            current = want
        except OSError:
            return f"nice {current} (nice {want} not permitted){refused}"
    return f"nice {current}{refused}"


class _SchedAttr(ctypes.Structure):
    _fields_ = [
        ("size", ctypes.c_uint32),
        ("sched_policy", ctypes.c_uint32),
        ("sched_flags", ctypes.c_uint64),
        ("sched_nice", ctypes.c_int32),
        ("sched_priority", ctypes.c_uint32),
        ("sched_runtime", ctypes.c_uint64),
        ("sched_deadline", ctypes.c_uint64),
        ("sched_period", ctypes.c_uint64),
        ("sched_util_min", ctypes.c_uint32),
        ("sched_util_max", ctypes.c_uint32),
    ]


_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}.get(platform.machine())


def request_short_slice(slice_us: int = 100) -> str:
    """Ask the fair scheduler (EEVDF, Linux >= 6.12) for a short time slice for this process.

    A task with a short slice gets an earlier virtual deadline, so when it wakes (a timerfd
    tick, a worker's call) it preempts a CPU-bound task of the same nice level instead of
    waiting for that task's slice to end. No privilege is needed and the CPU share is
    unchanged; it is a latency hint, not a priority. Returns what was granted ("" if not).
    ``slice_us=0`` gives the kernel's default back.
    """
    if _SYS_SCHED_SETATTR is None or not sys.platform.startswith("linux"):
        return ""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        attr = _SchedAttr(
            size=ctypes.sizeof(_SchedAttr),
            sched_policy=os.SCHED_OTHER,
            sched_nice=os.getpriority(os.PRIO_PROCESS, 0),
            sched_runtime=slice_us * 1000,
        )
        if libc.syscall(_SYS_SCHED_SETATTR, 0, ctypes.byref(attr), 0) != 0:
            return ""
    except (OSError, AttributeError):
        return ""
    return f"slice {slice_us} us" if slice_us else "default slice"
