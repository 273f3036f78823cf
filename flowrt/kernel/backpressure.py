"""A producer whose lossless readers are full waits for them: it does not drop.

``lossless`` edges deliver every value (a recorder, a CAN writer): when one is full, the
value is held by the producer, which stays busy (its next releases are overruns, counted)
until the reader has taken enough to make room. Results of pipelined calls that complete
meanwhile wait too, so that values keep their order.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from ..edges import LosslessBuffer, hold
from .activation import release_all


class Backpressure:
    """The values one producer holds for its full lossless readers.

    Invariant: ``blocked`` is non-empty only while ``draining`` (a drain task runs), and the
    runner stays busy until it is empty; each held value carries one link of its own
    (:func:`flowrt.edges.hold`), given back once it is in its buffer or abandoned.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, then: Callable[[], None]) -> None:
        self._loop = loop
        self._then = then  # the runner's idle(): called when everything is in
        self.blocked: list[tuple[LosslessBuffer, Any, float]] = []
        self.draining = False
        self.task: asyncio.Task[None] | None = None
        self._drained: asyncio.Event | None = None

    def hold(self, buf: LosslessBuffer, value: Any, t: float) -> None:
        hold(value)
        self.blocked.append((buf, value, t))

    def start(self) -> None:
        """Deliver the held values in the background, then make the runner idle."""
        if not self.draining:
            self.draining = True
            self.task = self._loop.create_task(self._drain_then_idle())

    async def wait_turn(self) -> None:
        """A result that completes while values are held waits for them (order kept)."""
        if self.draining:
            if self._drained is None:
                self._drained = asyncio.Event()
            await self._drained.wait()

    async def _drain_then_idle(self) -> None:
        try:
            while self.blocked:
                buf, value, t = self.blocked[0]
                await buf.wait_space()
                buf.put(value, t)
                self.blocked.pop(0)
                release_all([value])
        finally:
            self.draining = False
            if self._drained is not None:
                self._drained.set()
                self._drained = None
        self._then()

    def abandon(self, reason: str) -> None:
        """At stop: what is still held is counted as dropped with ``reason``."""
        for buf, value, _ in self.blocked:
            buf.abandon(value, reason)
        self.blocked = []
