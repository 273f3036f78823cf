"""One worker process seen from the event loop: its request queue, calls in flight, death."""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import multiprocessing
import multiprocessing.context
import os
import pickle
import select
import signal
import socket
import threading
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..frames import release_handoffs
from ..frames.lending import Grant, OutputGrants
from ..ipc import PICKLE, Framer, frame, pack
from .child import worker_main
from .errors import WorkerError, WorkerKind
from .forkserver import (
    EXIT_MAIN_UNGUARDED,
    NO_MAIN,
    WITH_MAIN,
    context,
    exit_if_importing_main,
    shut_at_exit,
    unguarded_main_message,
)
from .hops import SKIPPED, address
from .watchdog import proc_forget, progress_of, state_of
from .wire import OP_EXIT, OP_SKIP, R_ERR, R_FATAL, R_OK, R_SKIP, SIGNALS_KILLED


@dataclass(order=True)
class _Call:
    """One request to a worker, ordered for dispatch by priority then arrival."""

    sort_key: tuple[int, int]
    payload: bytes = field(compare=False)
    future: asyncio.Future[Any] = field(compare=False)
    node: str = field(compare=False)
    watchdog: float | None = field(compare=False)
    window: int = field(default=1, compare=False)  # >1: may be sent behind calls of its node
    index: int = field(default=-1, compare=False)  # its place on the wire (see R_OK)
    # The node's output slots and the grants this call carries (flowrt.frames.lending).
    outputs: tuple[OutputGrants, tuple[Grant, ...]] | None = field(default=None, compare=False)


class _Protocol(asyncio.Protocol):
    """Splits the worker's byte stream into replies."""

    def __init__(self, worker: Worker) -> None:
        self.worker = worker
        self.framer = Framer()

    def data_received(self, data: bytes) -> None:
        for msg in self.framer.feed(data):
            self.worker._on_reply(msg)

    def connection_lost(self, exc: Exception | None) -> None:
        self.worker._on_eof()


