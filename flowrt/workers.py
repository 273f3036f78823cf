"""Worker processes: running a node outside the event loop (``placement: process`` / ``pool``).

A node placed in a worker is described by a picklable zero-argument *factory*; called in the
worker it returns an object with ``setup()``, ``process(**inputs)`` (a value or a coroutine,
which the worker runs to completion on its own event loop) and ``teardown()``. The node class is
the same whatever its placement.

Why processes: the GIL serialises Python threads, and the CAMBADA model needs the *kernel* to
preempt a low-priority tracker when a high-priority one becomes runnable. Each worker therefore
gets an OS priority from its flowrt priority (:mod:`flowrt.oscheduling`), and :attr:`granted`
reports what the kernel actually allowed.

Transport: one AF_UNIX stream socketpair per worker, length-prefixed pickles. The main side is
an asyncio protocol (works unchanged on asyncio and uvloop and never blocks the loop); the
worker side is a plain blocking socket. Frames from a :class:`~flowrt.frames.FramePool` pickle
to a descriptor of their shared-memory slot, so a 1080p frame costs the same as an integer.
Results are pickled back. A frame the node received and passes on goes back as its descriptor;
a frame it makes is written into a shared-memory slot the main process lent it with the call
(:mod:`flowrt.grants`) and goes back as a descriptor too. Anything else (detections, poses, a
bare array) travels pickled.

Death detection: the process sentinel becomes readable when the worker exits for any reason
(exception escaping, segfault, abort, SIGKILL); EOF on the socket is seen as well. The in-flight
call fails with :class:`WorkerError` whose ``kind`` says what happened. A call running longer
than its watchdog is failed at that instant (kind ``hung``) and the worker is SIGKILLed,
unless the kernel says the worker was starved of CPU meanwhile (it waited on the run queue):
then the watchdog is extended and ``on_starved`` told, since killing it would not help.

Workers are forked from a ``forkserver`` that has preloaded numpy and OpenCV, so their pages
are shared (copy-on-write) and a worker starts in milliseconds. A worker dies with the runtime:
PR_SET_PDEATHSIG ties it to the forkserver, which exits when the main process does, and EOF on
its socket ends it too. Workers ignore SIGINT, SIGTERM and SIGHUP (sent to the whole process
group by Ctrl-C, ``kill`` of the group or a closed terminal): stopping is the main process's
business, which then stops them in order (SIGKILL still ends one, and it is replaced).
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import gc
import heapq
import inspect
import itertools
import math
import multiprocessing
import multiprocessing.context
import os
import pickle
import re
import select
import signal
import socket
import struct
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from flowrt.frames import release_handoffs
from flowrt.grants import Grant, OutputGrants, WorkerSlots, lazy_report
from flowrt.oscheduling import WorkerScheduling, apply_scheduling, nice_for

__all__ = [
    "PRELOAD_MODULES",
    "PoolExecutor",
    "PoolNodeExecutor",
    "ProcessExecutor",
    "WorkerError",
    "WorkerKind",
    "start_forkserver",
]

WorkerKind = Literal["exception", "crashed", "killed", "hung"]

#: Modules imported once by the forkserver, so every worker shares their pages.
PRELOAD_MODULES = [
    "numpy",
    "cv2",
    "flowrt.frames",
    "flowrt.grants",
    "flowrt.oscheduling",
    "flowrt.workers",
    "flowrt._forkserver_signals",  # SIGTERM/SIGHUP ignored, inherited by every worker
    "flowrt._forkserver_freeze",  # last: freezes all of the above before any fork
]

_HDR = struct.Struct("<I")
_PICKLE = pickle.HIGHEST_PROTOCOL

# Requests (main -> worker); every request gets exactly one reply.
_OP_ADD = 0  # (op, node_id, node_name, factory, WorkerScheduling) -> granted: str
_OP_CALL = 1  # (op, node_id, inputs, grants) -> result (grants: slots lent, flowrt.grants)
_OP_REMOVE = 2  # (op, node_id) -> None (teardown)
_OP_EXIT = 3  # (op,) -> None (teardown all, then exit)
_OP_PRIORITY = 4  # (op, node_id, WorkerScheduling) -> granted: str

# Replies (worker -> main), in the order of the requests; ``index`` counts the requests the
# worker has read (0, 1, 2, ...), so that the main side matches each reply to its call;
# ``report`` says what a call did with its output slots (flowrt.grants), else None.
_R_OK = 0  # (status, payload, run_seconds, index, report)
_R_ERR = 1  # (status, formatted traceback, run_seconds, index)
_R_FATAL = 2  # as _R_ERR, from an exception whose ``fatal`` is true: do not restart

_SIGNALS_KILLED = {signal.SIGKILL, signal.SIGTERM, signal.SIGINT, signal.SIGHUP}


class WorkerError(RuntimeError):
    """A node in a worker failed; ``kind`` tells the supervisor how.

    - ``exception``: ``process``/``setup`` raised; ``detail`` is the worker's traceback, and the
      worker (and the node object) are still alive.
    - ``crashed``: the worker died on its own (segfault, abort, exit) — or under another node of
      the same pool worker; ``detail`` names the signal or exit code.
    - ``killed``: the worker was killed from outside (SIGKILL, SIGTERM, the OOM killer).
    - ``hung``: a call exceeded its watchdog; the worker was SIGKILLed at that instant.

    After any kind, ``await executor.start()`` gives the node a fresh instance. ``fatal``
    says that it cannot help (the worker cannot load the node at all): the supervisor gives
    the node up at once instead of restarting it.
    """

    def __init__(
        self,
        node: str,
        kind: WorkerKind,
        detail: str,
        exitcode: int | None = None,
        *,
        fatal: bool = False,
    ) -> None:
        super().__init__(f"{node}: worker {kind}: {detail}")
        self.node = node
        self.kind: WorkerKind = kind
        self.detail = detail
        self.exitcode = exitcode
        self.fatal = fatal

    @property
    def summary(self) -> str:
        """One line for logs and reasons: the node's own exception, or what became of the
        worker (the supervisor shows this instead of the main side's stack)."""
        if self.kind == "exception":
            lines = [ln for ln in self.detail.strip().splitlines() if ln.strip()]
            # "pkg.mod.Error: text" -> "Error: text", as an inline node's failure reads
            return re.sub(r"^[\w.]+\.(\w+:)", r"\1", lines[-1].strip()) if lines else "exception"
        if self.fatal:
            return self.detail
        return f"worker {self.kind}: {self.detail}"

    @property
    def traceback(self) -> str:
        """The worker's traceback for an exception; nothing for a death (no stack to show)."""
        return self.detail if self.kind == "exception" else ""


# --------------------------------------------------------------------------------------------
# Process start


_ctx_lock = threading.Lock()
_ctx: multiprocessing.context.ForkServerContext | None = None


def _context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, with numpy/cv2 preloaded (set before the server first starts)."""
    global _ctx
    with _ctx_lock:
        if _ctx is None:
            ctx = multiprocessing.get_context("forkserver")
            assert isinstance(ctx, multiprocessing.context.ForkServerContext)
            ctx.set_forkserver_preload(PRELOAD_MODULES)
            _ctx = ctx
        return _ctx


# Process names of workers that must not re-import the main script (see _install_prepare_hook).
_NO_MAIN = "flowrt:"
_WITH_MAIN = "flowrt+main:"
# Exit code of a worker whose import of the main script started a flowrt runtime again.
_EXIT_MAIN_UNGUARDED = 78
_importing_main = False  # in a worker: re-running the main script to find the node's class


def _exit_if_importing_main() -> None:
    """Where a runtime would start worker processes: refuse inside a worker's import of the
    main script, at once and quietly (the parent explains, from the exit code).

    Reaching this there means the script starts a runtime at import: it has no
    ``if __name__ == "__main__":`` guard. Letting it go on would start a runtime inside each
    worker, whose workers would do the same (multiprocessing stops that with a traceback in
    every attempt, and the node would crash-loop).
    """
    if _importing_main:
        os._exit(_EXIT_MAIN_UNGUARDED)


def _check_main_importable(node: str, factory: Any) -> bool:
    """True if the factory needs the main module; fatal if a worker could never import it.

    A class defined in ``python -c``, on stdin or in a notebook lives in a ``__main__`` that
    no other process can import: every start would fail the same way.
    """
    if not _needs_main(factory):
        return False
    main = sys.modules.get("__main__")
    if getattr(main, "__file__", None) is None and getattr(main, "__spec__", None) is None:
        raise WorkerError(
            node,
            "crashed",
            "its node class is defined in an interactive session (python -c, stdin, a "
            "notebook), which a worker process cannot import: define the class in a module "
            "or a script file, or use placement: inline",
            fatal=True,
        )
    return True


def _unguarded_main_message() -> str:
    main = sys.modules.get("__main__")
    script = getattr(main, "__file__", None) or "the main script"
    return (
        f"its node class is defined in {script}, which starts a flowrt runtime "
        "again when a worker process imports it to load the class: put the code that starts "
        'the runtime under `if __name__ == "__main__":` (or define the node class in a module '
        "of its own)"
    )


def _install_prepare_hook() -> None:
    """Keep forkserver children from re-running the main script, unless the node lives there.

    multiprocessing re-imports ``__main__`` in every child so that objects defined in the main
    script unpickle. For a worker that is a waste at best (pytest, the CLI and their imports
    cost startup time and unshared memory in each of nine trackers) and a crash at worst (a
    script without a ``__main__`` guard). The hook runs in the forkserver (which preloads this
    module) and drops the main-module step for processes named ``flowrt:...``; a factory that
    is defined in ``__main__`` gets a ``flowrt+main:`` name and the usual behaviour.
    """
    from multiprocessing import spawn

    original = spawn.prepare
    if getattr(original, "_flowrt", False):
        return

    def prepare(data: Mapping[str, Any]) -> None:
        global _importing_main
        if str(data.get("name", "")).startswith(_NO_MAIN):
            data = {
                k: v
                for k, v in data.items()
                if k not in ("init_main_from_path", "init_main_from_name")
            }
        _importing_main = True
        try:
            original(data)
        finally:
            _importing_main = False

    prepare._flowrt = True  # type: ignore[attr-defined]
    spawn.prepare = prepare


_install_prepare_hook()


def _needs_main(obj: Any) -> bool:
    """True if unpickling ``obj`` needs the main script's module."""
    try:
        return b"__main__" in pickle.dumps(obj, _PICKLE)
    except Exception:
        return False


def start_forkserver() -> None:
    """Start the preloaded forkserver now (blocking, ~0.5 s the first time).

    The runtime calls this at start, before any deadline runs, so that the first worker start
    is not the one that pays for importing OpenCV.
    """
    from multiprocessing import forkserver

    _exit_if_importing_main()
    _context()
    # Python 3.11's forkserver runs ``python -c`` and ignores the sys.path it is given, so the
    # working directory comes first on its path: in the folder that holds a clone named
    # ``flowrt/``, the preloaded ``flowrt`` was that folder (a namespace package), and every
    # worker failed ("cannot import name 'Frame' from 'flowrt'"). PYTHONSAFEPATH (3.11+)
    # leaves the working directory out; workers get the main process's sys.path when they
    # start (multiprocessing's prepare), so user modules the main process can import work.
    before = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    try:
        forkserver.ensure_running()
    finally:
        if before is None:
            os.environ.pop("PYTHONSAFEPATH", None)
        else:
            os.environ["PYTHONSAFEPATH"] = before


# --------------------------------------------------------------------------------------------
# Worker side


class _BlockingConn:
    """Length-prefixed messages over the worker's end of the socketpair."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buf = bytearray()

    def recv(self, spin: tuple[float, float] | None = None) -> bytes | None:
        """The next message; with ``spin`` = (start, end), busy-poll for it in that window."""
        buf = self.buf
        if spin is not None and not self._complete():
            self._spin(*spin)
        while True:
            if len(buf) >= 4:
                (n,) = _HDR.unpack_from(buf)
                if len(buf) >= 4 + n:
                    msg = bytes(buf[4 : 4 + n])
                    del buf[: 4 + n]
                    return msg
                want = 4 + n - len(buf)
            else:
                want = 4
            try:
                chunk = self.sock.recv(max(want, 1 << 16))
            except ConnectionResetError:  # the runtime is gone (killed): as EOF
                return None
            if not chunk:
                return None
            buf += chunk

    def send(self, payload: bytes) -> None:
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):  # runtime gone: the
            self.sock.sendall(_HDR.pack(len(payload)) + payload)  # next recv sees EOF

    def _complete(self) -> bool:
        buf = self.buf
        return len(buf) >= 4 and len(buf) >= 4 + _HDR.unpack_from(buf)[0]

    def _spin(self, start: float, end: float) -> None:
        """Sleep until ``start`` (or data), then poll without sleeping until ``end`` (or data).

        A process blocked in recv is woken by the sender through the scheduler, and a CPU that
        went idle meanwhile has to come out of its sleep state first (tens to hundreds of
        microseconds, more in a VM, different every time). Polling keeps the CPU awake and the
        worker running at the instant the call arrives.
        """
        sock, now = self.sock, time.monotonic
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
                self.buf += chunk
            return  # data, or EOF (left for recv to see)


class _Anticipation:
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


def _set_pdeathsig() -> None:
    """Ask the kernel to SIGKILL this worker when its parent (the forkserver) dies."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _reply(
    conn: _BlockingConn,
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
        data = pickle.dumps((status, payload, seconds, index, report), _PICKLE)
    except Exception:
        if slots is not None:
            slots.abort()
        why = "result could not be pickled:\n" + traceback.format_exc()
        data = pickle.dumps((_R_ERR, why, seconds, index, None), _PICKLE)
    conn.send(data)


def _worker_main(sock: socket.socket, name: str, main_pid: int) -> None:
    """Entry point of a worker process: serve requests until EXIT or EOF."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    _set_pdeathsig()
    try:
        os.kill(main_pid, 0)
    except ProcessLookupError:
        return  # the runtime died while we were being forked: nothing to serve
    faulthandler.enable()  # a segfault prints the Python stack on stderr before dying
    conn = _BlockingConn(sock)
    nodes: dict[int, tuple[str, Any, WorkerScheduling]] = {}
    outputs: dict[int, WorkerSlots] = {}  # each node's output slots (flowrt.grants)
    current: WorkerScheduling | None = None
    expected = _Anticipation()
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
        raw = conn.recv(expected.window(time.monotonic()) if expected.spin else None)
        if raw is None:
            break
        t0 = time.perf_counter()
        slots: WorkerSlots | None = None
        try:
            msg = pickle.loads(raw)
            op = msg[0]
            if op == _OP_CALL:
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
            elif op == _OP_ADD:
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
            elif op == _OP_PRIORITY:
                _, nid, sched = msg
                node_name, node, _ = nodes[nid]
                nodes[nid] = (node_name, node, sched)
                result = apply_scheduling(sched)
                current = sched
            elif op == _OP_REMOVE:
                teardown(msg[1])
                result = None
            elif op == _OP_EXIT:
                for nid in list(nodes):
                    with contextlib.suppress(Exception):
                        teardown(nid)
                _reply(conn, _R_OK, None, time.perf_counter() - t0, index)
                break
            else:
                raise ValueError(f"unknown request {op!r}")
        except Exception as e:
            status = _R_FATAL if getattr(e, "fatal", False) is True else _R_ERR
            _reply(conn, status, traceback.format_exc(), time.perf_counter() - t0, index)
        else:
            _reply(conn, _R_OK, result, time.perf_counter() - t0, index, slots)
        if slots is not None:
            slots.end()
    if loop is not None:
        loop.close()
    sock.close()


async def _await(value: Any) -> Any:
    return await value


# --------------------------------------------------------------------------------------------
# Main side


@dataclass(order=True)
class _Call:
    """One request to a worker, ordered for dispatch by priority then arrival."""

    sort_key: tuple[int, int]
    payload: bytes = field(compare=False)
    future: asyncio.Future[Any] = field(compare=False)
    node: str = field(compare=False)
    watchdog: float | None = field(compare=False)
    window: int = field(default=1, compare=False)  # >1: may be sent behind calls of its node
    index: int = field(default=-1, compare=False)  # its place on the wire (see _R_OK)
    # The node's output slots and the grants this call carries (flowrt.grants).
    outputs: tuple[OutputGrants, tuple[Grant, ...]] | None = field(default=None, compare=False)


class _Protocol(asyncio.Protocol):
    """Splits the worker's byte stream into replies."""

    def __init__(self, worker: _Worker) -> None:
        self.worker = worker
        self.buf = bytearray()

    def data_received(self, data: bytes) -> None:
        buf = self.buf
        buf += data
        while len(buf) >= 4:
            (n,) = _HDR.unpack_from(buf)
            if len(buf) < 4 + n:
                break
            msg = bytes(buf[4 : 4 + n])
            del buf[: 4 + n]
            self.worker._on_reply(msg)

    def connection_lost(self, exc: Exception | None) -> None:
        self.worker._on_eof()


class _Worker:
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
        self.alive = False  # the process exists (until its sentinel fires)
        self._killing = False
        self.last_run_time = 0.0
        # Watchdog progress check (see _on_hung): the worker's CPU and run-queue wait at the
        # last check, and who hears of a call spared because the worker was starved of CPU.
        self._progress: tuple[float, float, float | None] | None = None
        self._call_cpu = 0.0  # the worker's CPU time when the call in flight was sent
        self.on_starved: Callable[[str, str], None] | None = None

    async def spawn(self) -> None:
        _exit_if_importing_main()
        loop = asyncio.get_running_loop()
        self._loop = loop
        ctx = _context()
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        proc = ctx.Process(
            target=_worker_main,
            args=(child, self.name, os.getpid()),
            name=(_WITH_MAIN if self.import_main else _NO_MAIN) + self.name,
            daemon=True,
        )
        try:
            # Blocking (talks to the forkserver, which may still be starting): off the loop.
            await asyncio.to_thread(proc.start)
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        self.proc = proc
        self.pid = proc.pid
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
            raise self.death_for(node)
        fut = self._loop.create_future()
        fut.add_done_callback(_retrieved)
        seq = next(self._seq)
        call = _Call(
            (-priority, seq), pickle.dumps(msg, _PICKLE), fut, node, watchdog, window, -1, outputs
        )
        if not self._inflight or self._may_follow(call):
            self._send(call)
        else:
            heapq.heappush(self._waiting, call)
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

    @property
    def in_flight(self) -> int:
        """Calls written to the worker and not answered yet."""
        return len(self._inflight)

    def _send(self, call: _Call) -> None:
        assert self._transport is not None
        call.index = next(self._wire)
        self._inflight.append(call)
        self._transport.write(_HDR.pack(len(call.payload)) + call.payload)
        if len(self._inflight) == 1:
            self._arm(call)

    def _arm(self, call: _Call) -> None:
        """The call at the head of the line starts running now: its watchdog starts too."""
        assert self._loop is not None
        if call.watchdog is not None:
            self._progress = _progress_of(self.pid, self._loop.time())
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
            status, payload, seconds, index = _R_ERR, traceback.format_exc(), 0.0, call.index
        if call.outputs is not None:
            call.outputs[0].replied(report)
        if fut.done() and status == _R_OK:
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
            if status == _R_OK:
                fut.set_result(payload)
            else:
                fatal = status == _R_FATAL
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
        before, now = self._progress, _progress_of(self.pid, self._loop.time())
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
        elif _state_of(self.pid) == "R":
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
        _proc_forget(self.pid)
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
            kind: WorkerKind = "killed" if -exitcode in _SIGNALS_KILLED else "crashed"
            return WorkerError(self.name, kind, f"worker {self.pid} died of {signame}", exitcode)
        if exitcode == _EXIT_MAIN_UNGUARDED and self.import_main:
            return WorkerError(
                self.name, "crashed", _unguarded_main_message(), exitcode, fatal=True
            )
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

    @property
    def usable(self) -> bool:
        """Alive and not condemned (a killed worker stays alive until its sentinel fires)."""
        return self.alive and not self._killing

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
                await asyncio.wait_for(self.request((_OP_EXIT,), self.name, 1 << 30, grace), grace)
        await self.wait_exit(grace)


_PROC_FDS: dict[tuple[int, str], int] = {}  # (pid, file) -> an open /proc descriptor


def _proc_read(pid: int, name: str) -> bytes:
    """/proc/PID/NAME through a descriptor kept open: ~2 us a read, against ~60 us to open,
    read and close it, which matters at every dispatch of a call that has a watchdog."""
    key = (pid, name)
    fd = _PROC_FDS.get(key)
    if fd is None:
        fd = os.open(f"/proc/{pid}/{name}", os.O_RDONLY | os.O_CLOEXEC)
        _PROC_FDS[key] = fd
    return os.pread(fd, 1024, 0)


def _proc_forget(pid: int | None) -> None:
    """Close the /proc descriptors of a worker that is gone."""
    for name in ("schedstat", "stat"):
        fd = _PROC_FDS.pop((pid, name), None) if pid is not None else None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)


