"""The embedding API: a graph running on the current event loop.

    async with flowrt.Runtime.from_file("graph.yaml") as rt:
        await rt.run(10.0)
        print(rt.stats())

The runtime owns the scheduler, the frame store, worker processes and the monitors (the
status table, the web view, JSON statistics all watch it through :class:`Monitor`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import os
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from .clock import Clock, SystemClock
from .edges import EMPTY, Buffer, make_buffer
from .eventloop import run as run
from .events import Event, HealthAlert, ModeChanged, NodeGaveUp, NodeSwapped, RealtimeStatus
from .frames import SHM_DIR, Frame, FrameStore
from .graph import Graph, resolve
from .node import Node, NodeFactory
from .scheduler import Executor, NodeRunner, Scheduler
from .spec import EdgePolicy, GraphSpec, ModeSpec, Placement, TimingOverride
from .stats import (
    FramePoolStats,
    LoopStats,
    NodeStats,
    Running,
    RuntimeStats,
    WorkerFrameStats,
)

if TYPE_CHECKING:
    from .oscheduling import FairShare
    from .qos import OverloadController, QosStatus
    from .rtdb import RTDB

log = logging.getLogger("flowrt")
T = TypeVar("T")


class SwapError(Exception):
    """A swap that did not happen; the old instance runs on. The message says why."""


class Monitor(Protocol):
    """Something that watches a runtime: told when it starts, of each event, when it stops."""

    def started(self, rt: Runtime) -> None: ...

    def event(self, event: Event) -> None: ...

    def stopped(self, rt: Runtime) -> None: ...


class Subscription:
    """Values published on a port, delivered to the host program through its own buffer."""

    def __init__(self, buf: Buffer) -> None:
        self._buf = buf
        self._ready = asyncio.Event()
        buf.on_put = self._ready.set

    def get_nowait(self) -> Any:
        """The next value, or raise LookupError when none is waiting."""
        value = self._buf.take_new()  # type: ignore[attr-defined]
        if value is EMPTY:
            raise LookupError("no value waiting")
        if isinstance(value, Frame):
            value.release()  # the host keeps a plain reference; the slot may be reused later
        return value

    def take_held(self) -> Any:
        """The next value with its frame link kept (the caller must ``release()`` it), or EMPTY.

        For a monitor that hands frames to another thread: the pool slot is not recycled
        before that thread is done with the pixels.
        """
        return self._buf.take_new()  # type: ignore[attr-defined]

    def drain(self) -> list[Any]:
        """Every value waiting now, oldest first (the newest only, for a latest buffer)."""
        out = []
        while self._buf.pending():
            out.append(self.get_nowait())
        return out

    async def get(self) -> Any:
        while not self._buf.pending():
            self._ready.clear()
            await self._ready.wait()
        return self.get_nowait()

    def __aiter__(self) -> AsyncIterator[Any]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[Any]:
        while True:
            yield await self.get()

    @property
    def dropped(self) -> int:
        return self._buf.dropped


class Runtime:
    """A graph, its scheduler and its resources, on the running event loop."""

    def __init__(
        self,
        graph: Graph | GraphSpec,
        *,
        clock: Clock | None = None,
        monitors: Iterable[Monitor] = (),
        realtime: bool = False,
        kinds: Mapping[str, type[Node]] | None = None,
        spin: float = 0.0,
        drain_timeout: float = 5.0,
        stop_on_failure: bool = False,
    ) -> None:
        """``drain_timeout``: seconds ``stop`` lets the graph finish what it holds (lossless
        edges, in-flight activations) after stopping the sources; reported when hit.
        ``stop_on_failure``: a node given up by supervision (state ``failed``) ends ``run``
        at once (``flowrt run`` does this unless ``--keep-going``); by default the rest of
        the graph keeps running and the host program reads :meth:`failures`."""
        if not drain_timeout >= 0 or math.isinf(drain_timeout):
            raise ValueError(f"drain_timeout must be finite and >= 0, got {drain_timeout}")
        self.drain_timeout = drain_timeout
        self.stop_on_failure = stop_on_failure
        self.graph = graph if isinstance(graph, Graph) else resolve(graph, kinds=kinds)
        if clock is not None and spin:
            raise ValueError("spin is the system clock's: pass SystemClock(spin=...) as clock")
        self.clock: Clock = clock or SystemClock(spin=spin)
        self.monitors: list[Monitor] = list(monitors)
        self.realtime_requested = realtime
        self.realtime = ""
        self.latency_hint = ""
        self.mode: str | None = None
        self.events: deque[Event] = deque(maxlen=1000)
        self.event_count = 0
        self._listeners: list[Callable[[Event], None]] = []
        self._sched: Scheduler | None = None
        self._stop = asyncio.Event()
        self._lag = Running()
        self._lag_handle: asyncio.TimerHandle | None = None
        self._frames: Any = None
        self._pool: Any = None
        self._grants: dict[str, list[Any]] = {}  # node -> its executors' output slots
        self._last_frame_stats: list[FramePoolStats] = []
        self._gap_cache: tuple[tuple[tuple[float, float], ...], tuple[float, float]] | None = None
        self._rtdb: RTDB | None = None
        self._fair: FairShare | None = None
        self._nice_before: int | None = None
        self.qos: OverloadController | None = None
        self._bridge: Any = None  # flowrt.remote.ZenohBridge when the graph spans machines
        self.started = False
        self.starvation_events = 0  # worker calls spared by the watchdog: starved, not hung
        self._starved_alert_at = -math.inf

    @property
    def remote_session(self) -> Any:
        """The graph's Zenoh session (``zenoh.Session``) while running, else None: for users
        of the runtime that talk through it (e.g. :class:`flowrt.remote_control.ZenohControl`)."""
        return None if self._bridge is None else self._bridge.session

    @classmethod
    def from_file(cls, path: str | Path, **kwargs: Any) -> Runtime:
        """Load and validate a graph file (raises GraphError listing every problem)."""
        return cls(Graph.from_file(path, kinds=kwargs.get("kinds")), **kwargs)

    # --- lifecycle ----------------------------------------------------------------------

    async def __aenter__(self) -> Runtime:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        if self.started:
            return
        spec = self.graph.spec
        if spec.zenoh is not None or spec.exports or spec.imports:
            # First: a port in use or a bad endpoint fails here, before anything runs.
            from .remote import ZenohBridge

            bridge = ZenohBridge(_RemoteHost(self), spec)
            await bridge.open()
            self._bridge = bridge
        if self.realtime_requested:
            from .realtime import enable_realtime

            granted, self.realtime = enable_realtime()
            if not granted:
                log.warning("--realtime: %s", self.realtime)
        if not self.realtime.startswith("SCHED_FIFO"):
            self._fair_share()
        self._frames = _frame_store()
        if any(n.spec.placement is not Placement.inline for n in self.graph.nodes.values()):
            from .workers import start_forkserver

            await asyncio.to_thread(start_forkserver)  # preloaded numpy/cv2: shared pages
        # Imported now, not at the first run-time change: an import on the loop at that moment
        # (tens of ms) would make the ticks around a `ctl timing` late.
        from .analysis import admission  # noqa: F401

        _freeze_heap()
        self.clock.origin = self.clock.now() + (
            0.005 if isinstance(self.clock, SystemClock) else 0.0
        )
        self._sched = Scheduler(
            self.graph,
            self.clock,
            self._emit,
            worker_executor=self._worker_executor,
            new_frame=self._new_frame if self._frames is not None else None,
            real_time=isinstance(self.clock, SystemClock),
        )
        self._sched.stats_provider = self.stats
        self._sched.stop_requester = self.request_stop
        self._sched.rtdb_provider = lambda: self.rtdb
        self._sched.mode_setter = self.set_mode
        self._sched.drain_timeout = self.drain_timeout
        if self._bridge is not None:
            self._bridge.attach_exports()
        overload = self.graph.spec.qos.overload
        if overload is not None and self.qos is None:
            from .qos import OverloadController

            self.qos = OverloadController(overload)
            self.monitors.append(self.qos)
        self.started = True
        for m in self.monitors:
            m.started(self)
        if self.realtime:
            self._emit(RealtimeStatus(0.0, None, self.realtime))
        await self._sched.start()
        if self._bridge is not None:
            self._bridge.attach_imports()
        gc.freeze()  # what the nodes' setup made, too
        if self.graph.spec.initial_mode:
            self.set_mode(self.graph.spec.initial_mode, origin="graph")
        if isinstance(self.clock, SystemClock):
            self._probe_lag(self.clock.now())

    async def stop(self) -> None:
        """Drain, tear every node down, stop workers, free shared memory; safe to call twice.

        The drain first stops the sources, then lets every lossless edge deliver what it
        holds and every in-flight activation finish, for at most ``drain_timeout`` seconds
        (a ``drain-timeout`` HealthAlert says what was left); what is still undelivered then
        is counted as dropped with its reason (``EdgeStats.drop_reasons``).
        """
        if not self.started:
            return
        self.started = False
        self._stop.set()
        if self._lag_handle is not None:
            self._lag_handle.cancel()
        if self._bridge is not None:
            with contextlib.suppress(Exception):
                await self._bridge.close()
            self._bridge = None
        try:
            if self._sched is not None:
                await self._sched.stop()
        finally:
            if self._pool is not None:
                with contextlib.suppress(Exception):
                    await self._pool.stop()
            if self._frames is not None:
                self._frame_stats()  # the final figures, before the pools go
                self._frames.close()
            for m in self.monitors:
                try:
                    m.stopped(self)
                except Exception:
                    log.exception("monitor failed at stop")
            if self._rtdb is not None:
                self._rtdb.close()
            self._restore_fair_share()
            gc.unfreeze()

    async def run(self, duration: float | None = None) -> None:
        """Run until ``duration`` seconds have passed or ``request_stop`` is called."""
        if not self.started:
            await self.start()
        if duration is None:
            await self._stop.wait()
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stop.wait(), timeout=duration)

    def request_stop(self) -> None:
        """Ask ``run`` to return (signal-handler safe on the loop thread)."""
        self._stop.set()

    @property
    def loop_scheduling(self) -> str:
        """What the loop process was granted: SCHED_FIFO, or its nice level and slice."""
        return self.realtime if self.realtime.startswith("SCHED_FIFO") else self.latency_hint

    # --- resources ----------------------------------------------------------------------

    def _fair_share(self) -> None:
        """Without SCHED_FIFO: the loop at the lowest nice permitted, workers ranked above it.

        The loop also asks for a short EEVDF slice, so that its timer wake-ups preempt a busy
        process instead of waiting for that process's slice to end.
        """
        from .oscheduling import FairShare, lowest_nice, request_short_slice

        floor = lowest_nice()
        self._nice_before = nice = os.getpriority(os.PRIO_PROCESS, 0)
        with contextlib.suppress(OSError):
            if floor < nice:
                os.setpriority(os.PRIO_PROCESS, 0, floor)
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        # Ranked among the workers only: inline nodes run in the loop, which is above them all.
        workers = {
            name for name, n in self.graph.nodes.items() if n.spec.placement is not Placement.inline
        }
        priorities = [self.graph.nodes[name].spec.priority for name in workers]
        for mode in self.graph.spec.modes.values():
            priorities += [
                o.priority
                for name, o in mode.nodes.items()
                if name in workers and o.priority is not None
            ]
        self._fair = FairShare(priorities, nice)
        self.latency_hint = ", ".join(x for x in (f"nice {nice}", request_short_slice()) if x)

    def _restore_fair_share(self) -> None:
        """Give an embedding program its nice level and slice back."""
        if self._nice_before is None:
            return
        from .oscheduling import request_short_slice

        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, self._nice_before)
        request_short_slice(0)
        self._nice_before = None

    def _worker_executor(self, runner: NodeRunner, factory: NodeFactory) -> Executor:
        from .workers import PoolExecutor, ProcessExecutor

        spec = runner.rnode.spec
        watchdog = None if spec.watchdog is None else spec.watchdog / 1000
        # Workers get SCHED_FIFO only when the loop process has it too (and above them):
        # otherwise busy trackers would starve the frame clock (priority inversion).
        rt_workers = self.realtime.startswith("SCHED_FIFO")
        nice_of = None if self._fair is None else self._fair.nice
        factory.rtdb = self.rtdb.handle  # the worker's ctx.rtdb attaches to the same records
        options: dict[str, Any] = {
            "priority": runner.timing.priority,
            "watchdog": watchdog,
            "cpus": None if spec.cpus is None else tuple(spec.cpus),
            "spin": 0.0 if spec.spin is None else spec.spin / 1000,
            "outputs": self._output_grants(runner),
        }
        if spec.placement is Placement.pool:
            if self._pool is None:
                self._pool = PoolExecutor(realtime=rt_workers, nice_of=nice_of)
            ex: Any = self._pool.executor_for(runner.name, factory, **options)
        else:
            ex = ProcessExecutor(
                runner.name, factory, realtime=rt_workers, nice_of=nice_of, **options
            )
        ex.on_starved = self._worker_starved
        return _WorkerAdapter(ex)

    def _output_grants(self, runner: NodeRunner) -> Any:
        """The slots lent to a worker node for the frames it makes (None: no frame store)."""
        from .grants import OutputGrants

        if self._frames is None or self._frames.closed:
            return None
        # One per executor (a swap's new instance has its own; the old one's stop takes its
        # own grants back), counted together per node.
        # Two slots to start (one lent, one held by a reader), not four: each is a frame of
        # shared memory per worker node; the pool grows if readers hold more.
        per_call = len(runner.rnode.cls.frame_ports())
        pool = self._frames.pool(runner.name, initial_slots=2)
        grants = OutputGrants(runner.name, pool, per_call)
        self._grants.setdefault(runner.name, []).append(grants)
        return grants

    @staticmethod
    def _worker_frame_stats(node: str, grants: list[Any]) -> WorkerFrameStats:
        parts = [g.stats() for g in grants]
        by_socket: dict[str, int] = {}
        for p in parts:
            for reason, n in p.by_socket.items():
                by_socket[reason] = by_socket.get(reason, 0) + n
        return WorkerFrameStats(
            node=node,
            in_slots=sum(p.in_slots for p in parts),
            by_socket=by_socket,
            granted=sum(p.granted for p in parts),
            outstanding=sum(p.outstanding for p in parts),
            refused=sum(p.refused for p in parts),
            reclaimed=sum(p.reclaimed for p in parts),
        )

    def _worker_starved(self, node: str, detail: str) -> None:
        """A watchdog spared a starved worker: counted each time, one alert per episode.

        An episode is a run of such events less than 10 s apart: the whole machine starved
        makes every worker's watchdog notice it, and one alert says it all.
        """
        self.starvation_events += 1
        now = self.clock.now()
        if now - self._starved_alert_at > 10.0:
            log.warning("%s: %s", node, detail)
            self._emit(HealthAlert(self.now(), node, "cpu-starvation", detail, "warning"))
        self._starved_alert_at = now

    def _new_frame(
        self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str
    ) -> Frame:
        import numpy as np

        pool = self._frames.pool(owner)
        frame: Frame | None = pool.reserve(
            shape, dtype, source=owner, seq=0, timestamp=self.clock.now(), pixel_format=pixel_format
        )
        if frame is None:  # every slot held and the pool at its bound: counted by the pool
            frame = Frame(np.empty(shape, dtype=dtype), source=owner, pixel_format=pixel_format)
        return frame

    # --- events -------------------------------------------------------------------------

    def _emit(self, event: Event) -> None:
        self.events.append(event)
        self.event_count += 1
        if isinstance(event, NodeGaveUp) and self.stop_on_failure:
            log.info(
                "node %s failed: stopping the run (--keep-going, or stop_on_failure=False, "
                "keeps the rest of the graph running)",
                event.node,
            )
            self.request_stop()
        if isinstance(event, HealthAlert):
            self._record("flowrt.alerts", event)
        for m in self.monitors:
            try:
                m.event(event)
            except Exception:
                log.exception("monitor failed on %s", event.kind)
        for cb in self._listeners:
            try:
                cb(event)
            except Exception:
                log.exception("event listener failed on %s", event.kind)

    def emit(self, event: Event) -> None:
        """Publish an event from the host program (e.g. a health alert)."""
        self._emit(event)

    def on_event(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call ``callback`` for every event; returns a function that unsubscribes."""
        self._listeners.append(callback)
        return lambda: self._listeners.remove(callback)

    def _probe_lag(self, expected: float) -> None:
        now = self.clock.now()
        self._lag.add(max(0.0, now - expected))
        loop = asyncio.get_running_loop()
        self._lag_handle = loop.call_later(0.010, self._probe_lag, now + 0.010)

    # --- inspection and control -----------------------------------------------------------

    @property
    def scheduler(self) -> Scheduler:
        if self._sched is None:
            raise RuntimeError("the runtime is not started")
        return self._sched

    def quiet_delay(self, at_least: float) -> float:
        """Seconds from now to the middle of the widest gap between timer releases.

        Monitors that hold the loop for a while (a terminal table, a summary line) wait for
        this, so their work falls where no timer (and so no frame tick) is due, at least
        ``at_least`` from now.
        """
        gap = self._quiet_gap()
        if gap is None:
            return at_least
        offset, cycle = gap
        now = self.clock.now()
        base = self.clock.origin + offset
        k = math.ceil((now + at_least - base) / cycle)
        return max(0.0, base + k * cycle - now)

    def _quiet_gap(self) -> tuple[float, float] | None:
        """(offset of the widest gap's middle, cycle) over the timers' hyperperiod, seconds."""
        timers = [
            (r.timing.timer, r.timing.timer_phase)
            for r in self.scheduler.runners.values()
            if r.timing.timer and r.timing.enabled
        ]
        if not timers:
            return None
        key = tuple(sorted(timers))
        if self._gap_cache is not None and self._gap_cache[0] == key:
            return self._gap_cache[1]
        us = [(round(p * 1e6), round(ph * 1e6)) for p, ph in timers]
        cycle = 1
        for p, _ in us:
            cycle = cycle * p // math.gcd(cycle, p)
        cycle = min(cycle, 10 * max(p for p, _ in us), 2_000_000)  # bounded: a window, not forever
        instants = sorted(
            {ph + k * p for p, ph in us for k in range(cycle // p + 1) if ph + k * p < cycle}
        )
        gaps = [
            (b - a, a) for a, b in zip(instants, [*instants[1:], instants[0] + cycle], strict=True)
        ]
        width, start = max(gaps)
        result = (((start + width / 2) % cycle) / 1e6, cycle / 1e6)
        self._gap_cache = (key, result)
        return result

    def now(self) -> float:
        """Seconds since the runtime started."""
        return self.clock.now() - self.clock.origin

    @property
    def rtdb(self) -> RTDB:
        """The real-time database of this run, created on first use, removed at stop."""
        if self._rtdb is None:
            if not self.started:
                raise RuntimeError("the runtime is not started")
            from .rtdb import RTDB

            self._rtdb = RTDB(clock=self.clock.now, origin=self.clock.origin)
        return self._rtdb

    def _record(self, name: str, value: Any) -> None:
        """Keep runtime state (alerts, mode) in the RTDB; never fails the caller."""
        if not self.started:
            return
        try:
            self.rtdb.write(name, value)
        except Exception as e:
            log.warning("RTDB record %s: %s", name, e)

    def qos_status(self) -> QosStatus:
        """Current mode and what the overload controller has shed (for tables and the API)."""
        from .qos import QosStatus

        q = self.qos
        if q is None:
            return QosStatus(self.mode, False)
        return QosStatus(self.mode, True, q.overloaded, q.reason, q.shed(), q.last)

    def stats(self) -> RuntimeStats:
        sched = self.scheduler
        return RuntimeStats(
            graph=self.graph.spec.name,
            uptime=self.now(),
            mode=self.mode,
            realtime=self.realtime,
            loop_scheduling=self.loop_scheduling,
            nodes=[r.stats() for r in sched.runners.values()],
            edges=[b.stats() for b in sched.buffers],
            loop=LoopStats(
                lag=self._lag.summary(),
                blocked_calls=sched.blocked_calls,
                starvation_events=self.starvation_events,
            ),
            frames=self._frame_stats(),
            worker_frames=[self._worker_frame_stats(n, gs) for n, gs in self._grants.items()],
            events=self.event_count,
            reports=self._reports(),
        )

    def failures(self) -> list[NodeStats]:
        """The nodes that failed: given up by supervision (state ``failed``) or in an error
        state they reported (``ctx.set_error``: e.g. a source that cannot be opened or never
        delivered a frame). Empty when the run went well; ``flowrt run`` exits 1 otherwise.
        Valid during the run and after it (the verdict of the run's end)."""
        if self._sched is None:
            return []
        return [n for n in self.stats().nodes if n.state in ("failed", "error")]

    def _reports(self) -> dict[str, Any]:
        """Each inline node's optional ``report()`` (also after stop: its last instance's)."""
        out: dict[str, Any] = {}
        for name, r in self.scheduler.runners.items():
            ex = r.executor
            node = getattr(ex, "node", None) or getattr(ex, "last_node", None)
            hook = getattr(node, "report", None)
            if not callable(hook):
                continue
            try:
                value = hook()
            except Exception as e:  # a report must never break the statistics
                log.warning("node %s: report() failed: %s", name, e)
                continue
            if value is not None:
                out[name] = value
        return out

    def _frame_stats(self) -> list[FramePoolStats]:
        if self._frames is None or getattr(self._frames, "closed", False):
            return self._last_frame_stats
        self._last_frame_stats = [
            FramePoolStats(
                owner=p.owner,
                slots=p.slots,
                slots_in_use=p.slots_in_use,
                max_slots=p.max_slots,
                grown=p.grown,
                dropped=p.dropped,
            )
            for p in self._frames.stats()
        ]
        return self._last_frame_stats

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
        force: bool = False,
        timer_phase: float | None = None,
    ) -> str:
        """Change a node's timing between ticks. ``timer`` and ``deadline`` are in ms.

        The whole change is checked first (the ranges of graph files: finite, in range, a
        phase below its period; ``force`` does not skip this) and applied at once, or refused
        with ValueError and nothing changed. Then admission control
        (:mod:`flowrt.analysis.admission`) refuses, the same way, a change that would make a
        node with a deadline unschedulable, unless ``force``. The overload controller's own
        steps (origin ``qos``) are not admission-checked: they act on measured load.
        """
        from .qos import check_change

        check_change(
            self.scheduler.runners,
            node,
            period=period,
            phase=phase,
            timer=timer,
            timer_phase=timer_phase,
            deadline=deadline,
            priority=priority,
            enabled=enabled,
        )
        if not force and origin != "qos":
            change = TimingOverride.model_construct(
                period=period,
                phase=phase,
                timer=timer,
                deadline=deadline,
                priority=priority,
                enabled=enabled,
            )
            self._admit({node: change})
        return self.scheduler.set_timing(
            node,
            period=period,
            phase=phase,
            timer=None if timer is None else timer / 1000,
            timer_phase=None if timer_phase is None else timer_phase / 1000,
            deadline=None if deadline is None else deadline / 1000,
            priority=priority,
            enabled=enabled,
            origin=origin,
        )

    def set_mode(self, mode: str, origin: str = "api", force: bool = False) -> None:
        """Apply a named mode of the graph file: all of its overrides in one step.

        Overrides are relative to the graph's own timing: what the previous mode changed and
        this one does not is returned to the graph's values first (so an empty mode returns
        to the graph's timing). Nothing else is touched. Admission control checks the whole
        switch as one change (see :meth:`set_timing`), unless ``force``.
        """
        spec = self.graph.spec.modes.get(mode)
        if spec is None:
            from .diagnostics import did_you_mean

            raise KeyError(f"unknown mode {mode!r}" + did_you_mean(mode, self.graph.spec.modes))
        from .qos import check_plan, mode_plan

        previous_spec = self.graph.spec.modes.get(self.mode) if self.mode else None
        plan = mode_plan(self.graph, previous_spec, spec)
        check_plan(self.scheduler.runners, plan)  # all or nothing
        if not force and origin != "graph":  # the initial mode is the graph's own choice
            self._admit(plan)
        for node, o in plan.items():
            self.set_timing(
                node,
                period=o.period,
                phase=o.phase,
                timer=o.timer,
                timer_phase=o.timer_phase,
                deadline=o.deadline,
                priority=o.priority,
                enabled=o.enabled,
                origin=f"mode {mode}",
                force=True,  # checked above as one change
            )
        self._apply_mode_params(previous_spec, spec)
        previous, self.mode = self.mode, mode
        self._emit(ModeChanged(self.now(), None, mode, previous, origin))
        self._record("flowrt.mode", mode)

    def _admit(self, plan: Mapping[str, TimingOverride]) -> None:
        """Raise ValueError (AdmissionRefused) if ``plan`` breaks a critical deadline."""
        from .analysis.admission import check_change

        if self._sched is not None:
            check_change(self.graph, self.scheduler.runners, plan)

    async def swap(
        self,
        node: str,
        kind: str | type[Node],
        params: Mapping[str, Any] | None = None,
        *,
        origin: str = "api",
        resolved: type[Node] | None = None,
    ) -> None:
        """Swap ``node``'s algorithm while running: a new instance of ``kind`` takes over.

        The new instance is set up beside the old one and takes over between two of the
        node's activations, with the old one's state (``get_state``/``set_state``); other
        nodes see nothing. ``params`` default to the node's current ones when the kind is
        unchanged, else to the new kind's defaults. Raises ``SwapError`` with the reason (an
        unknown kind, an import error, bad params, a failing ``setup``): the old instance
        keeps running. ``resolved`` is ``kind``'s class when the caller imported it already
        (the control endpoint does, off the loop).
        """
        from pydantic import ValidationError

        from .registry import KindError, resolve_kind

        runner = self._runner(node)
        old_kind = runner.rnode.spec.kind
        label = kind if isinstance(kind, str) else f"{kind.__module__}:{kind.__qualname__}"
        try:
            cls = resolved if resolved is not None else resolve_kind(kind, None)
        except KindError as e:
            raise SwapError(f"{node}: {e}") from None
        except Exception as e:
            raise SwapError(f"{node}: kind {label!r}: import failed: {e!r}") from None
        if params is None and cls is runner.rnode.cls:
            model = runner.rnode.params
        else:
            if params is None and label == old_kind:
                params = runner.rnode.params.model_dump()
            try:
                model = self.graph.validate_params(cls, params or {})
            except ValidationError as e:
                raise SwapError(f"{node}: params for {label}: {e}") from None
        await self._swap_to(runner, cls, model, label, origin)

    async def _swap_to(
        self,
        runner: NodeRunner,
        cls: type[Node],
        model: Any,
        label: str,
        origin: str,
        reload: bool = False,
    ) -> None:
        old_kind = runner.rnode.spec.kind
        try:
            await runner.swap(cls, model, label, reload=reload)
        except Exception as e:
            raise SwapError(
                f"{runner.name}: swap to {label} failed, the old instance runs on: {e}"
            ) from e
        self._emit(NodeSwapped(self.now(), runner.name, label, old_kind, origin))

    async def reload(self, node: str, *, origin: str = "api") -> None:
        """Re-import ``node``'s module from disk and swap to the edited class (see ``swap``)."""
        import importlib
        import sys

        runner = self._runner(node)
        cls = runner.rnode.cls
        try:  # off the loop, and whatever the module does at import is contained
            module = await asyncio.to_thread(importlib.reload, sys.modules[cls.__module__])
            new_cls = getattr(module, cls.__qualname__)
        except asyncio.CancelledError:
            raise
        except BaseException as e:
            raise SwapError(f"{node}: reloading {cls.__module__} failed: {e!r}") from None
        kind = runner.rnode.spec.kind
        await self._swap_to(runner, new_cls, runner.rnode.params, kind, origin, reload=True)

    def set_params(self, node: str, params: Mapping[str, Any], *, merge: bool = True) -> None:
        """Change a node's params between activations (merged over its current ones)."""
        from pydantic import ValidationError

        from .spec import merge_params

        runner = self._runner(node)
        current = runner.rnode.params.model_dump()
        target = merge_params(current, dict(params)) if merge else dict(params)
        try:
            model = self.graph.validate_params(runner.rnode.cls, target)
        except ValidationError as e:
            raise ValueError(f"{node}: params: {e}") from None
        runner.set_params(model)

    def _runner(self, node: str) -> NodeRunner:
        runner = self.scheduler.runners.get(node)
        if runner is None:
            from .diagnostics import did_you_mean

            raise KeyError(f"unknown node {node!r}" + did_you_mean(node, self.scheduler.runners))
        return runner

    def _apply_mode_params(self, previous: ModeSpec | None, new: ModeSpec) -> None:
        """Params a mode sets, merged over the graph file's; the previous mode's undone."""
        from .spec import merge_params

        before = previous.nodes if previous is not None else {}
        for name in dict.fromkeys([*before, *new.nodes]):
            o, old = new.nodes.get(name), before.get(name)
            if not (o is not None and o.params) and not (old is not None and old.params):
                continue
            base = self.graph.spec.nodes[name].params
            target = merge_params(base, o.params if o is not None else None)
            runner = self.scheduler.runners[name]
            runner.set_params(self.graph.validate_params(runner.rnode.cls, target))

    def _runner_port(self, target: str) -> tuple[NodeRunner, str]:
        from .diagnostics import did_you_mean

        node, _, port = target.partition(".")
        runner = self.scheduler.runners.get(node)
        if runner is None:
            raise KeyError(f"unknown node {node!r}" + did_you_mean(node, self.scheduler.runners))
        ports = [*runner.outputs, *runner.inputs, *runner.rnode.cls.inputs]
        if port not in ports:
            raise KeyError(f"{node} has no port {port!r}" + did_you_mean(port, ports))
        return runner, port

    def publish(self, target: str, value: Any) -> None:
        """Inject a value: into ``node.output`` (fans out, ticks frames) or ``node.input``."""
        runner, port = self._runner_port(target)
        t = self.clock.now()
        if port in runner.outputs:
            runner.publish(port, value, t)
        elif port in runner.inputs:
            runner.inputs[port].put(value, t)
        else:
            raise KeyError(f"{target} is an input that nothing feeds; connect it in the graph")

    def subscribe(
        self, target: str, policy: str = "queue", size: int = 64, *, sampled: bool = False
    ) -> Subscription:
        """Receive what ``node.output`` publishes, through a buffer of its own (counted).

        ``sampled``: the reader takes the newest value only when it wants one (a viewer with
        nobody watching): values replaced before it took them are ``unread``, not dropped.
        """
        runner, port = self._runner_port(target)
        if port not in runner.outputs:
            raise KeyError(f"{target} is not an output")
        EdgePolicy(policy)
        buf = make_buffer(policy, f"{target}->host", size, self.clock.now)
        buf.sampled = sampled
        runner.outputs[port].append(buf)
        self.scheduler.buffers.append(buf)
        return Subscription(buf)


class _RemoteHost:
    """The runtime as the Zenoh bridge sees it (flowrt.remote.BridgeHost)."""

    def __init__(self, rt: Runtime) -> None:
        self.rt = rt

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        return self.rt.scheduler.loop

    def now_mono(self) -> float:
        return self.rt.clock.now()

    def runner_output(self, node: str, port: str) -> list[Buffer]:
        return self.rt.scheduler.runners[node].outputs[port]

    def add_buffer(self, buf: Buffer) -> None:
        self.rt.scheduler.buffers.append(buf)

    def publish(self, node: str, port: str, value: Any) -> None:
        self.rt.scheduler.runners[node].publish(port, value, self.rt.clock.now())

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pf: str) -> Frame:
        return self.rt._new_frame(owner, shape, dtype, pf)

    def import_node(self, name: str) -> Any:
        return getattr(self.rt.scheduler.runners[name].executor, "node", None)

    def emit(self, event: Event) -> None:
        self.rt._emit(event)

    def record(self, name: str, value: Any, validity_ms: float | None) -> None:
        try:
            self.rt.rtdb.write(name, value, validity_ms=validity_ms)
        except Exception as e:  # a value the RTDB cannot hold: the edge still has it
            log.debug("RTDB record %s: %s", name, e)

    def is_frame_port(self, node: str, port: str) -> bool:
        return port in self.rt.graph.nodes[node].cls.frame_ports()