class Worker:
    """One worker process seen from the event loop: a request queue and the calls in flight.

    Normally one call at a time, so that waiting calls can be dispatched by priority (a pool
    worker shared by several nodes). A *pipelined* call (``window`` > 1, for a node whose
    inputs are queues: every value is to be processed, in order) is written behind the calls
    of the same node still in flight, up to ``window`` of them: the worker finds the next
    request in its socket when it answers one and runs back to back, while the loop goes on
    publishing. The worker serves requests in order, so replies come back in the order of the
    calls (FIFO over one stream socket), each with the sequence number of its call. The
    watchdog arms for the call at the head of the line only, when it starts running (sent
    into an idle worker, or when the reply of the call before it arrives): it still measures
    the call itself, not its wait.
    """

    def __init__(self, name: str, *, import_main: bool = False) -> None:
        self.name = name
        self.import_main = import_main
        self.proc: multiprocessing.process.BaseProcess | None = None
        self.pid: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._transport: asyncio.Transport | None = None
        self._inflight: deque[_Call] = deque()
        self._waiting: list[_Call] = []
        self._seq = itertools.count()
        self._wire = itertools.count()  # requests written, matched by the replies' index
        self._timer: asyncio.TimerHandle | None = None
        self._hung_node: str | None = None
        self._exited = asyncio.Event()
        self._eof_timer: asyncio.TimerHandle | None = None
        self.death: WorkerError | None = None
        self._deaths: set[asyncio.Task[None]] = set()  # calls waiting to fail with the death
        self.alive = False  # the process exists (until its sentinel fires)
        # Where other workers send this one's inputs straight to (workers/hops.py): named
        # after the runtime's pid and the worker's, so set once it is spawned.
        self.hop_address: str | None = None
        self._killing = False
        self.last_run_time = 0.0
        # Watchdog progress check (see _on_hung): the worker's CPU and run-queue wait at the
        # last check, and who hears of a call spared because the worker was starved of CPU.
        self._progress: tuple[float, float, float | None] | None = None
        self._call_cpu = 0.0  # the worker's CPU time when the call in flight was sent
        self.on_starved: Callable[[str, str], None] | None = None

    async def spawn(self) -> None:
        exit_if_importing_main()
        loop = asyncio.get_running_loop()
        self._loop = loop
        ctx = context()
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        proc = ctx.Process(
            target=worker_main,
            args=(child, self.name, os.getpid()),
            name=(WITH_MAIN if self.import_main else NO_MAIN) + self.name,
            daemon=True,
        )
        abandoned = threading.Event()
        try:
            # Blocking (talks to the forkserver, which may still be starting): off the loop,
            # in a daemon thread that an interrupted set-up neither waits for nor leaks: the
            # process it makes then is killed as soon as it exists (it ignores SIGTERM).
            await _start_in_thread(proc, abandoned)
        except BaseException:
            abandoned.set()
            _kill_started(proc)
            parent.close()
            raise
        finally:
            child.close()
        shut_at_exit(parent)
        self.proc = proc
        self.pid = proc.pid
        self.hop_address = None if proc.pid is None else address(os.getpid(), proc.pid)
        self.alive = True
        parent.setblocking(False)
        transport, _ = await loop.create_unix_connection(lambda: _Protocol(self), sock=parent)
        self._transport = transport
        loop.add_reader(proc.sentinel, self._on_exit)

    # -- requests ----------------------------------------------------------------------------

    def request(
        self,
        msg: tuple[Any, ...],
        node: str,
        priority: int,
        watchdog: float | None,
        window: int = 1,
        outputs: tuple[OutputGrants, tuple[Grant, ...]] | None = None,
    ) -> asyncio.Future[Any]:
        """Queue a request; the future resolves to the reply payload or a WorkerError.

        ``window`` > 1: send it at once behind calls of the same node already in flight, as
        long as fewer than ``window`` are (see the class docstring). ``outputs``: the node's
        output slots and the grants ``msg`` carries (told of the reply, or taken back).
        """
        if not self.usable or self._loop is None:
            if self.death is None and self.alive and self._loop is not None:
                return self._death_later(node)  # its socket closed before its exit was seen
            raise self.death_for(node)
        fut = self._loop.create_future()
        fut.add_done_callback(_retrieved)
        seq = next(self._seq)
        call = _Call(
            (-priority, seq), pickle.dumps(msg, PICKLE), fut, node, watchdog, window, -1, outputs
        )
        if not self._inflight or self._may_follow(call):
            self._send(call)
        else:
            heapq.heappush(self._waiting, call)
        return fut

    def _death_later(self, node: str) -> asyncio.Future[Any]:
        """A call to a worker whose socket is closed and whose exit is not reaped yet fails
        with the worker's death once it is (killed by whom, exit code), not with a bare "not
        running": the sentinel follows the EOF by microseconds, later on a loaded machine."""
        assert self._loop is not None
        fut = self._loop.create_future()
        fut.add_done_callback(_retrieved)

        async def fail() -> None:
            await self.wait_exit(1.0)  # killed after 1 s, as a worker that closed its socket
            if not fut.done():
                fut.set_exception(self.death_for(node))

        task = self._loop.create_task(fail())
        self._deaths.add(task)  # the loop keeps only a weak reference to a task
        task.add_done_callback(self._deaths.discard)
        return fut

    def _may_follow(self, call: _Call) -> bool:
        """A pipelined call may go behind the calls in flight: all its node's, window not full."""
        inflight = self._inflight
        return (
            call.window > 1
            and len(inflight) < call.window
            and not self._waiting
            and all(c.node == call.node and c.window > 1 for c in inflight)
        )

    def _send(self, call: _Call) -> None:
        assert self._transport is not None
        call.index = next(self._wire)
        self._inflight.append(call)
        self._transport.write(frame(call.payload))
        if len(self._inflight) == 1:
            self._arm(call)

    def _arm(self, call: _Call) -> None:
        """The call at the head of the line starts running now: its watchdog starts too."""
        assert self._loop is not None
        if call.watchdog is not None:
            self._progress = progress_of(self.pid, self._loop.time())
            self._call_cpu = 0.0 if self._progress is None else self._progress[1]
            self._timer = self._loop.call_later(call.watchdog, self._on_hung)

    def _dispatch_next(self) -> None:
        while self._waiting:
            call = self._waiting[0]
            if call.future.done():  # skip calls whose caller gave up
                heapq.heappop(self._waiting)
                if call.outputs is not None:
                    call.outputs[0].unsent(call.outputs[1])
                continue
            if self._inflight and not self._may_follow(call):
                return
            heapq.heappop(self._waiting)
            self._send(call)
            if call.window <= 1:
                return

    def _on_reply(self, raw: bytes) -> None:
        if not self._inflight:
            return
        call = self._inflight.popleft()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._inflight:
            self._arm(self._inflight[0])
        fut = call.future
        report = None
        try:
            status, payload, seconds, index, report = pickle.loads(raw)
        except Exception:
            status, payload, seconds, index = R_ERR, traceback.format_exc(), 0.0, call.index
        if call.outputs is not None:
            call.outputs[0].replied(report)
        if fut.done() and status == R_OK:
            release_handoffs(payload)  # nobody will take the frames it made
        if index != call.index:  # cannot happen on one stream socket; never hand out a
            # result to the wrong activation: the worker is condemned like a crashed one
            if not fut.done():
                fut.set_exception(
                    WorkerError(call.node, "crashed", f"reply {index} to call {call.index}")
                )
            self.kill()
            return
        self.last_run_time = seconds
        if not fut.done():
            if status == R_OK:
                fut.set_result(payload)
            elif status == R_SKIP:
                fut.set_result(SKIPPED)
            else:
                fatal = status == R_FATAL
                fut.set_exception(WorkerError(call.node, "exception", payload, fatal=fatal))
        self._dispatch_next()

    # -- failure -----------------------------------------------------------------------------

    def _on_hung(self) -> None:
        self._timer = None
        if not self._inflight or not self.alive:
            return
        call = self._inflight[0]
        assert self._loop is not None
        assert call.watchdog is not None
        if self._reply_waiting():  # answered; the loop was late to read it (uvloop runs
            self._timer = self._loop.call_later(0.005, self._on_hung)  # timers before I/O)
            return
        starved = self._starved(call.watchdog)
        if starved:
            if self.on_starved is not None:
                self.on_starved(call.node, starved)
            self._timer = self._loop.call_later(call.watchdog, self._on_hung)
            return
        self._hung_node = call.node
        self.death = self._classify(None)
        err = WorkerError(
            call.node,
            "hung",
            f"no result within the {call.watchdog:g} s watchdog; worker {self.pid} killed",
        )
        if not call.future.done():
            call.future.set_exception(err)
        self.kill()

    def _reply_waiting(self) -> bool:
        """Bytes from the worker wait in the socket (a reply, or EOF that the sentinel follows)."""
        sock = None if self._transport is None else self._transport.get_extra_info("socket")
        if sock is None:
            return False
        try:
            readable, _, _ = select.select([sock.fileno()], [], [], 0)
        except (OSError, ValueError):
            return False
        return bool(readable)

    def _starved(self, watchdog: float) -> str:
        """Why a call past its watchdog is spared ('' if it is not): the worker was starved.

        A hung worker and a starved machine look the same from the loop's clock. The kernel
        tells them apart: a starved worker got less than half the window's CPU and either
        waited on the run queue for most of it (``/proc/PID/schedstat``) or is runnable now
        (``/proc/PID/stat``: schedstat counts a wait only when it ends). A hung worker is
        asleep or blocked, or it spins and gets the CPU; and a call is killed anyway once it
        has had a whole watchdog of CPU time, so on a machine merely loaded (a spinning
        worker gets a share, not half), a spinning hang is killed a few watchdogs late, and
        on a starved one at the first check after the starvation ends.
        """
        assert self._loop is not None
        before, now = self._progress, progress_of(self.pid, self._loop.time())
        self._progress = now
        if before is None or now is None:
            return ""
        t0, cpu0, wait0 = before
        t1, cpu1, wait1 = now
        window = t1 - t0
        cpu = cpu1 - cpu0
        if cpu1 - self._call_cpu >= watchdog:
            return ""  # a whole watchdog of CPU time and no result: hung however loaded
        if window <= 0 or cpu >= 0.5 * window:
            return ""  # it had the CPU: a hang (or a call longer than its watchdog)
        if wait0 is not None and wait1 is not None and wait1 - wait0 >= 0.5 * window:
            what = f"waited {(wait1 - wait0) * 1000:.0f} ms for a CPU"
        elif state_of(self.pid) == "R":
            # schedstat adds a wait when it ends: a worker still queued shows none yet
            what = "is runnable but not running"
        else:
            return ""  # asleep or blocked: hung
        return (
            f"worker {self.pid} ran {cpu * 1000:.0f} ms of CPU in {window * 1000:.0f} ms and "
            f"{what}: starved of CPU, not hung; watchdog extended by {watchdog * 1000:g} ms"
        )

    def _on_eof(self) -> None:
        # Normally followed at once by the sentinel. A worker that closed its socket but lives
        # on would never answer again: give it a moment, then kill it.
        if self.alive and self._loop is not None and self._eof_timer is None:
            self._eof_timer = self._loop.call_later(1.0, self.kill)

    def _on_exit(self) -> None:
        assert self._loop is not None
        assert self.proc is not None
        self._loop.remove_reader(self.proc.sentinel)
        if self._eof_timer is not None:
            self._eof_timer.cancel()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.proc.join(0)
        exitcode = self.proc.exitcode
        self.alive = False
        proc_forget(self.pid)
        self.death = self._classify(exitcode)
        if self._transport is not None:
            self._transport.abort()
        calls = [*self._inflight, *self._waiting]
        self._inflight = deque()
        self._waiting = []
        for grants in {id(c.outputs[0]): c.outputs[0] for c in calls if c.outputs}.values():
            grants.reclaim()  # the slots lent to the dead worker return to their pool
        for call in calls:
            if not call.future.done():
                call.future.set_exception(self.death_for(call.node))
        with contextlib.suppress(ValueError):
            self.proc.close()
        self._exited.set()

    def _classify(self, exitcode: int | None) -> WorkerError:
        if self._hung_node is not None:
            return WorkerError(
                self._hung_node, "hung", f"worker {self.pid} killed after the watchdog", exitcode
            )
        if exitcode is None:
            return WorkerError(self.name, "crashed", f"worker {self.pid} vanished", exitcode)
        if exitcode < 0:
            try:
                signame = signal.Signals(-exitcode).name
            except ValueError:
                signame = f"signal {-exitcode}"
            kind: WorkerKind = "killed" if -exitcode in SIGNALS_KILLED else "crashed"
            return WorkerError(self.name, kind, f"worker {self.pid} died of {signame}", exitcode)
        if exitcode == EXIT_MAIN_UNGUARDED and self.import_main:
            return WorkerError(self.name, "crashed", unguarded_main_message(), exitcode, fatal=True)
        return WorkerError(
            self.name, "crashed", f"worker {self.pid} exited with code {exitcode}", exitcode
        )

    def death_for(self, node: str) -> WorkerError:
        """The error a node of this worker sees once the worker is dead."""
        d = self.death
        if d is None:
            return WorkerError(node, "crashed", f"worker {self.name} is not running")
        if d.kind == "hung" and d.node != node:
            return WorkerError(
                node, "crashed", f"worker shared with {d.node}, which hung: {d.detail}", d.exitcode
            )
        return WorkerError(node, d.kind, d.detail, d.exitcode, fatal=d.fatal)

    def skip_hop(self, tag: int) -> None:
        """The input a call waits for from another worker will not come: it answers R_SKIP
        (not a request: no reply of its own; ignored if the call has its input already)."""
        if self.usable and self._transport is not None:
            self._transport.write(pack((OP_SKIP, tag)))

    @property
    def busy(self) -> bool:
        """A request sent and not answered yet (a call still running in the worker)."""
        return bool(self._inflight)

    @property
    def usable(self) -> bool:
        """Alive and not condemned (a killed worker stays alive until its sentinel fires), and
        its socket open: a worker killed from outside closes it before its sentinel fires, and
        writing then would raise the transport's RuntimeError, not the worker's death."""
        t = self._transport
        return self.alive and not self._killing and (t is None or not t.is_closing())

    def kill(self) -> None:
        if self.alive and self.pid is not None:
            self._killing = True
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)

    async def wait_exit(self, grace: float = 2.0) -> None:
        """Wait until the process is gone and reaped (killing it if it takes too long)."""
        if not self.alive:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._exited.wait(), grace)
        if self.alive:
            self.kill()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._exited.wait(), grace)

    async def stop(self, grace: float = 2.0) -> None:
        """Tear every node down and let the worker exit; kill it if it does not in time."""
        if self.usable:
            with contextlib.suppress(WorkerError, TimeoutError):
                await asyncio.wait_for(self.request((OP_EXIT,), self.name, 1 << 30, grace), grace)
        await self.wait_exit(grace)


def _kill_started(proc: Any) -> None:
    with contextlib.suppress(Exception):
        if proc.pid is not None:
            os.kill(proc.pid, signal.SIGKILL)


async def _start_in_thread(proc: Any, abandoned: threading.Event) -> None:
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()

    def settle(exc: BaseException | None) -> None:
        if not done.done():
            done.set_result(None) if exc is None else done.set_exception(exc)

    def target() -> None:
        outcome: BaseException | None = None
        try:
            proc.start()
        except BaseException as e:
            outcome = e
        if abandoned.is_set():
            _kill_started(proc)
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody waits any more
            loop.call_soon_threadsafe(settle, outcome)

    threading.Thread(target=target, name="worker-start", daemon=True).start()
    await done


def _retrieved(fut: asyncio.Future[Any]) -> None:
    """Mark a request's error as seen: whoever awaits it still gets it, and a caller that
    gave up (a node task cancelled at stop while its worker died) leaves no "Future exception
    was never retrieved" behind."""
    if not fut.cancelled():
        fut.exception()
