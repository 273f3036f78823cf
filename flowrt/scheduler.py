"""The frame-tick scheduler: releases nodes on frame ticks, timers and inputs; watches deadlines.

One ``NodeRunner`` per node owns its timing, buffers, statistics and supervision. The
``Scheduler`` owns the frame clocks (one tick counter per frame source), the timers and the
order of dispatch (priority, then file order). Everything runs on one event loop, so a change
made by ``set_timing`` between two callbacks is atomic with respect to ticks.

Activation semantics (the CAMBADA process manager):
- frame trigger: on tick ``k`` of the source, release when ``k % period == phase``;
- timer trigger: release at ``origin + phase + n*period`` (timerfd, no drift);
- input trigger: release when a triggering input receives data; never re-entrant: data that
  arrives meanwhile waits in the buffer and causes one more activation afterwards;
- a release while the previous activation still runs is skipped and counted (overrun).
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import logging
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel

from .clock import Clock, Handle, PeriodicTimer
from .edges import EMPTY, Buffer, LatestBuffer, LosslessBuffer, hold, make_buffer
from .events import (
    DeadlineMissed,
    Event,
    HealthAlert,
    LoopBlocked,
    NodeFailed,
    NodeGaveUp,
    NodeRestarted,
    TimingChanged,
)
from .frames import Frame, release_handoffs
from .graph import Graph, ResolvedNode, checked_type
from .node import Node, NodeContext, NodeFactory, make_node
from .spec import FrameTrigger, InputTrigger, LoopTrigger, MissPolicy, Placement, TimerTrigger
from .stats import NodeStats, Running
from .supervision import FailureLog, backoff_s, failure_kind, give_up_reason, out_of_resources

log = logging.getLogger("flowrt.scheduler")

BLOCKING_THRESHOLD = 0.010  # an inline call longer than this is reported as blocking the loop
SWAP_WAIT = 5.0  # seconds a swap waits for the running activation to end
PIPELINE_WINDOW = 4  # activations in flight to a worker node fed by queues (spec: pipeline)
PACED_WINDOW = 2  # frames of a pacing: fast source in flight to a worker reader (spec: pipeline)


class Executor:
    """Where ``process`` runs: inline on the loop here; worker processes in flowrt.workers."""

    sync = False
    granted = ""
    pipelined = False  # submit() available: calls may overlap (a worker of its own)

    async def start(self) -> None: ...

    def call_sync(self, inputs: dict[str, Any]) -> Any:
        raise NotImplementedError

    async def call(self, inputs: dict[str, Any]) -> Any:
        raise NotImplementedError

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        """Start a call now; up to ``window`` run back to back in order (see run_pipelined)."""
        raise NotImplementedError

    async def stop(self) -> None: ...


class InlineExecutor(Executor):
    def __init__(self, factory: Callable[[], Node]) -> None:
        self._factory = factory
        self.node: Node | None = None
        self.last_node: Node | None = None
        self.sync = False

    async def start(self) -> None:
        node = self._factory()
        self.node = node
        self.sync = not inspect.iscoroutinefunction(node.process)
        result = node.setup()
        if inspect.isawaitable(result):
            await result

    def call_sync(self, inputs: dict[str, Any]) -> Any:
        assert self.node is not None
        return self.node.process(**inputs)

    async def call(self, inputs: dict[str, Any]) -> Any:
        assert self.node is not None
        result = self.node.process(**inputs)
        if inspect.isawaitable(result):
            result = await result
        return result

    async def stop(self) -> None:
        node, self.node = self.node, None
        self.last_node = node  # what it reported last stays readable after stop
        if node is not None:
            result = node.teardown()
            if inspect.isawaitable(result):
                await result


@dataclass
class Timing:
    """A node's run-time adjustable timing (what the QoS manager changes)."""

    period: int  # frames, for frame triggers
    phase: int
    timer: float | None  # seconds, for timer triggers
    timer_phase: float
    deadline: float | None  # seconds
    priority: int
    enabled: bool

    def describe_period(self) -> str:
        if self.timer is not None:
            return f"{self.timer * 1000:g}ms+{self.timer_phase * 1000:g}"
        return f"{self.period}/{self.phase}"


class RunnerContext(NodeContext):
    """The context of a node on the event loop: runtime clock, frame pool, publishing."""

    def __init__(self, runner: NodeRunner) -> None:
        super().__init__(runner.name)
        self._runner = runner

    def now(self) -> float:
        return self._runner.sched.clock.now()

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        frame = self._runner.sched.new_frame(self.name, shape, dtype, pixel_format)
        self._runner.created.append(frame)
        return frame

    def publish(self, port: str, value: Any) -> None:
        self._runner.publish(port, value, self._runner.sched.clock.now())

    def emit(self, event: Event) -> None:
        """Publish a typed event (e.g. a HealthAlert) to the runtime's monitors."""
        self._runner.sched.emit(event)

    def stats(self) -> Any:
        provider = self._runner.sched.stats_provider
        if provider is None:
            raise RuntimeError("no statistics outside a Runtime")
        return provider()

    @property
    def rtdb(self) -> Any:
        provider = self._runner.sched.rtdb_provider
        if provider is None:
            raise RuntimeError("no RTDB outside a Runtime")
        return provider()

    def set_mode(self, mode: str) -> None:
        setter = self._runner.sched.mode_setter
        if setter is None:
            raise RuntimeError("no modes outside a Runtime")
        setter(mode, f"node {self.name}")

    def elapsed(self) -> float:
        """Seconds since the runtime started: the time base of events and statistics."""
        return self._runner.sched.rel(self._runner.sched.clock.now())

    async def wait_readers(self) -> None:
        """Wait until this node's period-1 frame readers can take a new frame (fast pacing)."""
        await self._runner.sched.wait_readers(self._runner)

    def observe(self, observer: Any) -> None:  # determinism
        self._runner.sched.observer = observer  # determinism
        observer.attach(self._runner.sched.graph, self._runner.sched)  # determinism

    def request_stop(self) -> None:
        """Ask the runtime to stop (e.g. a video source at its end with on_eof: stop)."""
        stopper = self._runner.sched.stop_requester
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
        runner.error_reports += 1
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


