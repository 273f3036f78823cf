"""One actuator, several command sources: priority selection or a weighted blend.

The arbitration of the agent-based control system (several behaviours propose a command, a
weighted combination drives the motors) and twist_mux's priority rule, without their known
failure: with no fresh source, or a lock active, the output is the zero command on every
activation, never the last command repeated.

::

    drive:
      kind: arbiter
      trigger: {timer: 20ms}
      params:
        mode: priority                 # or: blend
        timeout: 200ms                 # older than this = not fresh
        sources: {joystick: {priority: 100}, planner: {priority: 10, weight: 1.0}}
        locks: [estop]                 # while fresh and true: zero command
        zero: {vx: 0.0, vy: 0.0, w: 0.0}
      inputs: {joystick: joy.command, planner: plan.command, estop: stop.output}

A source is *fresh* while its newest value is younger than ``timeout``: its age comes from the
value's own ``timestamp`` (an attribute or mapping key) when it has one, else from when the
arbiter first saw that value (inputs default to ``latest`` edges, so a value read again is the
same object). ``priority``: the fresh source with the highest priority wins. ``blend``: the
weighted sum of the fresh sources, weights renormalised over the fresh ones, each source
through its optional filters (``low_pass`` time constant, ``max_rate`` per second). Values are
mappings of the ``zero`` command's keys (missing keys count as 0; other keys are ignored).

Outputs on every activation: ``command`` (a mapping like ``zero``) and ``selected`` (the
winning source, ``"blend"``, or ``None``). A change of selected source is counted
(``switches``) and is an event (``HealthAlert`` of kind ``arbiter-switch``, severity info).
Modes set the weights between ticks (``modes: {avoid: {nodes: {drive: {params: {sources:
{avoid: {weight: 3}}}}}}}``): new params take effect at the next activation, filter state
kept.

The per-activation path reuses lists sized at set-up (one slot per source and per command
key); only the published ``command`` mapping is new, because readers may hold on to it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from flowrt import HealthAlert, Input, Node, Output, parse_duration_ms

__all__ = ["Arbiter", "SourceSpec"]


def _duration_s(v: Any) -> float:
    ms = parse_duration_ms(v) if isinstance(v, str) else float(v)
    if not math.isfinite(ms) or ms <= 0 or ms > 3_600_000:
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


class ArbiterParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["priority", "blend"] = "priority"
    timeout: float = Field(default=0.2, description="freshness window (duration, e.g. 200ms)")
    sources: dict[str, SourceSpec] = Field(min_length=1)
    locks: list[str] = Field(default_factory=list)
    zero: dict[str, float] = Field(min_length=1)

    @field_validator("timeout", mode="before")
    @classmethod
    def _timeout(cls, v: Any) -> Any:
        return _duration_s(v)

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
        return self


def _stamp(value: Any) -> float | None:
    t = value.get("timestamp") if isinstance(value, Mapping) else getattr(value, "timestamp", None)
    return float(t) if isinstance(t, int | float) and math.isfinite(t) else None


class Arbiter(Node):
    """Selects or blends the fresh command sources (see the module docstring)."""

    Params = ArbiterParams
    any_inputs = Input(object, required=False, policy="latest", doc="command sources and locks")
    command = Output(dict, doc="the command for the actuator: a mapping like `zero`")
    selected = Output(object, doc="the winning source, 'blend', or None")

    def setup(self) -> None:
        self.keys = list(self.params.zero)
        self.zero_values = [self.params.zero[k] for k in self.keys]
        self._size(list(self.params.sources))
        self.current: str | None = None
        self.switches = 0
        self.last_t: float | None = None
        self.acc = [0.0] * len(self.keys)

    def params_changed(self, old: Any) -> None:
        """A mode's weights arrive between activations; new sources need their slots."""
        if list(self.params.sources) != self.names:
            self._size(list(self.params.sources))

    def _size(self, names: list[str]) -> None:
        self.names = names
        n = len(names)
        self.seen: dict[str, tuple[int, float]] = {}  # source -> (id of value, first seen)
        self.filtered = [[z for z in self.zero_values] for _ in range(n)]
        self.fresh = [False] * n

    def _age_start(self, name: str, value: Any, now: float) -> float:
        stamp = _stamp(value)
        if stamp is not None:
            return stamp
        key = id(value)
        seen = self.seen.get(name)
        if seen is None or seen[0] != key:
            self.seen[name] = (key, now)
            return now
        return seen[1]

    def _is_fresh(self, name: str, value: Any, now: float) -> bool:
        if value is None:
            return False
        return now - self._age_start(name, value, now) <= self.params.timeout

    def process(self, **inputs: Any) -> dict[str, Any]:
        now = self.ctx.now()
        dt = 0.0 if self.last_t is None else max(0.0, now - self.last_t)
        self.last_t = now
        p = self.params
        locked = False
        for lock in p.locks:
            value = inputs.get(lock)
            if self._is_fresh(lock, value, now) and _truthy(value):
                locked = True
        winner: str | None = None
        if not locked:
            for i, name in enumerate(self.names):
                value = inputs.get(name)
                self.fresh[i] = self._is_fresh(name, value, now) and isinstance(value, Mapping)
                if self.fresh[i]:
                    self._filter(i, p.sources[name], value, dt)
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

    def _filter(self, i: int, spec: SourceSpec, value: Mapping[str, Any], dt: float) -> None:
        out = self.filtered[i]
        for j, key in enumerate(self.keys):
            raw = value.get(key, 0.0)
            x = float(raw) if isinstance(raw, int | float) and math.isfinite(raw) else 0.0
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


def _truthy(value: Any) -> bool:
    if isinstance(value, Mapping):
        for key in ("active", "value", "pressed"):
            if key in value:
                return bool(value[key])
        return bool(value)
    return bool(value)
