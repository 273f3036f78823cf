"""Run-time timing changes and modes: one :class:`~flowrt.kernel.timing.TimingChange` each, checked
whole (ranges, the node's trigger, then admission control) before any of it is applied.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from ..events import ModeChanged
from ..graph.spec import FrameTrigger
from ..kernel.timing import TimingChange
from ._hotswap import SwapHost, apply_mode_params


class TimingHost(SwapHost, Protocol):
    """What timing changes and modes need of the runtime (this module does not import it)."""

    mode: str | None

    def record_state(self, name: str, value: Any) -> None: ...


def check_plan(rt: TimingHost, plan: Mapping[str, TimingChange]) -> None:
    """Raise ValueError, before anything is applied, if any change of ``plan`` is invalid
    (KeyError for a node the graph does not have)."""
    problems = []
    for name, change in plan.items():
        if name not in rt.graph.nodes:
            from ..graph.diagnostics import did_you_mean

            raise KeyError(f"unknown node {name!r}" + did_you_mean(name, rt.graph.nodes))
        is_frame = isinstance(rt.graph.nodes[name].trigger, FrameTrigger)
        problems += change.problems(name, rt.scheduler.timing_of(name), is_frame)
    if problems:
        raise ValueError("; ".join(problems))


def apply_plan(
    rt: TimingHost, plan: Mapping[str, TimingChange], *, origin: str, admitted: bool
) -> list[str]:
    """Check every change of ``plan`` once (ranges and triggers, then admission control
    unless ``admitted``), then apply them all between ticks; what changed, node by node.

    The one door of run-time timing: ``Runtime.apply_timing`` (the control endpoint, the
    API, the overload controller) and modes. Nothing is applied when any change is refused.
    """
    check_plan(rt, plan)
    if not admitted:
        admit(rt, plan)
    return [rt.scheduler.apply_timing(node, change, origin) for node, change in plan.items()]


def set_mode(rt: TimingHost, mode: str, origin: str, force: bool) -> None:
    """See :meth:`flowrt.Runtime.set_mode`."""
    spec = rt.graph.spec.modes.get(mode)
    if spec is None:
        from ..graph.diagnostics import did_you_mean

        raise KeyError(f"unknown mode {mode!r}" + did_you_mean(mode, rt.graph.spec.modes))
    from ._qos import mode_plan

    previous_spec = rt.graph.spec.modes.get(rt.mode) if rt.mode else None
    plan = mode_plan(rt.graph, previous_spec, spec)
    # all or nothing; the initial mode is the graph's own choice (not admission-checked)
    apply_plan(rt, plan, origin=f"mode {mode}", admitted=force or origin == "graph")
    apply_mode_params(rt, previous_spec, spec)
    previous, rt.mode = rt.mode, mode
    rt.emit(ModeChanged(rt.now(), None, mode, previous, origin))
    rt.record_state("flowrt.mode", mode)


def admit(rt: TimingHost, plan: Mapping[str, TimingChange]) -> None:
    """Raise ValueError (AdmissionRefused) if ``plan`` breaks a critical deadline."""
    from ..analysis.admission import check_change

    check_change(rt.graph, rt.scheduler.runners, plan)
