"""The ``can-signals`` node: signal values from simple waveforms, for a ``can`` node's input.

A simulated sensor for examples, tests and benchmarks (graphs/can.yaml drives the robot side
of its bus with it).
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from flowrt import Node, Output, TimerTrigger

__all__ = ["SignalSource", "SignalSourceParams", "Wave"]


class Wave(BaseModel):
    model_config = ConfigDict(extra="forbid")
    wave: Literal["const", "sine", "ramp", "count"] = "const"
    value: float = Field(default=0.0, description="const value, or the offset of the others")
    amplitude: float = 1.0
    period_s: float = Field(default=1.0, gt=0)
    modulo: int = Field(default=256, ge=1, description="count wraps here")


class SignalSourceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    signals: dict[str, Wave] = Field(description="signal name -> waveform")
    rate_ms: float = Field(default=100.0, gt=0, description="default timer trigger")


class SignalSource(Node):
    """Signal values for a ``can`` node input, from simple waveforms (a simulated sensor).

    Outputs a mapping ``{signal: value}`` per activation (default trigger: ``rate_ms``):
    ``const`` value, ``sine``/``ramp`` of ``amplitude`` and ``period_s`` around ``value``, or
    ``count`` (0, 1, 2, ... modulo ``modulo``), with the runtime clock as time base.
    """

    swappable = frozenset({"rate_ms"})  # over the control endpoint: flowrt kinds

    Params = SignalSourceParams
    values = Output(dict, doc="signal name -> value")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=params.rate_ms)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> dict[str, float]:
        t = self.ctx.elapsed()
        out: dict[str, float] = {}
        for name, w in self.params.signals.items():
            if w.wave == "const":
                out[name] = w.value
            elif w.wave == "sine":
                out[name] = w.value + w.amplitude * math.sin(2 * math.pi * t / w.period_s)
            elif w.wave == "ramp":
                out[name] = w.value + w.amplitude * ((t / w.period_s) % 1.0)
            else:
                out[name] = float(self.n % w.modulo)
        self.n += 1
        return out
