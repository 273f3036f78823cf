"""Testing a node's logic without a runtime: ``harness = NodeHarness(MyNode, {"level": 3})``.

A node author wants to feed inputs and look at outputs and events, with no event loop, no
graph file and no timing; the harness gives the node the same context calls it has in a
runtime (``now``, ``new_frame``, ``emit``, ``publish``), recorded for assertions.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from types import SimpleNamespace
from typing import Any

import numpy as np
from pydantic import BaseModel

from .events import Event
from .frames import Frame
from .kernel.outputs import OutputCheck
from .node import Node, NodeContext, make_node

_NOTHING = object()


class HarnessContext(NodeContext):
    """Records what the node publishes and emits; time is set by the test."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.time = 0.0
        self.published: list[tuple[str, Any]] = []
        self.events: list[Event] = []
        self.error: str | None = None  # what set_error() said, until clear_error()
        self.waiting: str | None = None  # what set_waiting() said
        self.timer_period: float | None = None  # what ``period`` answers (seconds)
        # Publication time of each input's value, as an edge would stamp it: set by
        # NodeHarness.process (a new object = published now) or by the test directly.
        self.input_times: dict[str, float] = {}

    def now(self) -> float:
        return self.time

    def elapsed(self) -> float:
        return self.time

    @property
    def period(self) -> float | None:
        return self.timer_period

    def input_time(self, name: str) -> float | None:
        return self.input_times.get(name)

    def set_error(self, reason: str) -> None:
        self.error = reason

    def clear_error(self) -> None:
        self.error = None

    def set_waiting(self, reason: str | None) -> None:
        self.waiting = reason

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        return Frame(np.zeros(shape, dtype=dtype), source=self.name, pixel_format=pixel_format)

    def publish(self, port: str, value: Any) -> None:
        self.published.append((port, value))

    def emit(self, event: Any) -> None:
        self.events.append(event)


class NodeHarness:
    """Runs one node's ``setup``/``process``/``teardown`` directly (async ones too)."""

    def __init__(
        self,
        cls: type[Node],
        params: BaseModel | Mapping[str, Any] | None = None,
        name: str = "node",
    ) -> None:
        self.ctx = HarnessContext(name)
        self._held: dict[str, Any] = {}  # the value each input was last given (see process)
        self.node = make_node(cls, params, self.ctx)
        # what process returns is checked as the runtime checks it (a port it does not have,
        # a value of another type): {'scor': 1.0} passed here and failed the run
        ports = [*cls.outputs, *cls.params_outputs(self.node.params)]
        self._outputs = OutputCheck(SimpleNamespace(cls=cls), ports)  # type: ignore[arg-type]
        self._run(self.node.setup())

    def process(self, **inputs: Any) -> Any:
        """Call ``process`` once; unconnected optional inputs are passed as None.

        Publication times follow a ``latest`` edge: a value passed again (the same object) keeps
        the time it was first passed at; any other value is published at ``ctx.time``. To
        publish the same object anew (a source re-sending a constant), call :meth:`publish`.
        """
        for port in type(self.node).inputs:
            inputs.setdefault(port, None)
        for port, value in inputs.items():
            if value is None:
                self.ctx.input_times.pop(port, None)
                self._held.pop(port, None)
            elif self._held.get(port, _NOTHING) is not value or port not in self.ctx.input_times:
                self.ctx.input_times[port] = self.ctx.time
                self._held[port] = value
        result = self._run(self.node.process(**inputs))
        if result is not None and self._outputs.ports:
            self._outputs.result(result)  # OutputError, as in a run
        return result

    def publish(self, port: str, value: Any, t: float | None = None) -> None:
        """Mark ``value`` as newly published on input ``port`` at ``t`` (default now)."""
        self._held[port] = value
        self.ctx.input_times[port] = self.ctx.time if t is None else t

    def teardown(self) -> None:
        self._run(self.node.teardown())

    @staticmethod
    def _run(result: Any) -> Any:
        if inspect.isawaitable(result):
            import asyncio

            async def wait() -> Any:
                return await result

            return asyncio.run(wait())
        return result
