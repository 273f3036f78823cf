"""The embedding API: a graph running on the current event loop.

    async with flowrt.Runtime.from_file("graph.yaml") as rt:
        await rt.run(10.0)
        print(rt.stats())

The runtime is the composition root and the facade: it builds the kernel
(:mod:`flowrt.kernel`) from its parts, hands it the frames and workers of the run
(:mod:`flowrt.runtime._resources`) and its other services at construction, and answers the host
program. Monitors (the status table, the web view, JSON statistics) watch it through
:class:`Monitor`; what each change does is in a module of its own (:mod:`flowrt.runtime._hotswap`,
:mod:`flowrt.runtime._modes`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ..clock import Clock, SystemClock
from ..events import Event, HealthAlert, NodeGaveUp, RealtimeStatus
from ..graph._resolve import Graph, resolve
from ..graph.spec import GraphSpec, Placement
from ..kernel import NodeRunner, Scheduler, Services
from ..kernel.timing import TimingChange
from ..monitors._quiet import delay_to_gap
from ..node import Node
from ..stats import NodeStats, Running, RuntimeStats
from ..system._cpu_latency import CpuLatencyRequest
from ..system._eventloop import run as run
from ..system._loop_cpus import LoopCpus
from ..system._loop_share import LoopShare
from ._event_hub import EventHub
from ._event_hub import Monitor as Monitor
from ._host_ports import publish as inject_value
from ._host_ports import subscribe as subscribe_port
from ._hotswap import SwapError as SwapError
from ._hotswap import reload as reload_node
from ._hotswap import set_params as set_node_params
from ._hotswap import swap as swap_node
from ._interruption import Interruptible, in_daemon_thread
from ._modes import apply_plan
from ._modes import set_mode as switch_mode
from ._resources import RunResources
from ._stats import runtime_stats
from ._subscription import Subscription
from ._verdict import failures

if TYPE_CHECKING:
    from ..rtdb import RTDB
    from ..system._priorities import FairShare
    from ._qos import OverloadController, QosStatus

log = logging.getLogger("flowrt")
T = TypeVar("T")


class Runtime(Interruptible):
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
        cpu_latency: float | None = None,
    ) -> None:
        """``drain_timeout``: seconds ``stop`` lets the graph finish what it holds (lossless
        edges, in-flight activations) after stopping the sources; reported when hit.
        ``stop_on_failure``: a node given up by supervision (state ``failed``) ends ``run``
        at once (``flowrt run`` does this unless ``--keep-going``); by default the rest of
        the graph keeps running and the host program reads :meth:`failures`.
        ``cpu_latency``: seconds no CPU may take to wake while it runs (a PM QoS request,
        flowrt/system/_cpu_latency.py); refused without root: said, never fatal."""
        if not drain_timeout >= 0 or math.isinf(drain_timeout):
            raise ValueError(f"drain_timeout must be finite and >= 0, got {drain_timeout}")
        self.drain_timeout = drain_timeout
        self.stop_on_failure = stop_on_failure
        self._cpu_latency = CpuLatencyRequest(cpu_latency)  # held while running
        self.graph = _graph_of(graph, kinds)
        if clock is not None and spin:
            raise ValueError("spin is the system clock's: pass SystemClock(spin=...) as clock")
        self.clock: Clock = clock or SystemClock(spin=spin)
        self.hub = EventHub(list(monitors))
        self.monitors = self.hub.monitors  # watchers of the run (table, web view, QoS...)
        self.realtime_requested = realtime
        self.realtime = ""
        self._fifo = False  # the loop got SCHED_FIFO (``realtime`` says so, or why not)
        self.latency_hint = ""
        self.mode: str | None = None
        self.events = self.hub.events  # the last 1000 events
        self._sched: Scheduler | None = None
        self.resources: RunResources | None = None  # frames and workers, while running
        self._stop = asyncio.Event()
        self.lag = Running()  # the loop's lateness, by a 10 ms probe timer
        self._lag_handle: asyncio.TimerHandle | None = None
        self._rtdb: RTDB | None = None
        self._fair: FairShare | None = None
        self._loop_share = LoopShare()
        self._loop_cpus = LoopCpus()
        self.qos: OverloadController | None = None
        self._bridge: Any = None  # flowrt.remote._bridge.ZenohBridge when the graph spans machines
        self.started = False
        self.ended = False  # set at stop: a Runtime runs once (start again: RuntimeError)
        self._subscriptions: list[Subscription] = []  # closed at stop

    @property
    def remote_session(self) -> Any:
        """The graph's Zenoh session (``zenoh.Session``) while running, else None: for users
        of the runtime that talk through it (e.g. :class:`flowrt.remote.control.ZenohControl`)."""
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

    async def _start(self) -> None:
        spec = self.graph.spec
        if spec.zenoh is not None or spec.exports or spec.imports:
            # First: a port in use or a bad endpoint fails here, before anything runs.
            from ..remote._bridge import ZenohBridge
            from ..remote._host import RemoteHost

            bridge = ZenohBridge(RemoteHost(self), spec)
            await bridge.open()
            self._bridge = bridge
        if self.realtime_requested:
            from ..system._realtime import enable_realtime

            self._fifo, self.realtime = enable_realtime()
            if not self._fifo:
                log.warning("--realtime: %s", self.realtime)
        if not self._cpu_latency.hold():
            log.warning("--cpu-latency: %s", self._cpu_latency.granted)
        if not self._fifo:
            self._fair, self.latency_hint = self._loop_share.apply(self.graph)
        self.resources = resources = RunResources(
            self.clock,
            self._emit,
            realtime=lambda: self._fifo,
            fair=lambda: self._fair,
            rtdb_handle=lambda: self.rtdb.handle,
        )
        if any(n.spec.placement is not Placement.inline for n in self.graph.nodes.values()):
            from ..workers import start_forkserver

            await in_daemon_thread(start_forkserver)  # preloaded numpy/cv2: shared pages
        # Imported now, not at the first run-time change: an import on the loop at that moment
        # (tens of ms) would make the ticks around a `ctl timing` late.
        from ..analysis import admission  # noqa: F401

        _freeze_heap()
        self.clock.origin = self.clock.now() + (
            0.005 if isinstance(self.clock, SystemClock) else 0.0
        )
        services = Services(
            emit=self._emit,
            workers=resources,
            frames=resources,
            stats=self.stats,
            rtdb=lambda: self.rtdb,
            set_mode=self.set_mode,
            request_stop=self.request_stop,
            drain_timeout=self.drain_timeout,
            real_time=isinstance(self.clock, SystemClock),
        )
        self._sched = Scheduler(self.graph, self.clock, services)
        if self._bridge is not None:
            self._bridge.attach_exports()
        overload = self.graph.spec.qos.overload
        if overload is not None and self.qos is None:
            from ._qos import OverloadController

            self.qos = OverloadController(overload)
            self.monitors.append(self.qos)
        self.started = True
        for m in self.monitors:
            m.started(self)
        if self.realtime:
            self._emit(RealtimeStatus(0.0, None, self.realtime))
        self._loop_cpus.apply(self.graph)  # after the forkserver: workers keep every CPU
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
        self.ended = True
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
            if self.resources is not None:
                await self.resources.stop_workers()
                self.resources.close()
            for m in self.monitors:
                try:
                    m.stopped(self)
                except Exception:
                    log.exception("monitor failed at stop")
            if self._rtdb is not None:
                self._rtdb.close()
            for sub in self._subscriptions:  # a reader waiting for a value: none will come
                sub.close()
            self._give_back_the_system()

    @property
    def loop_scheduling(self) -> str:
        """What the loop process was granted: SCHED_FIFO, or its nice level and slice."""
        granted = self.realtime if self._fifo else self.latency_hint
        cpus = self._loop_cpus.granted
        return f"{granted}, {cpus}" if cpus and granted else granted

    # --- resources ----------------------------------------------------------------------

    def _emit(self, event: Event) -> None:
        if isinstance(event, NodeGaveUp) and self.stop_on_failure:
            log.info(
                "node %s failed: stopping the run (--keep-going, or stop_on_failure=False, "
                "keeps the rest of the graph running)",
                event.node,
            )
            self.request_stop()
        if isinstance(event, HealthAlert):
            self.record_state("flowrt.alerts", event)
        self.hub.publish(event)

    def emit(self, event: Event) -> None:
        """Publish an event from the host program (e.g. a health alert)."""
        self._emit(event)

    def on_event(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call ``callback`` for every event; returns a function that unsubscribes."""
        return self.hub.listen(callback)

    def _probe_lag(self, expected: float) -> None:
        now = self.clock.now()
        self.lag.add(max(0.0, now - expected))
        loop = asyncio.get_running_loop()
        self._lag_handle = loop.call_later(0.010, self._probe_lag, now + 0.010)

    # --- inspection and control -----------------------------------------------------------

    @property
    def scheduler(self) -> Scheduler:
        if self._sched is None:
            raise RuntimeError("the runtime is not started")
        return self._sched

    def quiet_delay(self, at_least: float) -> float:
        """Seconds from now to the middle of the widest gap between timer releases, at least
        ``at_least``: where a monitor may hold the loop (:mod:`flowrt.monitors._quiet`)."""
        tms = [r.timing for r in self.scheduler.order]
        timers = [(t.timer if t.enabled else None, t.timer_phase) for t in tms]
        return delay_to_gap(timers, self.clock.now(), self.clock.origin, at_least)

    def now(self) -> float:
        """Seconds since the runtime started."""
        return self.clock.now() - self.clock.origin

    @property
    def rtdb(self) -> RTDB:
        """The real-time database of this run, created on first use, removed at stop."""
        if self._rtdb is None:
            if not self.started:
                raise RuntimeError("the runtime is not started")
            from ..rtdb import RTDB

            self._rtdb = RTDB(clock=self.clock.now, origin=self.clock.origin)
        return self._rtdb

    def record_state(self, name: str, value: Any) -> None:
        """Keep runtime state (alerts, mode) in the RTDB; never fails the caller."""
        if not self.started:
            return
        try:
            self.rtdb.write(name, value)
        except Exception as e:
            log.warning("RTDB record %s: %s", name, e)

    def qos_status(self) -> QosStatus:
        """Current mode and what the overload controller has shed (for tables and the API)."""
        from ._qos import QosStatus

        q = self.qos
        if q is None:
            return QosStatus(self.mode, False)
        return QosStatus(self.mode, True, q.overloaded, q.reason, q.shed(), q.last)

    def stats(self) -> RuntimeStats:
        """Every node, edge, frame pool and the loop, now (:mod:`flowrt.runtime._stats`)."""
        return runtime_stats(
            {
                "graph": self.graph.spec.name,
                "uptime": self.now(),
                "mode": self.mode,
                "realtime": self.realtime,
                "loop_scheduling": self.loop_scheduling,
                "cpu_latency": self._cpu_latency.granted,
            },
            self.scheduler,
            self.resources,
            self.lag,
            self.starvation_events,
            self.hub.count,
        )

    def failures(self) -> list[NodeStats]:
        """The nodes that failed (given up, in an error state they reported, or never one
        activation completed: :mod:`._verdict`). Empty when the run went well; ``flowrt run``
        exits 1 otherwise. Valid during the run and after it (the verdict of the run's end)."""
        if self._sched is None:
            return []
        return failures(self.stats().nodes, list(self.events))

    @property
    def starvation_events(self) -> int:
        """Worker calls spared by the watchdog: starved of CPU, not hung."""
        return 0 if self.resources is None else self.resources.starvation_events

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
        """Change a node's timing between ticks (``timer``, ``deadline`` in ms, or
        ``"80ms"`` as in a graph file): :meth:`apply_timing` with the change these name."""
        given = dict(period=period, phase=phase, timer=timer, timer_phase=timer_phase)
        given.update(deadline=deadline, priority=priority, enabled=enabled)
        change = TimingChange.parse(node, **given)
        return self.apply_timing(node, change, origin=origin, force=force)

    def apply_timing(
        self, node: str, change: TimingChange, *, origin: str = "api", force: bool = False
    ) -> str:
        """The one door of every run-time timing change (``TimingRequest.change()`` of the
        control endpoint, :meth:`set_timing`, the overload controller; modes by the same
        ``apply_plan``), applied between ticks. Checked once, here, whole: the graph files'
        ranges (``force`` does not skip them), then admission control unless ``force`` or
        origin ``qos`` (which acts on measured load). Refused: ValueError (KeyError for an
        unknown node), nothing changed. Returns what changed (a ``TimingChanged`` event)."""
        admitted = force or origin == "qos"
        return apply_plan(self, {node: change}, origin=origin, admitted=admitted)[0]

    def set_mode(self, mode: str, origin: str = "api", force: bool = False) -> None:
        """Apply a named mode of the graph file: all of its overrides in one step.

        Overrides are relative to the graph's own timing: what the previous mode changed and
        this one does not is returned to the graph's values first (so an empty mode returns
        to the graph's timing). Nothing else is touched. Admission control checks the whole
        switch as one change (see :meth:`set_timing`), unless ``force``.
        """
        switch_mode(self, mode, origin, force)

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
        nodes see nothing. ``params`` are merged into the node's current ones (as written in
        the graph file) when the kind is unchanged, else over the new kind's defaults. A node
        that owns a socket (a display's port) releases it before its replacement binds.
        Raises ``SwapError`` with the reason (an
        unknown kind, an import error, bad params, a failing ``setup``): the old instance
        keeps running. ``resolved`` is ``kind``'s class when the caller imported it already
        (the control endpoint does, off the loop).
        """
        await swap_node(self, node, kind, params, origin, resolved)

    async def reload(self, node: str, *, origin: str = "api") -> None:
        """Re-import ``node``'s module from disk and swap to the edited class (see ``swap``)."""
        await reload_node(self, node, origin)

    def set_params(self, node: str, params: Mapping[str, Any], *, merge: bool = True) -> None:
        """Change a node's params between activations (merged over its current ones)."""
        set_node_params(self, node, params, merge)

    def runner(self, node: str) -> NodeRunner:
        """The kernel's runner of ``node`` (KeyError naming the nearest names otherwise)."""
        runner = self.scheduler.runners.get(node)
        if runner is None:
            from ..graph.diagnostics import did_you_mean

            raise KeyError(f"unknown node {node!r}" + did_you_mean(node, self.scheduler.runners))
        return runner

    def publish(self, target: str, value: Any) -> None:
        """Inject a value: into ``node.output`` (fans out, ticks frames) or ``node.input``."""
        _require_running(self, "publish")
        inject_value(self.scheduler, self.clock.now(), target, value)

    def subscribe(
        self, target: str, policy: str = "queue", size: int = 64, *, sampled: bool = False
    ) -> Subscription:
        """Receive what ``node.output`` publishes, through a buffer of its own (counted).

        ``sampled``: the reader takes the newest value only when it wants one (a viewer with
        nobody watching): values replaced before it took them are ``unread``, not dropped.
        """
        _require_running(self, "subscribe")
        sub = subscribe_port(self.scheduler, self.clock.now, target, policy, size, sampled)
        self._subscriptions.append(sub)
        return sub


def _graph_of(graph: Any, kinds: Mapping[str, type[Node]] | None) -> Graph:
    """``graph`` resolved; TypeError saying what to do with anything else (a path, a
    builder not built: it was an AttributeError on ``.imports``)."""
    if isinstance(graph, Graph):
        return graph
    if isinstance(graph, GraphSpec):
        return resolve(graph, kinds=kinds)
    hint = (
        "Runtime.from_file(path) loads a graph file"
        if isinstance(graph, str | Path)
        else "call .build() on a GraphBuilder"
        if hasattr(graph, "build")
        else "build one with GraphBuilder(...).build() or Graph.from_file(path)"
    )
    raise TypeError(f"Runtime needs a Graph, not {type(graph).__name__}: {hint}")


def _require_running(rt: Runtime, what: str) -> None:
    """RuntimeError unless the graph is running: after the stop, a call did nothing."""
    if rt.ended:
        raise RuntimeError(f"{what}: the runtime has stopped (a Runtime runs once)")
    if not rt.started:
        raise RuntimeError(f"{what}: the runtime is not started")


def _freeze_heap() -> None:
    """Collect once, then exempt everything that exists from Python's cyclic collector.

    A full (generation 2) collection walks every object: ~25 ms in a process that has
    imported numpy, OpenCV and pydantic, and it starts whenever allocations say so, e.g. at
    a frame tick. Frozen objects are never walked again (only what is made later), so that
    pause becomes microseconds. Undone at stop, for an embedding program.
    """
    gc.collect()
    gc.freeze()
