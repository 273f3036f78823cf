"""Copies that let the event loop run: the writer's large memory copies with the GIL released.

Why: the writer's threads share the interpreter with the event loop. A thread holding the GIL
in one C call (a ``bytes`` join, a ``BytesIO`` write, an ``mmap`` slice assignment) cannot be
asked to give it up until the call returns, whatever ``sys.setswitchinterval`` says; so every
large copy of a frame's bytes on the writer thread is a stretch in which a loop thread that
wakes from ``epoll`` for a timer waits. Measured (``python benchmarks/bench_record.py
lateness``), the ``mcap`` writer's ``BytesIO`` buffers copied each frame's bytes four to five
times with the GIL held, the 4 MiB chunks in ~1-2 ms stretches: at 1936x1216 a 1 kHz timer on
the loop was late by 15.7 ms at p99 and up to 824 ms. NumPy's array copy releases the GIL for
large arrays, so:

- :func:`join` builds a message (a small head, then the pixels) with one such copy;
- :class:`PartsBuilder` is the ``mcap`` writer's record buffer (its ``RecordBuilder``
  interface) that keeps large writes by reference and joins them once, with the GIL
  released, when the writer takes the bytes (a chunk, a flush);
- :func:`copy_into` is the copy into the direct-I/O buffer.

:func:`install` puts a :class:`PartsBuilder` into an ``mcap.writer.Writer`` (its record and
chunk buffers: private attributes of mcap 1.x, checked; without them the writer keeps its own
buffers and works as before, only with the longer GIL stretches).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from mcap.data_stream import RecordBuilder

__all__ = ["BIG", "Gathered", "PartsBuilder", "copy_into", "install", "join"]

BIG = 64 << 10
"""Writes from this size on are kept by reference; smaller ones are gathered in a bytearray."""


def _u8(data: Any) -> np.ndarray:
    return np.frombuffer(data, np.uint8)


def copy_into(dst: Any, offset: int, src: Any) -> None:
    """``dst[offset:offset+len(src)] = src`` (writable buffers), the GIL released if large."""
    n = memoryview(src).nbytes
    np.copyto(np.frombuffer(dst, np.uint8, n, offset), _u8(src))


def join(head: bytes, body: Any) -> np.ndarray:
    """``head + body`` in a new uint8 array: one copy of ``body``, with the GIL released."""
    body_u8 = _u8(memoryview(body).cast("B"))
    out = np.empty(len(head) + body_u8.size, np.uint8)
    out[: len(head)] = _u8(head)
    np.copyto(out[len(head) :], body_u8)
    return out


class Gathered(list[Any]):
    """Buffers to be written one after the other, as if joined (:meth:`PartsBuilder.end` for a
    stream that takes them: :mod:`.chunking`)."""


class PartsBuilder(RecordBuilder):
    """``mcap``'s ``RecordBuilder`` keeping large writes by reference (see the module).

    A record's length is patched in place in the small-writes bytearray that holds its
    header (records do not nest in ``mcap``'s writer). A buffer written here must not change
    until :meth:`end`: the writer's messages and chunks are not reused.
    """

    def __init__(self) -> None:  # no BytesIO: the parent's buffer is not used
        self.gather = False  # end() gives the parts as they are (a stream that takes them)
        self._parts: list[Any] = []
        self._small = bytearray()
        self._count = 0
        self._record: tuple[bytearray, int, int] = (self._small, 0, 0)

    @property
    def count(self) -> int:
        return self._count

    def start_record(self, opcode: Any) -> None:
        self._record = (self._small, len(self._small), self._count)
        self.write(struct.pack("<BQ", opcode, 0))  # placeholder size

    def finish_record(self) -> None:
        buf, offset, start = self._record
        buf[offset + 1 : offset + 9] = struct.pack("<Q", self._count - start - 9)

    def write(self, data: Any) -> None:
        if type(data) is bytes and len(data) < BIG:  # most writes: a record's header fields
            self._small += data
            self._count += len(data)
            return
        view = memoryview(data).cast("B")  # (a bytearray += ndarray would broadcast)
        n = view.nbytes
        if n >= BIG:
            if self._small:
                self._parts.append(self._small)
                self._small = bytearray()
            self._parts.append(data)
        else:
            self._small += view
        self._count += n

    def take(self) -> list[Any]:
        """Everything written, as the buffers it was written in (none joined); then empty."""
        parts = self._parts
        if self._small:
            parts.append(self._small)
        self._parts, self._small, self._count = [], bytearray(), 0
        self._record = (self._small, 0, 0)
        return parts

    def end(self) -> Any:
        """Everything written, as one buffer (a bytearray, or a uint8 array when joined), or
        with :attr:`gather` as a :class:`Gathered` list of them when several."""
        count = self._count
        parts = self.take()
        if not parts:
            return b""
        if len(parts) == 1 and isinstance(parts[0], bytearray):
            return parts[0]
        if self.gather:
            return Gathered(parts)
        out = np.empty(count, np.uint8)
        offset = 0
        for p in parts:
            u8 = _u8(memoryview(p).cast("B"))
            np.copyto(out[offset : offset + u8.size], u8)
            offset += u8.size
        return out


def install(writer: Any) -> bool:
    """Give an ``mcap.writer.Writer`` :class:`PartsBuilder` buffers; False if it has none."""
    if not isinstance(getattr(writer, "_Writer__record_builder", None), RecordBuilder):
        return False
    writer._Writer__record_builder = PartsBuilder()
    chunk = getattr(writer, "_Writer__chunk_builder", None)
    if chunk is not None and isinstance(getattr(chunk, "record_writer", None), RecordBuilder):
        chunk.record_writer = PartsBuilder()
    return True
