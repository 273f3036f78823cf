"""Deadline misses: one detector, one place that says so.

A deadline is relative to the release (CAMBADA's process manager): an activation released at
``t`` has missed it when it is still running at ``t + deadline``. Asynchronous activations
(a coroutine, a worker call) arm a timer so that the miss is reported when it happens, not
when the late result finally comes back; a synchronous inline call blocks the loop, so its
miss can only be seen when it returns. Either way :meth:`DeadlineWatch.finish` decides
whether the result is published (``miss_policy: discard`` drops a late one).
"""

from __future__ import annotations

from collections.abc import Callable

from ..clock import Clock
from ..events import DeadlineMissed, Event
from ..graph.spec import MissPolicy
from .activation import Activation
from .counters import Counters
from .timing import Timing


class DeadlineWatch:
    """Watches the deadlines of one node's activations."""

    def __init__(
        self,
        name: str,
        timing: Timing,
        counts: Counters,
        clock: Clock,
        emit: Callable[[Event], None],
        rel: Callable[[float], float],
        policy: Callable[[], MissPolicy],
    ) -> None:
        self._name = name
        self._timing = timing  # the runner's (changed in place by set_timing)
        self._counts = counts
        self._clock = clock
        self._emit = emit
        self._rel = rel
        self._policy = policy  # the node's miss_policy (a swap may change the spec)

    def arm(self, act: Activation) -> None:
        """Report a miss the moment ``act`` passes its deadline still running."""
        deadline = self._timing.deadline
        if deadline is not None:
            act.timer = self._clock.call_at(act.t_release + deadline, lambda: self._passed(act))

    def _passed(self, act: Activation) -> None:
        if not act.closed and not act.missed:
            self._miss(act, self._clock.now(), running=True)

    def disarm(self, act: Activation) -> None:
        if act.timer is not None:
            act.timer.cancel()
            act.timer = None

    def finish(self, act: Activation, end: float) -> bool:
        """``act`` ended at ``end``: count a miss not reported yet; True: discard its result."""
        if act.timer is not None:
            act.timer.cancel()
            act.timer = None
        deadline = self._timing.deadline
        if deadline is None or end - act.t_release <= deadline:
            return False
        if not act.missed:
            self._miss(act, end, running=False)
        return self._policy() is MissPolicy.discard

    def _miss(self, act: Activation, at: float, running: bool) -> None:
        """The one place a miss is counted and said."""
        act.missed = True
        self._counts.misses += 1
        assert self._timing.deadline is not None
        self._emit(
            DeadlineMissed(
                self._rel(at),
                self._name,
                self._timing.deadline * 1000,
                running,
                self._policy() is MissPolicy.discard,
            )
        )
