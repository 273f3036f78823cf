"""Pipelined worker calls: the next activation on its way while the worker computes one.

A node in a worker of its own whose every value is to be processed in order (queues or
lossless trigger inputs, or the period-1 reader of a ``pacing: fast`` source) may have up to
``window`` activations in flight: each takes its inputs and is written to the worker at
once (:meth:`flowrt.kernel.Executor.submit`); the worker runs them back to back; results
complete in order, each awaited by a task of its own. This hides the socket round trip and
the wake-up of the worker (the pipelining of dora-rs and of copper-rs' copperlists).

"Window" means one thing here: the most activations of one node in flight at once.
"""

from __future__ import annotations

import asyncio
from typing import Any, Protocol

from ..edges import Buffer, LatestBuffer
from ..graph._resolve import ResolvedNode
from ..graph.spec import InputTrigger
from .activation import Activation
from .backpressure import Backpressure
from .counters import Counters
from .deadlines import DeadlineWatch
from .executor import Executor
from .ports import SchedulerPort
from .state import RunState
from .swapping import Swapper
from .timing import Timing


class PipelinedRunner(Protocol):
    """What the pipeline reads of its runner (read-only: mypy refuses a write through it),
    and the runner's methods that apply what it decides (a deferred tick, a pipelined
    call's task, a failure)."""

    @property
    def executor(self) -> Executor: ...
    @property
    def rnode(self) -> ResolvedNode: ...
    @property
    def trigger_inputs(self) -> list[str]: ...
    @property
    def inputs(self) -> dict[str, Buffer]: ...
    @property
    def frame_key(self) -> str | None: ...
    @property
    def timing(self) -> Timing: ...
    @property
    def sched(self) -> SchedulerPort: ...
    @property
    def deferred(self) -> float | None: ...
    @property
    def busy(self) -> bool: ...
    @property
    def stopping(self) -> bool: ...
    @property
    def state(self) -> RunState: ...
    @property
    def counts(self) -> Counters: ...
    @property
    def backpressure(self) -> Backpressure: ...
    @property
    def swapper(self) -> Swapper: ...
    @property
    def deadlines(self) -> DeadlineWatch: ...

    def begin(self, t_release: float) -> Activation | None: ...

    def move(self, to: RunState) -> None: ...

    def defer(self, t: float | None) -> float | None: ...

    def started(self, task: asyncio.Task[None] | None = None) -> None: ...

    def fail(self, exc: BaseException, starting: bool = False) -> None:
        """The instance failed: supervision decides, the calls in flight are lost
        (:meth:`Pipeline.lose_in_flight`)."""

    def release(self, t_release: float) -> None: ...

    def readers_may_go(self) -> None: ...

    def idle(self) -> None: ...

    def complete(self, act: Activation, result: Any, end: float) -> None: ...


PIPELINE_WINDOW = 4  # activations in flight to a worker node fed by queues (spec: pipeline)
PACED_WINDOW = 2  # frames of a pacing: fast source in flight to a worker reader (spec: pipeline)


