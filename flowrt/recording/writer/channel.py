"""The recorder's side of a writer process: :class:`RecordingWriter`'s interface, off the GIL.

:class:`ProcessRecordingWriter` is what the ``recorder`` node holds by default (``writer:
process``): ``submit`` on the event loop only counts, and queues a small message for the
writer process (:mod:`.child`) on a non-blocking socket, sent once per loop iteration.
A frame in a shared-memory slot goes as the descriptor of its slot, and the recorder's link
on it is given back (through :attr:`done`, as with the thread) when the process says it has
copied the pixels; any other value is encoded here, a few microseconds (the writer process
then needs no class of the graph's). The process's answers (frames let go of, each
message's result) are read on the loop with ``add_reader``; closing hands the socket to a
thread that waits for the file to be finished, as the thread writer's threads do.

Every guarantee of the thread writer holds: a stream has at most ``max_frames`` frames whose
slot the process may still read (the thread writer's bound: frames not yet copied; copied
ones wait for the disk up to the writer's ``max_bytes``, 256 MiB, so a disk that stalls holds
memory, not slots, and not the recorder's count), and the writer ``max_messages`` other
messages in flight, beyond which a message is refused and counted (``lost_behind``); a write
error stops the file and counts what follows; split parts,
CRCs, the per-stream report and the flush interval are the same code, in the other process.
A writer process that dies (``kill -9``, out of memory) is seen at once: the recording
stops with the error said, every frame's link goes back, and what the file holds is counted
again from the file itself (the part being written, read as ``info`` would), so ``received =
written + lost`` stays true to what a reader finds.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import os
import pickle
import signal
import socket
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from ...frames import Frame
from ...ipc import PICKLE, BlockingConn, Framer, pack
from ..split import SplitPolicy, part_path
from .threads import (
    THREAD_PREFIX,
    StreamCounters,
    Unencodable,
    _ValueEncoder,
    count_written,
    value_encoder,
)
from .wire import ACKS, ATTACH, CLOSE, DECLARE, DETACH, DRAINED, FINISHED, MESSAGE, OPEN

__all__ = ["ProcessRecordingWriter"]

OPEN_TIMEOUT = 60.0
"""Seconds a writer process may take to start and create its file (a cold forkserver)."""
SEND_BUFFER = 4 << 20


class _Sent(NamedTuple):
    topic: str
    t: float
    is_frame: bool


class ProcessRecordingWriter:
    """MCAP file(s) written by a process of its own; the interface of :class:`RecordingWriter`.

    Args:
        loop: the event loop that calls :meth:`submit` (its thread does every send).
        options: the writer process's :class:`~.threads.RecordingWriter` keyword arguments
            (``image_formats``, ``epoch_offset``, ``chunk_size``, ``compression``, ``crc``,
            ``flush_interval``, ``max_bytes``, ``direct_io``), and ``priority``: ``normal``
            or ``idle`` (the process runs only on CPU time nobody else wants: it never delays
            the loop's timers, but falls behind under load; :func:`.child._set_priority`).
        The others: as :class:`~.threads.RecordingWriter`.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        loop: asyncio.AbstractEventLoop,
        max_frames: int = 8,
        max_messages: int = 10000,
        on_written: Callable[[], None] | None = None,
        split: SplitPolicy | None = None,
        **options: Any,
    ) -> None:
        self.split = split if split is not None and split.active else None
        self.base = Path(path)
        self.path = self.base.with_name(part_path(self.base.name, 0)) if self.split else self.base
        self.files: list[Path] = []
        self.part_messages: list[int] = []
        self.max_frames = max_frames
        self.max_messages = max_messages
        self.on_written = on_written
        self.streams: dict[str, StreamCounters] = {}
        self.error: str | None = None
        self.closed = False
        self.done: deque[Frame] = deque()  # frames let go of: their links go back on the loop
        self.notes: list[str] = []
        self._loop = loop
        self._config = {**options, "path": str(self.base), "split": self.split}
        formats = dict(options.get("image_formats") or {})
        self._values = value_encoder(
            formats, options.get("epoch_offset", 0.0), False, options.get("profile", "flowrt")
        )
        self._unencodable = Unencodable(self.notes)
        self._travels: dict[tuple[str, type], bool] = {}  # pickled as is, or encoded here
        # Invariant: ``_sent`` holds every message sent and not yet reported, ``_held`` every
        # frame of those whose slot the process may still read (the link this writer holds)
        # with its topic; ``_frames_waiting`` counts ``_held`` per topic, ``_messages_waiting``
        # the other messages of ``_sent``.
        self._sent: dict[int, _Sent] = {}
        self._held: dict[int, tuple[str, Frame]] = {}
        self._frames_waiting: dict[str, int] = {}
        self._messages_waiting = 0
        self._next_id = 0
        self._outbox: list[bytes] = []
        self._flush_due = False
        self._want_write = False
        self._sock: socket.socket | None = None
        self._proc: Any = None
        self._framer = Framer()
        self._part_counts: dict[str, list[int]] = {}  # messages, bytes per topic, current part
        self._closing = False
        self._on_loop = False  # the socket is read by the loop (else by nobody, or the closer)
        self._dead = False
        self._recount: threading.Thread | None = None
        self._finished = threading.Event()
        self._end_attachments: Callable[[], list[tuple[str, str, bytes]]] = list
        self._on_finished: Callable[[], None] | None = None

    # --- starting ------------------------------------------------------------------------

    def open(
        self,
        metadata: dict[str, dict[str, str]],
        attachments: list[tuple[str, str, bytes]] = (),  # type: ignore[assignment]
    ) -> None:
        """Start the process and create the file; OSError as the thread writer's ``open``.

        Blocking (the process starts, the file is created): call it off the loop.
        """
        parent, proc = self._sock, self._proc = _start_process(self.base.name)
        parent.settimeout(OPEN_TIMEOUT)
        conn = BlockingConn(parent)
        reply = None
        if conn.send_message((OPEN, self._config, dict(metadata), list(attachments))):
            reply = conn.recv_message()
        self._framer = Framer(bytes(conn.buf))  # (nothing comes before the first message)
        if reply is None or reply[1] is not None:
            parent.close()
            proc.join(5)
            if reply is None:
                raise OSError(f"{self.path}: the writer process did not start ({_how(proc)})")
            errno, strerror, filename = reply[1]
            raise OSError(errno, strerror, filename)
        parent.setblocking(False)
        with contextlib.suppress(OSError):
            parent.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        self.files.append(self.path)
        self.part_messages.append(0)
        self._loop.call_soon_threadsafe(self._attach)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    def _attach(self) -> None:
        """On the loop: read the process's answers, and see it die."""
        if self._dead or self._closing or self._sock is None:
            return
        self._loop.add_reader(self._sock.fileno(), self._on_readable)
        self._loop.add_reader(self._proc.sentinel, self._on_exit)
        self._on_loop = True
        if self._outbox:
            self._flush()

    # --- on the event loop ---------------------------------------------------------------

    def declare(self, topic: str, source: str = "", **meta: str) -> StreamCounters:
        """Name a stream before its first message (its source ``node.port`` and metadata)."""
        s = self.streams.get(topic)
        if s is None:
            s = self.streams[topic] = StreamCounters(topic, source)
        if source:
            s.source = source
        self._send((DECLARE, topic, {"source": s.source, **meta}))
        return s

    def submit(self, topic: str, value: Any, t: float, seq: int) -> bool:
        """Queue a message logged at runtime-clock time ``t``; False (and counted) if refused.

        A frame is kept by reference: the caller holds one link on it for the writer, given
        back through :attr:`done` once the process has let go of it (at once if refused).
        """
        s = self.streams.get(topic) or self.declare(topic)
        s.received += 1
        if s.first_seen is None:
            s.first_seen = t
        s.last_seen = t
        if self.error is not None or self._closing or self.closed:
            s.refused_error += 1
            return False
        mid = self._next_id
        is_frame = isinstance(value, Frame)
        payload: Any
        if is_frame:
            waiting = self._frames_waiting.get(topic, 0)
            if waiting >= self.max_frames:
                s.lost_behind += 1
                return False
            # A slot frame: its descriptor, unpickled (mapped) by the process on its own.
            payload = pickle.dumps(value, PICKLE) if value.shared else value
            self._frames_waiting[topic] = waiting + 1
            self._held[mid] = (topic, value)
        else:
            if self._messages_waiting >= self.max_messages:
                s.lost_behind += 1
                return False
            try:
                payload = _payload(topic, value, self._travels, self._values)
            except Exception as e:  # a value that cannot be encoded: counted, said once
                self._unencodable.say(topic, value, e)
                s.unwritten += 1
                return True
            self._messages_waiting += 1
        self._next_id = mid + 1
        self._sent[mid] = _Sent(topic, t, is_frame)
        self._send((MESSAGE, mid, topic, payload, t, seq))
        return True

    def _send(self, msg: tuple[Any, ...]) -> None:
        self._outbox.append(pack(msg))
        if not self._flush_due and not self._want_write:
            self._flush_due = True
            self._loop.call_soon(self._flush)  # one send for all of this loop iteration's

    def _flush(self) -> None:
        self._flush_due = False
        sock = self._sock
        if sock is None or self._dead or self._closing or not self._outbox:
            return
        data = b"".join(self._outbox) if len(self._outbox) > 1 else self._outbox[0]
        try:
            n = sock.send(data)
        except BlockingIOError:
            n = 0
        except OSError:
            self._died()
            return
        self._outbox = [data[n:]] if n < len(data) else []
        if self._outbox and not self._want_write and self._on_loop:
            self._want_write = True  # the process is behind: send when it reads again
            self._loop.add_writer(sock.fileno(), self._flush)
        elif not self._outbox and self._want_write:
            self._want_write = False
            self._loop.remove_writer(sock.fileno())

    def _on_readable(self) -> None:
        sock = self._sock
        assert sock is not None
        while True:
            try:
                chunk = sock.recv(1 << 16)
            except BlockingIOError:
                return
            except OSError:
                chunk = b""
            if not chunk:
                self._died()
                return
            for raw in self._framer.feed(chunk):
                self._handle(pickle.loads(raw))
            if len(chunk) < 1 << 16:
                return

    def _on_exit(self) -> None:
        self._on_readable()  # what it said before it went; then EOF: _died

    # --- the process's answers (on the loop; once closing, on the closer thread) ----------

    def _handle(self, msg: tuple[Any, ...]) -> None:
        op = msg[0]
        if op == ACKS:
            _, released, results, error = msg
            if error is not None and self.error is None:
                self.error = error
            for mid, nbytes, part in results:
                self._result(mid, nbytes, part)
            self._let_go(released)
        elif op == FINISHED:
            _, error, notes, files, part_messages = msg
            if error is not None and self.error is None:
                self.error = error
            self.notes.extend(notes)
            self.files = [Path(f) for f in files] or self.files
            self.part_messages = list(part_messages) or self.part_messages
            self._finish()
        # DETACHED: every frame was let go of in the acknowledgements before it

    def _result(self, mid: int, nbytes: int, part: int) -> None:
        sent = self._sent.pop(mid)
        if not sent.is_frame:  # (a frame left the count when its slot was let go of)
            self._messages_waiting -= 1
        s = self.streams[sent.topic]
        if nbytes < 0:
            s.unwritten += 1
            return
        while part >= len(self.files):  # the process started the next part
            self.files.append(self.base.with_name(part_path(self.base.name, len(self.files))))
            self.part_messages.append(0)
            self._part_counts = {}
        self.path = self.files[-1]
        count_written(s, sent.t, nbytes)
        self.part_messages[-1] += 1
        counts = self._part_counts.setdefault(sent.topic, [0, 0])
        counts[0] += 1
        counts[1] += nbytes

    def _let_go(self, ids: list[int]) -> None:
        got = False
        for mid in ids:
            held = self._held.pop(mid, None)
            if held is not None:
                self._frames_waiting[held[0]] -= 1
                self.done.append(held[1])
                got = True
        if got and self.on_written is not None:
            self.on_written()

    # --- closing -------------------------------------------------------------------------

    def request_close(
        self,
        attachments: Callable[[], list[tuple[str, str, bytes]]] = list,
        on_finished: Callable[[], None] | None = None,
    ) -> None:
        """Finish the file after what is queued, without waiting (see :meth:`join`).

        The process copies the frames it has not read yet off their slots and lets go of
        them (they come back through :attr:`done`); ``attachments`` is called once every
        message's result is in (on the closer thread), ``on_finished`` once the file is.
        """
        self._end_attachments = attachments
        self._on_finished = on_finished
        self._closing = True
        if self._sock is None:
            self._finish()
            return
        self._off_loop()
        closer = threading.Thread(target=self._close_run, name=f"{THREAD_PREFIX}{self.path.name}")
        closer.start()  # not a daemon: the process waits for the file, as with the thread

    def _close_run(self) -> None:
        sock = self._sock
        assert sock is not None
        if not self._dead:
            sock.setblocking(True)
            out = [*self._outbox, pack((DETACH,)), pack((CLOSE,))]
            self._outbox = []
            conn = BlockingConn(sock, self._framer.rest())
            try:
                sock.sendall(b"".join(out))
                while not self._finished.is_set():
                    msg = conn.recv_message()
                    if msg is None:
                        break
                    if msg[0] == DRAINED:
                        sock.sendall(pack((ATTACH, self._end_attachments())))
                    else:
                        self._handle(msg)
            except OSError:
                pass
            if not self._finished.is_set():
                self._died()
        if self._recount is not None:
            self._recount.join()
        self._finish()
        with contextlib.suppress(Exception):
            self._proc.join(5)
        sock.close()

    def _off_loop(self) -> None:
        """The loop stops reading the socket (the closer thread takes it, or nobody)."""
        if self._on_loop and self._sock is not None:
            self._on_loop = False
            with contextlib.suppress(Exception):  # (a closed loop: nothing to remove)
                self._loop.remove_reader(self._sock.fileno())
                self._loop.remove_reader(self._proc.sentinel)
                self._loop.remove_writer(self._sock.fileno())

    def join(self, timeout: float | None = None) -> bool:
        """Wait for a requested close; True when the file is finished."""
        return self._finished.wait(timeout)

    def detach_frames(self) -> list[Frame]:
        """Nothing to copy here: the process copies, and the frames come back in :attr:`done`."""
        return []

    def encoding_frame(self) -> bool:
        """True while the process may still read a frame's slot (the recorder holds its link)."""
        return bool(self._held)

    def _finish(self) -> None:
        if self._finished.is_set() or (self._dead and not self._closing):
            return
        self.closed = True
        if self._on_finished is not None:
            self._on_finished()
        self._finished.set()

    # --- a process that died -------------------------------------------------------------

    def _died(self) -> None:
        """The process is gone without finishing: say so, let go of everything, count."""
        if self._dead or self._finished.is_set():
            return
        self._dead = True
        proc = self._proc
        self._off_loop()
        with contextlib.suppress(Exception):
            proc.join(0.2)  # gone already (its socket closed): reaped at once
        if self.error is None:
            self.error = f"{self.path}: the writer process died ({_how(proc)})"
        self._let_go(list(self._held))
        for sent in self._sent.values():
            self.streams[sent.topic].unwritten += 1
        self._sent.clear()
        self._frames_waiting.clear()
        self._messages_waiting = 0
        # What the file holds past the last answers: counted again from the file, off the loop.
        self._recount = threading.Thread(
            target=self._count_again, name=f"{THREAD_PREFIX}{self.path.name} recount"
        )
        self._recount.start()

    def _count_again(self) -> None:
        """The messages of the current part (and any later) that a reader finds, per stream."""
        first = len(self.files) - 1
        paths = [self.path]
        while self.split is not None:  # a part it started, unanswered, counts too
            path = self.base.with_name(part_path(self.base.name, first + len(paths)))
            if not path.exists():
                break
            paths.append(path)
        found, messages = _in_files(paths)
        for i, (path, n) in enumerate(zip(paths, messages, strict=True)):
            if first + i >= len(self.files):
                self.files.append(path)
                self.part_messages.append(0)
            self.part_messages[first + i] = n
        for topic, s in self.streams.items():
            believed = self._part_counts.get(topic, [0, 0])
            there = found.get(topic, [0, 0])
            moved = there[0] - believed[0]  # > 0: in the file, unanswered; < 0: not flushed
            s.written += moved
            s.unwritten -= moved
            s.bytes += there[1] - believed[1]