class _WorkerAdapter(Executor):
    """Presents a worker-process executor through the scheduler's Executor interface."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.sync = False

    @property
    def granted(self) -> str:  # type: ignore[override]
        return str(getattr(self._inner, "granted", ""))

    async def start(self) -> None:
        await self._inner.start()

    async def call(self, inputs: dict[str, Any]) -> Any:
        return await self._inner.call(inputs)

    @property
    def pipelined(self) -> bool:  # type: ignore[override]
        return bool(getattr(self._inner, "pipelined", False))

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        return self._inner.submit(inputs, window)  # type: ignore[no-any-return]

    async def stop(self) -> None:
        await self._inner.stop()

    def set_priority(self, priority: int) -> None:
        setter = getattr(self._inner, "set_priority", None)
        if setter is not None:
            setter(priority)


def _freeze_heap() -> None:
    """Collect once, then exempt everything that exists from Python's cyclic collector.

    A full (generation 2) collection walks every object: ~25 ms in a process that has
    imported numpy, OpenCV and pydantic, and it starts whenever allocations say so, e.g. at
    a frame tick. Frozen objects are never walked again (only what is made later), so that
    pause becomes microseconds. Undone at stop, for an embedding program.
    """
    gc.collect()
    gc.freeze()


def _frame_store() -> FrameStore:
    """The shared-memory frame store, after reclaiming what a killed runtime left."""
    with contextlib.suppress(Exception):
        reclaimed = FrameStore.reclaim_orphans()
        if reclaimed:
            log.info(
                "reclaimed %d shared-memory segment%s left in %s by a runtime that was killed",
                reclaimed,
                "" if reclaimed == 1 else "s",
                SHM_DIR,
            )
    return FrameStore()
