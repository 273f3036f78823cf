"""Small general-purpose nodes: a counter source, a CPU burner, a relay and a sink.

Useful to try timing out, and as the workload of benchmarks and tests.
"""

from __future__ import annotations

import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from flowrt import Input, Node, Output


class Counter(Node):
    """Emits 0, 1, 2, ... once per activation (give it a timer trigger)."""

    swappable = frozenset({"start"})  # over the control endpoint: flowrt kinds

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        start: int = 0

    value = Output(int)

    def setup(self) -> None:
        self.n = self.params.start

    def process(self) -> int:
        n = self.n
        self.n += 1
        return n


class Burn(Node):
    """Keeps the CPU busy for ``ms`` (not a sleep), then passes its input through."""

    swappable = frozenset({"ms"})  # over the control endpoint: flowrt kinds

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
        ms: float = Field(1.0, ge=0, le=60_000, description="CPU time per call, ms")

    input = Input(object, required=False)
    output = Output(object)

    def process(self, input: Any) -> Any:
        end = time.perf_counter() + self.params.ms / 1000
        while time.perf_counter() < end:
            pass
        return input


class Relay(Node):
    """Passes its input through unchanged: a hop in a chain."""

    input = Input(object)
    output = Output(object)

    def process(self, input: Any) -> Any:
        return input


class Sink(Node):
    """Counts what arrives and optionally logs it."""

    swappable = frozenset({"log"})  # over the control endpoint: flowrt kinds

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        log: bool = False

    input = Input(object)

    def setup(self) -> None:
        self.received = 0

    def process(self, input: Any) -> None:
        self.received += 1
        if self.params.log:
            self.ctx.log.info("%s: %r", self.ctx.name, input)
