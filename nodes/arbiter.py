"""One actuator, several command sources: priority selection or a weighted blend.

The arbitration of the agent-based control system (several behaviours propose a command, a
weighted combination drives the motors) and twist_mux's priority rule, without their known
failures: with no fresh source, or a lock engaged, the output is the zero command on every
activation, never the last command repeated; a stop published once stays a stop.

::

    drive:
      kind: arbiter
      trigger: {timer: 20ms}
      params:
        mode: priority                 # or: blend
        timeout: 200ms                 # older than this = not fresh
        sources: {joystick: {priority: 100}, planner: {priority: 10, weight: 1.0}}
        locks: {estop: {heartbeat: 300ms}}   # or the list form: locks: [estop]
        zero: {vx: 0.0, vy: 0.0, w: 0.0}
        limits: {vx: [-0.5, 1.5], vy: 0.5, w: 2.0}   # clamped (counted); default ±100
      inputs: {joystick: joy.command, planner: plan.command, estop: stop.output}

Safety rules (proven by property tests on virtual time, tests/test_safety_arbiter.py):

- **Fresh** means published on the arbiter's input edge less than ``timeout`` ago, by the
  runtime clock (:meth:`flowrt.NodeContext.input_age`); a value's own ``timestamp`` can only
  make it older (one from another machine's clock, in the future, is ignored). Never the
  value's identity: a source publishing the same object every tick stays fresh.
- **Locks latch**: a lock holds its last value until a new one arrives (``True`` published once
  keeps the zero command until ``False`` is published). A lock never heard yet is engaged
  (zero) until its first false value, unless its spec says ``initial: released``.
- **Heartbeat locks** (``locks: {estop: {heartbeat: 300ms}}``): the lock also engages when its
  source has published nothing for longer than ``heartbeat`` (a dead e-stop node stops the
  robot), and releases when it publishes a false value again.
- **Commands are clamped to documented limits**: each key of a command within ``limits``
  (``vx: [-1.5, 1.5]``, or ``vx: 1.5``), keys not named within ``±default_limit`` (100:
  no robot command in SI units is near it, ``vx: 1e300`` is); a clamped command is counted
  per source (``clamped`` in :meth:`Arbiter.report`) with one ``HealthAlert`` (kind
  ``arbiter-clamped``) per burst.
- **A missed heartbeat may need a deliberate release** (``locks: {estop: {heartbeat: 300ms,
  after_silence: hold}}``): a lock engaged because its source fell silent (a link cut, a dead
  station) stays engaged when the source comes back still saying "released"; only a *new*
  release frees it: a value whose ``release`` id differs from the one last heard before the
  silence (the ``estop`` node gives every release by the operator an id of its own), or, for
  a source of plain booleans, a false value after a true one. The same holds from the start:
  a release the arbiter did not see being made (the first value it hears already says
  released: a restarted robot, a station released long ago) does not free it. ``resume``
  (the default) releases on the first false value.
- **Invalid commands are refused**: a command with NaN/inf or a key of the wrong type is not a
  fresh command; the arbiter falls back to the next source (or zero), counts it per source
  (``invalid`` in :meth:`Arbiter.report`, so in the statistics' ``reports``) and raises one
  ``HealthAlert`` (kind ``arbiter-invalid``) per burst, not per tick.

``priority``: the fresh source with the highest priority wins. ``blend``: the weighted sum of
the fresh sources, weights renormalised over the fresh ones, each source through its optional
filters (``low_pass`` time constant, ``max_rate`` per second). Values are mappings of the
``zero`` command's keys (missing keys count as 0; other keys are ignored).

Outputs on every activation: ``command`` (a mapping like ``zero``); and ``selected`` (the
winning source or ``"blend"``), on every activation that has one: while no source is valid
nothing is published there (the command is ``zero``), so the recording expects no rate of
it. A change of selected source is counted (``switches``) and is an event (``HealthAlert``
of kind ``arbiter-switch``, severity info). Modes set the weights between ticks
(``modes: {avoid: {nodes: {drive: {params: {sources: {avoid: {weight: 3}}}}}}}``): new
params take effect at the next activation, filter state kept.

The per-activation path reuses lists sized at set-up (one slot per source and per command
key); only the published ``command`` mapping is new, because readers may hold on to it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from flowrt import HealthAlert, Input, Node, Output, parse_duration_ms
from flowrt.refusals import Refusals, finite_number

__all__ = ["Arbiter", "LockSpec", "SourceSpec", "valid_command"]


def _duration_s(v: Any) -> float:
    """A duration param (``200ms``, ``1.5s``, a bare number of ms) in seconds, (0, 1 h].

    ``parse_duration_ms`` turns null, lists, mappings and 10**400 into a located error."""
    ms = parse_duration_ms(v)
    if ms <= 0 or ms > 3_600_000:
        raise ValueError("must be a duration between 0 and 1 h, e.g. 200ms")
    return ms / 1000


class SourceSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    priority: int = Field(default=0, ge=0, le=1000)
    weight: float = Field(default=1.0, ge=0, le=1e6, allow_inf_nan=False)
    low_pass: float | None = Field(
        default=None, description="time constant (duration) of a first-order low-pass filter"
    )
    max_rate: float | None = Field(
        default=None, gt=0, le=1e6, allow_inf_nan=False, description="units per second"
    )

    @field_validator("low_pass", mode="before")
    @classmethod
    def _tau(cls, v: Any) -> Any:
        return None if v is None else _duration_s(v)


class LockSpec(BaseModel):
    """One lock: engaged while its last value is true (latched), before its first value
    unless ``initial: released``, and when silent for longer than ``heartbeat``."""

    model_config = ConfigDict(extra="forbid")
    heartbeat: float | None = Field(
        default=None,
        description="engage when the lock's source published nothing for this long (duration)",
    )
    initial: Literal["engaged", "released"] = Field(
        default="engaged", description="the lock's state before its first value"
    )
    after_silence: Literal["resume", "hold"] = Field(
        default="resume",
        description="after a missed heartbeat: resume (a false value releases) or hold "
        "(engaged until a new release: a new release id, or true then false)",
    )

    @field_validator("heartbeat", mode="before")
    @classmethod
    def _heartbeat(cls, v: Any) -> Any:
        return None if v is None else _duration_s(v)


class ArbiterParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["priority", "blend"] = "priority"
    timeout: float = Field(default=0.2, description="freshness window (duration, e.g. 200ms)")
    sources: dict[str, SourceSpec] = Field(min_length=1)
    locks: dict[str, LockSpec] = Field(
        default_factory=dict,
        description="inputs that force the zero command: a list of names, or a mapping of "
        "name -> {heartbeat, initial}",
    )
    zero: dict[str, float] = Field(min_length=1)
    limits: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="per command key: [min, max], or a number m for [-m, m]; a command "
        "beyond them is clamped (counted). Keys not named: [-default_limit, default_limit]",
    )
    default_limit: float = Field(
        default=100.0, gt=0, le=1e6, allow_inf_nan=False, description="see limits"
    )

    @field_validator("limits", mode="before")
    @classmethod
    def _symmetric(cls, v: Any) -> Any:
        """``vx: 1.5`` is ``vx: [-1.5, 1.5]``."""
        if isinstance(v, Mapping):
            return {k: (-m, m) if finite_number(m) and m > 0 else m for k, m in v.items()}
        return v

    @field_validator("limits")
    @classmethod
    def _ordered(cls, v: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        for key, (lo, hi) in v.items():
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"{key}: limits are [min, max], finite, min <= max")
        return v

    def bounds(self, key: str) -> tuple[float, float]:
        """The range a command's ``key`` is clamped to."""
        return self.limits.get(key, (-self.default_limit, self.default_limit))

    @field_validator("timeout", mode="before")
    @classmethod
    def _timeout(cls, v: Any) -> Any:
        return _duration_s(v)

    @field_validator("locks", mode="before")
    @classmethod
    def _lock_list(cls, v: Any) -> Any:
        """The list form (``locks: [estop]``) is a mapping of default lock specs."""
        if isinstance(v, list | tuple):
            if not all(isinstance(name, str) for name in v):
                raise ValueError("locks: a list of input names, or a mapping name -> options")
            return {name: {} for name in v}
        if isinstance(v, Mapping):
            return {k: ({} if spec is None else spec) for k, spec in v.items()}
        return v

    @field_validator("zero")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        if not all(math.isfinite(x) for x in v.values()):
            raise ValueError("zero command values must be finite")
        return v

    @model_validator(mode="after")
    def _disjoint(self) -> ArbiterParams:
        both = set(self.sources) & set(self.locks)
        if both:
            raise ValueError(f"{sorted(both)} cannot be both a source and a lock")
        outside = [
            k for k, x in self.zero.items() if not self.bounds(k)[0] <= x <= self.bounds(k)[1]
        ]
        if outside:
            raise ValueError(f"zero command outside its limits: {', '.join(outside)}")
        return self


