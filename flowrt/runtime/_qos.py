"""The QoS manager: run-time timing changes, modes, and the overload controller.

Timing changes themselves are :meth:`flowrt.Runtime.apply_timing` (applied between ticks: the
loop runs one callback at a time, so a tick sees either the old timing or the new one, never
half of it) and modes are :meth:`flowrt.Runtime.set_mode`. This module holds what decides
*which* changes to make:

- :func:`nominal_timing`: a node's timing as the graph file gives it, so that a mode switch
  can return the nodes the previous mode changed before applying the next one;
- :class:`OverloadController`: CAMBADA's resource manager. When the loop lags, the CPU is
  saturated or deadlines are missed, it sheds the lowest-priority work — first a longer
  period, then disabled — one step per evaluation, and restores it, last step first, once
  the load has stayed low for a while. Critical nodes are never touched. Every change is a
  ``TimingChange`` through ``Runtime.apply_timing(node, change, origin="qos")``, so it is
  checked and becomes a timestamped ``TimingChanged`` event like any other change.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from ..clock import Clock, Handle, PeriodicTimer
from ..events import Event, TimingChanged
from ..graph.spec import (
    FrameTrigger,
    ModeSpec,
    OverloadSpec,
    TimerTrigger,
    TimingOverride,
)
from ..kernel.timing import TimingChange

if TYPE_CHECKING:
    from ..graph._resolve import Graph, ResolvedNode
    from ..kernel import NodeView

log = logging.getLogger("flowrt.runtime._qos")

LAG_PROBE = 0.010  # seconds between loop-lag probes
_MAX_BACKOFF = 8  # restore_after grows up to this factor when restoring re-overloads


def nominal_timing(node: ResolvedNode) -> TimingOverride:
    """The run-time adjustable timing of ``node`` as the graph gives it."""
    trig = node.trigger
    return TimingOverride(
        period=trig.period if isinstance(trig, FrameTrigger) else None,
        phase=trig.phase if isinstance(trig, FrameTrigger) else None,
        timer=trig.timer if isinstance(trig, TimerTrigger) else None,
        timer_phase=trig.phase if isinstance(trig, TimerTrigger) else None,
        deadline=node.spec.deadline,
        priority=node.spec.priority,
        enabled=node.spec.enabled,
    )


_FIELDS = ("period", "phase", "timer", "timer_phase", "deadline", "priority", "enabled")


def mode_plan(graph: Graph, previous: ModeSpec | None, new: ModeSpec) -> dict[str, TimingChange]:
    """The timing changes that switch from mode ``previous`` to mode ``new``.

    A field the new mode sets takes its value; a field only the previous mode set returns to
    the graph's value; fields neither mode sets keep what they are now (an operator's change).
    """
    before = previous.nodes if previous is not None else {}
    plan: dict[str, TimingChange] = {}
    for name in [*new.nodes, *(n for n in before if n not in new.nodes)]:
        nominal = nominal_timing(graph.nodes[name])
        old, o = before.get(name), new.nodes.get(name)
        values: dict[str, Any] = {}
        for f in _FIELDS:
            if o is not None and getattr(o, f) is not None:
                values[f] = getattr(o, f)
            elif old is not None and getattr(old, f) is not None:
                values[f] = getattr(nominal, f)
        if (
            "period" in values
            and "phase" not in values
            and isinstance(graph.nodes[name].trigger, FrameTrigger)
        ):
            values["phase"] = (
                nominal.phase
                if nominal.phase is not None and nominal.phase < values["period"]
                else 0
            )
        plan[name] = TimingChange.of(**values)  # the graph's values: checked when applied
    return plan


class NodeReads(Protocol):
    """What the controller reads of the scheduler: snapshots of its nodes, never a runner."""

    def node_views(self) -> list[NodeView]: ...


class QosHost(Protocol):
    """What the overload controller needs of the runtime that runs it (owned here, so that
    this module does not import :mod:`flowrt.runtime._runtime`, which imports it)."""

    @property
    def clock(self) -> Clock: ...

    @property
    def started(self) -> bool: ...

    @property
    def scheduler(self) -> NodeReads: ...

    def apply_timing(
        self, node: str, change: TimingChange, *, origin: str = "api", force: bool = False
    ) -> str: ...

    def qos_status(self) -> QosStatus: ...

    def record_state(self, name: str, value: Any) -> None: ...


@dataclass(frozen=True)
class LoadSample:
    """What the overload controller measured over one window."""

    loop_lag_ms: float = 0.0  # mean lateness of the probe timer
    cpu_percent: float | None = None  # system-wide, when a CPU threshold is configured
    miss_rate: float = 0.0  # deadline misses / activations of enabled nodes with a deadline
    activations: int = 0  # of those nodes, in the window


@dataclass(frozen=True)
class ShedNode:
    """A node the overload controller has shed: slowed by ``slowdown``, or disabled."""

    node: str
    slowdown: int
    disabled: bool

    def describe(self) -> str:
        return f"{self.node} off" if self.disabled else f"{self.node} x{self.slowdown}"


@dataclass(frozen=True)
class QosStatus:
    """The QoS manager's state, for the status table and the control endpoint."""

    mode: str | None
    overload_control: bool  # an overload controller is running
    overloaded: bool = False
    reason: str = ""  # which threshold was crossed, while overloaded
    shed: tuple[ShedNode, ...] = ()
    last: LoadSample | None = None

    def describe(self) -> str:
        parts = [f"mode {self.mode or '-'}"]
        if self.overload_control:
            parts.append(f"OVERLOAD {self.reason}" if self.overloaded else "load ok")
            parts.append("shed: " + (", ".join(s.describe() for s in self.shed) or "none"))
        return "qos: " + " · ".join(parts)


