"""The loop's CPUs: off the CPUs the graph gave its pinned workers, while others remain.

A node pinned to CPUs (``cpus`` in the graph) is given them for its worker to run on. Left
free, the runtime's loop thread, and the threads it starts once the graph runs (a file's
reader, precise release threads, a recorder's writer process), are woken onto those CPUs too:
the kernel places a woken thread near its waker, so at every reply of the worker the loop
landed beside it and preempted it in the middle of its next call. Measured with
graphs/video.yaml offline, the tracker in a worker pinned to CPU 1 on the 2-CPU machine: the
worker preempted about once per frame (1500 involuntary context switches a second), 1510
frames/s; with the loop kept on CPU 0, 30 a second and 1710 frames/s (benchmarks/RESULTS.md).

Only the loop thread (and what it starts later) is moved: workers come from a forkserver
started before, with every CPU of the process, and threads already running keep theirs.
Undone at stop, for an embedding program.
"""

from __future__ import annotations

import contextlib
import logging
import os

from ..graph._resolve import Graph
from ..graph.spec import Placement

log = logging.getLogger("flowrt.runtime")


class LoopCpus:
    """Invariant: ``_before`` is set exactly while the loop thread's CPUs are ours."""

    def __init__(self) -> None:
        self._before: set[int] | None = None
        self.granted = ""  # what the loop runs (ran) on when kept off ("": unchanged)

    def apply(self, graph: Graph) -> None:
        """Keep the calling (loop) thread off the pinned workers' CPUs, before the nodes'
        threads start (unchanged when no worker is pinned or no CPU would be left)."""
        if not hasattr(os, "sched_setaffinity"):
            return
        claimed = {
            c
            for n in graph.nodes.values()
            if n.spec.placement is not Placement.inline and n.spec.cpus
            for c in n.spec.cpus
        }
        mine = os.sched_getaffinity(0)
        rest = mine - claimed
        if not claimed or not rest or rest == mine:
            return
        try:
            os.sched_setaffinity(0, rest)
        except OSError:
            return
        self._before = mine
        self.granted = f"cpus {_cpus(rest)} (not {_cpus(mine & claimed)})"  # not: pinned workers'
        log.info("loop: %s: the CPUs of pinned workers", self.granted)

    def restore(self) -> None:
        before, self._before = self._before, None  # (granted: what it ran on, kept)
        if before is not None:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, before)


def _cpus(cpus: set[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus))