class Pipeline:
    """The pipelined calls of one runner.

    Invariants: ``0 <= inflight <= window``; ``inflight > 0`` implies the runner is busy;
    a result whose ``gen`` is older than ``gen`` belongs to a node instance that failed
    (:meth:`lose_in_flight`, at every failure) and is counted as aborted, never published
    nor checked.
    """

    def __init__(self, runner: PipelinedRunner) -> None:
        self._r = runner
        self.inflight = 0
        self.gen = 0  # bumped at each failure: results of an earlier instance are not used
        self._pump_soon = False
        self._end = 0.0  # when the previous pipelined activation finished
        self._window_of: tuple[Executor, bool, int] | None = None

    @property
    def window(self) -> int:
        """How many activations may be in flight at once (1: one at a time, as inline).

        More than one only for a node in a worker of its own whose trigger inputs are all
        queues or lossless edges: every value is to be processed in order, so the next one can
        be on its way to the worker while it computes the previous one. A ``latest`` input
        keeps one call at a time, so the worker always gets the newest value when it is free.
        """
        r = self._r
        ex = r.executor
        paced = self.paced_reader()
        if self._window_of is None or self._window_of[0] is not ex or self._window_of[1] != paced:
            n = 1
            if ex.pipelined and paced:
                n = r.rnode.spec.pipeline or PACED_WINDOW
            elif (
                ex.pipelined
                and isinstance(r.rnode.trigger, InputTrigger)
                and r.trigger_inputs
                and not any(isinstance(r.inputs[p], LatestBuffer) for p in r.trigger_inputs)
            ):
                n = r.rnode.spec.pipeline or PIPELINE_WINDOW
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
        r = self._r
        return r.frame_key is not None and r.timing.period == 1 and r.frame_key in r.sched.paced

    def lose_in_flight(self) -> None:
        """The node instance failed (a call raised, or a result failed its output check on
        the loop, or a set-up): the calls in flight on it are lost with it. Each is counted
        as aborted when it comes back, never as a failure of its own: one failure starts one
        back-off, and a node given up is not failed (restarted, given up) again by the
        calls that were on their way when it failed. Called by the runner's ``fail``, the
        one path every failure takes."""
        self.gen += 1

    def active(self) -> bool:
        """Calls may overlap now: a pipelined executor with a window above one."""
        return self._r.executor.pipelined and self.window > 1

    def release_paced(self, t_release: float) -> None:
        """A paced source's frame: sent to the worker at once while the window has room,
        else deferred (the source waits until it is taken)."""
        r = self._r
        if r.deferred is None and self._may_pipe():
            self._start(t_release)
        elif r.deferred is None and r.busy and r.timing.enabled and not r.stopping:
            r.defer(t_release)
        else:
            r.release(t_release)  # down, disabled or stopping: counted as release() does
        r.counts.lead_max = max(r.counts.lead_max, self.inflight + (r.deferred is not None))

    def _may_pipe(self) -> bool:
        r = self._r
        return (
            self.inflight < self.window
            and not r.stopping
            and r.timing.enabled
            and r.state in (RunState.idle, RunState.running)
            and not r.backpressure.blocked
            and not r.backpressure.draining
            and r.swapper.pending is None  # let the calls in flight finish: the swap is next
        )

    def schedule_pump(self) -> None:
        if not self._pump_soon:
            self._pump_soon = True
            self._r.sched.loop.call_soon(self._pump)

    def _pump(self) -> None:
        """Start activations while inputs wait and the window has room."""
        r = self._r
        self._pump_soon = False
        while self._may_pipe():
            deferred = r.defer(None)  # a paced source's frame waits for room
            if deferred is not None:
                t_release = deferred
            elif any(r.inputs[p].pending() for p in r.trigger_inputs):
                t_release = r.sched.clock.now()
            else:
                break
            if not self._start(t_release):
                break

    def _start(self, t_release: float) -> bool:
        """Take the inputs and submit one activation to the worker; False: stop pumping."""
        r = self._r
        window = self.window
        r.counts.activations += 1
        act = r.begin(t_release)
        if act is None:  # a required input is missing: counted as skipped
            if self.inflight == 0:
                r.move(RunState.idle)
            return False
        act.gen = self.gen
        try:
            fut = r.executor.submit(act.inputs, window)
        except Exception as e:
            act.close()
            if self.inflight == 0:
                r.fail(e)  # (the instance is lost: fail() calls lose_in_flight())
            else:
                r.counts.aborted += 1  # the worker is gone: the calls in flight report it
            return False
        self.inflight += 1
        r.deadlines.arm(act)
        r.started(r.sched.loop.create_task(self._finish(act, fut)))
        return True

    async def _finish(self, act: Activation, fut: asyncio.Future[Any]) -> None:
        """One pipelined activation: await its result, then complete it in order."""
        r = self._r
        try:
            result = await fut
        except asyncio.CancelledError:
            act.close()
            self.inflight -= 1
            if self.inflight == 0:
                r.idle()
            raise
        except Exception as e:
            act.close()
            self.inflight -= 1
            if act.gen != self.gen:
                r.counts.aborted += 1  # lost with the instance that failed under an earlier call
                return
            r.fail(e)  # (the calls behind this one are lost with it: see lose_in_flight)
            return
        finally:
            r.deadlines.disarm(act)
        self.inflight -= 1
        r.readers_may_go()  # the window has room: a paced source may publish its next frame
        if act.gen == self.gen:
            await r.backpressure.wait_turn()  # a lossless reader is full: keep the results' order
        # The node failed under an earlier call (it raised, or its result's check failed on
        # the loop, maybe while this one waited its turn): this instance is gone.
        if act.gen != self.gen:
            r.counts.aborted += 1
            act.abandon(result)
            return
        act.adopt(result)
        end = r.sched.clock.now()
        # The worker ran it from when the previous one finished (or from the send).
        act.start = max(act.start, self._end)
        self._end = end
        r.complete(act, result, end)