@dataclass
class _Step:
    node: str
    disabled: bool  # True: this step disabled the node; False: it doubled the slowdown
    previous: int  # slowdown before a slowing step


@dataclass
class _Base:
    """A shed node's timing before the controller touched it."""

    period: int
    timer_ms: float | None
    slowdown: int = 1
    disabled: bool = False


@dataclass
class _Window:
    lag_sum: float = 0.0
    lag_n: int = 0
    counters: dict[str, tuple[int, int]] = field(default_factory=dict)  # node -> (act, misses)


class OverloadController:
    """Sheds and restores low-priority work by the thresholds of an :class:`OverloadSpec`.

    The runtime creates one when the graph has ``qos: {overload: ...}`` and registers it as a
    monitor. ``measure`` may be replaced (tests, or a host program with its own load model)
    by any callable returning a :class:`LoadSample`.
    """

    def __init__(self, spec: OverloadSpec) -> None:
        self.spec = spec
        self.measure: Callable[[], LoadSample] | None = None
        self.rt: QosHost | None = None
        self.overloaded = False
        self.reason = ""
        self.last: LoadSample | None = None
        self._steps: list[_Step] = []
        self._base: dict[str, _Base] = {}
        self._timer: PeriodicTimer | None = None
        self._probe: Handle | None = None
        self._window = _Window()
        self._window_start = 0.0
        self._calm_since: float | None = None
        self._last_restore: float | None = None
        self._backoff = 1
        self._protect_priority = 99
        self._cpu_primed = False

    # --- monitor interface ----------------------------------------------------------------

    def started(self, rt: QosHost) -> None:
        self.rt = rt
        views = rt.scheduler.node_views()
        names = [v.name for v in views]
        for name in self.spec.protect:
            if name not in names:
                from ..graph.diagnostics import did_you_mean

                hint = did_you_mean(name, names)
                log.warning("qos.overload.protect: unknown node %r%s (ignored)", name, hint)
        candidates = [v for v in views if self._kind_sheddable(v)]
        self._protect_priority = self.spec.protect_priority or max(
            (v.node.spec.priority for v in candidates), default=99
        )
        self._window = self._new_window()
        interval = self.spec.interval / 1000
        self._timer = rt.clock.periodic(interval, 0.0, self._tick)
        if self.spec.loop_lag_ms is not None:
            self._arm_probe(rt.clock.now() + LAG_PROBE)

    def event(self, event: Event) -> None:
        """An operator's change (API, mode, node) to a shed node wins: forget that node."""
        if (
            not isinstance(event, TimingChanged)
            or event.origin == "qos"
            or event.node not in self._base
        ):
            return
        labels = {part.split(" ", 1)[0] for part in event.change.split(", ")}
        if labels & {"period", "timer_ms", "enabled"}:
            self._forget(event.node)

    def stopped(self, rt: QosHost) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._probe is not None:
            self._probe.cancel()
            self._probe = None

    # --- state ----------------------------------------------------------------------------

    def shed(self) -> tuple[ShedNode, ...]:
        return tuple(
            ShedNode(name, b.slowdown, b.disabled)
            for name, b in self._base.items()
            if b.slowdown > 1 or b.disabled
        )

    def protected(self, view: NodeView) -> bool:
        """Never shed: not slowable/disableable by kind, listed, or at the critical priority."""
        return (
            not self._kind_sheddable(view)
            or view.name in self.spec.protect
            or view.timing.priority >= self._protect_priority
        )

    @staticmethod
    def _kind_sheddable(v: NodeView) -> bool:
        trig = v.node.trigger
        return isinstance(trig, FrameTrigger | TimerTrigger) and not v.node.cls.frame_ports()

    # --- measuring ------------------------------------------------------------------------

    def _arm_probe(self, due: float) -> None:
        assert self.rt is not None
        clock = self.rt.clock
        self._probe = clock.call_at(due, lambda: self._probed(due))

    def _probed(self, due: float) -> None:
        assert self.rt is not None
        now = self.rt.clock.now()
        self._window.lag_sum += max(0.0, now - due)
        self._window.lag_n += 1
        self._arm_probe(now + LAG_PROBE)

    def _new_window(self) -> _Window:
        assert self.rt is not None
        self._window_start = self.rt.clock.now()
        counters = {v.name: (v.activations, v.misses) for v in self.rt.scheduler.node_views()}
        return _Window(counters=counters)

    def _measure_window(self) -> LoadSample:
        assert self.rt is not None
        old = self._window
        views = self.rt.scheduler.node_views()
        self._window_start = self.rt.clock.now()
        self._window = _Window(counters={v.name: (v.activations, v.misses) for v in views})
        acts = misses = 0
        for v in views:
            if v.timing.deadline is None or not v.timing.enabled:
                continue
            a0, m0 = old.counters.get(v.name, (0, 0))
            acts += v.activations - a0
            misses += v.misses - m0
        cpu: float | None = None
        if self.spec.cpu_percent is not None:
            import psutil

            cpu = float(psutil.cpu_percent(None))
            if not self._cpu_primed:  # the first call measures since import: meaningless
                self._cpu_primed = True
                cpu = 0.0
        return LoadSample(
            loop_lag_ms=old.lag_sum / old.lag_n * 1000 if old.lag_n else 0.0,
            cpu_percent=cpu,
            miss_rate=misses / acts if acts else 0.0,
            activations=acts,
        )

    def _assess(self, s: LoadSample) -> tuple[bool, bool, str]:
        """(overloaded, calm, reason) against the thresholds."""
        spec = self.spec
        checks: list[tuple[str, float, float | None, str]] = [
            ("loop lag", s.loop_lag_ms, spec.loop_lag_ms, "ms"),
            ("cpu", s.cpu_percent or 0.0, spec.cpu_percent, "%"),
            ("miss rate", s.miss_rate, spec.miss_rate, ""),
        ]
        over = [
            f"{label} {value:.3g}{unit} > {limit:g}{unit}"
            for label, value, limit, unit in checks
            if limit is not None and value > limit
        ]
        calm = all(
            limit is None or value < limit * spec.hysteresis for _, value, limit, _ in checks
        )
        return bool(over), calm, ", ".join(over)

    # --- deciding -------------------------------------------------------------------------

    def _tick(self, release: float, missed: int) -> None:
        rt = self.rt
        if rt is None or not rt.started:
            return
        if rt.clock.now() - self._window_start < self.spec.interval / 2000:
            self._window = self._new_window()  # the first tick: nothing measured yet
            return
        sample = self.measure() if self.measure is not None else self._measure_window()
        if self.measure is not None:
            self._window = self._new_window()
        self.last = sample
        over, calm, reason = self._assess(sample)
        now = rt.clock.now()
        was = self.overloaded
        self.overloaded, self.reason = over, reason
        if over:
            self._calm_since = None
            if (
                self._last_restore is not None
                and now - self._last_restore < self.spec.restore_after / 1000 * self._backoff
            ):
                self._backoff = min(self._backoff * 2, _MAX_BACKOFF)  # restoring brought it back
                self._last_restore = None
            if not was:
                log.warning("overload: %s", reason)
            if self._shed_one(reason):
                rt.record_state("flowrt.runtime._qos", rt.qos_status())
        elif calm:
            if self._calm_since is None:
                self._calm_since = now
            if (
                self._steps
                and now - self._calm_since >= self.spec.restore_after / 1000 * self._backoff
            ):
                self._restore_one()
                self._last_restore = now
                rt.record_state("flowrt.runtime._qos", rt.qos_status())
                if not self._steps:
                    self._backoff = 1
        else:
            self._calm_since = None

    def _pick(self, slow: bool) -> NodeView | None:
        assert self.rt is not None
        best: NodeView | None = None
        for v in self.rt.scheduler.node_views():
            if self.protected(v) or not v.timing.enabled:
                continue
            if slow:
                base = self._base.get(v.name)
                if (base.slowdown if base else 1) * 2 > self.spec.max_slowdown:
                    continue
            key = (v.timing.priority, -v.node.order)
            if best is None or key < (best.timing.priority, -best.node.order):
                best = v
        return best

    def _shed_one(self, reason: str) -> bool:
        """One step of shedding; False when there is nothing left to shed."""
        assert self.rt is not None
        v = self._pick(slow=True)
        disable = False
        if v is None and self.spec.disable:
            v = self._pick(slow=False)
            disable = True
        if v is None:
            return False
        tm = v.timing
        base = self._base.setdefault(
            v.name, _Base(period=tm.period, timer_ms=None if tm.timer is None else tm.timer * 1000)
        )
        if disable:
            self._steps.append(_Step(v.name, True, base.slowdown))
            base.disabled = True
            self._apply(v.name, TimingChange(enabled=False))
        else:
            self._steps.append(_Step(v.name, False, base.slowdown))
            base.slowdown *= 2
            self._apply_slowdown(v.name, base)
        log.info("qos: shed %s (%s)", self._steps[-1].node, reason)
        return True

    def _restore_one(self) -> None:
        step = self._steps.pop()
        base = self._base[step.node]
        if step.disabled:
            base.disabled = False
            self._apply(step.node, TimingChange(enabled=True))
        else:
            base.slowdown = step.previous
            self._apply_slowdown(step.node, base)
        if base.slowdown == 1 and not base.disabled:
            del self._base[step.node]

    def _apply_slowdown(self, node: str, base: _Base) -> None:
        if base.timer_ms is not None:
            self._apply(node, TimingChange(timer_ms=base.timer_ms * base.slowdown))
        else:
            self._apply(node, TimingChange(period=base.period * base.slowdown))

    def _apply(self, node: str, change: TimingChange) -> None:
        assert self.rt is not None
        try:
            self.rt.apply_timing(node, change, origin="qos")
        except (KeyError, ValueError) as e:  # e.g. a phase an operator set meanwhile
            log.warning("qos: cannot change %s: %s", node, e)

    def _forget(self, node: str) -> None:
        self._base.pop(node, None)
        self._steps = [s for s in self._steps if s.node != node]
