"""The runtime's statistics: what the table, ``--stats-json``, the web view and recordings show."""

from __future__ import annotations

from typing import Any

from ..kernel import Scheduler
from ..stats import LoopStats, Running, RuntimeStats
from ._resources import RunResources


def runtime_stats(
    head: dict[str, Any],
    sched: Scheduler,
    res: RunResources | None,
    lag: Running,
    starvation_events: int,
    event_count: int,
) -> RuntimeStats:
    """``head`` (the run's name, uptime, mode, scheduling) with every figure of the run."""
    return RuntimeStats(
        **head,
        nodes=sched.node_stats(),
        edges=[b.stats() for b in sched.buffers],
        loop=LoopStats(
            lag=lag.summary(),
            blocked_calls=sched.blocked_calls,
            starvation_events=starvation_events,
        ),
        frames=[] if res is None else res.frame_stats(),
        worker_frames=[] if res is None else res.worker_frame_stats(),
        events=event_count,
        reports=sched.node_reports(),
    )
