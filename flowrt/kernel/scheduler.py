"""The frame-tick scheduler: frame clocks, timers and dispatch order for a graph's runners.

The ``Scheduler`` owns the frame clocks (one tick counter per frame source), the timers and
the order of dispatch (priority, then file order); each :class:`NodeRunner` decides whether
a release runs. Everything runs on one event loop, so a change made by ``apply_timing``
between two callbacks is atomic with respect to ticks.

Activation semantics (the CAMBADA process manager):
- frame trigger: on tick ``k`` of the source, release when ``k % period == phase``;
- timer trigger: release at ``origin + phase + n*period`` (timerfd, no drift);
- input trigger: release when a triggering input receives data (see the runner);
- a release while the previous activation still runs is skipped and counted (overrun).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from ..clock import Clock, SystemClock
from ..edges import Buffer, make_buffer
from ..events import Event, TimingChanged
from ..frames import Frame
from ..graph._resolve import Graph, ResolvedNode
from ..graph.spec import LoopTrigger, Placement
from ..node import NodeFactory
from ..stats import NodeStats
from .drain import Drain
from .executor import Executor
from .hops import wire_hops
from .precise import PreciseNodeRunner
from .runner import NodeRunner
from .services import Services
from .state import RunState
from .timing import Timing, TimingChange
from .views import NodeView, reports_of, view_of

log = logging.getLogger("flowrt.scheduler")
TEARDOWN_GRACE = 2.0
"""Seconds a node's ``teardown`` may take at the run's end (a worker's, then its exit, as
long again): one that does not return is the node's failure, the run exits 1."""


