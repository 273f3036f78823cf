"""The worker process: serve requests from the loop until told to exit or the loop is gone."""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import gc
import inspect
import itertools
import math
import pickle
import select
import socket
import time
import traceback
from typing import Any

from ..frames.lending import WorkerSlots, lazy_report
from ..ipc import PICKLE, BlockingConn
from ..oscheduling import WorkerScheduling, apply_scheduling
from .forkserver import tied_to_runtime
from .wire import OP_ADD, OP_CALL, OP_EXIT, OP_PRIORITY, OP_REMOVE, R_ERR, R_FATAL, R_OK


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


def worker_main(sock: socket.socket, name: str, main_pid: int) -> None:
    """Entry point of a worker process: serve requests until EXIT or EOF."""
    if not tied_to_runtime(main_pid):
        return  # nothing to serve
    faulthandler.enable()  # a segfault prints the Python stack on stderr before dying
    conn = BlockingConn(sock)
    nodes: dict[int, tuple[str, Any, WorkerScheduling]] = {}
    outputs: dict[int, WorkerSlots] = {}  # each node's output slots (flowrt.frames.lending)
    current: WorkerScheduling | None = None
    expected = Anticipation()
    loop: asyncio.AbstractEventLoop | None = None

    def run(value: Any) -> Any:
        nonlocal loop
        if inspect.isawaitable(value):
            if loop is None:
                loop = asyncio.new_event_loop()
            return loop.run_until_complete(_await(value))
        return value

    def teardown(nid: int) -> None:
        entry = nodes.pop(nid, None)
        outputs.pop(nid, None)  # the main side takes its grants back (OutputGrants.reclaim)
        expected.configure(nid, 0.0)
        if entry is not None and hasattr(entry[1], "teardown"):
            run(entry[1].teardown())

    for index in itertools.count():
        raw = _next_request(conn, expected.window(time.monotonic()) if expected.spin else None)
        if raw is None:
            break
        t0 = time.perf_counter()
        slots: WorkerSlots | None = None
        try:
            msg = pickle.loads(raw)
            op = msg[0]
            if op == OP_CALL:
                _, nid, inputs, grants = msg
                expected.called(nid, time.monotonic())
                _, node, sched = nodes[nid]
                if current != sched:
                    apply_scheduling(sched)
                    current = sched
                slots = outputs.get(nid)
                if slots is None:
                    slots = outputs[nid] = WorkerSlots()
                slots.begin(grants)
                result = run(node.process(**inputs))
            elif op == OP_ADD:
                _, nid, node_name, factory, sched = msg
                teardown(nid)  # a restart in a live worker: the old instance goes first
                result = apply_scheduling(sched)
                current = sched
                expected.configure(nid, sched.spin)
                node = factory()
                if hasattr(node, "setup"):
                    run(node.setup())
                nodes[nid] = (node_name, node, sched)
                gc.freeze()  # the node's setup, too: never walked at a call (no collect first:
                # walking the inherited objects would copy their shared pages)
            elif op == OP_PRIORITY:
                _, nid, sched = msg
                node_name, node, _ = nodes[nid]
                nodes[nid] = (node_name, node, sched)
                result = apply_scheduling(sched)
                current = sched
            elif op == OP_REMOVE:
                teardown(msg[1])
                result = None
            elif op == OP_EXIT:
                for nid in list(nodes):
                    with contextlib.suppress(Exception):
                        teardown(nid)
                _reply(conn, R_OK, None, time.perf_counter() - t0, index)
                break
            else:
                raise ValueError(f"unknown request {op!r}")
        except Exception as e:
            status = R_FATAL if getattr(e, "fatal", False) is True else R_ERR
            _reply(conn, status, traceback.format_exc(), time.perf_counter() - t0, index)
        else:
            _reply(conn, R_OK, result, time.perf_counter() - t0, index, slots)
        if slots is not None:
            slots.end()
    if loop is not None:
        loop.close()
    sock.close()


async def _await(value: Any) -> Any:
    return await value
