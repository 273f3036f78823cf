"""The ``can`` node's wire: a python-can bus opened, read, written, lost and reopened, and the
trace file it logs to. No DBC and no signals here: frames only.

Threads, never the event loop, touch the device: opening an adapter may take seconds, a
serial write waits for the wire, and a trace file is disk I/O. The loop sees frames through
``call_soon_threadsafe`` callbacks. Every bus lives in a *generation*: closing bumps it and a
thread of an older generation stops at its next look, so a reopen never races a dying reader.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from flowrt import FatalError

__all__ = ["SERIAL_INTERFACES", "CanLink", "TraceLog", "TraceReplay", "copy_frame", "one_line"]

log = logging.getLogger("flowrt.nodes.can.node")

#: Interfaces whose write waits for the wire: written from a sender thread by default.
SERIAL_INTERFACES = {"slcan", "serial", "robotell", "seeedstudio", "cantact", "gs_usb"}
#: Frames waiting for the trace writer; past it frames are dropped from the trace, counted.
TRACE_QUEUE = 100_000


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def copy_frame(msg: Any, **changes: Any) -> Any:
    """A python-can message with everything a frame is on the wire: FD, bit-rate switch,
    error state, remote and error frames, the DLC of a remote frame (replay must not turn FD
    into classic frames or remote frames into empty data frames)."""
    import can

    fields: dict[str, Any] = {
        "arbitration_id": msg.arbitration_id,
        "is_extended_id": msg.is_extended_id,
        "is_remote_frame": msg.is_remote_frame,
        "is_error_frame": msg.is_error_frame,
        "is_fd": msg.is_fd,
        "bitrate_switch": msg.bitrate_switch,
        "error_state_indicator": msg.error_state_indicator,
        "data": None if msg.is_remote_frame else bytes(msg.data),
        "dlc": msg.dlc,
        "channel": msg.channel,
        "check": False,
    }
    fields.update(changes)
    return can.Message(**fields)


class TraceLog:
    """The bus as python-can writes it (candump ``.log``, ``.asc``, ``.blf``, ``.csv``: by the
    suffix), rotated by size with python-can's ``SizedRotatingLogger`` (the full file is
    renamed with a timestamp and a rollover count), written by a thread of its own; frames
    it cannot keep up with are counted (``dropped``), never waited for."""

    def __init__(self, path: str, max_bytes: int = 0) -> None:
        import can

        self.path = path
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.writer: Any = (
            can.SizedRotatingLogger(path, max_bytes=max_bytes) if max_bytes else can.Logger(path)
        )
        self.q: queue.Queue[Any] = queue.Queue(TRACE_QUEUE)
        self.written = 0
        self.dropped = 0
        self.failed: str | None = None
        self.thread = threading.Thread(target=self._run, name=f"can-trace {path}", daemon=True)
        self.thread.start()

    def put(self, msg: Any) -> None:
        """Keep a frame (from any thread); never blocks."""
        try:
            self.q.put_nowait(msg)
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while (msg := self.q.get()) is not None:
            if self.failed is not None:
                self.dropped += 1
                continue
            try:
                self.writer.on_message_received(msg)
                self.written += 1
            except Exception as exc:  # a full disk: counted from here on, said once
                self.failed = one_line(exc)
                self.dropped += 1
                log.warning("CAN trace %s: cannot write: %s", self.path, self.failed)
        try:
            self.writer.stop()
        except Exception as exc:
            log.warning("CAN trace %s: cannot close: %s", self.path, one_line(exc))

    def close(self) -> None:
        """Write what is queued and close the file (call off the loop: it joins the thread)."""
        self.q.put(None)
        self.thread.join(10.0)


class TraceReplay:
    """The frames of a trace (any format python-can reads) at their recorded timing, as they
    were (:func:`copy_frame`), onto ``channel``; once, or over and over with ``loop``."""

    def __init__(self, path: str, loop: bool, channel: str | None, t0: float) -> None:
        self.path, self.loop, self.channel = path, loop, channel
        self.done = False
        self._open(t0)

    def _open(self, t0: float) -> None:
        self.frames: Iterator[Any] = iter(_frames(self.path))
        self.t0 = t0
        self.first: float | None = None
        self.next: Any = next(self.frames, None)
        if self.next is None:  # (replayed "once" it sent nothing, and the run said nothing)
            raise FatalError(f"replay {self.path}: no CAN frame in it")

    def due(self, t: float, slack: float) -> list[Any]:
        """The frames due by ``t`` (seconds on the runtime clock; ``slack``: half a tick)."""
        out: list[Any] = []
        while self.next is not None:
            msg = self.next
            if self.first is None:
                self.first = float(msg.timestamp)
            if float(msg.timestamp) - self.first > t - self.t0 + slack:
                return out
            out.append(copy_frame(msg, channel=self.channel))
            self.next = next(self.frames, None)  # (damaged further on: FatalError)
        if self.loop:
            self._open(t)
        else:
            self.done = True
        return out


def _frames(path: str) -> Iterator[Any]:
    """A trace's frames; a file python-can cannot read (at its start or further on) is a
    :class:`FatalError` naming it, as ``flowrt can stats`` says it: a restart cannot mend it
    (a BLF of garbage failed every activation with "unpack requires a buffer of 72 bytes",
    naming neither the file nor the replay, and restarted the node over and over)."""
    from flowrt.analysis.can_trace import TraceError, read_trace, truncated

    cut = truncated(path)
    if cut is not None:  # replayed up to the cut, said once
        log.warning("replay %s: replaying the frames before the cut", cut)
    try:
        yield from read_trace(path)
    except TraceError as e:
        raise FatalError(f"replay {e}") from None


class CanLink:
    """One python-can bus: opened in a thread, read by a thread, written directly or by a
    sender thread, reopened with exponential backoff after it fails. Never raises.

    The owner gives callbacks, all run on the event loop: ``on_frame(msg)``,
    ``on_error(text)`` (the interface cannot open or was lost) and ``on_open(reopened)``.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        name: str,
        interface: str,
        kwargs: dict[str, Any],
        *,
        send_thread: bool,
        reopen_s: float,
        reopen_max_s: float,
        on_frame: Callable[[Any], None],
        on_error: Callable[[str], None],
        on_open: Callable[[bool], None],
        trace: TraceLog | None = None,
    ) -> None:
        self.loop = loop
        self._loop_thread = threading.get_ident()  # made in setup(), on the loop
        self.name = name
        self.interface = interface
        self.kwargs = kwargs
        self.send_thread = send_thread
        self.reopen_s = reopen_s
        self.reopen_max_s = reopen_max_s
        self.on_frame = on_frame
        self.on_error = on_error
        self.on_open = on_open
        self.trace = trace
        self.bus: Any = None
        self.gen = 0  # bumped at every close: a reader of an old bus stops
        self.opens = 0
        self.reopens = 0
        self.lost_count = 0
        self.send_errors = 0
        self.closed = False
        self.opening: asyncio.Future[Any] | None = None
        self.backoff = reopen_s
        self.reopen_at = 0.0
        self.threads: list[threading.Thread] = []
        self.txq: queue.SimpleQueue[Any] | None = None

    @property
    def where(self) -> str:
        channel = self.kwargs.get("channel")
        return f"{self.interface}:{channel}" if channel is not None else self.interface

    def open(self) -> None:
        """Open the interface in a thread (an adapter may take seconds)."""
        if self.opening is not None or self.bus is not None or self.closed:
            return
        interface, kwargs = self.interface, self.kwargs

        def open_bus() -> Any:
            import can

            return can.Bus(interface=interface, **kwargs)

        self.opening = self.loop.run_in_executor(None, open_bus)
        self.opening.add_done_callback(self._opened)

    def reopen_due(self) -> bool:
        return self.bus is None and self.opening is None and self.loop.time() >= self.reopen_at

    def _opened(self, fut: asyncio.Future[Any]) -> None:
        self.opening = None
        if fut.cancelled():
            return
        exc = fut.exception()
        if exc is not None:
            self.on_error(f"CAN interface {self.where} cannot open: {one_line(exc)}")
            self._backoff()
            return
        bus = fut.result()
        if self.closed:
            bus.shutdown()
            return
        self.bus = bus
        self.gen += 1
        gen = self.gen
        reopened = self.opens > 0
        self.reopens += reopened
        self.opens += 1
        self.backoff = self.reopen_s
        self.on_open(reopened)
        reader = threading.Thread(
            target=self._reader, args=(bus, gen), name=f"can-rx {self.name}", daemon=True
        )
        self.threads = [t for t in self.threads if t.is_alive()]
        self.threads.append(reader)
        reader.start()
        if self.send_thread:
            self.txq = queue.SimpleQueue()
            writer = threading.Thread(
                target=self._writer, args=(bus, gen, self.txq), name=f"can-tx {self.name}"
            )
            writer.daemon = True
            self.threads.append(writer)
            writer.start()

    def _backoff(self) -> None:
        self.reopen_at = self.loop.time() + self.backoff
        self.backoff = min(self.backoff * 2, self.reopen_max_s)

    def close(self) -> None:
        """Let go of the bus: its threads see the generation change and shut it down."""
        self.gen += 1
        self.bus = None
        if self.txq is not None:
            self.txq.put(None)
            self.txq = None

    async def shutdown(self) -> None:
        self.closed = True
        self.close()
        threads, self.threads = self.threads, []
        for t in threads:
            await asyncio.to_thread(t.join, 2.0)
        if self.trace is not None:
            await asyncio.to_thread(self.trace.close)

    def lost(self, gen: int, exc: BaseException) -> None:
        """The bus failed (read error, bus-off): close it and reopen after the backoff."""
        if gen != self.gen or self.bus is None:
            return
        self.lost_count += 1
        self.on_error(f"CAN interface {self.where} lost: {one_line(exc)}")
        self.close()
        self._backoff()

    def put(self, msg: Any) -> bool:
        """Send a frame now (or hand it to the sender thread); False when the send failed."""
        if self.txq is not None:
            self.txq.put(msg)
        else:
            try:
                self.bus.send(msg)
            except Exception as exc:
                self.on_loop(self._send_failed, self.gen, exc)
                return False
        if self.trace is not None:
            self.trace.put(copy_frame(msg, channel=msg.channel, timestamp=time.time(), is_rx=False))
        return True

    def on_loop(self, fn: Callable[..., Any], *args: Any) -> None:
        """``fn(*args)`` on the loop: now when called there, else handed over (the node's
        ``process`` runs in its release thread with ``timing: precise``)."""
        if threading.get_ident() == self._loop_thread:
            fn(*args)
        else:
            self.loop.call_soon_threadsafe(fn, *args)

    def _send_failed(self, gen: int, exc: BaseException) -> None:
        self.send_errors += 1
        if isinstance(exc, OSError) or "serial" in type(exc).__module__:
            self.lost(gen, exc)
        elif self.send_errors == 1 or self.send_errors % 1000 == 0:
            log.warning("%s: CAN send failed (%d): %s", self.name, self.send_errors, one_line(exc))

    def _reader(self, bus: Any, gen: int) -> None:
        call = self.loop.call_soon_threadsafe
        trace = self.trace
        try:
            while self.gen == gen:
                try:
                    msg = bus.recv(0.05)
                except Exception as exc:
                    if self.gen == gen:
                        call(self.lost, gen, exc)
                    return
                if msg is not None and self.gen == gen:
                    if trace is not None:
                        trace.put(msg)
                    call(self.on_frame, msg)
        except RuntimeError:  # the loop closed under us at shutdown
            return
        finally:
            try:
                bus.shutdown()
            except Exception as exc:  # an adapter already gone
                log.debug("CAN bus shutdown: %s", exc)

    def _writer(self, bus: Any, gen: int, q: queue.SimpleQueue[Any]) -> None:
        while True:
            msg = q.get()
            if msg is None or self.gen != gen:
                return
            try:
                bus.send(msg)
            except Exception as exc:
                try:
                    self.loop.call_soon_threadsafe(self._send_failed, gen, exc)
                except RuntimeError:
                    return
