"""The recorder's side of a writer process (flowrt.recording.writer.channel), without one.

Why: ``max_frames`` bounds the frames whose shared-memory slot the writer process may still
read, as the thread writer's does; frames already copied wait for the disk in the process
(up to its ``max_bytes``) without holding the count, so a disk that stalls for a moment holds
memory rather than refusing frames. The process's answers are fed by hand here.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

import flowrt
from flowrt.recording import ProcessRecordingWriter
from flowrt.recording.writer.wire import ACKS

pytestmark = pytest.mark.timeout(30)


async def test_a_frame_leaves_the_bound_when_its_slot_is_let_go_of(tmp_path: Path) -> None:
    w = ProcessRecordingWriter(tmp_path / "x.mcap", loop=asyncio.get_running_loop(), max_frames=2)
    frames = [flowrt.Frame(np.full((4, 4, 3), i, np.uint8), seq=i) for i in range(6)]
    assert w.submit("cam", frames[0], 0.0, 0)
    assert w.submit("cam", frames[1], 0.1, 1)
    assert not w.submit("cam", frames[2], 0.2, 2)  # two slots held: refused, counted
    assert w.encoding_frame()
    w._handle((ACKS, [0, 1], [], None))  # both copied by the process, neither written yet
    assert list(w.done) == frames[:2]  # their links go back
    assert not w.encoding_frame()
    assert w.submit("cam", frames[3], 0.3, 3)  # the disk's queue holds them, not the bound
    assert w.submit("cam", frames[4], 0.4, 4)
    assert not w.submit("cam", frames[5], 0.5, 5)
    # (ids number the messages sent: frames[3] and [4] are 2 and 3)
    w._handle((ACKS, [2], [(0, 48, 0), (1, 48, 0), (2, 48, 0)], None))
    s = w.streams["cam"]
    assert (s.received, s.written, s.lost_behind, s.bytes) == (6, 3, 2, 144)
    assert list(w.done) == [*frames[:2], frames[3]]


def test_a_stream_whose_values_change_type_has_a_channel_per_type(tmp_path: Path) -> None:
    """An ``Output(object)`` giving ints and text: the text was written on the channel of
    the first value's schema (``"value": {"type": "integer"}``), refused by a validator."""
    import json

    import jsonschema
    from mcap.reader import make_reader

    from flowrt.recording.writer.threads import RecordingWriter

    path = tmp_path / "m.mcap"
    w = RecordingWriter(path, epoch_offset=1.7e9)
    w.open({})
    w.declare("src.out", source="src.out")
    values: list[object] = [1, 2, "three", 4, "five", {"six": 6}]
    for i, v in enumerate(values):
        assert w.submit("src.out", v, 0.01 * i, i)
    w.close()
    assert w.error is None
    assert not w.notes
    schemas: dict[str, int] = {}
    with path.open("rb") as f:
        for schema, _channel, msg in make_reader(f).iter_messages(topics=["src.out"]):
            jsonschema.validate(json.loads(msg.data), json.loads(schema.data))
            schemas[schema.name] = schemas.get(schema.name, 0) + 1
    assert schemas == {"builtins.int": 3, "builtins.str": 2, "builtins.dict": 1}
