"""The loop's share of the CPU without SCHED_FIFO: the lowest nice permitted, a short slice.

The loop runs at the lowest nice level the process may take, and the workers are ranked above
it by priority (:class:`flowrt.system._priorities.FairShare`); the loop also asks for a short EEVDF
slice, so that its timer wake-ups preempt a busy process instead of waiting for that
process's slice to end. Undone at stop, for an embedding program.
"""

from __future__ import annotations

import contextlib
import os

from ..graph._resolve import Graph
from ..graph.spec import Placement
from ._priorities import FairShare, lowest_nice, request_short_slice


class LoopShare:
    """Invariant: ``_nice_before`` is set exactly while the process's nice level is ours."""

    def __init__(self) -> None:
        self._nice_before: int | None = None

    def apply(self, graph: Graph) -> tuple[FairShare, str]:
        """Lower the loop's nice level; the workers' ranking and the hint for the table."""
        floor = lowest_nice()
        self._nice_before = nice = os.getpriority(os.PRIO_PROCESS, 0)
        with contextlib.suppress(OSError):
            if floor < nice:
                os.setpriority(os.PRIO_PROCESS, 0, floor)
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        # Ranked among the workers only: inline nodes run in the loop, which is above them all.
        workers = {n for n, rn in graph.nodes.items() if rn.spec.placement is not Placement.inline}
        priorities = [graph.nodes[name].spec.priority for name in workers]
        for mode in graph.spec.modes.values():
            priorities += [
                o.priority
                for name, o in mode.nodes.items()
                if name in workers and o.priority is not None
            ]
        hint = ", ".join(x for x in (f"nice {nice}", request_short_slice()) if x)
        return FairShare(priorities, nice), hint

    def restore(self) -> None:
        """Give an embedding program its nice level and slice back."""
        if self._nice_before is None:
            return
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, self._nice_before)
        request_short_slice(0)
        self._nice_before = None
