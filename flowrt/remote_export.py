"""The sending side of a graph's ``export:`` entries: one thread encodes and publishes.

A buffer on the exported output (the edge's own policy: ``latest`` for frames, ``queue`` for
messages, counted like any edge) hands one value at a time to the sender thread, which
encodes it (:mod:`flowrt.zenoh_wire`) and puts it on the export's Zenoh publisher; when that
send is done the next value is taken. A slow network therefore drops at the edge, where it is
counted, and never slows the producer, and no network I/O runs on the event loop.
"""

from __future__ import annotations

import asyncio
import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from .edges import EMPTY, Buffer
from .frames import Frame
from .remote_host import BridgeHost
from .zenoh_wire import Header, encode_frame, own_timestamp, payload_encoding, to_wire

__all__ = ["Export", "ExportSender"]

log = logging.getLogger("flowrt.remote")


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
        value = exp.buf.take()
        if value is EMPTY:
            return
        exp.busy = True
        self._jobs.put((exp, value))

    def _sent(self, exp: Export, value: Any) -> None:
        if isinstance(value, Frame):
            value.release()
        exp.busy = False
        if exp.buf.pending():
            self.take(exp)

    def _run(self) -> None:
        mono0, wall0 = time.monotonic(), time.time()
        while True:
            job = self._jobs.get()
            if job is None:
                return
            exp, value = job
            try:
                now_wall = time.time()
                if isinstance(value, Frame):
                    meta, payload = encode_frame(value, exp.encoding, exp.quality)
                    captured = wall0 + (value.timestamp - mono0) if value.timestamp else now_wall
                    header = Header(
                        self.stream, self.zid, exp.seq, now_wall, captured, "frame", meta
                    )
                else:
                    payload = json.dumps(to_wire(value), separators=(",", ":")).encode()
                    stamp = own_timestamp(value)  # a detection: its frame's capture time
                    captured = wall0 + (stamp - mono0) if stamp is not None else now_wall
                    header = Header(self.stream, self.zid, exp.seq, now_wall, captured, "json")
                exp.seq += 1
                encoding = exp.encodings.get(header.kind)
                if encoding is None:  # one per kind: a Zenoh object made once, not per put
                    encoding = exp.encodings[header.kind] = payload_encoding(header)
                exp.publisher.put(payload, attachment=header.encode(), encoding=encoding)
            except Exception as e:
                exp.errors += 1
                log.warning("export %s: %s", exp.key, e)
            try:
                self.host.loop.call_soon_threadsafe(self._sent, exp, value)
            except RuntimeError:  # the loop is closed
                return
