"""A node's run-time timing, and the one value that changes it.

Every run-time timing change (the API's ``Runtime.set_timing``, ``flowrt ctl timing``'s
``TimingRequest.change()``, a mode switch, the overload controller's shedding, admission
control's what-if) is one :class:`TimingChange`, fields in the units their names say. It is
checked once, by :meth:`TimingChange.problems` (the graph files' ranges and the node's
trigger) in ``Runtime.apply_timing``, the one door for every origin, then applied by the
kernel without a second check (:meth:`flowrt.kernel.Scheduler.apply_timing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from ..graph.spec import (
    MAX_DURATION_MS,
    MAX_FRAME_PERIOD,
    MAX_PRIORITY,
    MIN_DEADLINE_MS,
    MIN_PRIORITY,
    MIN_TIMER_MS,
    TimingOverride,
)


@dataclass
class Timing:
    """A node's current timing, as the scheduler uses it (seconds, frames).

    Invariants: ``period >= 1`` and ``0 <= phase < period`` (frame triggers; 1/0 otherwise);
    ``timer`` is None exactly when the node is not timer-triggered, and then
    ``timer_phase == 0``; ``deadline`` is None or > 0.
    """

    period: int  # frames, for frame triggers
    phase: int
    timer: float | None  # seconds, for timer triggers
    timer_phase: float  # seconds
    deadline: float | None  # seconds
    priority: int
    enabled: bool

    def copy(self) -> Timing:
        """A copy for a reader outside the kernel (``Scheduler.timing_of``, node views): by
        the constructor, a fifth of ``copy.copy``'s time (the overload controller takes a
        view of every node each window: 300 nodes, ~0.2 ms)."""
        return Timing(
            self.period,
            self.phase,
            self.timer,
            self.timer_phase,
            self.deadline,
            self.priority,
            self.enabled,
        )

    def describe_period(self) -> str:
        """As the table shows it: ``66.67ms``, ``100ms +5ms``; frames as ``flowrt graph``
        does: ``each``, ``1/4``, ``1/4 +3`` (every 4th frame, 3 frames late)."""
        if self.timer is not None:
            phase = f" +{_ms(self.timer_phase)}" if self.timer_phase else ""
            return _ms(self.timer) + phase
        every = "each" if self.period == 1 else f"1/{self.period}"
        return every + (f" +{self.phase}" if self.phase else "")


def _ms(seconds: float) -> str:
    """Milliseconds to at most two decimals (``66.67ms``, ``0.5ms``), microseconds below."""
    ms = seconds * 1000
    if 0 < ms < 0.01:
        return f"{ms * 1000:.3g}us"
    return f"{ms:.2f}".rstrip("0").rstrip(".") + "ms"


#: The ranges a run-time change must keep: the graph files' own (flowrt.graph.spec, README "Timing
#: ranges"). A 1e-9 ms timer rounds to a zero timerfd interval (it fires once, then never); a
#: 1e300 ms timer or a 10**18-frame period stops a node for good; NaN makes every activation a
#: miss. Checked again for changes built without validation (:meth:`TimingChange.unchecked`).
TIMER_MS = (MIN_TIMER_MS, MAX_DURATION_MS)
DEADLINE_MS = (MIN_DEADLINE_MS, MAX_DURATION_MS)
MAX_PERIOD = MAX_FRAME_PERIOD
PRIORITY = (MIN_PRIORITY, MAX_PRIORITY)


#: The graph file's name of each field of :class:`TimingChange` (what users write, in ms).
GRAPH_NAMES = {
    "period": "period",
    "phase": "phase",
    "timer": "timer_ms",
    "timer_phase": "timer_phase_ms",
    "deadline": "deadline_ms",
    "priority": "priority",
    "enabled": "enabled",
}


@dataclass(frozen=True)
class TimingChange:
    """A change to one node's timing; None leaves a field as it is.

    Units are in the names: frames for ``period``/``phase`` (frame triggers), milliseconds
    for the rest. The graph file's names (``timer``, ``timer_phase``, ``deadline``, in ms)
    are what users write; :meth:`of` maps them.
    """

    period: int | None = None
    phase: int | None = None
    timer_ms: float | None = None
    timer_phase_ms: float | None = None
    deadline_ms: float | None = None
    priority: int | None = None
    enabled: bool | None = None

    @classmethod
    def of(cls, **graph_names: Any) -> TimingChange:
        """The change the graph file's names describe (``timer=80`` is ``timer_ms=80``);
        None and absent names leave a field as it is. Nothing is checked here: that is
        :meth:`problems`, once, where the change is applied (``Runtime.apply_timing``)."""
        return cls(**{GRAPH_NAMES[k]: v for k, v in graph_names.items() if v is not None})

    @classmethod
    def parse(cls, node: str, **given: Any) -> TimingChange:
        """The change the keywords of ``Runtime.set_timing`` describe, parsed by the graph
        model as a graph file's are (``"80ms"``, whole floats for frames): the API's edge,
        as the ``TimingRequest`` body is the control wire's.

        Raises ValueError naming the node and every bad field.
        """
        values = {k: v for k, v in given.items() if v is not None}
        if "enabled" in values and not isinstance(values["enabled"], bool):  # ("no" was False)
            raise ValueError(f"{node}: enabled must be True or False, got {values['enabled']!r}")
        try:
            override = TimingOverride.model_validate(values)
        except ValidationError as e:
            found = "; ".join(
                f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}" for err in e.errors()
            )
            raise ValueError(f"{node}: {found}") from None
        return cls.unchecked(override)

    @classmethod
    def unchecked(cls, o: TimingOverride) -> TimingChange:
        """A change from a model of the graph file (a mode, a ``TimingRequest``)."""
        return cls.of(**{name: getattr(o, name) for name in GRAPH_NAMES})

    def problems(self, name: str, timing: Timing, is_frame: bool) -> list[str]:
        """What makes this change wrong for node ``name`` with ``timing`` ([] when none)."""
        found = self._range_problems(name)
        if found:
            return found
        problems = []
        if (self.period is not None or self.phase is not None) and not is_frame:
            problems.append(f"{name}: period/phase in frames apply to frame-triggered nodes")
        if self.timer_ms is not None and timing.timer is None:
            problems.append(f"{name}: timer applies to timer-triggered nodes")
        if self.timer_phase_ms is not None:
            timer_ms = self.timer_ms if self.timer_ms is not None else (timing.timer or 0) * 1000
            if timing.timer is None:
                problems.append(f"{name}: timer_phase applies to timer-triggered nodes")
            elif not 0 <= self.timer_phase_ms < timer_ms:
                problems.append(
                    f"{name}: timer_phase must be in 0..{timer_ms:g} ms (its timer), "
                    f"got {self.timer_phase_ms:g}"
                )
        elif self.timer_ms is not None and timing.timer is not None:
            phase_ms = timing.timer_phase * 1000  # the phase it keeps must stay below it
            if phase_ms >= self.timer_ms:
                problems.append(
                    f"{name}: timer {self.timer_ms:g} ms must be above its phase "
                    f"{phase_ms:g} ms: change timer_phase with it"
                )
        period = timing.period if self.period is None else self.period
        phase = timing.phase if self.phase is None else self.phase
        if is_frame and (period <= 0 or not 0 <= phase < period):
            problems.append(
                f"{name}: need period > 0 and 0 <= phase < period (got {period}/{phase})"
            )
        return problems

    def _range_problems(self, name: str) -> list[str]:
        """Finite numbers within the documented ranges (whatever built the change)."""
        problems = []
        for label, value, (lo, hi) in (
            ("timer", self.timer_ms, TIMER_MS),
            ("deadline", self.deadline_ms, DEADLINE_MS),
        ):
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                problems.append(f"{name}: {label} must be a number of ms, got {value!r}")
            elif not math.isfinite(value) or not lo <= value <= hi:
                problems.append(
                    f"{name}: {label} must be between {lo:g} and {hi:g} ms, got {value!r}"
                )
        if self.timer_phase_ms is not None and (
            isinstance(self.timer_phase_ms, bool)
            or not isinstance(self.timer_phase_ms, int | float)
            or not math.isfinite(self.timer_phase_ms)
        ):
            problems.append(f"{name}: timer_phase must be a number of ms")
        for label, value, (lo, hi) in (
            ("period", self.period, (1, MAX_PERIOD)),
            ("phase", self.phase, (0, MAX_PERIOD - 1)),
            ("priority", self.priority, PRIORITY),
        ):
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int):
                problems.append(f"{name}: {label} must be an integer, got {value!r}")
            elif not lo <= value <= hi:
                problems.append(f"{name}: {label} must be between {lo} and {hi}, got {value}")
        if self.enabled is not None and not isinstance(self.enabled, bool):
            problems.append(f"{name}: enabled must be true or false, got {self.enabled!r}")
        return problems