class NodeRunner:
    """One node: its activations, buffers, statistics and supervision."""

    def __init__(self, sched: Scheduler, rnode: ResolvedNode) -> None:
        self.sched = sched
        self.rnode = rnode
        self.name = rnode.name
        spec = rnode.spec
        trig = rnode.trigger
        self.timing = Timing(
            period=trig.period if isinstance(trig, FrameTrigger) else 1,
            phase=trig.phase if isinstance(trig, FrameTrigger) else 0,
            timer=trig.timer / 1000 if isinstance(trig, TimerTrigger) else None,
            timer_phase=trig.phase / 1000 if isinstance(trig, TimerTrigger) else 0.0,
            deadline=spec.deadline / 1000 if spec.deadline else None,
            priority=spec.priority,
            enabled=spec.enabled,
        )
        self.inputs: dict[str, Buffer] = {}
        # Publication time (runtime clock) of the value each input held at the last take:
        # NodeContext.input_time/input_age. Invariant: a port is absent when it held no value.
        self.input_times: dict[str, float] = {}
        self.frame_seqs: dict[str, int] = {}  # next sequence of unstamped frames, per port
        self.ports = list(rnode.cls.inputs)  # declared inputs, then any-named ones connected
        self.outputs: dict[str, list[Buffer]] = {
            p: [] for p in [*rnode.cls.outputs, *rnode.cls.params_outputs(rnode.params)]
        }
        self.tick_ports = {p: f"{self.name}.{p}" for p in rnode.cls.frame_ports()}
        self.required = [p for p, port in rnode.cls.inputs.items() if port.required]
        self.port_types: dict[str, type] = {}  # inputs whose values are type-checked
        self.type_errors: set[tuple[str, str]] = set()  # (port, type) already logged
        self.trigger_inputs: list[str] = []
        self.executor: Executor = Executor()
        self.timer: PeriodicTimer | None = None
        self.created: list[Frame] = []
        # state
        self.state = "idle"
        self._busy = False
        self._idle_waiters: list[asyncio.Future[None]] = []
        self.lossless: list[LosslessBuffer] = []  # inputs that must deliver every value
        self.drain_task: asyncio.Task[None] | None = None
        self.deferred: float | None = None  # a paced source's tick that came while busy
        self.frame_key: str | None = None  # the frame clock this node is triggered by
        self.lead_max = 0  # most frames of a paced source published and not yet processed
        self.untaken = False  # released, inputs not yet taken (the run is scheduled)
        self.more_input = False
        self.stopping = False
        self.current = 0  # activation id, so a late deadline timer recognises its activation
        self.missed_current = False
        self.task: asyncio.Task[None] | None = None
        self.blocked: list[tuple[LosslessBuffer, Any, float]] = []
        self.consecutive_failures = 0
        self.failure_log = FailureLog(self.name)
        self.failed_reason = ""  # why supervision gave the node up (state "failed")
        self.swaps = 0
        self.idle_waiter: asyncio.Future[Executor] | None = None
        self.pending_swap: Callable[[], Executor] | None = None
        self.error_reason: str | None = None  # set_error(): an error state the node reports
        self.error_reports = 0
        # pipelined calls (a worker node fed by queues): see _pump
        self.inflight = 0
        self.aborted = 0  # activations in flight lost with their worker (or its instance)
        self._acts: dict[int, bool] = {}  # activation in flight -> its deadline was missed
        self._gen = 0  # bumped at each failure: results of an earlier instance are not used
        self._pump_soon = False
        self._pipe_end = 0.0  # when the previous pipelined activation finished
        self._window_of: tuple[Executor, bool, int] | None = None
        self._draining = False
        self._drained: asyncio.Event | None = None
        # counters
        self.activations = 0
        self.completions = 0
        self.skipped = 0
        self.misses = 0
        self.discarded = 0
        self.errors = 0
        self.restarts = 0
        self.last_start: float | None = None
        self.interval_from: float | None = None  # None after a timing change: a new series
        self.last_finish: float | None = None
        self.interval = Running()
        self.execution = Running()
        self.response = Running()

    @property
    def busy(self) -> bool:
        """An activation is running (or its producer waits on a full lossless edge)."""
        return self._busy

    @busy.setter
    def busy(self, value: bool) -> None:
        self._busy = value
        if not value and self._idle_waiters:
            self.notify()

    def notify(self) -> None:
        """Wake whoever waits for this node to be ready (a paced source)."""
        waiters, self._idle_waiters = self._idle_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    def ready_for_frame(self) -> bool:
        """True when this node has taken the previous frame of a paced source (or never will).

        It may still be running on it: the next tick is then deferred (see Scheduler.tick),
        so that the source prepares frame k+1 while a worker processes frame k; a pipelined
        reader in a worker of its own has up to ``window`` frames in flight instead.
        """
        if not self.timing.enabled or self.state == "failed" or self.stopping:
            return True
        if self.state in ("starting", "backoff") or self.deferred is not None or self.untaken:
            return False
        # A pipelined reader (see paced_reader) takes the next frame while its window has
        # room: the source runs ahead of the worker by at most ``window`` frames.
        window = self.window
        return window == 1 or self.inflight < window

    async def wait_ready(self) -> None:
        fut = self.sched.loop.create_future()
        self._idle_waiters.append(fut)
        await fut

    def _cancelled(self, task: asyncio.Task[None]) -> None:
        """A task cancelled before its first step never ran ``run_async``'s own clean-up."""
        if task is self.task and task.cancelled() and self.busy and not self.blocked:
            self._release_created()
            self.untaken = False
            self.busy = False
            if self.state == "running":
                self.state = "idle"

    def _backlog(self) -> bool:
        """A lossless input holds values not yet delivered."""
        return any(b.pending() for b in self.lossless)

    def _catch_up(self) -> None:
        """Run once more for a lossless input's backlog (never skipped: see release)."""
        if self.executor.pipelined and self.window > 1:
            self._schedule_pump()  # several activations may take from the backlog at once
            return
        if (
            not self.busy
            and self.state == "idle"
            and not self.stopping
            and self.timing.enabled
            and self._backlog()
        ):
            self.release(self.sched.clock.now())

    # --- wiring -------------------------------------------------------------------------

    def make_executor(self) -> Executor:
        placement = self.rnode.spec.placement
        factory = NodeFactory(self.rnode.cls, self.rnode.params, self.name)
        if placement is Placement.inline:
            ctx = RunnerContext(self)
            return InlineExecutor(lambda: make_node(self.rnode.cls, self.rnode.params, ctx))
        return self.sched.worker_executor(self, factory)

    def connect_input(self, port: str, buf: Buffer) -> None:
        self.inputs[port] = buf
        if port not in self.ports:
            self.ports.append(port)
        if isinstance(buf, LosslessBuffer):
            self.lossless.append(buf)
            buf.on_full = self._catch_up
        declared = self.rnode.cls.inputs.get(port) or self.rnode.cls.any_inputs
        checked = checked_type(declared.type) if declared is not None else None
        if checked is not None:
            self.port_types[port] = checked
        trig = self.rnode.trigger
        if isinstance(trig, InputTrigger):
            wanted = [trig.input] if isinstance(trig.input, str) else trig.input
            if "any" in wanted or port in wanted:
                self.trigger_inputs.append(port)
                buf.on_put = self.input_arrived
                return
        # Periodic readers sample: values they never read are expected, not lost.
        buf.sampled = isinstance(buf, LatestBuffer)

    # --- releases -----------------------------------------------------------------------

    def release(self, t_release: float) -> None:
        """A trigger fired: run now unless disabled, down, or still running (overrun)."""
        if not self.timing.enabled or self.stopping:
            return
        if (self.busy or self.state in ("backoff", "starting")) and self._backlog():
            return  # not skipped: the lossless value waits, and _idle runs the node for it
        self.activations += 1
        if self.state in ("backoff", "failed", "starting") or self.busy:
            self.skipped += 1
            for buf in self.inputs.values():
                buf.reader_skipped()  # the value it was due to read is lost if replaced
            return
        self.busy = True
        self.untaken = True
        self.current += 1
        self.missed_current = False
        loop = self.sched.loop
        if self.executor.sync:
            loop.call_soon(self.run_sync, t_release)
        else:
            self.task = loop.create_task(self.run_async(t_release))

    def input_arrived(self) -> None:
        if self.executor.pipelined and self.window > 1:  # (inline: one attribute, no more)
            self._schedule_pump()
            return
        if self.busy or self.state != "idle" or self.stopping or not self.timing.enabled:
            self.more_input = True
            return
        self.release(self.sched.clock.now())

    def _take_inputs(self) -> dict[str, Any] | None:
        values: dict[str, Any] = {}
        for port in self.ports:
            buf = self.inputs.get(port)
            if buf is None:
                values[port] = None
                continue
            value = buf.take_new() if port in self.trigger_inputs else buf.take()  # type: ignore[attr-defined]
            if value is EMPTY or buf.taken_t is None:
                self.input_times.pop(port, None)
            else:
                self.input_times[port] = buf.taken_t
            if value is EMPTY:
                if port in self.required:
                    _release_all(values.values())
                    return None
                value = None
            elif port in self.port_types and not isinstance(value, self.port_types[port]):
                self._wrong_type(port, value)
                _release_all([*values.values(), value])
                return None
            values[port] = value
        return values

    def _wrong_type(self, port: str, value: Any) -> None:
        """A value the input's type refuses: one counted error, one log line per type.

        Validation refuses edges whose declared types differ; this catches what an
        ``object``-typed output (a relay, ``Runtime.publish``) lets through. The node is
        not called (it would raise on every value) and the activation is skipped.
        """
        self.errors += 1
        got = type(value).__name__
        if (port, got) not in self.type_errors:
            self.type_errors.add((port, got))
            want = self.rnode.cls.inputs.get(port) or self.rnode.cls.any_inputs
            log.error(
                "node %s: input %r expects %s, got %s: values of this type are dropped "
                "and counted as errors",
                self.name,
                port,
                getattr(want.type if want else None, "__name__", "?"),
                got,
            )

    def _begin(self, t_release: float = 0.0) -> tuple[float, dict[str, Any] | None]:  # determinism
        now = self.sched.clock.now()
        inputs = self._take_inputs()
        self.untaken = False
        if self._idle_waiters:
            self.notify()  # a paced source may publish the next frame now
        if inputs is None:
            self.skipped += 1
            return now, None
        if self.interval_from is not None:
            self.interval.add(now - self.interval_from)
        self.interval_from = self.last_start = now
        self.state = "running"
        if (obs := self.sched.observer) is not None:  # determinism
            held = {p: b.taken_seq for p, b in self.inputs.items()}  # determinism
            obs.activation(self.name, t_release, now, held, self.rnode)  # determinism
        return now, inputs

    def run_sync(self, t_release: float) -> None:
        start, inputs = self._begin(t_release)  # determinism
        if inputs is None:
            self._idle()
            return
        try:
            result = self.executor.call_sync(inputs)
        except Exception as e:
            _release_all(inputs.values())
            self._release_created()
            self._failed(e)
            return
        _release_all(inputs.values())
        end = self.sched.clock.now()
        if end - start > BLOCKING_THRESHOLD and self.sched.real_time:
            self.sched.blocked_calls += 1
            self.sched.emit(LoopBlocked(self.sched.rel(end), self.name, (end - start) * 1000))
        self._complete(result, t_release, start, end)

    async def run_async(self, t_release: float) -> None:
        start, inputs = self._begin(t_release)  # determinism
        if inputs is None:
            self._idle()
            return
        act = self.current
        clock = self.sched.clock
        deadline: Handle | None = None
        if self.timing.deadline is not None:
            deadline = clock.call_at(
                t_release + self.timing.deadline, lambda: self._deadline_hit(act)
            )
        watchdog: Handle | None = None
        wd = self.rnode.spec.watchdog
        if (
            wd is not None
            and self.rnode.spec.placement is Placement.inline
            and self.task is not None
        ):
            task = self.task

            def cancel() -> None:
                task.cancel(f"watchdog {wd:g} ms")

            watchdog = clock.call_at(start + wd / 1000, cancel)
        try:
            result = await self.executor.call(inputs)
        except asyncio.CancelledError as e:
            _release_all(inputs.values())
            self._release_created()
            if self.stopping:
                self._idle()
                raise
            self._failed(TimeoutError(f"watchdog: no return within {wd:g} ms ({e})"))
            return
        except Exception as e:
            _release_all(inputs.values())
            self._release_created()
            self._failed(e)
            return
        finally:
            if deadline is not None:
                deadline.cancel()
            if watchdog is not None:
                watchdog.cancel()
        self._adopt(result)
        _release_all(inputs.values())
        self._complete(result, t_release, start, clock.now())

    def _adopt(self, result: Any) -> None:
        """Hold pooled frames in a result until they are published (released after).

        A worker that passes on a frame it received returns its descriptor, which resolves
        to the very frame the activation sent (:func:`flowrt.frames._attach_frame`): without
        a link of its own it would be recycled when the inputs are released. A frame the
        worker made in a slot lent to it (:mod:`flowrt.grants`) carries its link: taken over.
        """
        values = result.values() if isinstance(result, Mapping) else (result,)
        for v in values:
            if isinstance(v, Frame) and v.shared:
                v.take_link()
                self.created.append(v)

    # --- pipelined calls ------------------------------------------------------------------

    @property
    def window(self) -> int:
        """How many activations may be in flight at once (1: one at a time, as inline).

        More than one only for a node in a worker of its own whose trigger inputs are all
        queues or lossless edges: every value is to be processed in order, so the next one can
        be on its way to the worker while it computes the previous one. A ``latest`` input
        keeps one call at a time, so the worker always gets the newest value when it is free.
        """
        ex = self.executor
        paced = self.paced_reader()
        if self._window_of is None or self._window_of[0] is not ex or self._window_of[1] != paced:
            n = 1
            if ex.pipelined and paced:
                n = self.rnode.spec.pipeline or PACED_WINDOW
            elif (
                ex.pipelined
                and isinstance(self.rnode.trigger, InputTrigger)
                and self.trigger_inputs
                and not any(isinstance(self.inputs[p], LatestBuffer) for p in self.trigger_inputs)
            ):
                n = self.rnode.spec.pipeline or PIPELINE_WINDOW
            self._window_of = (ex, paced, n)
        return self._window_of[2]

    def paced_reader(self) -> bool:
        """A period-1 frame reader of a ``pacing: fast`` source: it takes every frame.

        Such a source publishes a frame only when its period-1 readers have taken the
        previous one (:meth:`Scheduler.wait_readers`), so a ``latest`` input never loses a
        value there, and a reader in a worker of its own may have the next frame on its way
        to the worker while it computes the current one (``window`` > 1): the source then
        runs ahead of the worker by at most ``window`` frames (``lead_max`` counts it).
        """
        return (
            self.frame_key is not None
            and self.timing.period == 1
            and self.frame_key in self.sched.paced
        )

    def release_paced(self, t_release: float) -> None:
        """A paced source's frame for a pipelined reader: sent to the worker at once while
        the window has room, else deferred (the source waits until it is taken)."""
        if self.deferred is None and self._may_pipe():
            self._start_pipelined(t_release)
        elif self.deferred is None and self.busy and self.timing.enabled and not self.stopping:
            self.deferred = t_release
        else:
            self.release(t_release)  # down, disabled or stopping: counted as release() does
        self.lead_max = max(self.lead_max, self.inflight + (self.deferred is not None))

    def _may_pipe(self) -> bool:
        return (
            self.inflight < self.window
            and not self.stopping
            and self.timing.enabled
            and self.state in ("idle", "running")
            and not self.blocked
            and not self._draining
            and self.pending_swap is None  # let the calls in flight finish: the swap is next
        )

    def _schedule_pump(self) -> None:
        if not self._pump_soon:
            self._pump_soon = True
            self.sched.loop.call_soon(self._pump)

    def _pump(self) -> None:
        """Start activations while inputs wait and the window has room (pipelined nodes).

        Each activation takes its inputs and is written to the worker at once; its result is
        awaited by its own task (:meth:`_finish`), and results complete in order.
        """
        self._pump_soon = False
        while self._may_pipe():
            if self.deferred is not None:  # a paced source's frame waits for room
                t_release, self.deferred = self.deferred, None
            elif any(self.inputs[p].pending() for p in self.trigger_inputs):
                t_release = self.sched.clock.now()
            else:
                break
            if not self._start_pipelined(t_release):
                break

    def _start_pipelined(self, t_release: float) -> bool:
        """Take the inputs and submit one activation to the worker; False: stop pumping."""
        window = self.window
        loop = self.sched.loop
        self.activations += 1
        self.current += 1
        act = self.current
        start, inputs = self._begin(t_release)  # determinism
        if inputs is None:  # a required input is missing: counted as skipped
            if self.inflight == 0:
                self.state = "idle"
            return False
        self.busy = True
        try:
            fut = self.executor.submit(inputs, window)
        except Exception as e:
            _release_all(inputs.values())
            self._release_created()
            if self.inflight == 0:
                self._gen += 1
                self._failed(e)
            else:
                self.aborted += 1  # the worker is gone: the calls in flight report it
            return False
        self.inflight += 1
        self._acts[act] = False
        self.task = loop.create_task(self._finish(act, t_release, start, inputs, fut))
        return True

    async def _finish(
        self,
        act: int,
        t_release: float,
        start: float,
        inputs: dict[str, Any],
        fut: asyncio.Future[Any],
    ) -> None:
        """One pipelined activation: await its result, then complete it in order."""
        gen = self._gen
        clock = self.sched.clock
        deadline: Handle | None = None
        if self.timing.deadline is not None:
            deadline = clock.call_at(
                t_release + self.timing.deadline, lambda: self._deadline_hit_pipelined(act)
            )
        try:
            result = await fut
        except asyncio.CancelledError:
            _release_all(inputs.values())
            self.inflight -= 1
            self._acts.pop(act, None)
            if self.inflight == 0:
                self._release_created()
                self._idle()
            raise
        except Exception as e:
            _release_all(inputs.values())
            self.inflight -= 1
            self._acts.pop(act, None)
            if gen != self._gen:
                self.aborted += 1  # lost with the instance that failed under an earlier call
                return
            self._gen += 1
            self._release_created()
            self._failed(e)
            return
        finally:
            if deadline is not None:
                deadline.cancel()
        self.inflight -= 1
        if self._idle_waiters:
            self.notify()  # the window has room: a paced source may publish its next frame
        missed = self._acts.pop(act, False)
        if gen != self._gen:  # the node failed under an earlier call: this instance is gone
            self.aborted += 1
            _release_all(inputs.values())
            release_handoffs(result)
            return
        if self._draining:  # a lossless reader is full: keep the order of the results
            if self._drained is None:
                self._drained = asyncio.Event()
            await self._drained.wait()
        self._adopt(result)
        _release_all(inputs.values())
        end = clock.now()
        # The worker ran it from when the previous one finished (or from the send).
        exec_start = max(start, self._pipe_end)
        self._pipe_end = end
        self.missed_current = missed
        self._complete(result, t_release, exec_start, end)

    def _deadline_hit_pipelined(self, act: int) -> None:
        if self._acts.get(act) is not False:
            return  # finished, or already counted
        self._acts[act] = True
        self._count_miss()

    def _deadline_hit(self, act: int) -> None:
        if act != self.current or not self.busy or self.missed_current:
            return
        self.missed_current = True
        self._count_miss()

    def _count_miss(self) -> None:
        """A deadline passed with the activation still running: counted and an event, now."""
        self.misses += 1
        discard = self.rnode.spec.miss_policy is MissPolicy.discard
        assert self.timing.deadline is not None
        self.sched.emit(
            DeadlineMissed(
                self.sched.rel(self.sched.clock.now()),
                self.name,
                self.timing.deadline * 1000,
                True,
                discard,
            )
        )

    # --- completion ---------------------------------------------------------------------

    def _complete(self, result: Any, t_release: float, start: float, end: float) -> None:
        self.completions += 1
        self.consecutive_failures = 0
        self.last_finish = end
        self.execution.add(end - start)
        self.response.add(end - t_release)
        deadline = self.timing.deadline
        late = deadline is not None and end - t_release > deadline
        discard = False
        if late:
            discard = self.rnode.spec.miss_policy is MissPolicy.discard
            if not self.missed_current:
                self.missed_current = True
                self.misses += 1
                assert deadline is not None
                self.sched.emit(
                    DeadlineMissed(self.sched.rel(end), self.name, deadline * 1000, False, discard)
                )
        if self.sched.observer is not None:  # determinism
            self.sched.observer.completed(self.name, t_release, end, discard)  # determinism
        if discard:
            self.discarded += 1
            values = [result] if not isinstance(result, Mapping) else result.values()
            # A frame the activation holds (made by new_frame, or adopted from a worker's
            # result) is released once, with the others it holds, just below.
            _release_all([v for v in values if not any(v is c for c in self.created)])
        elif result is not None:
            self._publish_result(result, end)
        self._release_created()
        self._idle()

    def _publish_result(self, result: Any, t: float) -> None:
        outs = self.outputs
        if len(outs) == 1:
            (port,) = outs
            self.publish(port, result, t)
            return
        if not isinstance(result, Mapping):
            raise TypeError(
                f"{self.name}: a node with outputs {list(outs)} must return a mapping of them"
            )
        for port, value in result.items():
            if port not in outs:
                raise TypeError(f"{self.name}: no output port {port!r}")
            if value is not None:
                self.publish(port, value, t)

    def publish(self, port: str, value: Any, t: float) -> None:
        """Fan a value out to every reader of ``port``; a frame port also ticks its frame clock."""
        if isinstance(value, Frame) and value.timestamp == 0.0:
            self._stamp(port, value, t)
        if self.sched.observer is not None:  # determinism
            self.sched.observer.published(self.name, port, value, t)  # determinism
        for buf in self.outputs[port]:
            if not buf.put(value, t):
                assert isinstance(buf, LosslessBuffer)
                hold(value)
                self.blocked.append((buf, value, t))
        key = self.tick_ports.get(port)
        if key is not None:
            self.sched.tick(key, t)

    def _stamp(self, port: str, frame: Frame, t: float) -> None:
        """A ``Frame(array)`` made without a timestamp: the activation's time, and the node's
        own sequence on that port when its seq was left at 0 too (recordings, health and
        freshness need both; a 4 s recording showed 'duration 1336 s, missing 19987')."""
        frame.timestamp = self.last_start if self.last_start is not None else t
        n = self.frame_seqs.get(port, 0)
        if frame.seq == 0:
            frame.seq = n
        self.frame_seqs[port] = max(n, frame.seq) + 1

    async def _drain_blocked(self) -> None:
        """Lossless readers are full: the producer waits (stays busy) until they take."""
        while self.blocked:
            buf, value, t = self.blocked[0]
            await buf.wait_space()
            buf.put(value, t)
            self.blocked.pop(0)
            _release_all([value])

    def _release_created(self) -> None:
        if self.created:
            _release_all(self.created)
            self.created = []

    def _idle(self) -> None:
        if self.blocked:
            if not self._draining:
                self._draining = True
                self.drain_task = self.sched.loop.create_task(self._drain_then_idle())
            return
        if self.inflight > 0:  # pipelined: more activations in flight; take the next input
            self._schedule_pump()
            return
        self.busy = False
        if self.state == "running":
            self.state = "idle"
        if self.pending_swap is not None:  # a swap waits for this moment
            take_over, self.pending_swap = self.pending_swap, None
            old = take_over()
            if self.idle_waiter is not None and not self.idle_waiter.done():
                self.idle_waiter.set_result(old)
        if self.stopping:
            return
        if self.deferred is not None:  # a paced source's frame waits: run on it now
            t, self.deferred = self.deferred, None
            if self.window > 1:
                self.release_paced(t)
            else:
                self.release(t)
        if isinstance(self.rnode.trigger, LoopTrigger):
            self.sched.loop.call_soon(self.release, self.sched.clock.now())
        elif self.trigger_inputs:
            self.more_input = False
            for p in self.trigger_inputs:
                if self.inputs[p].pending():
                    self.input_arrived()  # release() schedules the run: no re-entry
                    break
        if self.lossless and not self.busy:
            self.sched.loop.call_soon(self._catch_up)

    async def _drain_then_idle(self) -> None:
        try:
            await self._drain_blocked()
        finally:
            self._draining = False
            if self._drained is not None:
                self._drained.set()
                self._drained = None
        self._idle()

    # --- supervision --------------------------------------------------------------------

    def _failed(self, exc: BaseException, starting: bool = False) -> None:
        """Count, log (rate-limited), then restart after a back-off or give up: the one
        supervision rule of :mod:`flowrt.supervision`."""
        self.errors += 1
        self.consecutive_failures += 1
        # A worker's error brings its own one-line summary and the worker's traceback (none
        # for a dead worker): the main side's stack would only show the transport.
        tb = getattr(exc, "traceback", None)
        if not isinstance(tb, str):
            tb = "".join(traceback.format_exception(exc))
        error = getattr(exc, "summary", None) or f"{type(exc).__name__}: {exc}"
        now = self.sched.clock.now()
        fatal = bool(getattr(exc, "fatal", False))
        if not fatal:  # a fatal error is said once, below
            self.failure_log.failed(now, error, tb)
        self.sched.emit(NodeFailed(self.sched.rel(now), self.name, error, tb))
        self.busy = False
        policy = self.rnode.spec.restart
        # Out of descriptors/processes/memory: the machine's failure, retried without a bound.
        counted = 0 if out_of_resources(exc) else self.consecutive_failures
        never_started = starting and self.completions == 0
        why = give_up_reason(policy, counted, self.restarts, fatal, never_started)
        if why is not None:
            self.state = "failed"
            last = failure_kind(error)
            self.failed_reason = last if fatal else f"{why}; last error: {last}"
            self.failure_log.flush(now)
            log.error("node %s given up: %s", self.name, self.failed_reason)
            self.sched.emit(NodeGaveUp(self.sched.rel(now), self.name, self.failed_reason))
            self.sched.loop.create_task(self._stop_executor())
            return
        self.state = "backoff"
        self.sched.loop.create_task(self._restart(backoff_s(policy, self.consecutive_failures)))

    async def _stop_executor(self) -> None:
        try:
            await self.executor.stop()
        except Exception as e:
            log.warning("node %s: teardown failed: %s", self.name, e)

    async def _restart(self, backoff: float) -> None:
        await self._stop_executor()
        await self.sched.sleep(backoff)
        if self.stopping:
            return
        self.restarts += 1
        self.sched.emit(
            NodeRestarted(
                self.sched.rel(self.sched.clock.now()), self.name, self.restarts, backoff * 1000
            )
        )
        self.executor = self.make_executor()
        try:
            await self.executor.start()
        except Exception as e:
            self._failed(e, starting=True)
            return
        self.state = "idle"
        self._idle()

    # --- swapping an algorithm ------------------------------------------------------------

    def set_params(self, params: BaseModel) -> None:
        """New params between two activations (a mode's weights, a tuning change).

        An inline node gets them at once (``process`` reads ``self.params``; an optional
        ``params_changed(old)`` hook recomputes what ``setup`` derived from them); a worker
        node is swapped for a new instance with them (``swap``), in the background.
        """
        old_rnode = self.rnode
        self.rnode = dataclasses.replace(old_rnode, params=params)
        node = getattr(self.executor, "node", None)
        if isinstance(self.executor, InlineExecutor) and node is not None:
            old, node.params = node.params, params
            hook = getattr(node, "params_changed", None)
            if hook is not None:
                hook(old)
            return
        task = self.sched.loop.create_task(self.swap(self.rnode.cls, params, self.rnode.spec.kind))
        task.add_done_callback(_log_swap_failure)

    async def swap(
        self, cls: type[Node], params: BaseModel, kind: str, *, reload: bool = False
    ) -> None:
        """Replace the node's instance by a new one of ``cls``, between two activations.

        The new instance is set up beside the old one (a failure there leaves the old one
        running and raises), takes over when the old one is not running, receives the old
        one's ``get_state()`` through ``set_state()`` (inline nodes: both in this process),
        and the old one is torn down after. Other nodes are not touched.
        """
        missing = [p for p in self.inputs if p not in cls.inputs and cls.any_inputs is None]
        missing += [p for p, bufs in self.outputs.items() if bufs and p not in cls.outputs]
        if missing:
            raise ValueError(f"{self.name}: kind {kind!r} has no port(s) {', '.join(missing)}")
        unfed = [p for p, port in cls.inputs.items() if port.required and p not in self.inputs]
        if unfed:
            raise ValueError(
                f"{self.name}: kind {kind!r} needs input(s) {', '.join(unfed)}, "
                "which nothing feeds in this graph"
            )
        rnode = dataclasses.replace(
            self.rnode,
            cls=cls,
            params=params,
            spec=self.rnode.spec.model_copy(update={"kind": kind}),
        )
        if rnode.spec.placement is Placement.inline:
            ctx = RunnerContext(self)
            new: Executor = InlineExecutor(lambda: make_node(cls, params, ctx))
        else:
            factory = NodeFactory(cls, params, self.name)
            factory.reload = reload
            new = self.sched.worker_executor(self, factory)
        await new.start()  # raises: the old instance keeps running
        if self.busy:
            # Take over inside _idle, before a loop or input trigger can release again.
            loop = asyncio.get_running_loop()
            self.idle_waiter = loop.create_future()
            self.pending_swap = lambda: self._take_over(new, rnode)
            try:  # real time: a virtual clock may stand still
                old = await asyncio.wait_for(self.idle_waiter, SWAP_WAIT)
            except TimeoutError:
                self.pending_swap = None
                await new.stop()
                raise TimeoutError(
                    f"{self.name}: still running after {SWAP_WAIT:g} s; not swapped"
                ) from None
        else:
            old = self._take_over(new, rnode)
        try:
            await old.stop()
        except Exception as e:
            log.warning("node %s: teardown of the replaced instance failed: %s", self.name, e)

    def _take_over(self, new: Executor, rnode: ResolvedNode) -> Executor:
        """The new instance replaces the old one (synchronously: between two activations)."""
        old_node, new_node = getattr(self.executor, "node", None), getattr(new, "node", None)
        getter, setter = getattr(old_node, "get_state", None), getattr(new_node, "set_state", None)
        if getter is not None and setter is not None:
            setter(getter())
        old, self.executor, self.rnode = self.executor, new, rnode
        if self.state in ("failed", "backoff"):
            self.state = "idle"
        self.consecutive_failures = 0
        self.swaps += 1
        return old

    # --- statistics ---------------------------------------------------------------------

    def stats(self) -> NodeStats:
        rel = self.sched.rel
        spec = self.rnode.spec
        trig = self.rnode.trigger
        if isinstance(trig, FrameTrigger):
            trigger = f"frame {trig.frame}"
        elif isinstance(trig, TimerTrigger):
            trigger = "timer"
        elif isinstance(trig, InputTrigger):
            trigger = "input"
        else:
            trigger = "loop"
        period = (
            self.timing.describe_period() if isinstance(trig, FrameTrigger | TimerTrigger) else "-"
        )
        return NodeStats(
            name=self.name,
            kind=spec.kind,
            placement=spec.placement.value,
            trigger=trigger,
            priority=self.timing.priority,
            period=period,
            deadline_ms=None if self.timing.deadline is None else self.timing.deadline * 1000,
            watchdog_ms=spec.watchdog,
            enabled=self.timing.enabled,
            state=(
                "disabled"
                if not self.timing.enabled
                else "error"
                if self.error_reason is not None and self.state != "failed"
                else self.state
            ),
            reason=self.failed_reason if self.state == "failed" else self.error_reason or "",
            activations=self.activations,
            completions=self.completions,
            skipped=self.skipped,
            deadline_misses=self.misses,
            discarded=self.discarded,
            aborted=self.aborted,
            paced_lead_max=self.lead_max,
            dropped=self.discarded + self.aborted + sum(b.dropped for b in self.inputs.values()),
            errors=self.errors,
            restarts=self.restarts,
            last_start=None if self.last_start is None else rel(self.last_start),
            last_finish=None if self.last_finish is None else rel(self.last_finish),
            interval=self.interval.summary(),
            execution=self.execution.summary(),
            response=self.response.summary(),
            granted=self.executor.granted,
        )


