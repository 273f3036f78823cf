"""The sending side of a graph's ``export:`` entries: one thread encodes and publishes.

A buffer on the exported output (the edge's own policy: ``latest`` for frames, ``queue`` for
messages, counted like any edge) hands one value at a time to the sender thread, which
encodes it (frames: :mod:`flowrt.remote.wire`; messages: by the stream's description, as
the recorder does, :mod:`flowrt.remote._streams`) and puts it on the export's Zenoh publisher;
when that send is done the next value is taken. A slow network therefore drops at the edge,
where it is counted, and never slows the producer, and no network I/O runs on the event loop.

Messages (anything but a frame) are encoded and put on the loop itself, as they are
published: a ``put`` only queues the bytes for Zenoh's own transmission threads (with the
publisher's ``drop`` congestion control it never waits longer than Zenoh's drop wait), and a
small message's JSON costs microseconds on a loop that is awake anyway, whereas the hand-over
to the sender thread costs a thread wake-up per message (~0.1 ms, and a wait for a CPU under
load: the largest part of an 8-byte message's latency over flowrt). Frames (a copy of
megabytes, JPEG encoding) stay on the thread.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from ..edges import EMPTY, Buffer
from ..frames import Frame
from ..recording.streams import StreamBook, is_set, split_set
from ._host import BridgeHost
from ._streams import encoding_of
from .wire import Header, encode_frame, frame_meta, own_timestamp, payload_encoding

__all__ = ["Export", "ExportSender"]

log = logging.getLogger("flowrt.remote._bridge")


@dataclass
class Export:
    """One exported output: its key, how it is encoded, its buffer and publisher.

    ``busy``: a value of this export is with the sender (at most one at a time)."""

    key: str
    node: str
    port: str
    encoding: str
    quality: int
    buf: Buffer
    publisher: Any = None
    seq: int = 0
    busy: bool = False
    errors: int = 0
    encodings: dict[str, Any] = field(default_factory=dict)  # header kind -> Zenoh encoding


class ExportSender:
    """The thread that sends every export's values, under the session's stream and id."""

    def __init__(self, host: BridgeHost, stream: str, zid: str) -> None:
        self.host = host
        self.stream = stream
        self.zid = zid
        self._clock0 = (time.monotonic(), time.time())  # frames' capture time to wall clock
        mono0, wall0 = self._clock0
        self._book = StreamBook(epoch_offset=wall0 - mono0)  # the recorder's descriptions; ours
        self._jobs: queue.SimpleQueue[tuple[Export, Any] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="flowrt-zenoh-send", daemon=True)
        self._thread.start()

    async def stop(self) -> None:
        """Let the thread finish its current send and end (waited for at most 2 s)."""
        if self._thread is not None:
            self._jobs.put(None)
            await asyncio.to_thread(self._thread.join, 2.0)
            self._thread = None

    def take(self, exp: Export) -> None:
        """On the loop: hand the next value to the sender when the previous one is sent."""
        if exp.busy or self._thread is None:
            return
        while not isinstance(value := exp.buf.take(), Frame):  # messages: sent from here
            if value is EMPTY:
                return
            self._send(exp, value)
        exp.busy = True
        self._jobs.put((exp, value))

    def _sent(self, exp: Export, value: Any) -> None:
        if isinstance(value, Frame):
            value.release()
        exp.busy = False
        if exp.buf.pending():
            self.take(exp)

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            exp, value = job
            self._send(exp, value)
            try:
                self.host.loop.call_soon_threadsafe(self._sent, exp, value)
            except RuntimeError:  # the loop is closed
                return

    def _send(self, exp: Export, value: Any) -> None:
        """Encode and put one value (on the sender thread for frames, the loop otherwise);
        a failure is counted and logged, never raised."""
        try:
            now_wall = time.time()
            raw = isinstance(value, Frame) and exp.encoding == "raw"
            if isinstance(value, Frame):
                # Raw pixels are copied last (below): whatever follows that copy runs cold.
                if raw:
                    meta, payload = frame_meta(value, "raw"), b""
                else:
                    meta, payload = encode_frame(value, exp.encoding, exp.quality)
                mono0, wall0 = self._clock0
                captured = wall0 + (value.timestamp - mono0) if value.timestamp else now_wall
                header = Header(self.stream, self.zid, exp.seq, now_wall, captured, "frame", meta)
                zkey = "frame"
            else:
                topic = f"{exp.node}.{exp.port}"
                # a set: its index, as the recording's TOPIC channel (members not sent)
                shown = split_set(topic, value)[0] if is_set(value) else value
                msg = self._book.encode(topic, shown)  # the recording's message, byte for byte
                payload = msg.data
                stamp = own_timestamp(value)  # a detection: its frame's capture time
                mono0, wall0 = self._clock0
                captured = wall0 + (stamp - mono0) if stamp is not None else now_wall
                kind = "json" if msg.schema.message_encoding == "json" else "protobuf"
                header = Header(self.stream, self.zid, exp.seq, now_wall, captured, kind)
                zkey = msg.schema.name
            exp.seq += 1
            encoding = exp.encodings.get(zkey)
            if encoding is None:  # one per schema: a Zenoh object made once, not per put
                encoding = exp.encodings[zkey] = (
                    payload_encoding(header)
                    if zkey == "frame"
                    else encoding_of(msg.schema.message_encoding, zkey)
                )
            attachment = header.encode()
            if raw:
                payload = value.data.tobytes()  # Zenoh takes bytes: the one copy on this side
            exp.publisher.put(payload, attachment=attachment, encoding=encoding)
        except Exception as e:
            exp.errors += 1
            log.warning("export %s: %s", exp.key, e)
