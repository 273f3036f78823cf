"""The executors of worker nodes: one process per node, or a pool shared by several.

They implement the kernel's :class:`flowrt.kernel.Executor` directly.
"""

from __future__ import annotations

import asyncio
import itertools
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from ..frames.lending import OutputGrants
from ..system._priorities import WorkerScheduling, nice_for
from .channel import Worker
from .errors import WorkerError
from .forkserver import check_main_importable
from .hops import SKIPPED, Forward, FromPeer
from .wire import OP_ADD, OP_CALL, OP_DISABLE, OP_PRIORITY, OP_REMOVE


def _check_priority(priority: int) -> int:
    if not 1 <= int(priority) <= 99:
        raise ValueError(f"priority must be in 1..99, got {priority}")
    return int(priority)


@dataclass(frozen=True)
class WorkerOptions:
    """How a node runs in its worker (one value, not eleven positional arguments).

    priority: flowrt priority 1..99; becomes SCHED_FIFO or a nice level in the worker.
    watchdog: seconds a call may run before the worker is declared hung and killed; None
        disables it (a deadline still reports the miss; the watchdog is what recovers).
    realtime: try SCHED_FIFO at all (False: nice levels only).
    setup_timeout: seconds ``setup()`` may take in ``start``.
    nice_of: the nice level of a priority when SCHED_FIFO is not used (the runtime passes
        :meth:`FairShare.nice <flowrt.system._priorities.FairShare.nice>`; default
        :func:`~flowrt.system._priorities.nice_for`).
    cpus: CPUs the worker may run on (None: those it inherits).
    spin: seconds the worker busy-polls around the predicted instant of each call of a
        periodic node, so that it is awake when the call arrives (0: it sleeps).
    outputs: the shared-memory slots lent to the worker for the frames it makes.
    """

    priority: int = 50
    watchdog: float | None = None
    realtime: bool = True
    setup_timeout: float | None = 60.0
    nice_of: Callable[[int], int] | None = None
    cpus: tuple[int, ...] | None = None
    spin: float = 0.0
    outputs: OutputGrants | None = None


