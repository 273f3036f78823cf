"""Raw frames put from Zenoh's shared memory (flowrt/remote/_shm.py): the pool's rules, and
frames intact between two real sessions whether each side enables shared memory or not (a
subscriber without it, as on another machine, gets the bytes through the socket)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from flowrt import GraphBuilder, Runtime
from flowrt.remote._shm import MIN_BYTES, POOL_FRAMES, ShmFrames
from tests.test_remote import Pattern, free_port, intact_frames

pytestmark = pytest.mark.timeout(90)

MIB = 1 << 20


def test_a_small_payload_is_put_as_bytes_and_makes_no_pool() -> None:
    shm = ShmFrames()
    data = bytes(MIN_BYTES - 1)
    assert shm.payload(data) is data
    assert shm.provider is None
    assert shm.fallbacks == 0


def test_a_payload_is_copied_whole_into_a_shared_buffer() -> None:
    shm = ShmFrames()
    data = np.arange(3 * MIB, dtype=np.uint8).tobytes()
    buf = shm.payload(data)
    assert buf is not data
    assert bytes(buf) == data
    assert shm.size >= POOL_FRAMES * len(data) + (1 << 20)


def test_a_larger_payload_makes_a_larger_pool_and_old_buffers_stay_valid() -> None:
    shm = ShmFrames()
    small = shm.payload(b"\x01" * MIN_BYTES)
    first = shm.size
    big = bytes(range(256)) * (first // 256 // POOL_FRAMES + 4096)  # more than the pool holds
    buf = shm.payload(big)
    assert shm.size > first
    assert shm.size >= POOL_FRAMES * len(big)
    assert bytes(buf) == big
    assert bytes(small) == b"\x01" * MIN_BYTES  # its pool is dropped, not its buffers


def test_when_every_buffer_is_still_read_the_payload_goes_as_bytes_counted() -> None:
    shm = ShmFrames()
    data = bytes(5 * MIB)  # the pool: 21 MiB, four of these
    held = [shm.payload(data) for _ in range(POOL_FRAMES)]  # a reader holds each
    assert all(b is not data for b in held)
    assert shm.payload(data) is data
    assert shm.fallbacks == 1
    held.clear()  # read and let go: reclaimed by the next allocation
    assert shm.payload(data) is not data
    assert shm.fallbacks == 1


def test_without_room_in_dev_shm_frames_go_as_bytes(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A tmpfs written past its end kills the writer (SIGBUS): no pool unless it fits twice."""
    from flowrt.remote import _shm

    monkeypatch.setattr(_shm, "shm_free", lambda: 8 * MIB)
    shm = ShmFrames()
    data = bytes(2 * MIB)  # a 9 MiB pool
    assert shm.payload(data) is data
    assert shm.payload(data) is data  # not tried again
    assert shm.failed
    assert shm.provider is None
    assert shm.fallbacks == 1
    assert "/dev/shm has 8 MiB free, the pool takes 9" in caplog.text


SHAPE = (192, 256, 3)  # 147 KiB: above MIN_BYTES


def _shm(enabled: bool) -> dict[str, Any]:
    return {"transport/shared_memory/enabled": enabled}


@pytest.mark.realtime  # two Zenoh sessions exchanging frames for a second
@pytest.mark.parametrize(
    ("exporter_shm", "importer_shm"),
    [(True, True), (True, False), (False, True)],
    ids=["both", "importer-without", "exporter-without"],
)
async def test_large_frames_arrive_intact_with_or_without_shared_memory(
    exporter_shm: bool, importer_shm: bool
) -> None:
    port = free_port()
    ex = GraphBuilder("ex").add("src", Pattern, params={"shape": SHAPE}, trigger={"timer": "20ms"})
    ex.zenoh(listen=[f"tcp/127.0.0.1:{port}"], config=_shm(exporter_shm))
    ex.export("p/frame", "src.frame")
    im = GraphBuilder("im").zenoh(
        listen=[], connect=[f"tcp/127.0.0.1:{port}"], config=_shm(importer_shm)
    )
    im.import_("rx", {"key": "p/frame", "frames": True, "period": "20ms"})
    im.add("sink", "sink", inputs={"input": "rx.output"})
    async with Runtime(ex.build()) as tx, Runtime(im.build()) as rt:
        sub = rt.subscribe("rx.output", size=1024)
        seen = 0
        async for _ in intact_frames(sub, 30, SHAPE):
            seen += 1
        assert seen >= 30
        shm = tx._bridge._sender.shm
        if exporter_shm:
            assert shm is not None
            assert shm.provider is not None
            assert shm.fallbacks == 0
        else:
            assert shm is None
