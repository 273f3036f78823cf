"""Teleoperation input shaping: a human's stick becomes a safe speed command.

After ViCo/CoSMic's haptic input chain (scaling, dead band, speed mapping, axis lock, a
safe-start state machine) and against the known failures of ROS 2's teleop_twist_joy and
joy: a deadman released, an input gone stale or a device lost gives the zero command *on every
tick*, never one zero and then silence, and never the last command repeated.

::

    teleop:
      kind: teleop
      trigger: {timer: 20ms}
      params:
        axes:
          vx: {input: left_y, scale: 0.8, dead_band: 0.05, curve: expo, expo: 0.4, max_rate: 2.0}
          w:  {input: left_x, scale: 1.5, dead_band: 0.08, invert: true,
               lock: {value: 0.0, button: y, field: w, gain: 2.0}}
        buttons: {start: a, stop: b, deadman: lb}
      inputs: {joy: joystick.output}              # optional: {state: robot.state}

States (each transition is a ``HealthAlert`` event of kind ``teleop-state``, severity info):

- ``idle``: zero output; a click on ``start`` goes to ``calibration`` when
  ``calibration: true``, else to ``initialization``.
- ``calibration``: zero output; the centre (the first sample) and the range of each axis are
  recorded while the user moves the sticks; a click on ``start`` goes to ``initialization``.
- ``initialization``: zero output until every axis is inside ``centre_band`` of its centre;
  then ``run``.
- ``run``: shaped output. The deadman (when configured) must be held; released, an input older
  than ``timeout`` (default 3 trigger periods), or no input at all -> zero at once and back to
  ``initialization``. A click on ``stop`` from any state -> ``idle``.

Shaping of one axis, in order: calibration (centre and range to [-1, 1]), invert, dead band
(re-scaled so the output is continuous past the band: ``sign(x) * (|x| - d) / (1 - d)``),
curve (``linear`` or ``expo``: ``(1 - e) * x + e * x**3``), scale (displacement -> speed),
then the rate limit (``max_rate`` units per second). A locked axis discards its input and
holds ``lock.value``; when the robot's measured state is connected (input ``state``, a mapping
with ``lock.field``), it outputs a P controller towards the lock value instead
(``gain * (value - measured)``, clamped to ``scale``). ``lock.button`` toggles the lock.

The per-tick path works on state allocated at set-up (one list slot per axis); only the
published ``command`` mapping is new each tick, because readers may hold on to it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from flowrt import HealthAlert, Input, Node, Output
from flowrt.refusals import Refusals, finite_number

__all__ = ["AxisLock", "AxisShaping", "Teleop", "shape"]

STATES = ("idle", "calibration", "initialization", "run")


class AxisLock(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value: float = Field(default=0.0, allow_inf_nan=False, description="held output / setpoint")
    locked: bool = Field(default=True, description="locked at start")
    button: str | None = Field(default=None, description="a click toggles the lock")
    field: str | None = Field(default=None, description="key of the measured value in `state`")
    gain: float = Field(default=1.0, ge=0, le=1000, allow_inf_nan=False)


class AxisShaping(BaseModel):
    model_config = ConfigDict(extra="forbid")
    input: str = Field(description="name of the joystick axis")
    scale: float = Field(default=1.0, gt=0, le=1e6, allow_inf_nan=False)
    dead_band: float = Field(default=0.05, ge=0, lt=1)
    curve: Literal["linear", "expo"] = "linear"
    expo: float = Field(default=0.3, ge=0, le=1, description="cubic share of the expo curve")
    max_rate: float | None = Field(
        default=None, gt=0, le=1e6, allow_inf_nan=False, description="output units per second"
    )
    invert: bool = False
    lock: AxisLock | None = None


class Buttons(BaseModel):
    model_config = ConfigDict(extra="forbid")
    start: str | None = "start"
    stop: str | None = "stop"
    deadman: str | None = None


class TeleopParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    axes: dict[str, AxisShaping] = Field(min_length=1)
    buttons: Buttons = Field(default_factory=Buttons)
    timeout_ms: float | None = Field(
        default=None, gt=0, le=60_000, allow_inf_nan=False, description="default: 3 periods"
    )
    calibration: bool = False
    centre_band: float = Field(default=0.1, gt=0, lt=1)
    initial_state: Literal["idle", "initialization"] = "idle"

    @model_validator(mode="after")
    def _distinct_buttons(self) -> TeleopParams:
        b = self.buttons
        used = [x for x in (b.start, b.stop, b.deadman) if x]
        if len(used) != len(set(used)):
            raise ValueError("start, stop and deadman must be different buttons")
        return self


def shape(
    x: float, a: AxisShaping, centre: float = 0.0, span: tuple[float, float] = (1, 1)
) -> float:
    """One axis from raw displacement to speed (before the rate limit): see the module doc."""
    if not math.isfinite(x):
        return 0.0
    x -= centre
    x = x / span[1] if x >= 0 else x / span[0]
    x = max(-1.0, min(1.0, x))
    if a.invert:
        x = -x
    d = a.dead_band
    mag = abs(x)
    if mag <= d:
        return 0.0
    x = math.copysign((mag - d) / (1.0 - d), x)
    if a.curve == "expo":
        x = (1.0 - a.expo) * x + a.expo * x * x * x
    return x * a.scale


def _field(value: Any, key: str) -> Any:
    if isinstance(value, Mapping):
        return value.get(key)
    return getattr(value, key, None)


class Teleop(Node):
    """Joystick -> speed command, with a safe-start state machine (see the module docstring)."""

    # over the control endpoint (flowrt kinds); never timeouts, scaling or the safe start
    swappable = frozenset({"centre_band"})

    Params = TeleopParams
    joy = Input(object, required=False, policy="latest", doc="joystick: axes, buttons, timestamp")
    state = Input(object, required=False, policy="latest", doc="measured robot state (locks)")
    command = Output(dict, doc="axis -> speed; the zero command unless in run")
    mode = Output(str, doc="the state machine's state")

    def setup(self) -> None:
        p = self.params
        self.names = list(p.axes)
        self.shaping = [p.axes[n] for n in self.names]
        n = len(self.names)
        self.out = [0.0] * n
        self.centre = [0.0] * n
        self.lo = [1.0] * n  # calibrated range below and above the centre
        self.hi = [1.0] * n
        self.locked = [a.lock is not None and a.lock.locked for a in self.shaping]
        self.status = p.initial_state
        self.last_t: float | None = None
        self.pressed: dict[str, bool] = {}
        self.transitions = 0
        self.refused = Refusals(
            "teleop-invalid", "joystick value refused: an axis is NaN, inf or not a number"
        )

    # --- helpers ------------------------------------------------------------------------

    def _period(self) -> float:
        timer = self.ctx.period
        return float(timer) if timer else 0.02

    def _timeout(self) -> float:
        if self.params.timeout_ms is not None:
            return self.params.timeout_ms / 1000
        return 3 * self._period()

    def _go(self, state: str, why: str) -> None:
        if state == self.status:
            return
        previous, self.status = self.status, state
        self.transitions += 1
        self.ctx.log.info("%s: %s -> %s (%s)", self.ctx.name, previous, state, why)
        self.ctx.emit(
            HealthAlert(
                self.ctx.elapsed(),
                self.ctx.name,
                "teleop-state",
                f"{previous} -> {state}: {why}",
                "info",
            )
        )

    def _clicked(self, buttons: Mapping[str, Any], name: str | None) -> bool:
        """A click is a press edge: held buttons do not repeat."""
        if not name:
            return False
        now = bool(buttons.get(name, False))
        before = self.pressed.get(name, False)
        self.pressed[name] = now
        return now and not before

    def _zero(self) -> dict[str, float]:
        for i in range(len(self.out)):
            self.out[i] = 0.0
        return dict.fromkeys(self.names, 0.0)

    # --- the tick -----------------------------------------------------------------------

    def process(self, joy: Any = None, state: Any = None) -> dict[str, Any]:
        now = self.ctx.now()
        dt = 0.0 if self.last_t is None else max(0.0, now - self.last_t)
        self.last_t = now
        p = self.params
        age = self.ctx.input_age("joy", joy) if joy is not None else None
        fresh = age is not None and age <= self._timeout()
        axes: Mapping[str, Any] = (_field(joy, "axes") or {}) if fresh else {}
        buttons: Mapping[str, Any] = (_field(joy, "buttons") or {}) if fresh else {}
        if fresh and not self._valid(axes, buttons):
            fresh, axes, buttons = False, {}, {}  # refused like a stale input: zero
            if self.status == "run":
                self._go("initialization", "invalid joystick value (NaN, inf or wrong type)")

        if fresh:
            self._press(axes, buttons)
        if self.status == "calibration":
            self._calibrate(axes)
        if self.status == "run":
            if not fresh:
                self._go("initialization", "input timeout or device lost")
            elif p.buttons.deadman and not buttons.get(p.buttons.deadman, False):
                self._go("initialization", "deadman released")
        deadman_ok = not p.buttons.deadman or bool(buttons.get(p.buttons.deadman, False))
        if self.status == "initialization" and fresh and deadman_ok and self._centred(axes):
            self._go("run", "every axis centred")
        if self.status != "run":
            return {"command": self._zero(), "mode": self.status}
        return {"command": self._shaped(axes, state, dt), "mode": self.status}

    def _press(self, axes: Mapping[str, Any], buttons: Mapping[str, Any]) -> None:
        """The buttons' clicks of a fresh input: stop, start (or end calibration), axis locks."""
        p = self.params
        start = self._clicked(buttons, p.buttons.start)
        if self._clicked(buttons, p.buttons.stop):
            self._go("idle", "stop button")
        elif start and self.status == "idle":
            self._go("calibration" if p.calibration else "initialization", "start button")
            if p.calibration:
                self._begin_calibration(axes)
        elif start and self.status == "calibration":
            self._go("initialization", "calibration done")
        for i, a in enumerate(self.shaping):
            if a.lock is not None and self._clicked(buttons, a.lock.button):
                self.locked[i] = not self.locked[i]

    def _valid(self, axes: Any, buttons: Any) -> bool:
        """Axes that are finite numbers and mappings where mappings belong; else one counted
        refusal per publication and one alert per burst (flowrt.refusals)."""
        ok = (
            isinstance(axes, Mapping)
            and isinstance(buttons, Mapping)
            and all(finite_number(axes.get(a.input, 0.0)) for a in self.shaping)
        )
        if ok:
            self.refused.accept()
        else:
            self.refused.refuse(self.ctx, self.ctx.input_time("joy"))
        return ok

    def report(self) -> dict[str, Any]:
        """What the statistics show of teleop (``reports``: table, --stats-json)."""
        return {
            "state": self.status,
            "transitions": self.transitions,
            "invalid": self.refused.count,
        }

    def _begin_calibration(self, axes: Mapping[str, Any]) -> None:
        for i, a in enumerate(self.shaping):
            v = axes.get(a.input)
            self.centre[i] = float(v) if isinstance(v, int | float) and math.isfinite(v) else 0.0
            self.lo[i] = self.hi[i] = 0.0

    def _calibrate(self, axes: Mapping[str, Any]) -> None:
        for i, a in enumerate(self.shaping):
            v = axes.get(a.input)
            if isinstance(v, int | float) and math.isfinite(v):
                d = float(v) - self.centre[i]
                if d > self.hi[i]:
                    self.hi[i] = d
                elif -d > self.lo[i]:
                    self.lo[i] = -d
        if self.status != "calibration":
            return

    def _span(self, i: int) -> tuple[float, float]:
        lo, hi = self.lo[i], self.hi[i]
        return (lo if lo > 0.05 else 1.0, hi if hi > 0.05 else 1.0)

    def _centred(self, axes: Mapping[str, Any]) -> bool:
        band = self.params.centre_band
        for i, a in enumerate(self.shaping):
            if self.locked[i]:
                continue
            v = axes.get(a.input, 0.0)
            if not isinstance(v, int | float) or not math.isfinite(v):
                return False
            if abs(float(v) - self.centre[i]) > band:
                return False
        return True

    def _shaped(self, axes: Mapping[str, Any], state: Any, dt: float) -> dict[str, float]:
        command: dict[str, float] = {}
        for i, a in enumerate(self.shaping):
            if self.locked[i] and a.lock is not None:
                target = a.lock.value
                measured = (
                    _field(state, a.lock.field) if state is not None and a.lock.field else None
                )
                if isinstance(measured, int | float) and math.isfinite(measured):
                    target = max(-a.scale, min(a.scale, a.lock.gain * (a.lock.value - measured)))
            else:
                raw = axes.get(a.input, 0.0)
                raw = float(raw) if isinstance(raw, int | float) else 0.0
                target = shape(raw, a, self.centre[i], self._span(i))
            if a.max_rate is not None:
                step = a.max_rate * dt
                prev = self.out[i]
                target = max(prev - step, min(prev + step, target))
            self.out[i] = target
            command[self.names[i]] = target
        return command
