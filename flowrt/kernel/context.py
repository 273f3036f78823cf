"""The context a node on the event loop gets: the runtime's clock, frames, publishing."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from ..events import Event, HealthAlert
from ..frames import Frame
from ..node import NodeContext
from ..timing import Timing
from .counters import Counters
from .ports import SchedulerPort


class ContextRunner(Protocol):
    """What a node's ``ctx`` reads and changes of its runner."""

    name: str
    sched: SchedulerPort
    timing: Timing
    input_times: dict[str, float]
    error_reason: str | None
    counts: Counters

    def new_frame(self, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame: ...

    def publish(self, port: str, value: Any, t: float) -> None: ...


class RunnerContext(NodeContext):
    """``ctx`` of an inline node: every call goes to its runner or the runtime's services."""

    def __init__(self, runner: ContextRunner) -> None:
        super().__init__(runner.name)
        self._runner = runner

    def now(self) -> float:
        return self._runner.sched.clock.now()

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        return self._runner.new_frame(shape, dtype, pixel_format)

    def publish(self, port: str, value: Any) -> None:
        self._runner.publish(port, value, self._runner.sched.clock.now())

    def emit(self, event: Event) -> None:
        """Publish a typed event (e.g. a HealthAlert) to the runtime's monitors."""
        self._runner.sched.emit(event)

    def stats(self) -> Any:
        provider = self._runner.sched.services.stats
        if provider is None:
            raise RuntimeError("no statistics outside a Runtime")
        return provider()

    @property
    def rtdb(self) -> Any:
        provider = self._runner.sched.services.rtdb
        if provider is None:
            raise RuntimeError("no RTDB outside a Runtime")
        return provider()

    def set_mode(self, mode: str) -> None:
        setter = self._runner.sched.services.set_mode
        if setter is None:
            raise RuntimeError("no modes outside a Runtime")
        setter(mode, f"node {self.name}")

    def elapsed(self) -> float:
        """Seconds since the runtime started: the time base of events and statistics."""
        sched = self._runner.sched
        return sched.rel(sched.clock.now())

    async def wait_readers(self) -> None:
        """Wait until this node's period-1 frame readers can take a new frame (fast pacing)."""
        await self._runner.sched.wait_readers(self._runner)

    def observe(self, observer: Any) -> None:
        """Tell ``observer`` of every activation and publication from now on (what
        ``flowrt record --deterministic`` records; :mod:`flowrt.determinism`)."""
        sched = self._runner.sched
        sched.observer = observer
        observer.attach(sched.graph, sched)

    def request_stop(self) -> None:
        """Ask the runtime to stop (e.g. a video source at its end with on_eof: stop)."""
        stopper = self._runner.sched.services.request_stop
        if stopper is not None:
            stopper()

    @property
    def period(self) -> float | None:
        return self._runner.timing.timer

    def input_time(self, name: str) -> float | None:
        return self._runner.input_times.get(name)

    def set_error(self, reason: str) -> None:
        runner = self._runner
        if runner.error_reason == reason:
            return
        runner.error_reason = reason
        sched = runner.sched
        sched.emit(
            HealthAlert(sched.rel(sched.clock.now()), self.name, "node-error", reason, "error")
        )

    def clear_error(self) -> None:
        runner = self._runner
        if runner.error_reason is None:
            return
        runner.error_reason = None
        sched = runner.sched
        sched.emit(
            HealthAlert(sched.rel(sched.clock.now()), self.name, "node-recovered", "", "info")
        )