def valid_command(value: Any, keys: list[str]) -> bool:
    """A command the actuator may get: a mapping whose ``keys`` (when present) are finite
    numbers. NaN, inf, a string or a bool where a speed belongs make the whole value invalid."""
    return isinstance(value, Mapping) and all(
        finite_number(value[key]) for key in keys if key in value
    )


class _SourceState:
    """What the arbiter keeps per source: its refusals, clamped commands, stale activations."""

    __slots__ = ("clamped", "refused", "stale")

    def __init__(self, name: str) -> None:
        self.refused = Refusals(
            "arbiter-invalid",
            f"source {name}: a command with a non-finite or wrong-type value refused",
        )
        self.clamped = Refusals(
            "arbiter-clamped", f"source {name}: a command beyond the limits clamped"
        )
        self.stale = 0  # activations where the source held a value older than timeout


class Arbiter(Node):
    """Selects or blends the fresh command sources (see the module docstring)."""

    # over the control endpoint (flowrt kinds): weights and priorities, as modes set them;
    # never what keeps the robot safe (timeout, locks, zero, limits)
    swappable = frozenset({"mode", "sources"})
    # disabled or slowed over the control endpoint, the robot kept its last command (a mode or
    # a program disabling it: on_disable publishes the zero command)
    timing_fixed = True

    Params = ArbiterParams
    any_inputs = Input(object, required=False, policy="latest", doc="command sources and locks")
    command = Output(dict, doc="the command for the actuator: a mapping like `zero`")
    # not every activation: nothing is published while no source is valid (a None result)
    selected = Output(
        object, doc="the winning source or 'blend'; nothing while none is valid", rate_hz=None
    )

    def setup(self) -> None:
        self.keys = list(self.params.zero)
        self.zero_values = [self.params.zero[k] for k in self.keys]
        self.bounds = [self.params.bounds(k) for k in self.keys]
        self._size(list(self.params.sources))
        self.current: str | None = None
        self.switches = 0
        self.last_t: float | None = None
        self.started: float | None = None  # first activation: a silent lock's age from here
        self.acc = [0.0] * len(self.keys)
        # Invariant: a lock name is present once a value was received on it; its value is
        # the truth of the last value received (latched until a new one arrives).
        self.latched: dict[str, bool] = {}
        self.engaged: dict[str, bool] = {}
        # after_silence: hold. Invariant: a lock is in ``held`` from a missed heartbeat until
        # a new release; ``held[name]`` is the release id last heard before the silence, and
        # ``armed`` says a true value came since (a plain boolean's false then releases).
        # A held lock starts held (``_FIRST``): the first value heard sets the release id it
        # waits to see change; a release from before this start (a restarted robot hearing a
        # station released long ago) is not one.
        self.release_id: dict[str, Any] = {}
        self.held: dict[str, Any] = {
            name: _FIRST
            for name, spec in self.params.locks.items()
            if spec.after_silence == "hold" and spec.initial == "engaged"
        }
        self.armed: set[str] = set()
        self.lock_refused: dict[str, Refusals] = {}  # lock values neither true nor false

    def params_changed(self, old: Any) -> None:
        """A mode's weights arrive between activations; new sources need their slots."""
        self.bounds = [self.params.bounds(k) for k in self.keys]
        if list(self.params.sources) != self.names:
            self._size(list(self.params.sources))

    def _size(self, names: list[str]) -> None:
        self.names = names
        n = len(names)
        self.filtered = [[z for z in self.zero_values] for _ in range(n)]
        self.fresh = [False] * n
        old = getattr(self, "sources", {})
        self.sources: dict[str, _SourceState] = {k: old.get(k) or _SourceState(k) for k in names}

    # --- locks ----------------------------------------------------------------------------

    def _lock_engaged(self, name: str, spec: LockSpec, value: Any, now: float) -> bool:
        if value is not None:
            flag = _flag(value)
            refusals = self.lock_refused.setdefault(
                name, Refusals("arbiter-invalid-lock", f"lock {name}: not a true or false value")
            )
            if flag is None:  # {}, [], "", 0.0, {"active": None} released it (truthiness)
                refusals.refuse(self.ctx, self.ctx.input_time(name))
            else:
                refusals.accept()
            self.latched[name] = True if flag is None else flag  # malformed: engaged
            self._heard(name, value)
        engaged = self.latched.get(name, spec.initial == "engaged")
        if spec.heartbeat is not None and not engaged:
            age = self.ctx.input_age(name)
            if age is None:  # never heard: silent since the first activation
                age = now - (self.started if self.started is not None else now)
            engaged = age > spec.heartbeat
            if engaged and spec.after_silence == "hold" and name not in self.held:
                self.held[name] = self.release_id.get(name)
                self.armed.discard(name)
        engaged = engaged or name in self.held
        self.engaged[name] = engaged
        return engaged

    def _heard(self, name: str, value: Any) -> None:
        """A value on a held lock: a new release (a new id, or false after true) frees it."""
        rid = value.get("release") if isinstance(value, Mapping) else None
        if name in self.held and self.held[name] is _FIRST:  # the first value: the baseline
            self.held[name] = rid
            if self.latched[name]:
                self.armed.add(name)
        elif name in self.held and not self.latched[name]:
            if (rid is not None and rid != self.held[name]) or name in self.armed:
                del self.held[name]
                self.armed.discard(name)
        elif name in self.held:
            self.armed.add(name)
        if rid is not None:
            self.release_id[name] = rid

    # --- sources --------------------------------------------------------------------------

    def _fresh_valid(self, name: str, value: Any) -> bool:
        if value is None:
            return False
        age = self.ctx.input_age(name, value)
        state = self.sources[name]
        if age is None or age > self.params.timeout:
            state.stale += 1
            return False
        if valid_command(value, self.keys):
            state.refused.accept()
            return True
        state.refused.refuse(self.ctx, self.ctx.input_time(name))
        return False

    def process(self, **inputs: Any) -> dict[str, Any]:
        now = self.ctx.now()
        if self.started is None:
            self.started = now
        dt = 0.0 if self.last_t is None else max(0.0, now - self.last_t)
        self.last_t = now
        p = self.params
        locked = False
        for lock, spec in p.locks.items():  # every lock is evaluated: each one latches
            if self._lock_engaged(lock, spec, inputs.get(lock), now):
                locked = True
        winner: str | None = None
        if not locked:
            for i, name in enumerate(self.names):
                value = inputs.get(name)
                self.fresh[i] = self._fresh_valid(name, value)
                if self.fresh[i]:
                    self._filter(i, p.sources[name], self._clamp(name, value), dt)
                else:  # a source coming back starts from zero, not from its old filter state
                    self.filtered[i][:] = self.zero_values
            winner = self._priority() if p.mode == "priority" else self._blend()
        else:
            self.fresh[:] = [False] * len(self.names)
        self._switch(winner)
        if winner is None:
            return {"command": dict(p.zero), "selected": None}
        if winner == "blend":
            return {"command": dict(zip(self.keys, self.acc, strict=True)), "selected": "blend"}
        i = self.names.index(winner)
        return {"command": dict(zip(self.keys, self.filtered[i], strict=True)), "selected": winner}

    def on_disable(self) -> dict[str, Any]:
        """Disabled (a mode, ``Runtime.set_timing``): the zero command, once; the actuator's
        driver (a CAN transmitter resending its last value) otherwise kept the last command
        for as long as the arbiter stayed disabled. Every source starts from zero again."""
        for row in self.filtered:
            row[:] = self.zero_values
        self._switch(None)
        return {"command": dict(self.params.zero), "selected": None}

    def report(self) -> dict[str, Any]:
        """What the statistics show of the arbiter (``reports``: table, --stats-json)."""
        return {
            "selected": self.current,
            "switches": self.switches,
            "locks": dict(self.engaged),
            "held": sorted(self.held),  # engaged by a missed heartbeat, waiting for a release
            "sources": {
                name: {"invalid": st.refused.count, "clamped": st.clamped.count, "stale": st.stale}
                for name, st in self.sources.items()
            },
            "invalid": sum(st.refused.count for st in self.sources.values()),
            "locks_invalid": {name: r.count for name, r in self.lock_refused.items() if r.count},
            "clamped": sum(st.clamped.count for st in self.sources.values()),
        }

    def _clamp(self, name: str, value: Mapping[str, Any]) -> Mapping[str, Any]:
        """``value`` within the limits; a clamp is counted once per publication of it."""
        out: dict[str, Any] | None = None
        for j, key in enumerate(self.keys):
            if key in value:
                lo, hi = self.bounds[j]
                x = value[key]
                if not lo <= x <= hi:
                    if out is None:
                        out = dict(value)
                    out[key] = min(hi, max(lo, float(x)))
        state = self.sources[name].clamped
        if out is None:
            state.accept()
            return value
        state.refuse(self.ctx, self.ctx.input_time(name))
        return out

    def _filter(self, i: int, spec: SourceSpec, value: Mapping[str, Any], dt: float) -> None:
        out = self.filtered[i]
        for j, key in enumerate(self.keys):
            x = float(value.get(key, 0.0))  # valid_command: a finite number or absent
            if spec.low_pass is not None:
                a = dt / (spec.low_pass + dt)
                x = out[j] + a * (x - out[j])
            if spec.max_rate is not None:
                step = spec.max_rate * dt
                x = max(out[j] - step, min(out[j] + step, x))
            out[j] = x

    def _priority(self) -> str | None:
        best: str | None = None
        best_p = -1
        for i, name in enumerate(self.names):
            prio = self.params.sources[name].priority
            if self.fresh[i] and prio > best_p:
                best, best_p = name, prio
        return best

    def _blend(self) -> str | None:
        total = 0.0
        acc = self.acc
        acc[:] = [0.0] * len(self.keys)
        for i, name in enumerate(self.names):
            if not self.fresh[i]:
                continue
            w = self.params.sources[name].weight
            total += w
            row = self.filtered[i]
            for j in range(len(acc)):
                acc[j] += w * row[j]
        if total <= 0:
            return None
        for j in range(len(acc)):
            acc[j] /= total
        return "blend"

    def _switch(self, winner: str | None) -> None:
        if winner == self.current:
            return
        previous, self.current = self.current, winner
        self.switches += 1
        self.ctx.emit(
            HealthAlert(
                self.ctx.elapsed(),
                self.ctx.name,
                "arbiter-switch",
                f"{previous} -> {winner}",
                "info",
            )
        )


_FIRST = object()  # a held lock before its first value (see Arbiter.setup)


def _flag(value: Any) -> bool | None:
    """A lock value as true or false: a bool, the integers 1 and 0, or a mapping's
    ``active``, ``value`` or ``pressed`` (the first present) as one of those; None for
    anything else, which keeps the lock engaged (only a false value releases it)."""
    if isinstance(value, Mapping):
        key = next((k for k in ("active", "value", "pressed") if k in value), None)
        return None if key is None else _flag(value[key])
    if isinstance(value, bool):
        return value
    if type(value) is int and value in (0, 1):
        return bool(value)
    return None
