"""The writer's GIL-free copies (flowrt.recording.gilfree) change nothing in the files.

Why: the buffers are swapped into ``mcap``'s writer by private attribute names; a file that
differs by one byte from what ``mcap`` writes itself would be a silent corruption. So the same
records are written both ways and the files compared byte for byte, for a chunked file with
messages small and large (kept by reference), several chunks, metadata and attachments.
"""

from __future__ import annotations

import io
import mmap

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

import flowrt
from flowrt.recording.encoding import encode_frame
from flowrt.recording.gilfree import BIG, PartsBuilder, copy_into, install, join

pytestmark = pytest.mark.timeout(30)


def _write(gil_free: bool, crc: bool, chunk_size: int) -> bytes:
    out = io.BytesIO()
    w = Writer(out, chunk_size=chunk_size, enable_crcs=crc)
    if gil_free:
        assert install(w)
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
            data = payload if gil_free else payload.tobytes()  # buffers, as the writer gives
            w.add_message(big, i, data, i, i)
        if i == 20:
            w.flush()
    w.finish()
    return out.getvalue()


@pytest.mark.parametrize(
    ("crc", "chunk_size"),
    [(True, 4 << 20), (False, 4 << 20), (True, 1 << 16), (True, 1024)],
)
def test_files_are_byte_for_byte_mcaps_own(crc: bool, chunk_size: int) -> None:
    ours, theirs = _write(True, crc, chunk_size), _write(False, crc, chunk_size)
    assert ours == theirs
    msgs = list(make_reader(io.BytesIO(ours)).iter_messages())
    assert len(msgs) == 40 + 14


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