def _progress_of(pid: int | None, now: float) -> tuple[float, float, float | None] | None:
    """(now, CPU seconds, run-queue wait seconds or None) of a process, from /proc."""
    if pid is None:
        return None
    try:
        cpu_ns, wait_ns, _ = _proc_read(pid, "schedstat").split()
        return now, int(cpu_ns) / 1e9, int(wait_ns) / 1e9
    except (OSError, ValueError):
        pass
    try:
        fields = _proc_read(pid, "stat").rsplit(b")", 1)[1].split()
        ticks = os.sysconf("SC_CLK_TCK")
        return now, (int(fields[11]) + int(fields[12])) / ticks, None  # utime + stime
    except (OSError, ValueError, IndexError):
        return None


def _state_of(pid: int | None) -> str:
    """The process state letter of /proc/PID/stat (R runnable, S sleeping, ...), or ''."""
    if pid is None:
        return ""
    try:
        return _proc_read(pid, "stat").rsplit(b")", 1)[1].split()[0].decode()
    except (OSError, IndexError, UnicodeDecodeError):
        return ""


def _retrieved(fut: asyncio.Future[Any]) -> None:
    """Mark a request's error as seen: whoever awaits it still gets it, and a caller that
    gave up (a node task cancelled at stop while its worker died) leaves no "Future exception
    was never retrieved" behind."""
    if not fut.cancelled():
        fut.exception()


