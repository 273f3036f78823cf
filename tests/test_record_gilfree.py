"""The writer's GIL-free copies (flowrt.recording.gilfree) change nothing in the files.

Why: the buffers are swapped into ``mcap``'s writer by private attribute names; a file that
differs by one byte from what ``mcap`` writes itself would be a silent corruption. So the same
records are written both ways and the files compared byte for byte, for a chunked file with
messages small and large (kept by reference), several chunks, metadata and attachments.
"""

from __future__ import annotations

import io
import mmap
import random
import zlib
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

import flowrt
from flowrt.recording.chunking import checked, crc32_combine, install_chunks
from flowrt.recording.encoding import encode_frame
from flowrt.recording.gilfree import BIG, Gathered, PartsBuilder, copy_into, install, join

pytestmark = pytest.mark.timeout(30)


class _GatherIO(io.BytesIO):
    """A stream taking gathered buffers, as flowrt.recording.directio.DirectFile does."""

    gathers = True
    gathered = 0

    def write(self, data: Any) -> int:
        if isinstance(data, Gathered):
            self.gathered += 1
            return sum(super(_GatherIO, self).write(p) for p in data)
        return super().write(data)


def _write(gil_free: bool, crc: bool, chunk_size: int, gather: bool) -> bytes:
    out = _GatherIO() if gather else io.BytesIO()
    # (mcap's default is zstd; flowrt's raw frames are not compressed, and gathered chunks
    # are the uncompressed ones)
    comp = CompressionType.NONE if gather else CompressionType.ZSTD
    w = Writer(out, chunk_size=chunk_size, enable_crcs=crc, compression=comp)
    if gil_free:
        assert install(w)
        assert install_chunks(w) == gather
    else:
        gather = False  # mcap's own writer: the reference
    w.start(profile="flowrt", library="test")
    w.add_metadata("m", {"a": "b"})
    w.add_attachment(1, 2, "a.bin", "application/octet-stream", bytes(range(256)) * 400)
    sid = w.register_schema("s", "jsonschema", b"{}")
    small = w.register_channel("small", "json", sid)
    big = w.register_channel("big", "raw", sid)
    rng = np.random.default_rng(3)
    for i in range(40):
        w.add_message(small, i, b'{"i": %d}' % i, i, i)
        if i % 3 == 0:
            payload = rng.integers(0, 255, BIG * 3 + i, np.uint8)
            data: Any = payload if gil_free else payload.tobytes()  # as the writer gives
            if gather and i % 2:
                data = checked(payload)  # its CRC computed before (the encoder thread)
            w.add_message(big, i, data, i, i)
        if i == 20:
            w.flush()
    w.finish()
    if gather:
        assert isinstance(out, _GatherIO)
        assert out.gathered > 0  # parts were not joined
    return out.getvalue()


@pytest.mark.parametrize("gather", [False, True])
@pytest.mark.parametrize(
    ("crc", "chunk_size"),
    [(True, 4 << 20), (False, 4 << 20), (True, 1 << 16), (True, 1024)],
)
def test_files_are_byte_for_byte_mcaps_own(crc: bool, chunk_size: int, gather: bool) -> None:
    ours = _write(True, crc, chunk_size, gather)
    theirs = _write(False, crc, chunk_size, gather)
    assert ours == theirs
    msgs = list(make_reader(io.BytesIO(ours), validate_crcs=True).iter_messages())
    assert len(msgs) == 40 + 14


def test_compressed_chunks_keep_mcaps_own_code() -> None:
    w = Writer(_GatherIO(), compression=CompressionType.LZ4)
    assert install(w)
    assert not install_chunks(w)
    assert not install_chunks(Writer(io.BytesIO(), compression=CompressionType.NONE))


def test_crc32_combine_is_zlibs() -> None:
    rng = random.Random(5)
    for n1, n2 in [(0, 0), (0, 9), (31, 0), (31, 1), (50, 4097), (3, 70001)] + [
        (rng.randrange(100), rng.randrange(200000)) for _ in range(10)
    ]:
        a, b = rng.randbytes(n1), rng.randbytes(n2)
        assert crc32_combine(zlib.crc32(a), zlib.crc32(b), len(b)) == zlib.crc32(a + b)


def test_record_lengths_are_patched_across_large_parts() -> None:
    b = PartsBuilder()
    b.start_record(5)
    b.write(b"x" * 10)
    b.write(bytes(BIG))  # kept by reference, after the header's bytearray
    b.finish_record()
    out = bytes(b.end())
    assert out[0] == 5
    assert int.from_bytes(out[1:9], "little") == 10 + BIG
    assert len(out) == 9 + 10 + BIG
    assert b.count == 0
    assert bytes(b.end()) == b""


def test_join_and_copy_into_copy_exactly() -> None:
    body = np.arange(BIG * 2, dtype=np.uint16).view(np.uint8)
    assert join(b"head", body).tobytes() == b"head" + body.tobytes()
    buf = mmap.mmap(-1, 1 << 20)
    copy_into(buf, 4096, memoryview(body))
    assert buf[4096 : 4096 + body.nbytes] == body.tobytes()
    assert buf[:4096] == bytes(4096)


def test_gil_free_frame_encoding_is_the_same_message() -> None:
    frame = flowrt.Frame(
        np.arange(480 * 640 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 640, 3)
    )
    a = encode_frame(frame, 1700000000.5)
    b = encode_frame(frame, 1700000000.5, gil_free=True)
    assert a.schema == b.schema
    assert bytes(b.data) == a.data


def test_the_writer_writes_frames_in_parts_with_their_crcs(tmp_path: Any) -> None:
    """The recording writer as the recorder runs it: direct I/O, chunks in parts, the frames'
    CRCs from the encoder thread; the file reads back with every chunk CRC checked."""
    from flowrt.recording import RecordingWriter
    from flowrt.recording.directio import open_direct

    probe = open_direct(tmp_path / "probe")
    if probe is None:
        pytest.skip("no O_DIRECT on this file system (the chunks are joined there)")
    probe.close()
    rng = np.random.default_rng(7)
    images = [rng.integers(0, 255, (240 + 8 * i, 320, 3), np.uint8) for i in range(2)]
    w = RecordingWriter(tmp_path / "r.mcap", direct_io=True, crc=True, max_frames=64)
    w.open({}, [])
    assert w._crc_now  # the path measured in benchmarks/RESULTS.md, not the fallback
    for i in range(12):
        img = images[i % 2]
        assert w.submit(f"cam{i % 2}.frame", flowrt.Frame(img, seq=i), i * 0.05, i)
        assert w.submit("note", {"i": i}, i * 0.05, i)
    w.close()
    with open(tmp_path / "r.mcap", "rb") as f:
        got = list(make_reader(f, validate_crcs=True).iter_messages())
    frames = [m for _, c, m in got if c.topic.startswith("cam")]
    assert len(frames) == 12
    assert len(got) == 24
    for i, m in enumerate(frames):  # the pixels are the RawImage's last bytes
        assert bytes(m.data[-images[i % 2].nbytes :]) == images[i % 2].tobytes()
