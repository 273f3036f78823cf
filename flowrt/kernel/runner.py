"""One node's runner: its releases, inputs, activations and outputs.

The runner decides *whether* a release runs and moves the values; each other concern is a
collaborator of its own (trio's ``_core`` hands each concern to a named object the same way):
:class:`~flowrt.kernel.activation.Activation` (the frame links one run holds),
:class:`~flowrt.kernel.deadlines.DeadlineWatch`, :class:`~flowrt.kernel.pipeline.Pipeline`
(overlapping worker calls), :class:`~flowrt.kernel.backpressure.Backpressure` (full lossless
readers), :class:`~flowrt.kernel.supervisor.Supervisor` (failures, restarts),
:class:`~flowrt.kernel.swapping.Swapper`, :class:`~flowrt.kernel.counters.Counters`.

Activation semantics (the CAMBADA process manager): a release while the previous activation
still runs is skipped and counted (overrun); an input-triggered node is never re-entered:
data that arrives meanwhile waits in its buffer and causes one more activation afterwards.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from ..clock import Handle, PeriodicTimer
from ..edges import Buffer, LosslessBuffer
from ..events import LoopBlocked
from ..frames import Frame
from ..graph._resolve import ResolvedNode
from ..graph.spec import FrameTrigger, LoopTrigger, Placement, TimerTrigger
from ..node import NodeFactory, make_node
from ..stats import NodeStats
from .activation import Activation, release_all
from .backpressure import Backpressure
from .context import RunnerContext
from .counters import Counters, node_stats
from .deadlines import DeadlineWatch
from .disabling import DisableHook
from .executor import Executor, InlineExecutor, NoExecutor
from .hops import Hops
from .inputs import Inputs
from .outputs import OutputCheck
from .pipeline import Pipeline
from .ports import SchedulerPort
from .state import STAY_OR_MOVE, RunState, StateError
from .supervisor import GiveUp, Restart, Supervisor
from .swapping import Swapper
from .timing import Timing

log = logging.getLogger("flowrt.scheduler")

_DOWN = frozenset((RunState.starting, RunState.backoff, RunState.failed))  # releases skipped
_WAITING = frozenset((RunState.starting, RunState.backoff))  # a backlog waits for idle()
# The hot path reads these instead of ``RunState.x``: an enum member's attribute access costs
# ~65 ns on CPython 3.11, paid several times per activation (bench_hops: +1.2 us per hop).
_IDLE, _RUNNING = RunState.idle, RunState.running
BLOCKING_THRESHOLD = 0.010  # an inline call longer than this is reported as blocking the loop


def _timing_of(rnode: ResolvedNode) -> Timing:
    spec, trig = rnode.spec, rnode.trigger
    return Timing(
        period=trig.period if isinstance(trig, FrameTrigger) else 1,
        phase=trig.phase if isinstance(trig, FrameTrigger) else 0,
        timer=trig.timer / 1000 if isinstance(trig, TimerTrigger) else None,
        timer_phase=trig.phase / 1000 if isinstance(trig, TimerTrigger) else 0.0,
        deadline=spec.deadline / 1000 if spec.deadline else None,
        priority=spec.priority,
        enabled=spec.enabled,
    )


class RunnerFields:
    """A runner's fields, each with its invariant, and the methods that change them on what a
    collaborator decided: the runner is the one writer of its state (issue 39).

    Collaborators (supervisor, pipeline, swapper, context, scheduler) read these fields and
    return what is to change: a supervisor's :data:`~flowrt.kernel.supervisor.Decision`, a
    swap's executor, a pipelined call's task; the runner applies it here. The state changes
    by :meth:`move` only, along :data:`~flowrt.kernel.state.MOVES`
    (``tests/test_runner_state.py`` holds both: the table, and no assignment elsewhere).
    Readiness, which these fields decide, is read here too (``busy``, ``ready_for_frame``).
    """

    # Fixed at construction (wiring):
    sched: SchedulerPort
    name: str
    counts: Counters
    ins: Inputs
    inputs: dict[str, Buffer]  # by port: ``ins.buffers`` (the same dict, read by the runtime)
    input_times: dict[str, float]  # ``ins.times``: NodeContext.input_time/input_age
    trigger_inputs: list[str]
    lossless: list[LosslessBuffer]  # the lossless input edges (a backlog may wait there)
    frame_seqs: dict[str, int]  # next sequence of unstamped frames, per port
    outputs: dict[str, list[Buffer]]  # readers by port; filled while the graph is wired
    tick_ports: dict[str, str]  # frame port -> its frame clock's key
    out_check: OutputCheck  # output names and types, made once
    frame_key: str | None  # the frame clock this node is triggered by (None: not frame)
    timing: Timing  # one object for the run: the QoS manager changes its fields
    deadlines: DeadlineWatch
    pipeline: Pipeline
    backpressure: Backpressure
    supervisor: Supervisor
    swapper: Swapper
    disable_hook: DisableHook  # on_disable() between calls, once per disabling
    hops: Hops  # direct hops between workers: its reader, its call sent ahead
    # Changed by the methods below only:
    rnode: ResolvedNode  # install(): a swap's class and params, new params
    executor: Executor  # install(): set up at start, a restart, a swap; NoExecutor before
    timer: PeriodicTimer | None  # arm(); cancelled and None from stop_releasing()
    state: RunState  # move() only, along MOVES; ``running`` implies ``busy``
    # Changed by the runner's own releases and activations:
    task: asyncio.Task[None] | None  # the last activation's task (a pipelined one: started())
    _busy: bool  # exactly while an activation is released and not ended, pipelined calls
    # are in flight, or values wait for full lossless readers (release() sets, idle() clears;
    # fail() clears it with the activation lost)
    _idle_waiters: list[asyncio.Future[None]]  # paced sources waiting for this reader
    deferred: float | None  # at most one release of a paced source (defer()), taken by
    # idle() or the pipeline
    untaken: bool  # released, inputs not taken yet (the run is scheduled); implies busy
    stopping: bool  # no release from now on; never returns to false
    # stopped by a drain past its deadline or cut: what it still holds is the drain's leftover
    # (reason "drain timeout" or "interrupted"), not a stopped source's ("stop")
    cut_short: bool
    act: Activation | None  # the inline activation in progress (None between activations
    # and for pipelined nodes, whose activations belong to their tasks)
    _acts: int  # activations begun: their ids
    _loose: list[Frame]  # frames made outside an activation: the next one's
    error_reason: str | None  # ctx.set_error/clear_error: an error state the node reports
    waiting_reason: str | None  # ctx.set_waiting: the node waits for an operator

    def move(self, to: RunState, _may: dict[RunState, frozenset[RunState]] = STAY_OR_MOVE) -> None:
        """The one place the state changes; a move the table refuses raises (a kernel bug).
        (``_may`` bound once: this runs twice per activation, ~40 ns each.)"""
        if to not in _may[self.state]:
            raise StateError(f"node {self.name}: no move from {self.state} to {to}")
        self.state = to

    def install(self, executor: Executor, rnode: ResolvedNode | None = None) -> Executor:
        """``executor`` (and ``rnode``) are the node's from now on; the one replaced."""
        old, self.executor = self.executor, executor
        if rnode is not None:
            self.rnode = rnode
        return old

    def arm(self, timer: PeriodicTimer) -> None:
        """The node's release timer (a precise release thread is one too)."""
        self.timer = timer

    def defer(self, t: float | None) -> float | None:
        """Keep a paced source's tick at ``t`` for later (None: take it); the one kept."""
        kept, self.deferred = self.deferred, t
        return kept

    def started(self, task: asyncio.Task[None] | None = None) -> None:
        """An activation begun outside release(): a pipelined call (its task, from the
        pipeline), or a call a precise thread made, the loop's from now on (None)."""
        self._busy = True
        if task is not None:
            self.task = task

    def set_error_reason(self, reason: str | None) -> None:
        self.error_reason = reason

    def set_waiting_reason(self, reason: str | None) -> None:
        self.waiting_reason = reason

    # --- readiness (what a paced source waits for) ---------------------------------------

    @property
    def busy(self) -> bool:
        """An activation is running (or its producer waits on a full lossless edge)."""
        return self._busy

    @busy.setter
    def busy(self, value: bool) -> None:
        self._busy = value
        if not value and self._idle_waiters:
            self.readers_may_go()

    def readers_may_go(self) -> None:
        """Wake whoever waits for this node to be ready (a paced source)."""
        waiters, self._idle_waiters = self._idle_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    @property
    def window(self) -> int:
        return self.pipeline.window

    def ready_for_frame(self) -> bool:
        """True when this node has taken the previous frame of a paced source (or never will).

        It may still be running on it: the next tick is then deferred (see Scheduler.tick),
        so that the source prepares frame k+1 while a worker processes frame k; a pipelined
        reader in a worker of its own has up to ``window`` frames in flight instead.
        """
        if not self.timing.enabled or self.state is RunState.failed or self.stopping:
            return True
        if self.state in _WAITING:
            return False
        if self.deferred is not None or self.untaken:
            return False
        window = self.window
        return window == 1 or self.pipeline.inflight < window

    def stats(self) -> NodeStats:
        """The runner's statistics, times relative to the runtime's origin."""
        return node_stats(
            self.rnode,
            self.timing,
            self.counts,
            self.state.value,
            self.error_reason,
            self.supervisor.failed_reason,
            sum(b.dropped for b in self.inputs.values()),
            self.waiting_reason,
            self.executor.granted,
            self.sched.rel,
        )

    async def wait_ready(self) -> None:
        fut = self.sched.loop.create_future()
        self._idle_waiters.append(fut)
        await fut


