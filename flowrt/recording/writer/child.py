"""The writer process: a recorder's MCAP files written outside the runtime's process.

Why a process: the writer's work is CPU (a copy of each frame's pixels, the chunk CRCs,
``mcap``'s record building and indexes, mostly pure Python) and a thread doing it in the
runtime's process shares the GIL with the event loop, so a timer due on the loop waits for
the writer thread's turn (measured: +0.4 ms at p99 of a 1 kHz timer at 320x240, the writer
at 19-30 % of the disk's direct-I/O rate; benchmarks/RESULTS.md). Here the same
:class:`~.threads.RecordingWriter` (its encoder and disk threads) runs in a process of its own,
started by the workers' forkserver; the recorder sends it small messages
(:mod:`.wire`) and the process maps each frame's shared-memory slot to read the pixels
where the camera put them.

A frame's slot stays held by the recorder (one link) until this process says it has copied
the pixels into the message (``released``); every message gets a result (written, its size
and the part it went into, or not), so the recorder keeps the per-stream counters exactly as
the thread does. The process ignores SIGINT/SIGTERM/SIGHUP (the runtime stops it in order)
and dies with the runtime (PR_SET_PDEATHSIG through the forkserver, or end of file on its
socket): a runtime killed with ``kill -9`` leaves the file as a killed writer thread did,
readable up to its last finished chunk.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import queue
import socket
import threading
import time
from collections import deque
from typing import Any

from ...frames import Frame
from ...ipc import BlockingConn
from .threads import RecordingWriter
from .wire import (
    ACKS,
    ATTACH,
    CLOSE,
    DECLARE,
    DETACH,
    DETACHED,
    DRAINED,
    FINISHED,
    MESSAGE,
    OPEN,
    OPENED,
)

__all__ = ["writer_main"]

COALESCE = 0.001
"""Seconds the acknowledgements wait for company: one wake-up of the loop for several."""
ATTACH_WAIT = 60.0
"""Seconds the finished queue waits for the recorder's report before closing without it."""


def writer_main(sock: socket.socket, main_pid: int) -> None:
    """Entry point of a writer process: one session (a file or its parts), then exit."""
    from ...workers.forkserver import tied_to_runtime

    if tied_to_runtime(main_pid):
        _Session(sock).serve()


def _set_priority(priority: str) -> str | None:
    """``idle``: SCHED_IDLE for this process's threads (they inherit it from the main one).

    Each message the recorder sends wakes this process, and the kernel places a task woken
    by a socket on the waker's CPU: as an ordinary task that has slept, the writer then
    preempted the event loop there for the ~0.3 ms of its work (unpickle, map the slot,
    copy), which the loop's next timer waited out (the 1 kHz probe's p99 +0.12-0.15 ms at
    640x480). A SCHED_IDLE task is preempted by any other at once (Linux ``sched(7)``), so the
    loop's timers see no writer at all; the price is that it runs only on CPU time nobody
    else wants: under load it falls behind and messages are refused (counted). SCHED_BATCH
    (no wake-up preemption, but not preempted at once either) measured worse than normal.
    """
    if priority != "idle":
        return None
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError) as e:  # not Linux: said in the recording's notes
        return f"writer_priority idle: cannot set SCHED_IDLE ({e}); writing at normal priority"
    return None


class _Acks:
    """What the process tells the recorder, sent in batches by one thread, in order.

    Released frames and results first, then the control messages posted after them: the
    recorder reads ``DRAINED`` only after every result.
    """

    def __init__(self, conn: BlockingConn) -> None:
        self._conn = conn
        self._cond = threading.Condition()
        self._released: list[int] = []
        self._results: list[tuple[int, int, int]] = []
        self._controls: list[tuple[Any, ...]] = []
        self._error: str | None = None
        self._said_error = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="writer acks", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def released(self, ids: list[int]) -> None:
        with self._cond:
            self._released.extend(ids)
            self._cond.notify()

    def result(self, mid: int, nbytes: int, part: int, error: str | None) -> None:
        with self._cond:
            self._results.append((mid, nbytes, part))
            if error is not None and self._error is None:
                self._error = error
            self._cond.notify()

    def control(self, msg: tuple[Any, ...]) -> None:
        with self._cond:
            self._controls.append(msg)
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not (self._released or self._results or self._controls or self._stop):
                    self._cond.wait()
                if self._stop and not (self._released or self._results or self._controls):
                    return
            time.sleep(COALESCE)
            with self._cond:
                released, self._released = self._released, []
                results, self._results = self._results, []
                controls, self._controls = self._controls, []
                error = None
                if self._error is not None and not self._said_error:
                    error, self._said_error = self._error, True
            if (released or results or error) and not self._conn.send_message(
                (ACKS, released, results, error)
            ):
                return
            for msg in controls:
                if not self._conn.send_message(msg):
                    return


