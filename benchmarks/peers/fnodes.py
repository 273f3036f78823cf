"""The flowrt side of the peer benchmark: the same work as ``dora_nodes/`` (public API only).

Every timestamp is ``time.monotonic()`` (CLOCK_MONOTONIC, one clock for every process of the
machine), written into the first 8 bytes of the payload exactly as the dora nodes do, so both
systems are measured by the same arithmetic. Results go to a JSON file named by the ``out``
parameter; the orchestrator (``__main__.py``) polls for it.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from flowrt import Frame, Input, Node, Output

STAMP = np.dtype("<f8")


def _write(path: str, data: dict[str, Any]) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f)
    import os

    os.replace(tmp, path)


def _stamp_of(value: Any) -> float:
    data = value.data if isinstance(value, Frame) else value
    return float(np.asarray(data).reshape(-1)[:8].view(STAMP)[0])


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")
    out: str = ""


class LatSource(Node):
    """A timer source: a payload of ``nbytes`` with the send time in its first 8 bytes.

    8 bytes travel as a small numpy array (a message); larger payloads as a pooled frame
    (width x 3 bytes per row), written in place (flowrt's zero-copy path).
    """

    class Params(_Out):
        nbytes: int = 8

    out = Output(object)

    def setup(self) -> None:
        n = self.params.nbytes
        self.shape = (max(1, n // 3), 3) if n > 64 else None
        if self.shape is not None:
            self.ctx.new_frame(self.shape)  # allocate the pool's slots before the first tick

    def process(self) -> Any:
        if self.shape is None:
            msg = np.empty(1, STAMP)
            msg[0] = time.monotonic()
            return msg.view(np.uint8)
        frame = self.ctx.new_frame(self.shape)
        frame.data.reshape(-1)[:8].view(STAMP)[0] = time.monotonic()
        return frame


class Echo(Node):
    """Takes the payload (a zero-copy view for frames), answers (sent, one-way) seconds."""

    x = Input(object)
    back = Output(object)

    def process(self, x: Any) -> tuple[float, float]:
        now = time.monotonic()
        sent = _stamp_of(x)
        return (sent, now - sent)


class LatSink(Node):
    """Records one-way (from the echo) and round-trip latency; writes them after ``count``."""

    class Params(_Out):
        count: int = 200
        warmup: int = 20

    back = Input(object)

    def setup(self) -> None:
        self.one: list[float] = []
        self.rtt: list[float] = []
        self.seen = 0
        self.done = False

    def process(self, back: tuple[float, float]) -> None:
        now = time.monotonic()
        self.seen += 1
        if self.seen <= self.params.warmup or self.done:
            return
        sent, one_way = back
        self.one.append(one_way)
        self.rtt.append(now - sent)
        if len(self.rtt) >= self.params.count:
            self.done = True
            _write(self.params.out, {"one_way": self.one, "rtt": self.rtt})


class TimerRecorder(Node):
    """A timer node that records the instant of each activation."""

    class Params(_Out):
        count: int = 120

    def setup(self) -> None:
        self.t: list[float] = []

    def process(self) -> None:
        self.t.append(time.monotonic())
        if len(self.t) == self.params.count + 1:
            _write(self.params.out, {"t": self.t})


class FrameSource(Node):
    """640x480x3 (or any size) frames, sequence number and send time in the first 16 bytes.

    Stops publishing after ``seconds`` and records how many it sent.
    """

    class Params(_Out):
        width: int = 640
        height: int = 480
        seconds: float = 3.0

    frame = Output(Frame)

    def setup(self) -> None:
        self.shape = (self.params.height, self.params.width, 3)
        self.ctx.new_frame(self.shape)
        self.sent = 0
        self.first: float | None = None
        self.wrote = False

    def process(self) -> Frame | None:
        now = time.monotonic()
        if self.first is None:
            self.first = now
        if now - self.first >= self.params.seconds:
            if not self.wrote and self.params.out:
                self.wrote = True
                _write(self.params.out, {"sent": self.sent, "seconds": now - self.first})
            return None
        frame = self.ctx.new_frame(self.shape)
        head = frame.data.reshape(-1)[:16].view(STAMP)
        head[0] = now
        head[1] = self.sent
        self.sent += 1
        return frame


class Mean(Node):
    """The worker's work: the mean of the frame (a zero-copy view), returned with its seq."""

    frame = Input(Frame)
    result = Output(object)

    def process(self, frame: Frame) -> tuple[float, float]:
        data = frame.data
        return (float(data.reshape(-1)[8:16].view(STAMP)[0]), float(data.mean()))


class Count(Node):
    """Counts the worker's results (first/last arrival and sequence number) at teardown."""

    class Params(_Out):
        seconds: float = 3.0

    result = Input(object)

    def setup(self) -> None:
        self.n = 0
        self.first = 0.0
        self.last = 0.0
        self.seqs_in_order = True
        self.prev = -1.0
        self.first_seq = -1.0

    def process(self, result: tuple[float, float]) -> None:
        now = time.monotonic()
        if self.n == 0:
            self.first = now
            self.first_seq = result[0]
        self.n += 1
        self.last = now
        if result[0] <= self.prev:
            self.seqs_in_order = False
        self.prev = result[0]

    def teardown(self) -> None:
        _write(
            self.params.out,
            {
                "n": self.n,
                "first": self.first,
                "last": self.last,
                "ordered": self.seqs_in_order,
                "first_seq": self.first_seq,
                "last_seq": self.prev,
            },
        )


class NewFrameRelay(Node):
    """A hop that makes a new frame, as dora's relay does (``send_output`` copies the value
    into a new message): a copy of its input in ``ctx.new_frame`` (in a worker, a slot lent
    by the main process: only its descriptor goes back)."""

    input = Input(Frame)
    output = Output(Frame)

    def process(self, input: Frame) -> Frame:
        out = self.ctx.new_frame(input.shape, input.dtype, input.pixel_format)
        np.copyto(out.data, input.data)
        out.seq, out.timestamp = input.seq, input.timestamp
        return out


class PipeSink(Node):
    """End of the 10-node pipeline: end-to-end latency from the stamp in the frame."""

    class Params(_Out):
        count: int = 90
        warmup: int = 15  # the first frames queue behind start-up (both systems)

    frame = Input(Frame)

    def setup(self) -> None:
        self.lat: list[float] = []
        self.first: float | None = None
        self.seen = 0

    def process(self, frame: Frame) -> None:
        now = time.monotonic()
        if self.first is None:
            self.first = now
            _write(self.params.out + ".first", {"first": now})
        self.seen += 1
        if self.seen > self.params.warmup and len(self.lat) < self.params.count:
            self.lat.append(now - _stamp_of(frame))
            if len(self.lat) == self.params.count:
                _write(self.params.out, {"lat": self.lat, "first": self.first})