def _log_swap_failure(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("params change by swap failed: %s", task.exception())


def _release_all(values: Any) -> None:
    for v in values:
        if isinstance(v, Frame):
            v.release()


class Scheduler:
    """Frame clocks, timers and dispatch order for a graph's runners."""

    def __init__(
        self,
        graph: Graph,
        clock: Clock,
        emit: Callable[[Event], None],
        worker_executor: Callable[[NodeRunner, NodeFactory], Executor] | None = None,
        new_frame: Callable[[str, tuple[int, ...], Any, str], Frame] | None = None,
        real_time: bool = True,
    ) -> None:
        self.graph = graph
        self.clock = clock
        self.emit = emit
        self.real_time = real_time
        self._worker_executor = worker_executor
        self._new_frame = new_frame
        self.loop = asyncio.get_event_loop()
        self.blocked_calls = 0
        self.stats_provider: Callable[[], Any] | None = None
        self.stop_requester: Callable[[], None] | None = None
        self.rtdb_provider: Callable[[], Any] | None = None
        self.mode_setter: Callable[[str, str], None] | None = None
        self.observer: Any = None  # set by ctx.observe (flowrt.determinism)  # determinism
        self.runners: dict[str, NodeRunner] = {}
        for name in sorted(graph.nodes, key=lambda n: graph.nodes[n].order):
            self.runners[name] = NodeRunner(self, graph.nodes[name])
        self.buffers: list[Buffer] = []
        self.reader_of: dict[int, NodeRunner] = {}  # id(edge buffer) -> the node reading it
        for edge in graph.edges:
            buf = make_buffer(edge.policy.value, edge.name, edge.size, clock.now)
            self.runners[edge.src].outputs[edge.src_port].append(buf)
            self.runners[edge.dst].connect_input(edge.dst_port, buf)
            self.buffers.append(buf)
            self.reader_of[id(buf)] = self.runners[edge.dst]
        self.paced: set[str] = set()  # frame clocks whose source waits for its readers
        self.drain_timeout = 5.0  # seconds the drain at stop may take (then reported)
        self.drained = False
        self.drain_left: list[str] = []  # what a timed-out drain left undone
        # frame clocks: source key -> (tick count, readers in dispatch order)
        self.ticks: dict[str, int] = {}
        self.readers: dict[str, list[NodeRunner]] = {}
        for r in self.runners.values():
            src = r.rnode.frame_source
            if src is not None:
                key = graph.frame_port(src)
                r.frame_key = key
                self.readers.setdefault(key, []).append(r)
                self.ticks.setdefault(key, 0)
        self.resort()

    def rel(self, t: float) -> float:
        """Seconds since the runtime's time origin."""
        return t - self.clock.origin

    def resort(self) -> None:
        """Dispatch order within a tick: higher priority first, then file order."""
        for readers in self.readers.values():
            readers.sort(key=lambda r: (-r.timing.priority, r.rnode.order))
        self.order = sorted(
            self.runners.values(), key=lambda r: (-r.timing.priority, r.rnode.order)
        )

    def worker_executor(self, runner: NodeRunner, factory: NodeFactory) -> Executor:
        if self._worker_executor is None:
            raise RuntimeError(
                f"{runner.name}: placement {runner.rnode.spec.placement.value} needs worker support"
            )
        return self._worker_executor(runner, factory)

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame:
        if self._new_frame is not None:
            return self._new_frame(owner, shape, dtype, pixel_format)
        return Frame(np.empty(shape, dtype=dtype), source=owner, pixel_format=pixel_format)

    def tick(self, key: str, t: float) -> None:
        """A frame was published on ``key``: release the readers whose period/phase match."""
        k = self.ticks.get(key)
        if k is None:
            return
        self.ticks[key] = k + 1
        paced = key in self.paced
        for r in self.readers[key]:
            tm = r.timing
            if k % tm.period == tm.phase:
                if paced and tm.period == 1 and r.window > 1:
                    r.release_paced(t)  # a worker's call may follow the one in flight
                elif paced and tm.period == 1 and r.busy and r.deferred is None:
                    r.deferred = t  # not an overrun: the source waited for this reader
                    r.lead_max = max(r.lead_max, 2)  # one running, this one waiting
                else:
                    r.release(t)
                    if paced and tm.period == 1:
                        r.lead_max = max(r.lead_max, int(r.busy))

    async def wait_readers(self, runner: NodeRunner) -> None:
        """Wait until every period-1 frame-triggered reader of ``runner``'s frames is ready.

        A ``pacing: fast`` source calls this before publishing: a reader in a worker process
        that is slower than the source is then never skipped (the source follows the slowest
        such reader instead of outrunning it). "Ready" means the reader has taken the previous
        frame: it may still run on it, and the new frame's tick then waits for it to finish
        (deferred, not skipped), so that the source prepares frame k+1 while the worker
        processes frame k. A reader in a worker of its own is pipelined instead: it is
        ready while fewer than its window of frames are in flight (see
        :meth:`NodeRunner.paced_reader`). Readers with a longer period sample by design
        and are not waited for; nor are failed, disabled or stopping ones.
        """
        self.paced.update(runner.tick_ports.values())
        while not runner.stopping:
            waiting = [
                r
                for key in runner.tick_ports.values()
                for r in self.readers.get(key, ())
                if r.timing.period == 1 and not r.ready_for_frame()
            ]
            if not waiting:
                return
            await waiting[0].wait_ready()

    async def sleep(self, seconds: float) -> None:
        fut = self.loop.create_future()

        def wake() -> None:
            if not fut.done():
                fut.set_result(None)

        self.clock.call_at(self.clock.now() + seconds, wake)
        await fut

    # --- lifecycle ----------------------------------------------------------------------

    async def start(self) -> None:
        """Set every node up (workers in parallel), then arm triggers."""
        for r in self.runners.values():
            r.executor = r.make_executor()
            r.state = "starting"

        async def start_one(r: NodeRunner) -> None:
            try:
                await r.executor.start()
                r.state = "idle"
            except Exception as e:
                r.state = "idle"
                r._failed(e, starting=True)

        inline = [r for r in self.runners.values() if r.rnode.spec.placement is Placement.inline]
        others = [
            r for r in self.runners.values() if r.rnode.spec.placement is not Placement.inline
        ]
        await asyncio.gather(*(start_one(r) for r in others))
        for r in inline:
            await start_one(r)
        for r in self.order:
            if r.timing.timer is not None:
                r.timer = self.clock.periodic(
                    r.timing.timer, r.timing.timer_phase, self._timer_cb(r)
                )
            elif isinstance(r.rnode.trigger, LoopTrigger):
                self.loop.call_soon(r.release, self.clock.now())

    @staticmethod
    def _timer_cb(r: NodeRunner) -> Callable[[float, int], None]:
        def fire(release: float, missed: int) -> None:
            if missed and r.timing.enabled:
                r.activations += missed
                r.skipped += missed
            r.release(release)

        return fire

    async def drain(self, limit: float | None = None) -> list[str]:
        """Stop the sources, then let the graph finish what it holds (at most ``limit`` s).

        Sources (nodes without inputs, and free-running ones) are released no more and their
        in-flight activation is cancelled (a capture waiting for a frame, a paced source
        waiting for its readers): nothing new is published after the stop request, but what
        a source did publish, even a value waiting on a full lossless edge, is delivered.
        Every other node keeps running: in-flight activations finish, every lossless edge
        delivers what it holds, producers waiting on a full lossless edge get their values in.
        Returns what was left undone when the limit hit (then reported as a ``drain-timeout``
        HealthAlert and a warning), or []. The limit is a deadline for the whole graph, not
        for one awaited call (hence no ``asyncio.timeout``).
        """
        if self.drained:
            return self.drain_left
        self.drained = True
        timeout = self.drain_timeout if limit is None else limit
        loop = self.loop
        t0 = loop.time()
        for r in self.runners.values():
            if not r.inputs or isinstance(r.rnode.trigger, LoopTrigger):
                r.stopping = True
                if r.timer is not None:
                    r.timer.cancel()
                    r.timer = None
                if r.task is not None and not r.task.done():
                    r.task.add_done_callback(r._cancelled)
                    r.task.cancel()  # e.g. a capture waiting for its next frame
        while True:
            left = self._undrained()
            if not left or loop.time() - t0 >= timeout:
                break
            for r in self.runners.values():
                r._catch_up()
            await asyncio.sleep(0.002)
        self.drain_left = left
        if left:
            detail = f"not drained within {timeout:g} s: " + "; ".join(left)
            log.warning("drain: %s", detail)
            self.emit(HealthAlert(self.rel(self.clock.now()), None, "drain-timeout", detail))
        else:
            log.debug("drained in %.1f ms", (loop.time() - t0) * 1000)
        return left

    def _undrained(self) -> list[str]:
        """What the drain still waits for, in words."""
        left = []
        for r in self.runners.values():
            if r.busy:
                left.append(
                    f"{r.name} waits on a full lossless edge" if r.blocked else f"{r.name} running"
                )
            elif r.state in ("starting", "backoff") and r._backlog() and r.timing.enabled:
                left.append(f"{r.name} restarting")
        for buf in self.buffers:
            reader = self.reader_of.get(id(buf))
            if (
                reader is not None
                and isinstance(buf, LosslessBuffer)
                and buf.pending()
                and reader.timing.enabled
                and reader.state != "failed"
            ):
                left.append(f"{buf.name} holds {buf.pending()}")
        return left

    def _discard_leftovers(self) -> None:
        """Count what a stop leaves undelivered on queue and lossless edges, with a reason."""
        late = "drain timeout" if self.drain_left else "stop"
        for r in self.runners.values():
            for blocked, value, _ in r.blocked:
                blocked.abandon(value, late)
            r.blocked = []
        for buf in self.buffers:
            reader = self.reader_of.get(id(buf))
            if reader is None or isinstance(buf, LatestBuffer):
                buf.clear()  # a host subscription, or a sampled/latest value: not a loss
                continue
            why = (
                "reader failed"
                if reader.state == "failed"
                else "reader disabled"
                if not reader.timing.enabled
                else late
            )
            n = buf.discard(why)
            if n:
                log.warning("%s: %d value(s) dropped at stop (%s)", buf.name, n, why)

    async def stop(self, grace: float = 1.0) -> None:
        """Drain (bounded), stop releasing, cancel what still runs, tear every node down."""
        await self.drain()
        for r in self.runners.values():
            r.stopping = True
            if r.timer is not None:
                r.timer.cancel()
                r.timer = None
        pending = [
            r.task for r in self.runners.values() if r.task is not None and not r.task.done()
        ]
        if pending:
            _, still = await asyncio.wait(pending, timeout=grace)
            for t in still:
                t.cancel()
            if still:
                await asyncio.wait(still, timeout=grace)
        drains = [
            r.drain_task
            for r in self.runners.values()
            if r.drain_task is not None and not r.drain_task.done()
        ]
        for t in drains:
            t.cancel()
        if drains:
            await asyncio.wait(drains, timeout=grace)
        self._discard_leftovers()
        for r in reversed(self.order):
            try:
                await asyncio.wait_for(r.executor.stop(), timeout=max(grace, 2.0))
            except Exception as e:
                log.warning("node %s: teardown failed: %s", r.name, e)
        for r in self.runners.values():
            r.failure_log.flush(self.clock.now())

    # --- run-time changes ---------------------------------------------------------------

    def set_timing(
        self,
        node: str,
        *,
        period: int | None = None,
        phase: int | None = None,
        timer: float | None = None,
        deadline: float | None = None,
        priority: int | None = None,
        enabled: bool | None = None,
        origin: str = "api",
        timer_phase: float | None = None,
    ) -> str:
        """Apply a timing change now (between ticks: the loop runs one callback at a time)."""
        r = self.runners.get(node)
        if r is None:
            from .diagnostics import did_you_mean

            raise KeyError(f"unknown node {node!r}" + did_you_mean(node, self.runners))
        tm = r.timing
        new_period = tm.period if period is None else period
        new_phase = tm.phase if phase is None else phase
        is_frame = isinstance(r.rnode.trigger, FrameTrigger)
        if (period is not None or phase is not None) and not is_frame:
            raise ValueError(
                f"{node}: period/phase in frames apply to frame-triggered nodes; use timer="
            )
        if timer is not None and tm.timer is None:
            raise ValueError(f"{node}: timer= applies to timer-triggered nodes")
        if new_period <= 0 or not 0 <= new_phase < new_period:
            raise ValueError(
                f"{node}: need period > 0 and 0 <= phase < period (got {new_period}/{new_phase})"
            )
        if timer is not None and timer <= 0:
            raise ValueError(f"{node}: timer period must be positive")
        if deadline is not None and deadline <= 0:
            raise ValueError(f"{node}: deadline must be positive")
        if priority is not None and not 1 <= priority <= 99:
            raise ValueError(f"{node}: priority must be in 1..99")
        changes = []

        def note(label: str, old: Any, new: Any) -> None:
            if new is not None and new != old:
                changes.append(f"{label} {old} -> {new}")

        note("period", tm.period, period)
        note("phase", tm.phase, phase)
        note(
            "timer_ms",
            None if tm.timer is None else tm.timer * 1000,
            None if timer is None else timer * 1000,
        )
        note(
            "deadline_ms",
            None if tm.deadline is None else tm.deadline * 1000,
            None if deadline is None else deadline * 1000,
        )
        note(
            "timer_phase_ms",
            None if tm.timer is None else tm.timer_phase * 1000,
            None if timer_phase is None else timer_phase * 1000,
        )
        note("priority", tm.priority, priority)
        note("enabled", tm.enabled, enabled)
        tm.period, tm.phase = new_period, new_phase
        if deadline is not None:
            tm.deadline = deadline
        if priority is not None:
            tm.priority = priority
            self.resort()
            setter = getattr(r.executor, "set_priority", None)
            if setter is not None:
                setter(priority)
        if enabled is not None:
            was = tm.enabled
            tm.enabled = enabled
            if enabled and not was and isinstance(r.rnode.trigger, LoopTrigger) and not r.busy:
                self.loop.call_soon(r.release, self.clock.now())
        if timer_phase is not None and tm.timer is not None:
            tm.timer_phase = timer_phase
        if (timer is not None or timer_phase is not None) and r.timer is not None:
            tm.timer = tm.timer if timer is None else timer
            assert tm.timer is not None
            r.timer.reset(tm.timer, min(tm.timer_phase, tm.timer * 0.999))
        elif timer is not None:
            tm.timer = timer
        restart = ("period", "phase", "timer_ms", "timer_phase_ms", "enabled")
        if any(c.split()[0] in restart for c in changes):
            # the interval statistics describe the new timing, not a mean of old and new
            r.interval = Running()
            r.interval_from = None
        text = ", ".join(changes) or "no change"
        if changes:
            self.emit(TimingChanged(self.rel(self.clock.now()), node, text, origin))
        return text
