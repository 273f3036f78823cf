"""What a re-executed node sees of the world: the recorded time, the recorded seed, nothing real.

``ctx.now()`` is the recorded start of the activation being replayed (before the first one, the
recorded clock's origin), ``ctx.input_time(port)`` the recorded publication time of the value
the port holds, ``ctx.random`` is seeded as in the recorded run. What a replay cannot give
back is refused the way a node outside a runtime is refused (``RuntimeError``): statistics,
the RTDB. Mode switches and errors a node asks for are noted, not acted on: the recorded run's
own changes are in the log and are applied from there.

In a worker process the same context is built by :class:`ReplayFactory`; the time and input
times of each call travel with its inputs under reserved names that the wrapper removes.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable
from random import Random
from typing import Any

import numpy as np
from pydantic import BaseModel

from ..frames import Frame
from ..node import Node, NodeContext, make_node, node_seed

__all__ = ["NOW_KEY", "TIMES_KEY", "ReplayContext", "ReplayFactory"]

NOW_KEY = "_flowrt_replay_now"
TIMES_KEY = "_flowrt_replay_input_times"

log = logging.getLogger("flowrt.determinism")


class ReplayContext(NodeContext):
    """A node's context during a deterministic replay (see the module docstring)."""

    def __init__(
        self,
        name: str,
        seed: str,
        origin: float,
        period: float | None = None,
        publish: Callable[[str, Any], None] | None = None,
    ) -> None:
        super().__init__(name)
        self.seed = seed
        self.origin = origin
        self.time = origin
        self.times: dict[str, float] = {}
        self._period = period
        self._publish = publish

    @property
    def random(self) -> Random:
        if self._random is None:
            self._random = Random(node_seed(self.name, self.seed))
        return self._random

    def now(self) -> float:
        return self.time

    def elapsed(self) -> float:
        return self.time - self.origin

    def input_time(self, name: str) -> float | None:
        return self.times.get(name)

    @property
    def period(self) -> float | None:
        return self._period

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        return Frame(np.empty(shape, dtype=dtype), source=self.name, pixel_format=pixel_format)

    def publish(self, port: str, value: Any) -> None:
        if self._publish is None:
            super().publish(port, value)
        else:
            self._publish(port, value)

    def emit(self, event: Any) -> None:
        log.debug("%s: event during replay: %s", self.name, event)

    def stats(self) -> Any:
        raise RuntimeError("no runtime statistics in a deterministic replay")

    @property
    def rtdb(self) -> Any:
        raise RuntimeError(
            f"{self.name}: no RTDB in a deterministic replay (another node's state read through "
            "it is not recorded)"
        )

    def set_mode(self, mode: str) -> None:
        log.debug("%s: set_mode(%s) during replay: the recorded changes apply", self.name, mode)

    def request_stop(self) -> None:
        """A replay ends with its recording."""

    def set_error(self, reason: str) -> None:
        log.debug("%s: error state during replay: %s", self.name, reason)

    def clear_error(self) -> None:
        """Nothing to clear: replay keeps no error state."""


class _Timed:
    """A node in a worker process whose context takes each call's time from its inputs."""

    def __init__(self, node: Node, ctx: ReplayContext) -> None:
        self.node = node
        self.ctx = ctx

    def setup(self) -> Any:
        return self.node.setup()

    def teardown(self) -> Any:
        return self.node.teardown()

    def process(self, **inputs: Any) -> Any:
        self.ctx.time = inputs.pop(NOW_KEY)
        self.ctx.times = inputs.pop(TIMES_KEY)
        return self.node.process(**inputs)


class ReplayFactory:
    """A picklable recipe for a replayed node in a worker process (like ``NodeFactory``)."""

    def __init__(
        self,
        cls: type[Node],
        params: BaseModel,
        name: str,
        seed: str,
        origin: float,
        period: float | None,
    ) -> None:
        self.cls, self.params, self.name = cls, params, name
        self.seed, self.origin, self.period = seed, origin, period

    def __call__(self) -> _Timed:
        ctx = ReplayContext(self.name, self.seed, self.origin, self.period)
        return _Timed(make_node(self.cls, self.params, ctx), ctx)


async def maybe_await(value: Any) -> Any:
    """``value``, awaited when a node's method returned an awaitable."""
    if inspect.isawaitable(value):
        return await value
    return value
