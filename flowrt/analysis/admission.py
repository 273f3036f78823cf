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

A change is judged against the timing the graph started with too: the graph was admitted
with its own timing (``flowrt run`` checks it, and its initial mode, at load), so going back
to it (a node enabled again after ``--disable``) must never be refused. A node unschedulable
after a change is let through when it was already so in the started timing, with today's
budgets, at least as late. Each precise node is analysed where it runs now: in its release
thread, or on the loop once it has left the thread (long calls, a swap to a coroutine).

The runtime is known here only through :class:`RunnerView` (what a node runner exposes), so
this module imports nothing above :mod:`flowrt.analysis`.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

from ..graph._resolve import Graph
from ..kernel.timing import TimingChange
from .schedulability import GraphVerdict, NodeVerdict, analyse
from .timing import Budget, NodeTiming, apply_changes, graph_timing, with_mode

log = logging.getLogger("flowrt.admission")


class AdmissionRefused(ValueError):
    """A timing change refused by admission control; nothing was applied."""


class RunnerView(Protocol):
    """What admission control reads of a running node: its timing and its execution times.

    ``timing`` has ``period``, ``phase``, ``timer`` and ``deadline`` (seconds), ``priority``
    and ``enabled``; ``counts.execution`` has ``count`` and ``summary()`` (milliseconds,
    ``p99``). A precise node's runner also has ``precise``: its release (None on virtual
    time and before the start), whose ``thread_mode`` says whether calls run in its thread.
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
    started: GraphVerdict | None = None  # the timing the graph started with, if given


def _graph_now(graph: Graph, runners: Mapping[str, RunnerView]) -> dict[str, NodeTiming]:
    """The graph file's timing with today's budgets, each precise node where it runs now."""
    budgets: dict[str, Budget] = {}
    for name, r in runners.items():
        if name in graph.nodes and graph.nodes[name].spec.wcet is None and r.counts.execution.count:
            budgets[name] = Budget(max(r.counts.execution.summary().p99, 1e-6), "measured p99")
    timing = graph_timing(graph, budgets)
    for name, r in runners.items():
        release = getattr(r, "precise", None)  # None: not precise, or no thread (virtual time)
        if name in timing and release is not None:
            timing[name] = replace(timing[name], thread=bool(release.thread_mode))
    return timing


def started_timing(graph: Graph, runners: Mapping[str, RunnerView]) -> dict[str, NodeTiming]:
    """The timing a running graph started with (its file's, in its initial mode), with
    today's budgets: what ``flowrt run`` admitted at load."""
    timing = _graph_now(graph, runners)
    if graph.spec.initial_mode in graph.spec.modes:
        timing = with_mode(timing, graph, graph.spec.initial_mode)
    return timing


def current_timing(graph: Graph, runners: Mapping[str, RunnerView]) -> dict[str, NodeTiming]:
    """The timing table of a running graph: its current timing and today's budgets."""
    timing = _graph_now(graph, runners)
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
    timing: Mapping[str, NodeTiming],
    plan: Mapping[str, TimingChange],
    cpus: int | None = None,
    started: Mapping[str, NodeTiming] | None = None,
) -> Admission:
    """Would ``plan`` applied to ``timing`` keep every critical node schedulable, or at
    least no later than in the ``started`` timing (what the graph was admitted with)?"""
    cpus = cpus or os.cpu_count() or 1
    before = analyse(timing, cpus)
    after = analyse(apply_changes(timing, plan), cpus)
    at_start = None if started is None else analyse(started, cpus)
    was_bad = {v.name for v in before.nodes if v.schedulable is False}
    # the bound each node had where it already missed in the started timing
    missed = [] if at_start is None else [v for v in at_start.nodes if v.schedulable is False]
    start_bad = {v.name: _late(v) for v in missed}

    def new_miss(v: NodeVerdict) -> bool:
        if not v.has_deadline or v.schedulable is not False or v.name in was_bad:
            return False
        return _late(v) > start_bad.get(v.name, -math.inf) + 1e-6

    bad = [v for v in after.nodes if new_miss(v)]
    if not bad:
        return Admission(True, [], "", before, after, at_start)
    worst = ", ".join(
        f"{v.name} unschedulable (worst-case response {_fmt(v.response_ms)} ms"
        f" > deadline {_fmt(v.deadline_ms)} ms)"
        for v in bad
    )
    msg = (
        f"refused by admission control: it would make {worst}; nothing was changed (force to apply)"
    )
    return Admission(False, [v.name for v in bad], msg, before, after, at_start)


def _late(v: NodeVerdict) -> float:
    return math.inf if v.response_ms is None else v.response_ms


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
        now = current_timing(graph, runners)
        result = admit(now, plan, cpus, started_timing(graph, runners))
    except (ValueError, ZeroDivisionError):
        return
    except Exception:  # an analysis bug must not take run-time control down with it
        log.exception("admission control could not analyse the change; admitted unchecked")
        return
    if not result.admitted:
        raise AdmissionRefused(result.message)
