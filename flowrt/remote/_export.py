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
from ._shm import ShmFrames
from ._streams import encoding_of
from .wire import (
    FrameHeaders,
    Header,
    MessageHeaders,
    encode_frame,
    header_ids,
    own_timestamp,
    payload_encoding,
)

__all__ = ["STOPPED", "Export", "ExportSender"]

STOPPED = "stop"  # the drop reason of a value published once the sender stopped (as the drain's)

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
    encodings: dict[str, Any] = field(default_factory=dict)  # schema -> (headers, encoding)
    topic: str = field(init=False, default="")  # node.port: the stream's name in the book

    def __post_init__(self) -> None:
        self.topic = f"{self.node}.{self.port}"


class ExportSender:
    """The thread that sends every export's values, under the session's stream and id.

    ``shm``: the session enables Zenoh's shared memory; raw frames are then put from it."""

    def __init__(self, host: BridgeHost, stream: str, zid: str, shm: bool = False) -> None:
        self.host = host
        self.stream = stream
        self.zid = zid
        self._mono0, self._wall0 = time.monotonic(), time.time()  # capture time to wall clock
        self._book = StreamBook(epoch_offset=self._wall0 - self._mono0)  # the recorder's
        # The stream's start in every header (whole seconds, floored: the stream looks older
        # than it is, never younger): an importer that first hears it at sequence number N
        # counts the N values before as lost only if the stream began after it listened.
        self._started = int(self._wall0)
        self._ids = header_ids(stream, zid)
        self._frames = FrameHeaders(stream, zid, self._started)  # raw frames' headers
        self.shm = ShmFrames() if shm else None  # raw frames' shared buffers (sender thread)
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
        """On the loop: hand the next value to the sender when the previous one is sent.
        Once the sender has stopped (the runtime closes the bridge before its sources stop),
        what is published is never sent: counted as dropped (``stop``), not left to be
        cleared with the buffer (which the drain takes for a host's own: no loss)."""
        if self._thread is None:
            exp.buf.discard(STOPPED)
            return
        if exp.busy:
            return
        while not isinstance(value := exp.buf.take(), Frame):  # messages: sent from here
            if value is EMPTY:
                return
            try:
                self._send_message(exp, value)
            except Exception as e:
                self._failed(exp, e)
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
            if isinstance(value, Frame):
                self._send_frame(exp, value)
            else:
                self._send_message(exp, value)
        except Exception as e:
            self._failed(exp, e)

    @staticmethod
    def _failed(exp: Export, e: Exception) -> None:
        """A value not sent: counted and logged, never raised."""
        exp.errors += 1
        log.warning("export %s: %s", exp.key, e)

    def _send_message(self, exp: Export, value: Any) -> None:
        """A message, by the recording's description of its stream, byte for byte.

        Kept short: at 20 Hz this path runs cold (the caches evicted between messages, ~10x
        the warm cost per call), and every call between the source's publication and the
        ``put`` is latency (its encoding took 0.12 ms cold, Zenoh's whole hop 0.3 ms)."""
        now_wall = time.time()
        topic = exp.topic
        msg = self._book.encode_flat(topic, value)  # a flat mapping: one walk (never a set)
        if msg is None:
            # a set: its index, as the recording's TOPIC channel (members not sent)
            shown = split_set(topic, value)[0] if type(value) is dict and is_set(value) else value
            msg = self._book.encode(topic, shown)
        stamp = own_timestamp(value)  # a detection: its frame's capture time
        captured = self._wall0 + (stamp - self._mono0) if stamp is not None else now_wall
        zkey = msg.schema.name
        sent = exp.encodings.get(zkey)
        if sent is None:  # one per schema: the Zenoh encoding and header made once, not per put
            json_ = msg.schema.message_encoding == "json"
            number = sum(k != "frame" for k in exp.encodings) + 1  # the schema's, in the header
            sent = exp.encodings[zkey] = (
                MessageHeaders(
                    self._ids,
                    "json" if json_ else "protobuf",
                    self._started,
                    number if number <= 255 else 0,
                ),
                encoding_of(msg.schema.message_encoding, zkey),
            )
        header, encoding = sent
        attachment = header(exp.seq, now_wall, captured)
        exp.seq += 1
        exp.publisher.put(msg.data, attachment=attachment, encoding=encoding)

    def _send_frame(self, exp: Export, value: Frame) -> None:
        now_wall = time.time()
        captured = self._wall0 + (value.timestamp - self._mono0) if value.timestamp else now_wall
        encoding = exp.encodings.get("frame")
        if encoding is None:  # a Zenoh object made once, not per put
            encoding = exp.encodings["frame"] = payload_encoding(exp.encoding)
        if exp.encoding == "raw":  # the header from the stream's template, the pixels last:
            attachment = self._frames(value, exp.seq, now_wall, captured)  # what follows the
            exp.seq += 1  # copy runs cold
            payload = value.data.tobytes()  # Zenoh takes bytes (or its shared buffer)
            if self.shm is not None:
                payload = self.shm.payload(payload)
        else:
            meta, payload = encode_frame(value, exp.encoding, exp.quality)
            header = Header(
                self.stream, self.zid, exp.seq, now_wall, captured, "frame", meta, self._started
            )
            exp.seq += 1
            attachment = header.encode()
        exp.publisher.put(payload, attachment=attachment, encoding=encoding)
