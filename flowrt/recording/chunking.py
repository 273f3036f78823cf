"""An MCAP chunk finished without joining its bytes: its parts go to the disk as they are.

Why: ``mcap``'s writer finishes a chunk by joining its records into one buffer (for the CRC and
the chunk record), then joins the chunk record with its header again before the stream's
``write``: at 1936x1216 two full copies of every 7 MB frame on the writer's disk thread, on top
of the copy into the direct-I/O buffer that cannot be avoided. Profiled in the writer process
(``py-spy`` on ``benchmarks/bench_record.py throughput``), those two joins took about a fifth
of the disk thread and the chunk CRC another fifth, while the disk was idle half of the time.

Here, for uncompressed chunks written to a stream that takes :class:`~.gilfree.Gathered`
buffers (the direct-I/O file, :mod:`.directio`):

- the chunk's CRC is chained over its parts (``zlib.crc32(part, crc)``), and a part that
  carries its own CRC (:class:`Checked`: computed by the encoder thread right after it copied
  the pixels, while they are in the cache, and in parallel with the disk thread) is combined
  in (:func:`crc32_combine`) instead of read again; ISA-L's CRC-32 (``isal``) where installed,
  five times zlib's speed on the dev VM, the same value;
- the chunk record keeps its parts by reference, and the record builder hands them to the
  stream as a :class:`~.gilfree.Gathered` list, which the stream copies one by one into its buffer.

The records written are the ones ``mcap`` writes, in the same order, byte for byte (tested
against ``mcap``'s own writer: tests/test_record_gilfree.py). :func:`install_chunks` replaces
the writer's private ``__finalize_chunk`` (``mcap`` 1.x, checked); where an attribute is
missing, or the chunks are compressed, the writer keeps its own code.
"""

from __future__ import annotations

import zlib
from functools import lru_cache
from typing import Any

import numpy as np
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, IndexType

from .gilfree import BIG, PartsBuilder

try:  # ISA-L's CRC-32: the same value, 0.2 ms for a 7 MB frame against zlib's 1.0 (GIL released)
    from isal.isal_zlib import crc32 as _crc32
except ImportError:  # a dependency, but the recording works without it
    _crc32 = zlib.crc32

__all__ = ["Checked", "checked", "checked_if_large", "crc32_combine", "install_chunks"]

_CHUNK = 0x06  # mcap's Opcode.CHUNK
_PRIVATE = (
    "chunk_builder",
    "statistics",
    "compression",
    "enable_crcs",
    "enable_data_crcs",
    "record_builder",
    "stream",
    "index_types",
    "chunk_indices",
)


class Checked(np.ndarray):
    """A uint8 buffer that carries the CRC-32 of its bytes (``crc``), computed once."""

    crc: int


def checked(data: Any) -> Checked:
    """``data`` (a uint8 array) with its CRC-32, computed now (zlib releases the GIL)."""
    out: Checked = data.view(Checked)
    out.crc = _crc32(memoryview(data))
    return out


def checked_if_large(data: Any) -> Any:
    """A large message's bytes with their CRC (the writer's encoder thread: the bytes are in
    the cache, and the disk thread has the rest of the chunk to do); others as they are."""
    if isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.nbytes >= BIG:
        return checked(data)
    return data


def _times(mat: tuple[int, ...], vec: int) -> int:
    """A 32x32 GF(2) matrix (its columns as integers) times a vector."""
    out, i = 0, 0
    while vec:
        if vec & 1:
            out ^= mat[i]
        vec >>= 1
        i += 1
    return out


def _square(mat: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(_times(mat, mat[n]) for n in range(32))


def _product(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    """The matrix of ``a`` applied after ``b``."""
    return tuple(_times(a, b[n]) for n in range(32))


@lru_cache(maxsize=64)
def _shift(length: int) -> tuple[int, ...]:
    """The operator that appends ``length`` zero bytes to a CRC-32's register.

    A few milliseconds in Python (squarings of zlib's ``crc32_combine``), so it is kept per
    length: a camera's messages all have one length, and applying it is 32 steps.
    """
    odd = [0xEDB88320] + [1 << n for n in range(31)]  # one zero bit
    even = _square(tuple(odd))  # two
    op = _square(even)  # four
    result: tuple[int, ...] = tuple(1 << n for n in range(32))  # the identity
    bits = length  # a byte is 8 zero bits: the operator for 8 zero bits is op squared once
    op = _square(op)
    while bits:
        if bits & 1:
            result = _product(op, result)
        bits >>= 1
        if bits:
            op = _square(op)
    return result


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """The CRC-32 of ``A + B`` from ``crc32(A)``, ``crc32(B)`` and ``len(B)`` (zlib's)."""
    if len2 == 0:
        return crc1
    return _times(_shift(len2), crc1) ^ crc2


def _crc(parts: list[Any]) -> int:
    crc = 0
    for p in parts:
        own = getattr(p, "crc", None)
        if isinstance(p, Checked) and own is not None:
            crc = crc32_combine(crc, own, p.nbytes)
        else:
            crc = _crc32(p, crc)
    return crc


def _nbytes(p: Any) -> int:
    return memoryview(p).nbytes


def install_chunks(writer: Any) -> bool:
    """Finish ``writer``'s chunks here (see the module); False if it keeps its own code.

    Call it after :func:`.gilfree.install` (its buffers are what this takes parts from).
    """
    got = {name: getattr(writer, f"_Writer__{name}", None) for name in _PRIVATE}
    if any(v is None for v in got.values()) or not callable(
        getattr(writer, "_Writer__flush", None)
    ):
        return False
    if got["compression"] != CompressionType.NONE or got["enable_data_crcs"]:
        return False
    if not getattr(got["stream"], "gathers", False):
        return False
    records, chunks = got["record_builder"], got["chunk_builder"]
    if not isinstance(records, PartsBuilder) or not isinstance(
        getattr(chunks, "record_writer", None), PartsBuilder
    ):
        return False
    records.gather = True
    writer._Writer__finalize_chunk = lambda: _finish_chunk(writer)
    return True


def _finish_chunk(w: Any) -> None:
    """``mcap.writer.Writer.__finalize_chunk`` for uncompressed chunks, without joining."""
    builder = w._Writer__chunk_builder
    if builder.num_messages == 0:
        return
    w._Writer__statistics.chunk_count += 1
    parts = builder.record_writer.take()
    size = sum(_nbytes(p) for p in parts)
    crc = _crc(parts) if w._Writer__enable_crcs else 0
    w._Writer__flush()
    stream, records = w._Writer__stream, w._Writer__record_builder
    start = stream.tell()
    records.start_record(_CHUNK)  # the fields of mcap's Chunk.write, its data by reference
    records.write8(builder.message_start_time)
    records.write8(builder.message_end_time)
    records.write8(size)
    records.write4(crc)
    records.write_prefixed_string("")
    records.write8(size)
    for p in parts:
        records.write(p)
    records.finish_record()
    index = ChunkIndex(
        message_start_time=builder.message_start_time,
        message_end_time=builder.message_end_time,
        chunk_start_offset=start,
        chunk_length=records.count,
        message_index_offsets={},
        message_index_length=0,
        compression="",
        compressed_size=size,
        uncompressed_size=size,
    )
    w._Writer__flush()
    index_start = stream.tell()
    if w._Writer__index_types & IndexType.MESSAGE:
        for cid, message_index in builder.message_indices.items():
            index.message_index_offsets[cid] = index_start + records.count
            message_index.write(records)
    index.message_index_length = records.count
    w._Writer__flush()
    w._Writer__chunk_indices.append(index)
    builder.reset()