class _NodeExecutor:
    """What a node's executor does whatever its worker: call, re-prioritise, report."""

    sync = False  # calls are awaited (call/submit), never made from a loop callback
    pipelined = False  # may calls be pipelined (submit)? Only a worker of its own

    def __init__(
        self, name: str, factory: Callable[[], Any], nid: int, options: WorkerOptions
    ) -> None:
        self.name = name
        self.factory = factory
        self.nid = nid
        opts = options
        # The slots lent to the worker for the frames this node makes (None: no frame store,
        # its frames travel by the socket).
        self.outputs = opts.outputs
        self.priority = _check_priority(opts.priority)
        self.watchdog = opts.watchdog
        self.realtime = opts.realtime
        self.setup_timeout = opts.setup_timeout
        self.nice_of = opts.nice_of or nice_for
        self.cpus = opts.cpus
        self.spin = opts.spin
        self._worker: Worker | None = None
        self._granted = "not started"
        # Told (node, detail) when a call past its watchdog is spared because the worker
        # was starved of CPU rather than hung (the runtime emits a HealthAlert).
        self.on_starved: Callable[[str, str], None] | None = None

    def call_sync(self, inputs: dict[str, Any]) -> Any:
        raise NotImplementedError("a worker call is asynchronous (call or submit)")

    @property
    def granted(self) -> str:
        """The OS scheduling the worker was actually granted, e.g. ``SCHED_FIFO 45``."""
        return self._granted

    @property
    def pid(self) -> int | None:
        w = self._worker
        return w.pid if w is not None and w.alive else None

    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.alive

    @property
    def last_run_time(self) -> float:
        """Seconds the last call spent inside the worker (excludes transport and queueing)."""
        return self._worker.last_run_time if self._worker is not None else 0.0

    @property
    def scheduling(self) -> WorkerScheduling:
        """What the worker applies before running this node."""
        return WorkerScheduling(
            self.priority, self.realtime, self.nice_of(self.priority), self.cpus, self.spin
        )

    async def _add_to(self, worker: Worker) -> None:
        if self.outputs is not None:  # a new instance, or a new worker: start with no grant
            self.outputs.reclaim()
        self._worker = worker
        if self.on_starved is not None:
            worker.on_starved = self.on_starved
        msg = (OP_ADD, self.nid, self.name, self.factory, self.scheduling)
        self._granted = await worker.request(msg, self.name, self.priority, self.setup_timeout)

    async def call(self, inputs: dict[str, Any]) -> Any:
        """Run ``process(**inputs)`` in the worker and return its result.

        Pooled frames travel as descriptors (the caller must hold their link until this
        returns). Cancelling the awaiting task abandons the result, not the running call: the
        worker finishes it (or the watchdog kills it).
        """
        return await self._request(inputs, 1)

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        """Send ``process(**inputs)`` now and return the future of its result (pipelined).

        Up to ``window`` calls of this node are in flight at once (the caller bounds how many
        it submits); they run in the worker in the order submitted and resolve in that order.
        The same contract as :meth:`call` otherwise (descriptors, watchdog per call).
        """
        return self._request(inputs, window)

    @property
    def hop_address(self) -> str | None:
        """Where another worker may send this node's input straight to (workers/hops.py);
        None: no direct hop (a pool's worker is shared: a call waiting there would hold up
        its other nodes)."""
        return None

    def call_hop(
        self,
        inputs: dict[str, Any],
        to: Forward | None,
        peer: tuple[str, int, int] | None = None,
    ) -> asyncio.Future[Any]:
        """Send a call now whose output may go straight to another worker (``to``) and whose
        input ``peer`` = (port, tag, frame size) may come straight from one: the future's
        result is ``(True, result)``, or ``(False, None)`` when that input did not come."""
        size = 0
        if peer is not None:
            inputs = {**inputs, peer[0]: FromPeer(peer[1])}
            size = peer[2]
        fut = self._request(inputs, 1, to, size)
        loop = asyncio.get_running_loop()
        out: asyncio.Future[Any] = loop.create_future()

        def done(f: asyncio.Future[Any]) -> None:
            if out.done():
                return
            if f.cancelled():
                out.cancel()
            elif (e := f.exception()) is not None:
                out.set_exception(e)
            else:
                r = f.result()
                out.set_result((False, None) if r is SKIPPED else (True, r))

        fut.add_done_callback(done)
        # A caller that gives up gives up the call, as awaiting it directly does: its result's
        # frames are then let go when it comes (Worker._on_reply), not held for nobody.
        out.add_done_callback(lambda o: fut.cancel() if o.cancelled() else None)
        return out

    def skip_hop(self, tag: int) -> None:
        """A call's input from another worker will not come (see ``call_hop``)."""
        if self._worker is not None:
            self._worker.skip_hop(tag)

    def _request(
        self, inputs: dict[str, Any], window: int, to: Forward | None = None, size: int = 0
    ) -> asyncio.Future[Any]:
        w = self._worker
        if w is None:
            raise RuntimeError(f"{self.name}: executor not started")
        out = self.outputs
        hop = () if to is None else (to,)
        if out is None:
            return w.request(
                (OP_CALL, self.nid, inputs, (), window == 1, *hop),
                self.name,
                self.priority,
                self.watchdog,
                window,
            )
        grants = out.grant(inputs, window, size) if w.usable else ()
        try:
            fut = w.request(
                (OP_CALL, self.nid, inputs, grants, window == 1, *hop),
                self.name,
                self.priority,
                self.watchdog,
                window,
                (out, grants),
            )
        except BaseException:
            out.unsent(grants)
            raise
        out.lend_ahead()  # the next call's slots, off its path: the worker computes now
        return fut

    def set_priority(self, priority: int) -> None:
        """Change the node's priority at run time (QoS); the worker re-applies its OS priority.

        Returns at once; :attr:`granted` is updated when the worker has answered.
        """
        self.priority = _check_priority(priority)
        w = self._worker
        if w is None or not w.alive:
            return
        msg = (OP_PRIORITY, self.nid, self.scheduling)
        fut = w.request(msg, self.name, self.priority, None)

        def done(f: asyncio.Future[Any]) -> None:
            if not f.cancelled() and f.exception() is None:
                self._granted = f.result()

        fut.add_done_callback(done)

    def on_disable(self) -> asyncio.Future[Any] | None:
        """The node was disabled: its ``on_disable`` in the worker (kernel/disabling.py),
        after the calls sent before; None when no worker runs it. The future's result: what
        the hook returned, to publish."""
        w = self._worker
        if w is None or not w.alive:
            return None
        try:
            return w.request((OP_DISABLE, self.nid), self.name, self.priority, self.watchdog)
        except WorkerError:  # it died meanwhile: its supervisor says so
            return None