def _check_priority(priority: int) -> int:
    if not 1 <= int(priority) <= 99:
        raise ValueError(f"priority must be in 1..99, got {priority}")
    return int(priority)


class _NodeExecutor:
    """What a node's executor does whatever its worker: call, re-prioritise, report."""

    pipelined = False  # may calls be pipelined (submit)? Only a worker of its own

    def __init__(
        self,
        name: str,
        factory: Callable[[], Any],
        nid: int,
        priority: int,
        watchdog: float | None,
        realtime: bool,
        setup_timeout: float | None,
        nice_of: Callable[[int], int] | None = None,
        cpus: tuple[int, ...] | None = None,
        spin: float = 0.0,
        outputs: OutputGrants | None = None,
    ) -> None:
        self.name = name
        self.factory = factory
        # The slots lent to the worker for the frames this node makes (None: no frame store,
        # its frames travel by the socket).
        self.outputs = outputs
        self.nid = nid
        self.priority = _check_priority(priority)
        self.watchdog = watchdog
        self.realtime = realtime
        self.setup_timeout = setup_timeout
        self.nice_of = nice_of or nice_for
        self.cpus = cpus
        self.spin = spin
        self._worker: _Worker | None = None
        self._granted = "not started"
        # Told (node, detail) when a call past its watchdog is spared because the worker
        # was starved of CPU rather than hung (the runtime emits a HealthAlert).
        self.on_starved: Callable[[str, str], None] | None = None

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

    async def _add_to(self, worker: _Worker) -> None:
        if self.outputs is not None:  # a new instance, or a new worker: start with no grant
            self.outputs.reclaim()
        self._worker = worker
        if self.on_starved is not None:
            worker.on_starved = self.on_starved
        msg = (_OP_ADD, self.nid, self.name, self.factory, self.scheduling)
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

    def _request(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        w = self._worker
        if w is None:
            raise RuntimeError(f"{self.name}: executor not started")
        out = self.outputs
        if out is None:
            return w.request(
                (_OP_CALL, self.nid, inputs, ()), self.name, self.priority, self.watchdog, window
            )
        grants = out.grant(inputs, window) if w.usable else ()
        try:
            return w.request(
                (_OP_CALL, self.nid, inputs, grants),
                self.name,
                self.priority,
                self.watchdog,
                window,
                (out, grants),
            )
        except BaseException:
            out.unsent(grants)
            raise

    def set_priority(self, priority: int) -> None:
        """Change the node's priority at run time (QoS); the worker re-applies its OS priority.

        Returns at once; :attr:`granted` is updated when the worker has answered.
        """
        self.priority = _check_priority(priority)
        w = self._worker
        if w is None or not w.alive:
            return
        msg = (_OP_PRIORITY, self.nid, self.scheduling)
        fut = w.request(msg, self.name, self.priority, None)

        def done(f: asyncio.Future[Any]) -> None:
            if not f.cancelled() and f.exception() is None:
                self._granted = f.result()

        fut.add_done_callback(done)


class ProcessExecutor(_NodeExecutor):
    """Runs one node in its own worker process (``placement: process``).

    Its calls may be pipelined (:meth:`submit`): the worker is the node's alone, so calls in
    flight never hold up another node.

    Args:
        name: the node's name (used in errors and the process title).
        factory: picklable zero-argument callable returning the node object, called in the
            worker. Must be importable there (module level), like anything sent to a process.
        priority: flowrt priority 1..99; becomes SCHED_FIFO or a nice level in the worker.
        watchdog: seconds a call may run before the worker is declared hung and killed; None
            disables it (a deadline still reports the miss — the watchdog is what recovers).
        realtime: try SCHED_FIFO at all (False: nice levels only).
        setup_timeout: seconds ``setup()`` may take in ``start``.
        nice_of: the nice level of a priority when SCHED_FIFO is not used (the runtime passes
            :meth:`FairShare.nice <flowrt.oscheduling.FairShare.nice>`; default
            :func:`~flowrt.oscheduling.nice_for`).
        cpus: CPUs the worker may run on (None: those it inherits).
        spin: seconds the worker busy-polls around the predicted instant of each call of a
            periodic node, so that it is awake when the call arrives (0: it sleeps).
    """

    pipelined = True

    def __init__(
        self,
        name: str,
        factory: Callable[[], Any],
        *,
        priority: int,
        watchdog: float | None = None,
        realtime: bool = True,
        setup_timeout: float | None = 60.0,
        nice_of: Callable[[int], int] | None = None,
        cpus: tuple[int, ...] | None = None,
        spin: float = 0.0,
        outputs: OutputGrants | None = None,
    ) -> None:
        super().__init__(
            name,
            factory,
            0,
            priority,
            watchdog,
            realtime,
            setup_timeout,
            nice_of,
            cpus,
            spin,
            outputs,
        )

    async def start(self) -> None:
        """Spawn the worker if needed and (re)create the node in it; WorkerError if setup fails.

        Called again after a failure of any kind it gives the node a fresh instance: a dead
        worker is replaced, a live one tears the old instance down first.
        """
        w = self._worker
        if w is None or not w.usable:
            if w is not None:
                await w.wait_exit()  # a killed worker: let it go before its successor starts
            w = _Worker(self.name, import_main=_check_main_importable(self.name, self.factory))
            await w.spawn()
        await self._add_to(w)

    async def stop(self, grace: float = 2.0) -> None:
        """Teardown in the worker, then join; kill after ``grace`` seconds. Never hangs."""
        w, self._worker = self._worker, None
        if w is not None:
            await w.stop(grace)
        if self.outputs is not None:
            self.outputs.reclaim(count=False)


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
        self._workers: list[_Worker | None] = [None] * self.size
        self._locks = [asyncio.Lock() for _ in range(self.size)]
        self._next_node = itertools.count()

    def executor_for(
        self,
        name: str,
        factory: Callable[[], Any],
        priority: int,
        *,
        watchdog: float | None = None,
        setup_timeout: float | None = 60.0,
        cpus: tuple[int, ...] | None = None,
        spin: float = 0.0,
        outputs: OutputGrants | None = None,
    ) -> PoolNodeExecutor:
        """The executor of node ``name``, pinned to the next worker in round-robin order.

        ``cpus`` and ``spin`` are the node's own: the worker switches to them for its calls.
        """
        nid = next(self._next_node)
        return PoolNodeExecutor(
            self, nid, name, factory, priority, watchdog, setup_timeout, cpus, spin, outputs
        )

    async def _worker(self, index: int, *, import_main: bool = False) -> _Worker:
        async with self._locks[index]:
            w = self._workers[index]
            if w is None or not w.usable:
                if w is not None:
                    await w.wait_exit()
                w = _Worker(f"{self.name}[{index}]", import_main=import_main)
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
        priority: int,
        watchdog: float | None,
        setup_timeout: float | None,
        cpus: tuple[int, ...] | None = None,
        spin: float = 0.0,
        outputs: OutputGrants | None = None,
    ) -> None:
        super().__init__(
            name,
            factory,
            nid,
            priority,
            watchdog,
            pool.realtime,
            setup_timeout,
            pool.nice_of,
            cpus,
            spin,
            outputs,
        )
        self.pool = pool
        self.index = nid % pool.size

    async def start(self) -> None:
        """Make sure this node's worker runs, then (re)create the node in it."""
        import_main = _check_main_importable(self.name, self.factory)
        await self._add_to(await self.pool._worker(self.index, import_main=import_main))

    async def stop(self, grace: float = 2.0) -> None:
        """Tear this node down in its worker (the worker stays for the pool's other nodes)."""
        w, self._worker = self._worker, None
        if w is not None and w.alive:
            with contextlib.suppress(WorkerError, TimeoutError):
                await asyncio.wait_for(
                    w.request((_OP_REMOVE, self.nid), self.name, self.priority, grace), grace
                )
        if self.outputs is not None:
            self.outputs.reclaim(count=False)
