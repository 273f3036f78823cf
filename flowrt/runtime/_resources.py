"""The shared-memory frames and the worker processes of one run.

The runtime builds one :class:`RunResources` and hands it to the kernel as both of its
ports (:class:`flowrt.kernel.FramePort`, :class:`flowrt.kernel.WorkerPort`): the kernel
allocates frames and gets worker executors through it, never through the runtime, and the
worker executors it gets implement the kernel's ``Executor`` directly.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..clock import Clock
from ..events import Event, HealthAlert
from ..frames import SHM_DIR, Frame, FrameStore
from ..graph._resolve import ResolvedNode
from ..graph.spec import Placement
from ..node import NodeFactory
from ..stats import FramePoolStats, WorkerFrameStats

if TYPE_CHECKING:
    from ..frames.lending import OutputGrants
    from ..kernel import Executor
    from ..system._priorities import FairShare
    from ..workers import PoolExecutor

log = logging.getLogger("flowrt")


class RunResources:
    """Frames and workers: what a run allocates, counts and frees at its end.

    Invariant: after :meth:`close` the frame store is closed and its last figures stay
    readable (``frame_stats``); workers are stopped by :meth:`stop_workers` before that.
    """

    def __init__(
        self,
        clock: Clock,
        emit: Callable[[Event], None],
        *,
        realtime: Callable[[], bool],
        fair: Callable[[], FairShare | None],
        rtdb_handle: Callable[[], Any],
    ) -> None:
        self._clock = clock
        self._emit = emit
        self._realtime = realtime  # the loop has SCHED_FIFO: workers may have it too
        self._fair = fair
        self._rtdb_handle = rtdb_handle
        self.frames = frame_store()
        self._pool: PoolExecutor | None = None
        self._grants: dict[str, list[OutputGrants]] = {}  # node -> its executors' output slots
        self._last_frame_stats: list[FramePoolStats] = []
        self.starvation_events = 0  # worker calls spared by the watchdog: starved, not hung
        self._starved_alert_at = -math.inf

    # --- the kernel's FramePort -----------------------------------------------------------

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str) -> Frame:
        pool = self.frames.pool(owner)
        frame: Frame | None = pool.reserve(
            shape,
            dtype,
            source=owner,
            seq=0,
            timestamp=self._clock.now(),
            pixel_format=pixel_format,
        )
        if frame is None:  # every slot held and the pool at its bound: counted by the pool
            frame = Frame(np.empty(shape, dtype=dtype), source=owner, pixel_format=pixel_format)
        return frame

    # --- the kernel's WorkerPort ----------------------------------------------------------

    def executor_for(self, rnode: ResolvedNode, priority: int, factory: NodeFactory) -> Executor:
        from ..workers import PoolExecutor, ProcessExecutor, WorkerOptions

        spec = rnode.spec
        fair = self._fair()
        # Workers get SCHED_FIFO only when the loop process has it too (and above them):
        # otherwise busy trackers would starve the frame clock (priority inversion).
        options = WorkerOptions(
            priority=priority,
            watchdog=None if spec.watchdog is None else spec.watchdog / 1000,
            realtime=self._realtime(),
            nice_of=None if fair is None else fair.nice,
            cpus=None if spec.cpus is None else tuple(spec.cpus),
            spin=0.0 if spec.spin is None else spec.spin / 1000,
            outputs=self._output_grants(rnode),
        )
        factory.rtdb = self._rtdb_handle()  # the worker's ctx.rtdb attaches to the same records
        ex: ProcessExecutor | Any
        if spec.placement is Placement.pool:
            if self._pool is None:
                self._pool = PoolExecutor(realtime=options.realtime, nice_of=options.nice_of)
            ex = self._pool.executor_for(rnode.name, factory, options=options)
        else:
            ex = ProcessExecutor(rnode.name, factory, options=options)
        ex.on_starved = self._worker_starved
        return ex

    def _output_grants(self, rnode: ResolvedNode) -> OutputGrants | None:
        """The slots lent to a worker node for the frames it makes (None: no frame store)."""
        from ..frames.lending import OutputGrants

        if self.frames.closed:
            return None
        # One per executor (a swap's new instance has its own; the old one's stop takes its
        # own grants back), counted together per node.
        # Two slots to start (one lent, one held by a reader), not four: each is a frame of
        # shared memory per worker node; the pool grows if readers hold more.
        per_call = len(rnode.cls.frame_ports())
        pool = self.frames.pool(rnode.name, initial_slots=2)
        grants = OutputGrants(rnode.name, pool, per_call)
        self._grants.setdefault(rnode.name, []).append(grants)
        return grants

    def _worker_starved(self, node: str, detail: str) -> None:
        """A watchdog spared a starved worker: counted each time, one alert per episode.

        An episode is a run of such events less than 10 s apart: the whole machine starved
        makes every worker's watchdog notice it, and one alert says it all.
        """
        self.starvation_events += 1
        now = self._clock.now()
        if now - self._starved_alert_at > 10.0:
            log.warning("%s: %s", node, detail)
            rel = now - self._clock.origin
            self._emit(HealthAlert(rel, node, "cpu-starvation", detail, "warning"))
        self._starved_alert_at = now

    # --- figures and the end ---------------------------------------------------------------

    def worker_frame_stats(self) -> list[WorkerFrameStats]:
        return [_worker_frame_stats(n, gs) for n, gs in self._grants.items()]

    def frame_stats(self) -> list[FramePoolStats]:
        if self.frames.closed:
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
            for p in self.frames.stats()
        ]
        return self._last_frame_stats

    async def stop_workers(self) -> None:
        if self._pool is not None:
            with contextlib.suppress(Exception):
                await self._pool.stop()

    def close(self) -> None:
        self.frame_stats()  # the final figures, before the pools go
        self.frames.close()


def _worker_frame_stats(node: str, grants: list[OutputGrants]) -> WorkerFrameStats:
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


def frame_store() -> FrameStore:
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
