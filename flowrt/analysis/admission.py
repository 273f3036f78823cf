"""Admission control: refuse a run-time timing change that would break a critical deadline.

The CAMBADA QoS manager changes periods, phases and priorities while the robot runs; a change
that looks harmless (a tracker every frame instead of every 4th) can push a higher-critical
tracker past its deadline. Before a change is applied, the runtime asks :func:`admit` to run
the same response-time analysis as ``flowrt check`` on the timing the change would produce,
with the budgets available now: each node's declared ``wcet``, else its execution-time p99
measured so far in this run. A change is refused when a *critical* node (one with a
deadline) would be unschedulable after it and was not before, so a graph that is already
overloaded can still be relieved; nodes without a budget yet are not judged. The caller may
force a change past the check.

The runtime is known here only through :class:`RunnerView` (what a node runner exposes), so
this module imports nothing above :mod:`flowrt.analysis`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from ..graph._resolve import Graph
from ..kernel.timing import TimingChange
from .schedulability import GraphVerdict, analyse
from .timing import Budget, NodeTiming, apply_changes, graph_timing

log = logging.getLogger("flowrt.admission")


class AdmissionRefused(ValueError):
    """A timing change refused by admission control; nothing was applied."""


class RunnerView(Protocol):
    """What admission control reads of a running node: its timing and its execution times.

    ``timing`` has ``period``, ``phase``, ``timer`` and ``deadline`` (seconds), ``priority``
    and ``enabled``; ``counts.execution`` has ``count`` and ``summary()`` (milliseconds,
    ``p99``).
    """

    @property
    def timing(self) -> Any: ...

    @property
    def counts(self) -> Any: ...


@dataclass(frozen=True)
class Admission:
    admitted: bool
    refused_nodes: list[str]
    message: str
    before: GraphVerdict
    after: GraphVerdict


def current_timing(graph: Graph, runners: Mapping[str, RunnerView]) -> dict[str, NodeTiming]:
    """The timing table of a running graph: its current timing and today's budgets."""
    budgets: dict[str, Budget] = {}
    for name, r in runners.items():
        if name in graph.nodes and graph.nodes[name].spec.wcet is None and r.counts.execution.count:
            budgets[name] = Budget(max(r.counts.execution.summary().p99, 1e-6), "measured p99")
    timing = graph_timing(graph, budgets)
    now: dict[str, TimingChange] = {}
    for name, r in runners.items():
        if name not in timing:
            continue
        tm, frame = r.timing, timing[name].trigger == "frame"
        now[name] = TimingChange(
            period=tm.period if frame else None,
            phase=tm.phase if frame else None,
            timer_ms=None if tm.timer is None else tm.timer * 1000,
            deadline_ms=None if tm.deadline is None else tm.deadline * 1000,
            priority=tm.priority,
            enabled=tm.enabled,
        )
    return apply_changes(timing, now)


def admit(
    timing: Mapping[str, NodeTiming], plan: Mapping[str, TimingChange], cpus: int | None = None
) -> Admission:
    """Would ``plan`` applied to ``timing`` keep every critical node schedulable?"""
    cpus = cpus or os.cpu_count() or 1
    before = analyse(timing, cpus)
    after = analyse(apply_changes(timing, plan), cpus)
    was_bad = {v.name for v in before.nodes if v.schedulable is False}
    bad = [
        v
        for v in after.nodes
        if v.has_deadline and v.schedulable is False and v.name not in was_bad
    ]
    if not bad:
        return Admission(True, [], "", before, after)
    worst = ", ".join(
        f"{v.name} unschedulable (worst-case response {_fmt(v.response_ms)} ms"
        f" > deadline {_fmt(v.deadline_ms)} ms)"
        for v in bad
    )
    msg = (
        f"refused by admission control: it would make {worst}; nothing was changed (force to apply)"
    )
    return Admission(False, [v.name for v in bad], msg, before, after)


def _fmt(x: float | None) -> str:
    return "-" if x is None else ("inf" if x == float("inf") else f"{x:.3g}")


def check_change(
    graph: Graph,
    runners: Mapping[str, RunnerView],
    plan: Mapping[str, TimingChange],
    cpus: int | None = None,
) -> None:
    """Raise :class:`AdmissionRefused` if ``plan`` would make a critical node unschedulable.

    A plan the analysis cannot even model (an unknown node, a zero period: the scheduler
    refuses those with its own message) is let through to that check.
    """
    if any(name not in graph.nodes for name in plan):
        return
    try:
        result = admit(current_timing(graph, runners), plan, cpus)
    except (ValueError, ZeroDivisionError):
        return
    except Exception:  # an analysis bug must not take run-time control down with it
        log.exception("admission control could not analyse the change; admitted unchecked")
        return
    if not result.admitted:
        raise AdmissionRefused(result.message)