class Scheduler:
    """Frame clocks, timers and dispatch order for a graph's runners."""

    def __init__(self, graph: Graph, clock: Clock, services: Services) -> None:
        self.graph = graph
        self.clock = clock
        self.services = services
        self.emit: Callable[[Event], None] = services.emit
        self.real_time = services.real_time
        self.loop = asyncio.get_event_loop()
        self.blocked_calls = 0
        self.observer: Any = None  # set by ctx.observe (flowrt.determinism)
        self.runners: dict[str, NodeRunner] = {}
        for name in sorted(graph.nodes, key=lambda n: graph.nodes[n].order):
            rnode = graph.nodes[name]
            precise = rnode.spec.timing == "precise"
            self.runners[name] = (PreciseNodeRunner if precise else NodeRunner)(self, rnode)
        self.buffers: list[Buffer] = []
        self.reader_of: dict[int, NodeRunner] = {}  # id(edge buffer) -> the node reading it
        for edge in graph.edges:
            buf = make_buffer(edge.policy.value, edge.name, edge.size, clock.now)
            self.runners[edge.src].outputs[edge.src_port].append(buf)
            self.runners[edge.dst].connect_input(edge.dst_port, buf)
            self.buffers.append(buf)
            self.reader_of[id(buf)] = self.runners[edge.dst]
        wire_hops(self.runners, graph.edges)
        self.paced: set[str] = set()  # frame clocks whose source waits for its readers
        # When the run's stop is due (Runtime.run's then_stop): no source is released from
        # then on, though its timer's handle, due earlier, runs after it (a loop held).
        self.stop_at: float | None = None
        self._drain = Drain(self, services.drain_timeout)
        # frame clocks: source key -> (tick count, readers in dispatch order)
        self.ticks: dict[str, int] = {}
        self.readers: dict[str, list[NodeRunner]] = {}
        for r in self.runners.values():
            key = r.frame_key  # the runner's frame clock, from the same graph
            if key is not None:
                self.readers.setdefault(key, []).append(r)
                self.ticks.setdefault(key, 0)
        self.order: list[NodeRunner] = []
        self.resort()
        # "setting up", "running", "draining", "tearing down": what a signal interrupts
        self.stage = "setting up"
        self.setting_up: list[str] = []  # nodes whose setup() runs now (what a signal cuts)

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

    def worker_executor(self, rnode: ResolvedNode, priority: int, factory: NodeFactory) -> Executor:
        workers = self.services.workers
        if workers is None:
            raise RuntimeError(
                f"{rnode.name}: placement {rnode.spec.placement.value} needs worker support"
            )
        return workers.executor_for(rnode, priority, factory)

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame:
        frames = self.services.frames
        if frames is not None:
            return frames.new_frame(owner, shape, dtype, pixel_format)
        return Frame(np.empty(shape, dtype=dtype), source=owner, pixel_format=pixel_format)

    def tick(self, key: str, t: float) -> None:
        """A frame was published on ``key``: release the readers whose period/phase match."""
        k = self.ticks.get(key)
        if k is None:
            return
        self.ticks[key] = k + 1
        paced = key in self.paced
        for r in self.readers[key]:
            if k % r.timing.period == r.timing.phase:
                r.release_frame(t, paced)

    async def wait_readers(self, runner: NodeRunner) -> None:
        """Wait until every period-1 frame-triggered reader of ``runner``'s frames is ready.

        A ``pacing: fast`` source calls this before publishing: a reader in a worker process
        that is slower than the source is then never skipped (the source follows the slowest
        such reader instead of outrunning it). "Ready" means the reader has taken the previous
        frame: it may still run on it, and the new frame's tick then waits for it to finish
        (deferred, not skipped), so that the source prepares frame k+1 while the worker
        processes frame k. A reader in a worker of its own is pipelined instead: it is
        ready while fewer than its window of frames are in flight (see
        :meth:`flowrt.kernel.pipeline.Pipeline.paced_reader`). Readers with a longer period
        sample by design and are not waited for; nor are failed, disabled or stopping ones.
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
            r.install(r.make_executor())
            r.move(RunState.starting)

        async def start_one(r: NodeRunner) -> None:
            self.setting_up.append(r.name)
            try:
                await r.executor.start()
                r.move(RunState.idle)
            except Exception as e:
                r.fail(e, starting=True)
            finally:
                self.setting_up.remove(r.name)

        inline = [r for r in self.runners.values() if r.rnode.spec.placement is Placement.inline]
        others = [
            r for r in self.runners.values() if r.rnode.spec.placement is not Placement.inline
        ]
        await asyncio.gather(*(start_one(r) for r in others))
        for r in inline:
            await start_one(r)
        for r in self.order:
            if isinstance(r, PreciseNodeRunner) and self._real_time_clock():
                r.start_precise(_ms_s(r.rnode.spec.spin))
            elif r.timing.timer is not None:
                r.arm(self.clock.periodic(r.timing.timer, r.timing.timer_phase, r.release_timer))
            elif isinstance(r.rnode.trigger, LoopTrigger):
                self.loop.call_soon(r.release, self.clock.now())
        self.stage = "running"

    def _real_time_clock(self) -> bool:
        """``timing: precise`` needs real time (virtual time has no instant to sleep to: the
        clock's own timer releases the node there, by the same rules)."""
        return isinstance(self.clock, SystemClock)

    @property
    def drain_timeout(self) -> float:
        return self._drain.timeout

    async def drain(self, limit: float | None = None) -> list[str]:
        """See :meth:`flowrt.kernel.drain.Drain.run`."""
        return await self._drain.run(limit)

    @property
    def drain_cut(self) -> bool:
        return self._drain.cut

    def drain_over(self) -> bool:
        """The drain is past its deadline or cut: no activation begins any more."""
        return self.stage == "draining" and self._drain.over()

    def stop_due(self, t: float) -> None:
        """The run's stop is due at ``t`` (the earliest asked is kept): no source is released
        from then on (NodeRunner.release). Only writes a time: safe in a signal handler."""
        if self.stop_at is None or t < self.stop_at:
            self.stop_at = t

    def stop_sources(self) -> None:
        """The stop is asked for: sources publish nothing more (see Drain.stop_sources)."""
        if self.stage in ("running", "draining"):
            self._drain.stop_sources()

    def cut_drain(self) -> bool:
        """Cut the drain short (a signal once the stop is asked for): in progress, or before
        it begins; its leftovers are counted as dropped, reason ``interrupted``. False once
        the teardown has begun."""
        if self.stage not in ("running", "draining"):
            return False
        self._drain.cut = True
        return True

    async def abort(self, grace: float = 0.3) -> None:
        """The set-up was interrupted: every node torn down at once, in parallel, its worker
        killed if it does not exit within ``grace`` (a ``setup`` still running in it is not
        waited for). Nothing has run yet, so there is nothing to drain."""
        self.stage = "tearing down"
        for r in self.runners.values():
            r.stop_releasing()

        async def one(r: NodeRunner) -> None:
            try:
                await asyncio.wait_for(r.executor.stop(grace), timeout=4 * grace + 1.0)
            except Exception as e:
                log.debug("node %s: stop at an interrupted set-up: %r", r.name, e)

        await asyncio.gather(*(one(r) for r in self.runners.values()))

    async def stop(self, grace: float = 1.0) -> None:
        """Drain (bounded), stop releasing, cancel what still runs, tear every node down."""
        self.stage = "draining"
        await self.drain()
        self.stage = "tearing down"
        for r in self.runners.values():
            r.stop_releasing()
        for r in self.runners.values():
            if isinstance(r, PreciseNodeRunner):
                await r.precise_stopped()  # a call in its thread ends before the teardown
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
            r.backpressure.task
            for r in self.runners.values()
            if r.backpressure.task is not None and not r.backpressure.task.done()
        ]
        for t in drains:
            t.cancel()
        if drains:
            await asyncio.wait(drains, timeout=grace)
        self._drain.discard_leftovers()
        teardown = max(grace, TEARDOWN_GRACE)
        for r in reversed(self.order):
            try:  # each executor bounds its teardown by ``teardown``; this, its worker's exit
                await asyncio.wait_for(r.executor.stop(teardown), timeout=4 * teardown + 1.0)
            except Exception as e:
                r.teardown_failed(e)
        for r in self.runners.values():
            r.supervisor.log.flush(self.clock.now())

    # --- reads from outside the kernel (flowrt.kernel.views) ----------------------------

    def timing_of(self, node: str) -> Timing:
        """A copy of ``node``'s timing now (KeyError: no such node)."""
        return self.runners[node].timing.copy()

    def node_views(self) -> list[NodeView]:
        """Every node as of now, in the graph's order."""
        return [view_of(r) for r in self.runners.values()]

    def node_view(self, node: str) -> NodeView:
        """``node`` as of now (KeyError: no such node)."""
        return view_of(self.runners[node])

    def node_stats(self) -> list[NodeStats]:
        """Every node's row of the statistics table, in the graph's order."""
        return [r.stats() for r in self.runners.values()]

    def node_reports(self) -> dict[str, Any]:
        """Each inline node's optional ``report()`` (also after stop: its last instance's)."""
        return reports_of(self.runners.values())

    # --- run-time changes ---------------------------------------------------------------

    def apply_timing(self, node: str, change: TimingChange, origin: str = "api") -> str:
        """Apply a timing change now (between ticks: the loop runs one callback at a time).

        ``change`` was validated by whoever made it (:meth:`TimingChange.problems`, checked
        by ``Runtime.set_timing``/``set_mode``): this applies it, says what changed (a
        ``TimingChanged`` event) and returns the same words.
        """
        r = self.runners[node]
        tm = r.timing
        changes: list[str] = []

        def note(label: str, old: Any, new: Any) -> None:
            if new is not None and new != old:
                changes.append(f"{label} {old} -> {new}")

        note("period", tm.period, change.period)
        note("phase", tm.phase, change.phase)
        note("timer_ms", _ms(tm.timer), _float(change.timer_ms))
        note("deadline_ms", _ms(tm.deadline), _float(change.deadline_ms))
        phase_ms = None if tm.timer is None else tm.timer_phase * 1000
        note("timer_phase_ms", phase_ms, _float(change.timer_phase_ms))
        note("priority", tm.priority, change.priority)
        note("enabled", tm.enabled, change.enabled)
        if change.period is not None:
            tm.period = change.period
        if change.phase is not None:
            tm.phase = change.phase
        if change.deadline_ms is not None:
            tm.deadline = change.deadline_ms / 1000
        if change.priority is not None:
            tm.priority = change.priority
            self.resort()
            r.executor.set_priority(change.priority)
        if change.enabled is not None:
            was = tm.enabled
            tm.enabled = change.enabled
            loop_node = isinstance(r.rnode.trigger, LoopTrigger)
            if change.enabled and not was and loop_node and not r.busy:
                self.loop.call_soon(r.release, self.clock.now())
            if was and not change.enabled:
                r.disable_hook.disabled(r)  # what it drives made safe (Node.on_disable)
        self._apply_timer(r, change)
        restart = ("period", "phase", "timer_ms", "timer_phase_ms", "enabled")
        if any(c.split()[0] in restart for c in changes):
            r.counts.new_interval_series(self.clock.now())
        text = ", ".join(changes) or "no change"
        if changes:
            self.emit(TimingChanged(self.rel(self.clock.now()), node, text, origin))
        return text

    @staticmethod
    def _apply_timer(r: NodeRunner, change: TimingChange) -> None:
        tm = r.timing
        timer = None if change.timer_ms is None else change.timer_ms / 1000
        if change.timer_phase_ms is not None and tm.timer is not None:
            tm.timer_phase = change.timer_phase_ms / 1000
        if (timer is not None or change.timer_phase_ms is not None) and r.timer is not None:
            tm.timer = tm.timer if timer is None else timer
            assert tm.timer is not None
            r.timer.reset(tm.timer, min(tm.timer_phase, tm.timer * 0.999))
        elif timer is not None:
            tm.timer = timer


def _ms_s(ms: float | None) -> float:
    return 0.0 if ms is None else ms / 1000


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1000


def _float(ms: float | None) -> float | None:
    return None if ms is None else float(ms)
