"""What a node's runner counts, and the statistics it reports from them.

Every activation that does not complete is counted with its reason (skipped, discarded,
aborted, failed): nothing is lost silently, and the same figures reach the status table,
``--stats-json``, the web view and recordings through :class:`flowrt.stats.NodeStats`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from ..graph._resolve import ResolvedNode
from ..graph.spec import FrameTrigger, InputTrigger, TimerTrigger
from ..stats import NodeStats, Running
from .timing import Timing

log = logging.getLogger("flowrt")


@dataclass
class Counters:
    """Invariant: ``activations >= completions + skipped`` (a release is counted once, and
    ends completed, skipped, or still running / failed / discarded / aborted)."""

    activations: int = 0  # releases, including the skipped ones
    completions: int = 0
    skipped: int = 0  # overruns, missing required inputs, the node down
    misses: int = 0  # deadline misses (flowrt.kernel.deadlines)
    discarded: int = 0  # late results dropped by miss_policy: discard
    aborted: int = 0  # activations in flight lost with their worker (or its instance)
    direct_hops: int = 0  # activations whose input came straight from the writer's worker
    errors: int = 0  # exceptions, and values of a refused type
    restarts: int = 0
    lead_max: int = 0  # most frames of a paced source published and not yet processed
    last_start: float | None = None
    last_finish: float | None = None
    interval_from: float | None = None  # None after a timing change: a new series
    timing_changed: float | None = None  # when its release timing last changed (None: never)
    interval: Running = field(default_factory=Running)
    execution: Running = field(default_factory=Running)
    response: Running = field(default_factory=Running)

    def new_interval_series(self, at: float) -> None:
        """The interval statistics describe the new timing (from ``at``), not a mean of old
        and new."""
        self.interval = Running()
        self.interval_from = None
        self.timing_changed = at


def node_stats(
    rnode: ResolvedNode,
    timing: Timing,
    c: Counters,
    state: str,
    error_reason: str | None,
    failed_reason: str,
    input_drops: int,
    waiting_reason: str | None,
    granted: str,
    rel: Callable[[float], float],
) -> NodeStats:
    """A node's statistics, as the table, ``--stats-json`` and the web view show them."""
    spec, trig = rnode.spec, rnode.trigger
    if isinstance(trig, FrameTrigger):
        trigger = f"frame {trig.frame}"
    elif isinstance(trig, TimerTrigger):
        trigger = "timer"
    elif isinstance(trig, InputTrigger):
        trigger = "input"
    else:
        trigger = "loop"
    period = timing.describe_period() if isinstance(trig, FrameTrigger | TimerTrigger) else "-"
    failed = state == "failed"
    if not timing.enabled:
        shown = "disabled"
    elif error_reason is not None and not failed:
        shown = "error"
    elif waiting_reason is not None and state in ("idle", "running"):
        shown = "waiting"
        error_reason = waiting_reason
    else:
        shown = state
    return NodeStats(
        name=rnode.name,
        kind=spec.kind,
        placement=spec.placement.value,
        trigger=trigger,
        priority=timing.priority,
        period=period,
        period_frames=timing.period if isinstance(trig, FrameTrigger) else None,
        timer_ms=None if timing.timer is None else timing.timer * 1000,
        deadline_ms=None if timing.deadline is None else timing.deadline * 1000,
        watchdog_ms=spec.watchdog,
        enabled=timing.enabled,
        state=shown,
        reason=failed_reason if failed else error_reason or "",
        activations=c.activations,
        completions=c.completions,
        skipped=c.skipped,
        deadline_misses=c.misses,
        discarded=c.discarded,
        aborted=c.aborted,
        direct_hops=c.direct_hops,
        paced_lead_max=c.lead_max,
        dropped=c.discarded + c.aborted + input_drops,
        errors=c.errors,
        restarts=c.restarts,
        last_start=None if c.last_start is None else rel(c.last_start),
        last_finish=None if c.last_finish is None else rel(c.last_finish),
        timing_changed=None if c.timing_changed is None else rel(c.timing_changed),
        interval=c.interval.summary(),
        execution=c.execution.summary(),
        response=c.response.summary(),
        granted=granted,
        output_hz=output_rates(rnode),
    )


_rates: dict[int, tuple[object, dict[str, float | None]]] = {}


def output_rates(rnode: ResolvedNode) -> dict[str, float | None]:
    """The node's declared output rates (``Node.output_rates``), once per params object: a
    CAN node's walk over a vehicle's DBC is not redone at every statistics call."""
    key = id(rnode.params)
    hit = _rates.get(key)
    if hit is not None and hit[0] is rnode.params:
        return hit[1]
    try:
        rates = dict(rnode.cls.output_rates(rnode.params))
    except Exception as e:  # a node's declaration must never break the statistics
        log.warning("node %s: output_rates() failed: %s", rnode.name, e)
        rates = {}
    if len(_rates) > 1024:  # params of runtimes long gone
        _rates.clear()
    _rates[key] = (rnode.params, rates)
    return rates