class ProcessExecutor(_NodeExecutor):
    """Runs one node in its own worker process (``placement: process``).

    Its calls may be pipelined (:meth:`submit`): the worker is the node's alone, so calls in
    flight never hold up another node.

    ``factory``: picklable zero-argument callable returning the node object, called in the
    worker (importable there, like anything sent to a process). ``options``, or the same
    fields as keywords: see :class:`WorkerOptions`.
    """

    pipelined = True

    def __init__(
        self,
        name: str,
        factory: Callable[[], Any],
        *,
        options: WorkerOptions | None = None,
        **fields: Any,
    ) -> None:
        super().__init__(name, factory, 0, _options(options, fields))

    @property
    def hop_address(self) -> str | None:
        w = self._worker
        return w.hop_address if w is not None and w.usable else None

    async def start(self) -> None:
        """Spawn the worker if needed and (re)create the node in it; WorkerError if setup fails.

        Called again after a failure of any kind it gives the node a fresh instance: a dead
        worker is replaced, a live one tears the old instance down first.
        """
        w = self._worker
        if w is None or not w.usable:
            if w is not None:
                await w.wait_exit()  # a killed worker: let it go before its successor starts
            w = Worker(self.name, import_main=check_main_importable(self.name, self.factory))
            self._worker = w  # from now on ``stop`` ends it, even in the middle of its set-up
            await w.spawn()
        await self._add_to(w)

    async def stop(self, grace: float = 2.0) -> None:
        """Teardown in the worker, then join; kill after ``grace`` seconds. Never hangs.

        A ``teardown`` that raised is raised here (a WorkerError of kind ``exception``), or
        did not return within ``grace`` (a TimeoutError), once the worker is gone: it is the
        node's error, counted by its supervisor."""
        w, self._worker = self._worker, None
        failure = None
        if w is not None:
            failure = await _remove(w, self.nid, self.name, self.priority, grace)
            await w.stop(grace)
        if self.outputs is not None:
            self.outputs.reclaim(count=False)
        if failure is not None:
            raise failure


