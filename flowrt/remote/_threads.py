"""The Zenoh session's threads at the loop's priority.

On Linux a nice level belongs to a thread, not to a process. The runtime lowers the loop
thread's nice (:mod:`flowrt.system._loop_share`) after the Zenoh session is open (a port in
use must fail first), so Zenoh's own threads (its runtimes' ``net``, ``acc``, ``tx``, ``rx``
and ``app`` workers, which carry every export and import) stayed at nice 0 while every thread
the loop starts later inherits the loop's level. Under load each of them then waited for a
CPU behind the machine's other programs at every hop of a remote edge, where the loop did
not (measured: the flowrt exporter's ``tx-0`` and importer's ``rx-0`` at nice 0 beside a loop
at -20). :class:`ThreadShare` gives the threads made since the first bridge was created the
loop thread's nice, as if the loop had started them, when the exports and the imports are
attached, and their level back at close. An embedding program's threads from before the
first session are never touched; Zenoh's runtime threads outlive a session, so a later
runtime lowers them again. Zenoh starts some workers lazily (a link's ``tx``/``rx`` when a
peer connects), from its own threads, which pass the level on (checked with ``ps -L``).
"""

from __future__ import annotations

import contextlib
import os
import threading

__all__ = ["ThreadShare"]

_BEFORE: set[int] | None = None


def _tids() -> set[int]:
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except OSError:  # not Linux: nice levels are the process's there
        return set()


class ThreadShare:
    """Invariant: ``_changed`` holds the nice level before ours of every thread we lowered."""

    def __init__(self) -> None:
        global _BEFORE
        if _BEFORE is None:  # Zenoh's runtimes are the process's: made by the first session
            _BEFORE = _tids()
        self._before = _BEFORE  # the threads before the first session: not ours
        self._changed: dict[int, int] = {}

    def share(self) -> None:
        """On the loop: the threads made since then take the calling thread's nice, when it
        is lower than theirs (never raised; a refusal is left as it is)."""
        want = os.getpriority(os.PRIO_PROCESS, 0)  # Linux: the calling thread's
        me = threading.get_native_id()
        for tid in _tids() - self._before - {me}:
            with contextlib.suppress(OSError):  # the thread ended, or not permitted
                now = os.getpriority(os.PRIO_PROCESS, tid)
                if now > want:
                    os.setpriority(os.PRIO_PROCESS, tid, want)
                    self._changed.setdefault(tid, now)

    def restore(self) -> None:
        """The lowered threads still running get their level back."""
        for tid, nice in self._changed.items():
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        self._changed.clear()
