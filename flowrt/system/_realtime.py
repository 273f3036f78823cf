"""Real-time scheduling of the loop process: SCHED_FIFO and locked memory, where permitted.

Under CPU load a normal-priority loop process is preempted by anything; with SCHED_FIFO the
kernel runs it as soon as its timerfd fires. Refusal is expected on unprivileged machines and
is reported, never fatal.
"""

from __future__ import annotations

import ctypes
import os
import sys

_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4


def enable_realtime(priority: int = 90) -> tuple[bool, str]:
    """Try SCHED_FIFO at ``priority`` for this process; returns (granted, description): a
    refusal's description starts "normal priority", a grant's "SCHED_FIFO".

    90 is above every worker (they are capped at 89): the frame clock and the dispatch of
    activations must never wait for a tracker.
    """
    if not hasattr(os, "sched_setscheduler"):
        return False, f"normal priority: SCHED_FIFO not available on {sys.platform}"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return (
            False,
            "normal priority: SCHED_FIFO not permitted (needs root or CAP_SYS_NICE / rtprio limit)",
        )
    except OSError as e:
        return False, f"normal priority: SCHED_FIFO refused ({e.strerror})"
    locked = ""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        # MCL_ONFAULT (Linux 4.4): pages are locked as they are first touched. Without it,
        # every later mapping is populated whole when it is made, on the thread that makes it:
        # the RTDB (sparse, several MB) took ~6 ms of the loop at the first health alert of a
        # run, and each new frame-pool slot ~1 ms (whose pages a thread populates anyway).
        flags = _MCL_CURRENT | _MCL_FUTURE
        if libc.mlockall(flags | _MCL_ONFAULT) == 0 or libc.mlockall(flags) == 0:  # before 4.4
            locked = ", memory locked"
    except (OSError, AttributeError):
        pass
    return True, f"SCHED_FIFO {priority}{locked}"