class PoolExecutor:
    """A bounded pool of worker processes shared by several nodes (``placement: pool``).

    Node affinity: each node is pinned to one worker, chosen round-robin when it is added, and
    its object lives there for good — node state survives between calls exactly as in a
    process of its own, and a node is never instantiated twice. Calls waiting for a busy
    worker are dispatched highest priority first, and the worker switches its OS priority to
    that of the node it is running (one syscall, only when it changes).

    A worker that dies takes its nodes with it: each sees a WorkerError on its next (or
    pending) call and is restarted by the supervisor through its own ``start()``.
    """

    def __init__(
        self,
        name: str = "pool",
        size: int | None = None,
        *,
        realtime: bool = True,
        nice_of: Callable[[int], int] | None = None,
    ) -> None:
        self.name = name
        self.size = max(1, size if size is not None else (os.cpu_count() or 1))
        self.realtime = realtime
        self.nice_of = nice_of
        self._workers: list[Worker | None] = [None] * self.size
        self._locks = [asyncio.Lock() for _ in range(self.size)]
        self._next_node = itertools.count()

    def executor_for(
        self,
        name: str,
        factory: Callable[[], Any],
        priority: int | None = None,
        *,
        options: WorkerOptions | None = None,
        **fields: Any,
    ) -> PoolNodeExecutor:
        """The executor of node ``name``, pinned to the next worker in round-robin order.

        ``cpus`` and ``spin`` are the node's own: the worker switches to them for its calls;
        ``realtime`` and ``nice_of`` are the pool's.
        """
        if priority is not None:
            fields["priority"] = priority
        opts = _options(options, fields)
        opts = replace(opts, realtime=self.realtime, nice_of=self.nice_of)
        return PoolNodeExecutor(self, next(self._next_node), name, factory, opts)

    async def _worker(self, index: int, *, import_main: bool = False) -> Worker:
        async with self._locks[index]:
            w = self._workers[index]
            if w is None or not w.usable:
                if w is not None:
                    await w.wait_exit()
                w = Worker(f"{self.name}[{index}]", import_main=import_main)
                await w.spawn()
                self._workers[index] = w
            return w

    def pids(self) -> list[int]:
        return [w.pid for w in self._workers if w is not None and w.alive and w.pid is not None]

    async def stop(self, grace: float = 2.0) -> None:
        """Stop every worker (tearing down the nodes they hold)."""
        workers = [w for w in self._workers if w is not None]
        self._workers = [None] * self.size
        await asyncio.gather(*(w.stop(grace) for w in workers))


class PoolNodeExecutor(_NodeExecutor):
    """One node's handle on a :class:`PoolExecutor`; same interface as ProcessExecutor."""

    def __init__(
        self,
        pool: PoolExecutor,
        nid: int,
        name: str,
        factory: Callable[[], Any],
        options: WorkerOptions,
    ) -> None:
        super().__init__(name, factory, nid, options)
        self.pool = pool
        self.index = nid % pool.size

    async def start(self) -> None:
        """Make sure this node's worker runs, then (re)create the node in it."""
        import_main = check_main_importable(self.name, self.factory)
        await self._add_to(await self.pool._worker(self.index, import_main=import_main))

    async def stop(self, grace: float = 2.0) -> None:
        """Tear this node down in its worker (the worker stays for the pool's other nodes)."""
        w, self._worker = self._worker, None
        failure = None
        if w is not None and w.alive:
            failure = await _remove(w, self.nid, self.name, self.priority, grace)
        if self.outputs is not None:
            self.outputs.reclaim(count=False)
        if failure is not None:
            raise failure


async def _remove(w: Worker, nid: int, name: str, priority: int, grace: float) -> Exception | None:
    """Tear one node down in its worker: the error its ``teardown`` raised, a TimeoutError
    when it did not return within ``grace`` (the worker is then killed: a device left
    unreleased is the node's failure, as inline), else None (a worker that died, or one
    still busy with a call the stop gave up on, is its stop's business)."""
    if not w.usable:
        return None
    busy = w.busy  # a call of the node's still running in the worker: the teardown waits
    try:
        await asyncio.wait_for(w.request((OP_REMOVE, nid), name, priority, grace), grace)
    except WorkerError as e:
        if e.kind == "exception":
            return e
        return TimeoutError() if e.kind == "hung" and not busy else None
    except TimeoutError:
        return None if busy else TimeoutError()
    return None


def _options(options: WorkerOptions | None, fields: dict[str, Any]) -> WorkerOptions:
    """``options``, or one made of keyword fields (``priority=30, watchdog=0.5``)."""
    if options is not None and fields:
        raise TypeError("give options= or its fields as keywords, not both")
    return options if options is not None else WorkerOptions(**fields)