class NodeRunner(RunnerFields):
    """One node: when it runs, what it takes and what it publishes (its fields and their
    invariants: :class:`RunnerFields`)."""

    def __init__(self, sched: SchedulerPort, rnode: ResolvedNode) -> None:
        self.sched = sched
        self.rnode = rnode
        self.name = rnode.name
        self.timing = _timing_of(rnode)
        self.counts = Counters()
        self.ins = Inputs(self.name, rnode, self.counts)
        self.inputs = self.ins.buffers
        self.input_times = self.ins.times
        self.trigger_inputs = self.ins.triggers
        self.lossless = self.ins.lossless
        self.frame_seqs = {}
        self.outputs = {
            p: [] for p in [*rnode.cls.outputs, *rnode.cls.params_outputs(rnode.params)]
        }
        self.tick_ports = {p: f"{self.name}.{p}" for p in rnode.cls.frame_ports()}
        self.out_check = OutputCheck(rnode, self.outputs)
        src = rnode.frame_source
        self.frame_key = sched.graph.frame_port(src) if src is not None else None
        self.executor = NoExecutor()
        self.timer = None
        self.task = None
        self.state = RunState.idle
        self._busy = False
        self._idle_waiters = []
        self.deferred = None
        self.untaken = False
        self.stopping = False
        self.cut_short = False
        self.act = None
        self._acts = 0
        self._loose = []
        self.error_reason = None
        self.waiting_reason = None
        self.deadlines = DeadlineWatch(
            self.name,
            self.timing,
            self.counts,
            sched.clock,
            lambda e: sched.emit(e),  # late-bound: an observer may tee the scheduler's emit
            sched.rel,
            lambda: self.rnode.spec.miss_policy,
        )
        self.pipeline = Pipeline(self)
        self.backpressure = Backpressure(sched.loop, self.idle)
        self.supervisor = Supervisor(self)
        self.swapper = Swapper(self)
        self.disable_hook = DisableHook(self.name)
        self.hops = Hops(self)

    # --- failures (supervision decides, the runner applies) ------------------------------

    def fail(self, exc: BaseException, starting: bool = False) -> None:
        """The node raised (or could not start, or returned what its outputs cannot carry):
        restart after a back-off, or give up. Either way this instance is gone, and with it
        the pipelined calls still in flight on it: whichever of them failed first is the one
        failure (an output check on the loop, as a raise in the worker), the others are
        aborted, so they neither fail the node again nor restart a node given up."""
        self.pipeline.lose_in_flight()
        decision = self.supervisor.failed(exc, starting)
        self.busy = False
        if isinstance(decision, GiveUp):
            self.move(RunState.failed)
            self.supervisor.gave_up(decision)
            self.sched.loop.create_task(self.supervisor.stop_executor(self.executor))
        else:
            self.move(RunState.backoff)
            self.sched.loop.create_task(self._restart(decision))

    async def _restart(self, decision: Restart) -> None:
        if not await self.supervisor.backoff(decision, self.executor):
            return
        self.install(self.make_executor())  # before its setup: a stop meanwhile tears it down
        try:
            await self.executor.start()
        except Exception as e:
            self.fail(e, starting=True)
            return
        self.move(RunState.idle)
        self.idle()

    def teardown_failed(self, exc: BaseException) -> None:
        """``teardown`` failed at the run's end: the node ends ``failed`` (the run exits 1)."""
        if self.supervisor.teardown_failed(exc) is not None:
            self.move(RunState.failed)

    # --- readiness ----------------------------------------------------------------------

    def cancelled(self, task: asyncio.Task[None]) -> None:
        """A task cancelled before its first step never ran ``run_async``'s own clean-up."""
        if task is self.task and task.cancelled() and self.busy and not self.backpressure.blocked:
            self._drop_loose()
            self.untaken = False
            self.busy = False
            if self.state is RunState.running:
                self.move(RunState.idle)

    def catch_up(self) -> None:
        """Run once more for a lossless input's backlog (never skipped: see release)."""
        if self.pipeline.active():
            self.pipeline.schedule_pump()  # several activations may take from the backlog
            return
        if (
            not self.busy
            and self.state is _IDLE
            and not self.stopping
            and self.timing.enabled
            and self.ins.backlog()
        ):
            self.release(self.sched.clock.now())

    def stop_releasing(self) -> None:
        """No release from now on (stop, or the drain of a source)."""
        self.stopping = True
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None

    # --- wiring -------------------------------------------------------------------------

    def make_executor(self, rnode: ResolvedNode | None = None, reload: bool = False) -> Executor:
        """An executor for ``rnode`` (default: the runner's own) where its placement says."""
        rnode = rnode or self.rnode
        if rnode.spec.placement is Placement.inline:
            ctx = RunnerContext(self)
            cls, params = rnode.cls, rnode.params
            return InlineExecutor(lambda: make_node(cls, params, ctx))
        factory = NodeFactory(rnode.cls, rnode.params, self.name)
        factory.reload = reload
        return self.sched.worker_executor(rnode, self.timing.priority, factory)

    def connect_input(self, port: str, buf: Buffer) -> None:
        self.ins.connect(port, buf, self.input_arrived, self.catch_up)

    # --- releases -----------------------------------------------------------------------

    def release(self, t_release: float) -> None:
        """A trigger fired: run now unless disabled, down, or still running (overrun)."""
        if not self.timing.enabled or self.stopping:
            return
        if self.sched.stop_at is not None and self._past_stop():
            return
        busy = self.busy  # (read once: a property; the two moves below cost as much)
        if (busy or self.state in _WAITING) and self.ins.backlog():
            return  # not skipped: the lossless value waits, and idle() runs the node for it
        self.counts.activations += 1
        if busy or self.state in _DOWN:
            self.counts.skipped += 1
            for buf in self.inputs.values():
                buf.reader_skipped()  # the value it was due to read is lost if replaced
            return
        self._busy = True  # (the setter acts on False only)
        self.untaken = True
        loop = self.sched.loop
        if self.executor.sync:
            loop.call_soon(self.run_sync, t_release)
        else:
            self.task = loop.create_task(self.run_async(t_release))

    @property
    def source(self) -> bool:  # no inputs, or free-running: stopped at once (the rest drains)
        return not self.inputs or isinstance(self.rnode.trigger, LoopTrigger)

    def _past_stop(self) -> bool:
        """A source released at or after the run's stop: never again (see Scheduler.stop_at)."""
        stop_at = self.sched.stop_at
        if stop_at is None or self.sched.clock.now() < stop_at or not self.source:
            return False
        self.stop_releasing()
        return True

    def release_frame(self, t: float, paced: bool) -> None:
        """Tick of this node's frame source, on its period and phase (see Scheduler.tick)."""
        if paced and self.timing.period == 1:
            if self.window > 1:
                self.pipeline.release_paced(t)  # a worker's call may follow the one in flight
                return
            if self.busy and self.deferred is None:
                self.deferred = t  # not an overrun: the source waited for this reader
                self.counts.lead_max = max(self.counts.lead_max, 2)  # one running, one waiting
                return
            self.release(t)
            self.counts.lead_max = max(self.counts.lead_max, int(self.busy))
            return
        self.release(t)

    def release_timer(self, t: float, missed: int) -> None:
        """The node's timer fired at ``t``; ``missed`` releases passed unserved before it."""
        if missed and self.timing.enabled:
            self.counts.activations += missed
            self.counts.skipped += missed
        self.release(t)

    def input_arrived(self) -> None:
        if self.hops.armed is not None:  # its call went ahead: the activation begins now
            self.hops.arrived()
            return
        if self.executor.pipelined and self.pipeline.window > 1:  # (inline: one attribute)
            self.pipeline.schedule_pump()
            return
        if self.busy or self.state is not _IDLE or self.stopping or not self.timing.enabled:
            return  # the pending input is taken when the run ends (see the end of a run)
        self.release(self.sched.clock.now())

    # --- one activation -----------------------------------------------------------------

    def begin(self, t_release: float, taken: tuple[float, Any] | None = None) -> Activation | None:
        """Take the inputs of a released activation (``taken``: the start and inputs of a
        precise thread's call, see kernel/precise.py); None: skipped (counted)."""
        if taken is None and self.sched.stop_at is not None and _taken_back(self):
            return None
        now, inputs = taken or (self.sched.clock.now(), self.ins.take())
        self.untaken = False
        if self._idle_waiters:
            self.readers_may_go()  # a paced source may publish the next frame now
        if inputs is None:
            self.counts.skipped += 1
            return None
        c = self.counts
        if c.interval_from is not None:
            c.interval.add(now - c.interval_from)
        c.interval_from = c.last_start = now
        self.move(_RUNNING)  # (pipelined: it may be running already)
        if (obs := self.sched.observer) is not None:
            held = {p: b.taken_seq for p, b in self.inputs.items()}
            obs.activation(self.name, t_release, now, held, self.rnode)
        self._acts += 1
        act = Activation(self._acts, t_release, now, inputs=inputs)
        if self._loose:
            act.made, self._loose = self._loose, []
        return act

    def new_frame(self, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame:
        """A frame for this node to fill (``ctx.new_frame``), held by its activation."""
        frame = self.sched.new_frame(self.name, shape, dtype, pixel_format)
        (self.act.made if self.act is not None else self._loose).append(frame)
        return frame

    def _drop_loose(self) -> None:
        loose, self._loose = self._loose, []
        release_all(loose)

    def run_sync(self, t_release: float) -> None:
        act = self.begin(t_release)
        if act is None:
            self.idle()
            return
        self.act = act
        try:
            result = self.executor.call_sync(act.inputs)
        except Exception as e:
            self.act = None
            act.close()
            self.fail(e)
            return
        self.act = None
        end = self.sched.clock.now()
        if end - act.start > BLOCKING_THRESHOLD and self.sched.real_time:
            self.sched.blocked_calls += 1
            self.sched.emit(LoopBlocked(self.sched.rel(end), self.name, (end - act.start) * 1000))
        self.complete(act, result, end)

    async def run_async(self, t_release: float) -> None:
        act = self.begin(t_release)
        if act is None:
            self.hops.drop()
            self.idle()
            return
        self.act = act
        self.deadlines.arm(act)
        spec = self.rnode.spec
        inline = spec.placement is Placement.inline
        watchdog = _watchdog(self.sched, self.task, spec.watchdog, act.start) if inline else None
        try:
            result = await self.hops.call(act.inputs)
        except asyncio.CancelledError as e:
            act.close()
            if self.stopping:
                self.idle()
                raise
            wd = self.rnode.spec.watchdog or 0
            self.fail(TimeoutError(f"watchdog: no return within {wd:g} ms ({e})"))
            return
        except Exception as e:
            act.close()
            self.fail(e)
            return
        finally:
            self.hops.ended()
            self.act = None
            self.deadlines.disarm(act)
            if watchdog is not None:
                watchdog.cancel()
        act.adopt(result)
        self.complete(act, result, self.sched.clock.now())

    def complete(self, act: Activation, result: Any, end: float) -> None:
        """``act`` returned ``result`` at ``end``: count it, publish (or discard), close."""
        if result is not None and (bad := self.out_check.problem(result)) is not None:
            act.close()  # what its outputs cannot carry: the node's failure, as if raised
            self.fail(bad)
            return
        c = self.counts
        c.completions += 1
        c.last_finish = end
        try:
            timed = act.timer is not None or self.timing.deadline is not None  # else: no call
            discard = self.deadlines.finish(act, end) if timed else False
            if (obs := self.sched.observer) is not None:
                obs.completed(self.name, act.t_release, end, discard)
            if discard:
                c.discarded += 1
                act.discard(result)
            elif result is not None:
                self.publish_result(result, end)
        finally:
            act.close()
            # The statistics after the publication: a reader served on the spot (an
            # export's send) does not wait for them; nothing between reads them (no await).
            c.execution.add(end - act.start)
            c.response.add(end - act.t_release)
            if self.supervisor.consecutive:
                self.supervisor.succeeded()
        self.idle()

    def publish_result(self, result: Any, t: float) -> None:  # (on_disable's too)
        outs = self.outputs
        if len(outs) == 1:
            (port,) = outs
            self.publish(port, result, t)
            return
        for port, value in result.items():
            if value is not None:
                self.publish(port, value, t)

    def publish(self, port: str, value: Any, t: float) -> None:
        """Fan a value out to every reader of ``port``; a frame port also ticks its frame clock."""
        if isinstance(value, Frame) and value.timestamp == 0.0:
            _stamp(value, port, self.frame_seqs, self.counts.last_start, t)
        if self.sched.observer is not None:
            self.sched.observer.published(self.name, port, value, t)
        for buf in self.outputs[port]:
            if not buf.put(value, t):
                assert isinstance(buf, LosslessBuffer)
                self.backpressure.hold(buf, value, t)
        key = self.tick_ports.get(port)
        if key is not None:
            self.sched.tick(key, t)

    # --- between activations ------------------------------------------------------------

    def idle(self) -> None:
        """An activation ended: the node is free unless values wait; start what is due."""
        if self.backpressure.blocked:
            self.backpressure.start()  # idle() again once the values are in
            return
        if self.pipeline.inflight > 0:  # more activations in flight; take the next input
            self.pipeline.schedule_pump()
            return
        self.busy = False
        if self.state is _RUNNING:
            self.move(_IDLE)
        if self.swapper.pending is not None and not self.busy:  # (precise: calls in flight)
            self.swapper.take_pending()  # a swap waits for this moment
        self.disable_hook.idle(self)  # a disabling waited for this moment
        if self.stopping:
            return
        if self.sched.drain_over():  # a call that ended past the drain's deadline: no next
            self.stop_releasing()
            self.cut_short = True
            return
        if self.deferred is not None:  # a paced source's frame waits: run on it now
            t, self.deferred = self.deferred, None
            if self.window > 1:
                self.pipeline.release_paced(t)
            else:
                self.release(t)
        if isinstance(self.rnode.trigger, LoopTrigger):
            self.sched.loop.call_soon(self.release, self.sched.clock.now())
        elif self.trigger_inputs:
            buffers = self.inputs
            for p in self.trigger_inputs:
                if buffers[p].pending():
                    self.input_arrived()  # release() schedules the run: no re-entry
                    break
        if self.lossless and not self.busy:
            self.sched.loop.call_soon(self.catch_up)


def _taken_back(r: NodeRunner) -> bool:
    """A source released before the run's stop and begun after it (a slow call held the loop
    between; uvloop runs due timers before queued callbacks): it publishes nothing after the
    stop, as one released after it does not; the stop takes the release back."""
    if not r._past_stop():
        return False
    r.untaken = False
    r.counts.activations -= 1  # (counted by release())
    return True


def _stamp(frame: Frame, port: str, seqs: dict[str, int], last: float | None, t: float) -> None:
    """A ``Frame(array)`` made without a timestamp: the activation's time, and the node's own
    sequence on that port when its seq was left at 0 too (recordings, health and freshness
    need both; a 4 s recording showed 'duration 1336 s, missing 19987')."""
    frame.timestamp = last if last is not None else t
    n = seqs.get(port, 0)
    if frame.seq == 0:
        frame.seq = n
    seqs[port] = max(n, frame.seq) + 1


def _watchdog(sched: SchedulerPort, task: Any, wd: float | None, start: float) -> Handle | None:
    """An inline coroutine that does not return within its watchdog (ms) is cancelled."""
    if wd is None or task is None:
        return None

    def cancel() -> None:
        task.cancel(f"watchdog {wd:g} ms")

    return sched.clock.call_at(start + wd / 1000, cancel)
