"""The runtime's statistics: what the table, ``--stats-json``, the web view and recordings show."""

from __future__ import annotations

import logging
from typing import Any

from .kernel import NodeRunner, Scheduler
from .resources import RunResources
from .stats import LoopStats, Running, RuntimeStats

log = logging.getLogger("flowrt")


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
        nodes=[r.stats() for r in sched.runners.values()],
        edges=[b.stats() for b in sched.buffers],
        loop=LoopStats(
            lag=lag.summary(),
            blocked_calls=sched.blocked_calls,
            starvation_events=starvation_events,
        ),
        frames=[] if res is None else res.frame_stats(),
        worker_frames=[] if res is None else res.worker_frame_stats(),
        events=event_count,
        reports=node_reports(sched.runners),
    )


def node_reports(runners: dict[str, NodeRunner]) -> dict[str, Any]:
    """Each inline node's optional ``report()`` (also after stop: its last instance's)."""
    out: dict[str, Any] = {}
    for name, r in runners.items():
        ex = r.executor
        node = getattr(ex, "node", None) or getattr(ex, "last_node", None)
        hook = getattr(node, "report", None)
        if not callable(hook):
            continue
        try:
            value = hook()
        except Exception as e:  # a report must never break the statistics
            log.warning("node %s: report() failed: %s", name, e)
            continue
        if value is not None:
            out[name] = value
    return out