class _Session:
    """One writer's life: open, messages, detach, close; the ids matched to results."""

    def __init__(self, sock: socket.socket) -> None:
        self.conn = BlockingConn(sock)  # read here, written by the acks thread once open
        self.acks = _Acks(self.conn)
        self.lock = threading.Lock()
        # Invariant: ``ids`` holds the ids of the messages the writer accepted and has not
        # reported, in the order it reports them (one encoder, one disk thread, FIFO);
        # ``frame_ids`` likewise for the frames whose slot it has not let go of.
        self.ids: deque[int] = deque()
        self.frame_ids: deque[int] = deque()
        self.detached = False  # every slot let go of: later frames are heap copies
        self.finished = False
        self.attachments: queue.Queue[list[tuple[str, str, bytes]]] = queue.Queue()
        self.writer: RecordingWriter | None = None
        self.unreadable: set[str] = set()

    def serve(self) -> None:
        first = self.conn.recv_message()
        if first is None or first[0] != OPEN:
            return
        _, config, metadata, attachments = first
        refused = _set_priority(config.pop("priority", "normal"))
        w = self.writer = RecordingWriter(
            on_written=self._written,
            on_result=self._result,
            max_frames=1 << 30,  # the recorder bounds what is in flight: never refused here
            max_messages=1 << 30,
            **config,
        )
        if refused is not None:
            w.notes.append(refused)
        try:
            w.open(metadata, attachments)
        except OSError as e:
            self.conn.send_message((OPENED, (e.errno, e.strerror or str(e), e.filename)))
            return
        if not self.conn.send_message((OPENED, None)):
            os._exit(0)
        self.acks.start()
        while True:
            msg = self.conn.recv_message()
            if msg is None:
                if not self.finished:
                    os._exit(0)  # the runtime is gone: stop as its writer thread would
                break
            op = msg[0]
            if op == MESSAGE:
                self._message(w, *msg[1:])
            elif op == DECLARE:
                w.declare(msg[1], **msg[2])
            elif op == DETACH:
                self._detach(w)
            elif op == CLOSE:
                w.request_close(self._end_attachments, self._finished)
            elif op == ATTACH:
                self.attachments.put(msg[1])
                break
        w.join()
        self.acks.close()

    def _message(
        self, w: RecordingWriter, mid: int, topic: str, value: Any, t: float, seq: int
    ) -> None:
        if isinstance(value, bytes):  # a value, or a frame's slot: mapped now (read-only)
            try:
                value = pickle.loads(value)
            except Exception as e:  # the slot is gone (the runtime freed its pools)
                if topic not in self.unreadable:
                    self.unreadable.add(topic)
                    w.notes.append(f"{topic}: cannot read the message: {e}")
                self.acks.released([mid])
                self.acks.result(mid, -1, len(w.files) - 1, None)
                return
        is_frame = isinstance(value, Frame)
        with self.lock:
            self.ids.append(mid)
            if is_frame and not self.detached:
                self.frame_ids.append(mid)
        if w.submit(topic, value, t, seq):
            return
        with self.lock:  # refused (a write error, or closed): never reported by the writer
            self.ids.pop()
            if is_frame and not self.detached:
                self.frame_ids.pop()
        if is_frame:
            self.acks.released([mid])
        self.acks.result(mid, -1, len(w.files) - 1, w.error)

    def _written(self) -> None:
        """Encoder thread: a frame's pixels are in its message, the slot is not read again."""
        w = self.writer
        assert w is not None
        with contextlib.suppress(IndexError):
            w.done.popleft()  # a view of the slot: nothing to give back in this process
        with self.lock:
            if self.detached:
                return
            mid = self.frame_ids.popleft()
        self.acks.released([mid])

    def _result(self, topic: str, nbytes: int, part: int) -> None:
        """Disk thread: one message written (its size) or not (-1)."""
        with self.lock:
            mid = self.ids.popleft()
        w = self.writer
        self.acks.result(mid, nbytes, part, w.error if w is not None else None)

    def _detach(self, w: RecordingWriter) -> None:
        """Copy the queued frames off their slots; then say so: the runtime may free them."""
        w.detach_frames()  # the originals are views of the slots: dropped
        while w.encoding_frame():  # the frame being copied now, a few ms
            time.sleep(0.001)
        with self.lock:
            self.detached = True
            ids, self.frame_ids = list(self.frame_ids), deque()
        self.acks.released(ids)
        self.acks.control((DETACHED,))

    def _end_attachments(self) -> list[tuple[str, str, bytes]]:
        """Disk thread, everything written: the recorder's report, from its counters."""
        self.acks.control((DRAINED,))
        try:
            return self.attachments.get(timeout=ATTACH_WAIT)
        except queue.Empty:
            return []

    def _finished(self) -> None:
        w = self.writer
        assert w is not None
        self.finished = True
        files = [str(f) for f in w.files]
        self.acks.control((FINISHED, w.error, list(w.notes), files, list(w.part_messages)))
