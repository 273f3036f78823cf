"""The worker process: serve requests from the loop until told to exit or the loop is gone."""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import gc
import inspect
import itertools
import math
import os
import pickle
import select
import socket
import sys
import time
import traceback
from typing import Any

from ..frames.lending import WorkerSlots, lazy_report
from ..ipc import PICKLE, BlockingConn
from ..system._priorities import WorkerScheduling, apply_scheduling
from .forkserver import tied_to_runtime
from .hops import SKIPPED, Forward, FromPeer, Hops
from .wire import (
    OP_ADD,
    OP_CALL,
    OP_DISABLE,
    OP_EXIT,
    OP_PRIORITY,
    OP_REMOVE,
    OP_SKIP,
    R_ERR,
    R_FATAL,
    R_OK,
    R_SKIP,
)


def _spin(conn: BlockingConn, start: float, end: float) -> None:
    """Sleep until ``start`` (or data), then poll without sleeping until ``end`` (or data).

    A process blocked in recv is woken by the sender through the scheduler, and a CPU that
    went idle meanwhile has to come out of its sleep state first (tens to hundreds of
    microseconds, more in a VM, different every time). Polling keeps the CPU awake and the
    worker running at the instant the call arrives.
    """
    sock, now = conn.sock, time.monotonic
    wait = start - now()
    if wait > 0:
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        if poller.poll(math.ceil(wait * 1000)):
            return
    while now() < end:
        try:
            chunk = sock.recv(1 << 16, socket.MSG_DONTWAIT)
        except BlockingIOError:
            continue
        except ConnectionResetError:
            return  # left for recv to see
        if chunk:
            conn.buf += chunk
        return  # data, or EOF (left for recv to see)


def _next_request(conn: BlockingConn, spin: tuple[float, float] | None) -> bytes | None:
    """The next request; with ``spin`` = (start, end), busy-poll for it in that window."""
    if spin is not None and not conn.complete():
        _spin(conn, *spin)
    return conn.recv()