def _start_process(name: str) -> tuple[socket.socket, Any]:
    """A writer process from the workers' forkserver, and the recorder's end of its socket."""
    from ...workers.forkserver import NO_MAIN, context, shut_at_exit
    from .child import writer_main

    parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    proc = context().Process(
        target=writer_main,
        args=(child, os.getpid()),
        name=f"{NO_MAIN}recorder {name}",  # the main script is not imported again there
        daemon=True,
    )
    try:
        proc.start()
    except BaseException:
        parent.close()
        raise
    finally:
        child.close()
    shut_at_exit(parent)
    return parent, proc


def _in_files(paths: list[Path]) -> tuple[dict[str, list[int]], list[int]]:
    """Messages and bytes per topic that a reader finds in ``paths``; messages per file."""
    from ..reader import scan

    found: dict[str, list[int]] = {}
    messages = []
    for path in paths:
        try:
            info = scan(path)
        except Exception:  # not even a header: nothing in it
            messages.append(0)
            continue
        for st in info.streams:
            f = found.setdefault(st.topic, [0, 0])
            f[0] += st.count
            f[1] += st.bytes
        messages.append(info.messages)
    return found, messages


def _payload(
    topic: str, value: Any, travels: dict[tuple[str, type], bool], values: _ValueEncoder
) -> Any:
    """The value pickled (a few us; the process encodes it), or encoded here (tens of us)
    when the process could not unpickle it: its class lives in the main script."""
    key = (topic, type(value))
    ok = travels.get(key)
    if ok is None:
        ok = travels[key] = _travels(value)
    if ok:
        with contextlib.suppress(Exception):
            return pickle.dumps(value, PICKLE)
        travels[key] = False
    return values.encode(topic, value)


def _travels(value: Any) -> bool:
    """True when the writer process can unpickle ``value``: its classes import there."""
    module = type(value).__module__
    if module == "__main__":
        return False
    try:
        if b"__main__" in pickle.dumps(value, PICKLE):
            return False
        return importlib.util.find_spec(module) is not None
    except Exception:
        return False


def _how(proc: Any) -> str:
    code = getattr(proc, "exitcode", None)
    if code is None:
        return "no exit status"
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
    return f"exit code {code}"
