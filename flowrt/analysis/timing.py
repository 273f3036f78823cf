"""The timing view of a graph that the analyses work on, and run-time changes applied to it.

A graph file, a running runtime (whose operator may have changed periods) and a proposed
change all reduce to the same table: per node its trigger, period, phase, deadline, priority,
placement and CPUs, plus an execution-time budget. Keeping it a plain frozen value lets
``flowrt check`` and admission control (:mod:`flowrt.analysis.admission`) run the very same
analysis, one before a run and one before a change.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

from ..graph._resolve import Graph
from ..graph.spec import EdgePolicy, FrameTrigger, InputTrigger, Placement, TimerTrigger
from ..kernel.timing import TimingChange

TriggerKind = Literal["frame", "timer", "input", "loop"]


@dataclass(frozen=True)
class Budget:
    """An execution-time budget (ms) and where it came from, e.g. ``wcet`` or ``stats p99``."""

    ms: float
    source: str


@dataclass(frozen=True)
class NodeTiming:
    """What the analyses need to know about one node. Times in ms, periods of frame
    triggers in frames of ``source``."""

    name: str
    trigger: TriggerKind
    priority: int
    placement: str  # inline, process, pool
    order: int
    enabled: bool = True
    source: str | None = None  # frame triggers: the source node
    period: int = 1  # frames
    phase: int = 0  # frames
    timer_ms: float | None = None
    timer_phase_ms: float = 0.0
    own_interval_ms: float | None = None  # loop-triggered sources paced by their fps
    producers: tuple[str, ...] = ()  # input triggers: nodes whose data activates this one
    deadline_ms: float | None = None
    cpus: tuple[int, ...] | None = None
    budget: Budget | None = None
    thread: bool = False  # timing: precise, called in its own release thread (not the loop)


def graph_timing(
    graph: Graph, budgets: Mapping[str, Budget] | None = None
) -> dict[str, NodeTiming]:
    """The timing table of ``graph`` as written in its file, with ``budgets`` where known
    (else the node's declared ``wcet``)."""
    out: dict[str, NodeTiming] = {}
    budgets = budgets or {}
    for name, n in graph.nodes.items():
        s = n.spec
        trig = n.trigger
        budget = budgets.get(name)
        if budget is None and s.wcet is not None:
            budget = Budget(s.wcet, "wcet")
        t = NodeTiming(
            name=name,
            trigger="loop",
            priority=s.priority,
            placement=s.placement.value,
            order=n.order,
            enabled=s.enabled,
            deadline_ms=s.deadline,
            cpus=tuple(s.cpus) if s.cpus else None,
            budget=budget,
            thread=in_precise_thread(graph, name) and not _leaves_thread(trig, budget),
        )
        if isinstance(trig, FrameTrigger):
            t = replace(
                t,
                trigger="frame",
                source=graph.frame_port(trig.frame).split(".")[0],
                period=trig.period,
                phase=trig.phase,
            )
        elif isinstance(trig, TimerTrigger):
            t = replace(t, trigger="timer", timer_ms=trig.timer, timer_phase_ms=trig.phase)
        elif isinstance(trig, InputTrigger):
            wanted = (
                None
                if trig.input == "any"
                else set([trig.input] if isinstance(trig.input, str) else trig.input)
            )
            producers = sorted(
                {
                    e.src
                    for e in graph.edges
                    if e.dst == name and (wanted is None or e.dst_port in wanted)
                }
            )
            t = replace(t, trigger="input", producers=tuple(producers))
        else:
            t = replace(t, own_interval_ms=graph.frame_interval_ms(name))
        out[name] = t
    return out


def _leaves_thread(trig: Any, budget: Budget | None) -> bool:
    """A precise node whose budget is over half its period: the runtime moves it to the loop
    after a few such calls (kernel/precise.py ``LONG_CALLS``), so it is analysed there (a
    0.866 ms p99 on a 1 ms timer was checked as in its thread and found fine)."""
    return (
        budget is not None
        and isinstance(trig, TimerTrigger)
        and trig.timer is not None
        and budget.ms > trig.timer / 2
    )


def in_precise_thread(graph: Graph, name: str) -> bool:
    """Whether ``timing: precise`` node ``name`` is called in its own release thread rather
    than handed to the event loop at each instant: the same rules as
    :func:`flowrt.kernel.precise.why_not_thread` decides by when the node is set up (an
    inline node whose ``process`` is a plain function, no frame output or input, no lossless
    input), read here from the graph so that ``flowrt check`` and ``flowrt run`` see it
    before anything runs. A running node that left its thread (long calls, a swap to a
    coroutine) is known to the runtime only: admission control takes it from there. The two
    are kept in step by a table of graphs run both ways (tests/test_precise.py)."""
    n = graph.nodes[name]
    if n.spec.timing != "precise" or not isinstance(n.trigger, TimerTrigger):
        return False
    if n.spec.placement is not Placement.inline or inspect.iscoroutinefunction(n.cls.process):
        return False
    if n.cls.frame_ports():
        return False
    for e in graph.edges:
        if e.dst != name:
            continue
        if e.policy is EdgePolicy.lossless:
            return False
        src = graph.nodes.get(e.src)
        if src is not None and e.src_port in src.cls.frame_ports():
            return False
    return True


def apply_changes(
    timing: Mapping[str, NodeTiming], plan: Mapping[str, TimingChange]
) -> dict[str, NodeTiming]:
    """``timing`` with the overrides of ``plan`` applied (unset fields keep their value)."""
    out = dict(timing)
    for name, o in plan.items():
        t = out[name]
        changes: dict[str, object] = {}
        for f_o, f_t in (
            ("period", "period"),
            ("phase", "phase"),
            ("timer_ms", "timer_ms"),
            ("deadline_ms", "deadline_ms"),
            ("priority", "priority"),
            ("enabled", "enabled"),
        ):
            v = getattr(o, f_o)
            if v is not None:
                changes[f_t] = v
        out[name] = replace(t, **changes)  # type: ignore[arg-type]
    return out


def interval_ms(timing: Mapping[str, NodeTiming], name: str, _depth: int = 0) -> float | None:
    """Nominal time between activations of ``name`` (ms), or None when it has no known rate.

    Frame triggers: ``period`` times the source's interval; timers: the timer; loop-triggered
    sources: their fps; input triggers: the shortest interval of their producers (the node
    should be done before its fastest input brings the next data; the analysis itself treats
    each producer as an arrival stream of its own).
    """
    t = timing.get(name)
    if t is None or _depth > 32:
        return None
    if t.trigger == "timer":
        return t.timer_ms
    if t.trigger == "frame" and t.source is not None:
        inner = interval_ms(timing, t.source, _depth + 1)
        return None if inner is None else inner * t.period
    if t.trigger == "input":
        rates = [interval_ms(timing, p, _depth + 1) for p in t.producers]
        known = [r for r in rates if r is not None]
        if not known or len(known) < len(rates):
            return None
        return min(known)
    return t.own_interval_ms


def finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def with_mode(timing: Mapping[str, NodeTiming], graph: Graph, mode: str) -> dict[str, NodeTiming]:
    """``timing`` (the graph's own) with the timing overrides of ``mode`` applied, as
    ``Runtime.set_mode`` applies them from the graph's timing: a new period without a phase
    keeps the phase if it still fits, else 0. Raises KeyError for an unknown mode."""
    spec = graph.spec.modes[mode]
    plan: dict[str, TimingChange] = {}
    for name, o in spec.nodes.items():
        phase = o.phase
        t = timing[name]
        if o.period is not None and phase is None and t.trigger == "frame":
            phase = t.phase if t.phase < o.period else 0
        plan[name] = TimingChange(
            period=o.period,
            phase=phase,
            timer_ms=o.timer,
            deadline_ms=o.deadline,
            priority=o.priority,
            enabled=o.enabled,
        )
    return apply_changes(timing, plan)
