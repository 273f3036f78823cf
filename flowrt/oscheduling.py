"""Operating-system scheduling of worker processes: flowrt priority -> SCHED_FIFO or nice.

flowrt priorities run 1..99, higher = more important (CAMBADA uses 15..45). In a worker the
priority becomes a real-time SCHED_FIFO priority when the process may have one, so that the
kernel preempts a low-priority tracker the instant a high-priority one becomes runnable, and a
nice level otherwise (only a weighting of CPU shares, but better than nothing). What was
actually granted is reported as a string, because an operator must see when "priority 45"
quietly meant "nice 0".

Real-time priorities are capped at :data:`MAX_WORKER_RT_PRIORITY` so that the event-loop
process (which may itself run SCHED_FIFO to keep its timers precise) stays above every worker:
a busy worker must never starve the scheduler that detects its deadline miss. The kernel's RT
throttling (sched_rt_runtime_us, 95 % by default) still leaves other tasks a slice of a CPU
that a runaway SCHED_FIFO worker occupies.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

__all__ = ["MAX_WORKER_RT_PRIORITY", "apply_os_priority", "nice_for", "rt_priority_for"]

MAX_WORKER_RT_PRIORITY = 89


def rt_priority_for(priority: int) -> int:
    """SCHED_FIFO priority of a worker: the flowrt number itself, capped below the loop's."""
    return max(1, min(int(priority), MAX_WORKER_RT_PRIORITY))


def nice_for(priority: int) -> int:
    """Nice level of a worker: priority 1 -> 19, 50 -> 0, 99 -> -20 (linear)."""
    p = max(1, min(int(priority), 99))
    return max(-20, min(19, round(19 - (p - 1) * 39 / 98)))


def apply_os_priority(priority: int, *, realtime: bool = True) -> str:
    """Give the calling process the OS priority of ``priority``; return what was granted.

    Tries SCHED_FIFO (when ``realtime``), then the nice level; if lowering nice is refused,
    keeps the current nice. Never raises: a refused request is reported, not fatal.
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
    want = nice_for(priority)
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
    return f"slice {slice_us} us"