class Anticipation:
    """When each spinning node's next call is due, from the spacing of its recent calls.

    Periodic triggers make calls regular; the median of the last few gaps ignores a skipped
    release. Nothing is predicted until three gaps agree within 20 %.
    """

    def __init__(self) -> None:
        self.calls: dict[int, list[float]] = {}
        self.spin: dict[int, float] = {}

    def configure(self, nid: int, spin: float) -> None:
        self.calls.pop(nid, None)
        if spin > 0:
            self.spin[nid] = spin
        else:
            self.spin.pop(nid, None)

    def called(self, nid: int, at: float) -> None:
        if nid in self.spin:
            times = self.calls.setdefault(nid, [])
            times.append(at)
            del times[:-6]

    def window(self, now: float) -> tuple[float, float] | None:
        best: tuple[float, float] | None = None
        for nid, spin in self.spin.items():
            times = self.calls.get(nid, ())
            if len(times) < 4:
                continue
            gaps = sorted(b - a for a, b in itertools.pairwise(times))
            gap = gaps[len(gaps) // 2]
            if gap <= 4 * spin or gaps[0] < 0.8 * gap:
                continue  # irregular, or so frequent that the worker would spin all the time
            due = times[-1] + gap
            if due + spin < now:  # releases skipped: look at the next one still ahead
                due += math.ceil((now - spin - due) / gap) * gap
            if best is None or due - spin < best[0]:
                best = (due - spin, due + spin)
        return best


LINGER = 200e-6  # s: how long a worker fed back to back polls for its next request


class Linger:
    """Whether a worker polls for its next request before sleeping: calls back to back.

    A worker fed one call at a time, flat out (a ``pipeline: 1`` reader of a queue or of a
    lossless edge), gets its next request tens of microseconds after its reply: the loop's
    turn to complete the call and start the next. Sleeping in ``recv`` meanwhile puts a
    wake-up on the path of every call (the sender's interrupt, an idle CPU coming back: tens
    of microseconds, more in a VM). So once three requests running came within ``span`` of
    the reply before them, the worker polls for up to ``span`` before it sleeps; the first
    request that comes later (the stream slowed or stopped) ends it. The CPU it costs is at
    most ``span`` a call, and only while calls come that fast; a periodic node (a camera's
    reader, a 30 Hz relay) never lingers. Nor does a worker whose node has calls pipelined
    (``alone`` false): its next request is usually queued already, and when it is not, the
    loop is the bottleneck and a worker spinning on a shared CPU would slow it (measured
    under load: pipelined flat out behind the baseline in 3 of 3 rounds while it lingered).
    """

    def __init__(self, span: float = LINGER, after: int = 3) -> None:
        self.span = span
        self.after = after
        self.quick = 0  # requests running that came within ``span`` of the reply before
        self.replied: float | None = None
        self.alone = True  # the last call had no other of its node in flight behind it

    def replied_at(self, t: float) -> None:
        self.replied = t

    def arrived(self, t: float) -> None:
        """A request was read at ``t``."""
        if self.replied is not None:
            self.quick = self.quick + 1 if t - self.replied <= self.span else 0
            self.replied = None

    def window(self, now: float) -> tuple[float, float] | None:
        """The polling window before the next ``recv`` (see :func:`_spin`), or None."""
        return (now, now + self.span) if self.alone and self.quick >= self.after else None


def _reply(
    conn: BlockingConn,
    status: int,
    payload: Any,
    seconds: float,
    index: int,
    slots: WorkerSlots | None = None,
) -> None:
    try:
        if slots is not None:  # a call's result: the frames it made may take their slots
            slots.reply(payload)
            report: Any = lazy_report(slots)  # pickled after the payload: knows what it did
        else:
            report = None
        data = pickle.dumps((status, payload, seconds, index, report), PICKLE)
    except Exception:
        if slots is not None:
            slots.abort()
        why = "result could not be pickled:\n" + traceback.format_exc()
        data = pickle.dumps((R_ERR, why, seconds, index, None), PICKLE)
    conn.send(data)


class _Nodes:
    """What a worker serves: its nodes, their output slots, the scheduling in force, the loop
    that runs their coroutines. One method per request (workers/wire.py)."""

    def __init__(self) -> None:
        self.nodes: dict[int, tuple[str, Any, WorkerScheduling]] = {}
        self.outputs: dict[int, WorkerSlots] = {}  # each node's slots (flowrt.frames.lending)
        self.current: WorkerScheduling | None = None
        self.expected = Anticipation()
        self.loop: asyncio.AbstractEventLoop | None = None

    def run(self, value: Any) -> Any:
        if inspect.isawaitable(value):
            if self.loop is None:
                self.loop = asyncio.new_event_loop()
            return self.loop.run_until_complete(_await(value))
        return value

    def request(self, msg: tuple[Any, ...]) -> Any:
        """A request other than a call or the exit (workers/wire.py): its reply's payload."""
        op = msg[0]
        if op == OP_ADD:
            return self.add(*msg[1:])
        if op == OP_PRIORITY:
            return self.priority(*msg[1:])
        if op == OP_DISABLE:
            return self.disabled(msg[1])
        if op == OP_REMOVE:
            self.teardown(msg[1])
            return None
        raise ValueError(f"unknown request {op!r}")

    def call(
        self, nid: int, inputs: dict[str, Any], grants: Any, alone: bool = True
    ) -> tuple[Any, WorkerSlots]:
        """OP_CALL: the node's ``process``; its output slots, told of the reply after."""
        self.expected.called(nid, time.monotonic())
        _, node, sched = self.nodes[nid]
        if self.current != sched:
            apply_scheduling(sched)
            self.current = sched
        slots = self.outputs.get(nid)
        if slots is None:
            slots = self.outputs[nid] = WorkerSlots()
        slots.begin(grants)
        return self.run(node.process(**inputs)), slots

    def add(self, nid: int, node_name: str, factory: Any, sched: WorkerScheduling) -> str:
        """OP_ADD: a node set up here; the scheduling the kernel granted."""
        self.teardown(nid)  # a restart in a live worker: the old instance goes first
        granted = apply_scheduling(sched)
        self.current = sched
        self.expected.configure(nid, sched.spin)
        node = factory()
        if hasattr(node, "setup"):
            self.run(node.setup())
        self.nodes[nid] = (node_name, node, sched)
        gc.freeze()  # the node's setup, too: never walked at a call (no collect first:
        # walking the inherited objects would copy their shared pages)
        return granted

    def priority(self, nid: int, sched: WorkerScheduling) -> str:
        """OP_PRIORITY: the node's new scheduling, applied now (and at each of its calls)."""
        node_name, node, _ = self.nodes[nid]
        self.nodes[nid] = (node_name, node, sched)
        granted = apply_scheduling(sched)
        self.current = sched
        return granted

    def disabled(self, nid: int) -> Any:
        """OP_DISABLE: the node's ``on_disable`` (kernel/disabling.py): what it returned (to
        publish), None when it has none."""
        hook = getattr(self.nodes[nid][1], "on_disable", None)
        return self.run(hook()) if callable(hook) else None

    def teardown(self, nid: int) -> None:
        entry = self.nodes.pop(nid, None)
        self.outputs.pop(nid, None)  # the main side takes its grants back (reclaim)
        self.expected.configure(nid, 0.0)
        if entry is not None and hasattr(entry[1], "teardown"):
            self.run(entry[1].teardown())

    def teardown_all(self) -> None:
        for nid in list(self.nodes):
            with contextlib.suppress(Exception):
                self.teardown(nid)


def single_threaded_opencv() -> bool:
    """OpenCV's own thread pool off in a worker (True when this call turned it off).

    A worker is one CPU's worth of a node, preempted by the priority the graph gave it. An
    OpenCV call that parallelises (``connectedComponentsWithStats``, resizes, filters) wakes
    the pool's threads, which then spin for their next job on the other CPUs, at the worker's
    priority: there they starved an offline capture's decoder, which runs below its worker
    readers (nodes/capture/reader.py). Measured with graphs/video.yaml's tracker in a worker
    (2 CPUs, ``--realtime``): the decoder lowered and the pool kept, 0.70 ms per frame; the
    pool off as well, 0.43 ms (RESULTS.md, issue 44 item 5). A node that wants the pool
    calls ``cv2.setNumThreads(n)`` in its ``setup()`` (which runs after this);
    ``OPENCV_FOR_THREADS_NUM`` in the environment is respected and left alone.
    """
    cv2 = sys.modules.get("cv2")  # preloaded by the forkserver; never imported for this
    if cv2 is None or "OPENCV_FOR_THREADS_NUM" in os.environ:
        return False
    cv2.setNumThreads(1)
    return True


def worker_main(sock: socket.socket, name: str, main_pid: int) -> None:
    """Entry point of a worker process: serve requests until EXIT or EOF."""
    if not tied_to_runtime(main_pid):
        return  # nothing to serve
    faulthandler.enable()  # a segfault prints the Python stack on stderr before dying
    single_threaded_opencv()
    conn = BlockingConn(sock)
    w = _Nodes()
    hops = Hops(main_pid)
    expected = w.expected
    linger = Linger()
    now = time.monotonic
    index = -1  # requests read (OP_SKIP is not one)
    while True:
        t = now()
        raw = _next_request(conn, expected.window(t) if expected.spin else linger.window(t))
        if raw is None:
            break
        linger.arrived(now())
        t0 = time.perf_counter()
        slots: WorkerSlots | None = None
        to: Forward | None = None
        try:
            msg = pickle.loads(raw)
            op = msg[0]
            if op == OP_SKIP:
                continue  # stale: the call it was for had its input already
            index += 1
            if op == OP_CALL:
                nid, inputs, grants, alone = msg[1:5]
                linger.alone = alone
                to = msg[5] if len(msg) > 5 else None
                if not _inputs_from_peers(inputs, hops, conn):
                    hops.skip(to)
                    _reply(conn, R_SKIP, None, time.perf_counter() - t0, index)
                    continue
                result, slots = w.call(nid, inputs, grants, alone)
                if to is not None:
                    hops.forward(to, result, slots)
                    to = None
            elif op == OP_EXIT:
                w.teardown_all()
                _reply(conn, R_OK, None, time.perf_counter() - t0, index)
                break
            else:
                result = w.request(msg)
        except Exception as e:
            hops.skip(to)
            status = R_FATAL if getattr(e, "fatal", False) is True else R_ERR
            _reply(conn, status, traceback.format_exc(), time.perf_counter() - t0, index)
        else:
            _reply(conn, R_OK, result, time.perf_counter() - t0, index, slots)
        linger.replied_at(now())
        if slots is not None:
            slots.end()
    if w.loop is not None:
        w.loop.close()
    sock.close()


def _inputs_from_peers(inputs: dict[str, Any], hops: Hops, conn: BlockingConn) -> bool:
    """Wait for the inputs that come from other workers (workers/hops.py); False: one will not
    come (the call is answered R_SKIP, the kernel sends it again the usual way)."""
    for port, value in inputs.items():
        if isinstance(value, FromPeer):
            got = hops.wait(value.tag, conn)
            if got is SKIPPED:
                return False
            inputs[port] = got
    return True


async def _await(value: Any) -> Any:
    return await value
