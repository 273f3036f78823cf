"""The context a node on the event loop gets: the runtime's clock, frames, publishing.

A ``timing: precise`` node may be called from its release thread
(:mod:`flowrt.kernel.precise`): what its ``ctx`` changes on the runtime's side (publish,
emit, error state, modes, stop) is then handed to the loop with ``call_soon_threadsafe``,
in call order; ``new_frame`` is refused there (the frame pool belongs to the loop).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from ..events import Event, HealthAlert
from ..frames import Frame
from ..node import NodeContext
from .counters import Counters
from .outputs import OutputCheck
from .ports import SchedulerPort
from .timing import Timing


class ContextRunner(Protocol):
    """What a node's ``ctx`` reads of its runner (read-only: mypy refuses a write through
    it), and the runner's methods for what the node reports of itself (an error, a wait
    for an operator)."""

    @property
    def name(self) -> str: ...
    @property
    def sched(self) -> SchedulerPort: ...
    @property
    def timing(self) -> Timing: ...
    @property
    def input_times(self) -> dict[str, float]: ...
    @property
    def error_reason(self) -> str | None: ...
    @property
    def waiting_reason(self) -> str | None: ...
    @property
    def counts(self) -> Counters: ...

    def new_frame(self, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame: ...

    @property
    def out_check(self) -> OutputCheck: ...

    def publish(self, port: str, value: Any, t: float) -> None: ...

    def set_error_reason(self, reason: str | None) -> None: ...

    def set_waiting_reason(self, reason: str | None) -> None: ...


class RunnerContext(NodeContext):
    """``ctx`` of an inline node: every call goes to its runner or the runtime's services."""

    def __init__(self, runner: ContextRunner) -> None:
        super().__init__(runner.name)
        self._runner = runner
        self._loop_thread = threading.get_ident()  # made on the loop (make_executor)

    def _elsewhere(self, fn: Callable[..., Any], *args: Any) -> bool:
        """Called from a precise release thread: ``fn(*args)`` is handed to the loop."""
        if threading.get_ident() == self._loop_thread:
            return False
        self._runner.sched.loop.call_soon_threadsafe(fn, *args)
        return True

    def now(self) -> float:
        return self._runner.sched.clock.now()

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        if threading.get_ident() != self._loop_thread:
            raise RuntimeError(f"{self.name}: ctx.new_frame is not available in a precise thread")
        return self._runner.new_frame(shape, dtype, pixel_format)

    def publish(self, port: str, value: Any) -> None:
        """Raises :class:`~flowrt.kernel.outputs.OutputError` (the node's failure, from its
        ``process``) for a port it does not have or a value of another type than declared."""
        runner = self._runner
        runner.out_check.value(port, value)
        t = runner.sched.clock.now()
        if not self._elsewhere(runner.publish, port, value, t):
            runner.publish(port, value, t)

    def emit(self, event: Event) -> None:
        """Publish a typed event (e.g. a HealthAlert) to the runtime's monitors."""
        if not self._elsewhere(self._runner.sched.emit, event):
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
        if not self._elsewhere(setter, mode, f"node {self.name}"):
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
        observer.attach(sched.graph, sched)  # (it may take over from sched.observer)
        sched.observer = observer

    def request_stop(self) -> None:
        """Ask the runtime to stop (e.g. a video source at its end with on_eof: stop)."""
        stopper = self._runner.sched.services.request_stop
        if stopper is not None and not self._elsewhere(stopper):
            stopper()

    @property
    def period(self) -> float | None:
        return self._runner.timing.timer

    def input_time(self, name: str) -> float | None:
        return self._runner.input_times.get(name)

    def set_error(self, reason: str) -> None:
        if self._elsewhere(self.set_error, reason):
            return
        runner = self._runner
        if runner.error_reason == reason:
            return
        runner.set_error_reason(reason)
        sched = runner.sched
        sched.emit(
            HealthAlert(sched.rel(sched.clock.now()), self.name, "node-error", reason, "error")
        )

    @property
    def graph(self) -> Any:
        return self._runner.sched.graph

    def set_waiting(self, reason: str | None) -> None:
        if self._elsewhere(self.set_waiting, reason):
            return
        runner = self._runner
        if runner.waiting_reason == reason:
            return
        runner.set_waiting_reason(reason)
        if reason is not None:
            sched = runner.sched
            now = sched.rel(sched.clock.now())
            sched.emit(HealthAlert(now, self.name, "node-waiting", reason, "info"))

    def clear_error(self) -> None:
        if self._elsewhere(self.clear_error):
            return
        runner = self._runner
        if runner.error_reason is None:
            return
        runner.set_error_reason(None)
        sched = runner.sched
        sched.emit(
            HealthAlert(sched.rel(sched.clock.now()), self.name, "node-recovered", "", "info")
        )
