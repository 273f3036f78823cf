"""Shared-memory frame pool: link counting, growth and drops, pickling, cleanup, orphans."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from flowrt.frames import SHM_DIR, Frame, FramePool, FrameStore, StaleFrameError

REPO = Path(__file__).resolve().parents[1]


def own_segments() -> list[str]:
    """Segments created by this test process (other processes' runtimes may share /dev/shm)."""
    prefix = f"flowrt_{os.getpid()}_"
    return sorted(n for n in os.listdir(SHM_DIR) if n.startswith(prefix))


@pytest.fixture(autouse=True)
def no_leaked_segments() -> Iterator[None]:
    before = own_segments()
    yield
    assert own_segments() == before


@pytest.fixture
def store() -> Iterator[FrameStore]:
    s = FrameStore()
    yield s
    s.close()


def fill(pool: FramePool, seq: int, shape: tuple[int, ...] = (4, 6, 3)) -> Frame:
    frame = pool.reserve(shape, np.uint8, source="cam", seq=seq, timestamp=float(seq))
    assert frame is not None
    frame.data[:] = seq % 256
    return frame


def test_heap_frame_keeps_constructor_and_pickles_pixels() -> None:
    data = np.arange(24, dtype=np.uint16).reshape(2, 4, 3)
    f = Frame(data, source="host", seq=3, timestamp=1.5, pixel_format="RGB")
    assert (f.shape, f.dtype.str, f.nbytes, f.refs, f.shared) == ((2, 4, 3), "<u2", 48, 1, False)
    g = pickle.loads(pickle.dumps(f))
    assert (g.source, g.seq, g.timestamp, g.pixel_format) == ("host", 3, 1.5, "RGB")
    np.testing.assert_array_equal(g.data, data)
    assert not np.shares_memory(g.data, data)


def test_reserve_gives_writable_frame_with_one_link(store: FrameStore) -> None:
    pool = store.pool("cam")
    f = fill(pool, 1)
    assert f.shared
    assert f.refs == 1
    assert f.data.flags.writeable
    assert (f.source, f.seq, f.timestamp) == ("cam", 1, 1.0)
    assert pool.stats().slots_in_use == 1
    f.release()
    assert pool.stats().slots_in_use == 0
    with pytest.raises(RuntimeError, match="released more often"):
        f.release()


def test_slot_held_by_slow_reader_is_not_overwritten(store: FrameStore) -> None:
    pool = store.pool("cam", max_slots=4, initial_slots=2)
    held = fill(pool, 1)
    held.acquire()  # a slow reader
    held.release()  # the producer's link
    for seq in range(2, 40):  # the producer goes on; each frame is read and released at once
        f = fill(pool, seq)
        f.release()
        assert not np.shares_memory(f.data, held.data)
    assert (held.data == 1).all()
    assert pool.stats().slots == 2  # one slot held, the other recycled over and over
    held.release()
    assert pool.stats().slots_in_use == 0


def test_released_slot_is_recycled_most_recent_first(store: FrameStore) -> None:
    pool = store.pool("cam", initial_slots=3)
    a = fill(pool, 1)
    addr = a.data.ctypes.data
    a.release()
    b = fill(pool, 2)
    assert b.data.ctypes.data == addr  # hot slot reused; no growth
    b.release()
    assert pool.stats().grown == 0


def test_pool_grows_within_bound_then_drops_and_counts(store: FrameStore) -> None:
    pool = store.pool("cam", max_slots=3, initial_slots=2)
    held = [fill(pool, i) for i in range(3)]
    s = pool.stats()
    assert (s.slots, s.slots_in_use, s.grown, s.dropped) == (3, 3, 1, 0)
    assert pool.reserve((4, 6, 3), np.uint8) is None  # the producer does not wait
    assert pool.reserve((4, 6, 3), np.uint8) is None
    assert pool.stats().dropped == 2
    held[1].release()
    f = fill(pool, 9)
    assert f.data.ctypes.data == held[1].data.ctypes.data
    assert [int(h.data[0, 0, 0]) for h in (held[0], held[2])] == [0, 2]
    for h in (held[0], held[2], f):
        h.release()
    assert pool.stats() == pool.stats().__class__(
        owner="cam",
        slots=3,
        slots_in_use=0,
        max_slots=3,
        reserved=4,
        grown=1,
        dropped=2,
        reallocated=0,
        bytes=pool.stats().bytes,
    )


def test_larger_frame_reallocates_a_free_slot(store: FrameStore) -> None:
    pool = store.pool("cam", max_slots=1, initial_slots=1)
    small = fill(pool, 1)
    old = pool.segment_names()
    small.release()
    big = fill(pool, 2, shape=(480, 640, 3))
    assert pool.stats().reallocated == 1
    assert pool.segment_names() != old
    assert not os.path.exists(os.path.join(SHM_DIR, old[0]))
    big.release()


def test_pooled_frame_pickles_to_a_descriptor_of_the_same_memory(
    store: FrameStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    import weakref

    import flowrt.frames

    pool = store.pool("cam")
    f = pool.reserve((1080, 1920, 3), np.uint8, source="cam", seq=5, pixel_format="BGR")
    assert f is not None
    f.data[:] = 7
    blob = pickle.dumps(f)
    assert len(blob) < 1000  # a 6 MB frame: only the descriptor travels
    # Back in the owner process the descriptor is the frame itself (a worker's result).
    assert pickle.loads(blob) is f
    # As a worker sees it (it owns no slot): a read-only view of the same pages.
    owner = flowrt.frames.frame.occupants
    monkeypatch.setattr(flowrt.frames.frame, "occupants", weakref.WeakValueDictionary())
    g = pickle.loads(blob)
    assert (g.source, g.seq, g.shape, g.pixel_format, g.shared) == (
        "cam",
        5,
        (1080, 1920, 3),
        "BGR",
        False,
    )
    assert not g.data.flags.writeable  # readers cannot scribble on the producer's frame
    f.data[100, 200] = (1, 2, 3)  # written after the descriptor was made...
    assert tuple(g.data[100, 200]) == (1, 2, 3)  # ...and seen: the same pages, not a copy
    # Passed on unchanged, an attached frame goes back as its descriptor: in the owner, f.
    back = pickle.dumps(g)
    assert len(back) < 1000
    monkeypatch.setattr(flowrt.frames.frame, "occupants", owner)
    assert pickle.loads(back) is f
    # New pixels travel as pixels (a worker returning an image it made).
    h = pickle.loads(pickle.dumps(Frame(g.data + 1, source="cam", seq=5)))
    assert not h.shared
    assert int(h.data[0, 0, 0]) == 8
    # Changed metadata on the same pixels: a copy, the shared original is left alone.
    g.seq = 6
    k = pickle.loads(pickle.dumps(g))
    assert k is not f
    assert (k.seq, f.seq, k.shared) == (6, 5, False)
    del g, h, k
    f.release()


def test_descriptor_of_a_recycled_slot_is_refused(store: FrameStore) -> None:
    pool = store.pool("cam", max_slots=1, initial_slots=1)
    f = fill(pool, 1)
    blob = pickle.dumps(f)
    f.release()  # the sender broke the rule: released before the reader attached
    g = fill(pool, 2)  # same slot, next generation
    with pytest.raises(StaleFrameError, match="generation"):
        pickle.loads(blob)
    g.release()


def test_store_close_unlinks_everything_and_is_idempotent() -> None:
    s = FrameStore()
    try:
        held = fill(s.pool("a"), 1)
        fill(s.pool("b", max_slots=2), 1).release()
        assert len(own_segments()) == 6  # 4 initial slots, and 2 (the bound)
        assert [st.owner for st in s.stats()] == ["a", "b"]
    finally:
        s.close()
    assert own_segments() == []
    assert held.data[0, 0, 0] == 1  # a frame still held keeps its mapping, not its name
    s.close()
    with pytest.raises(RuntimeError):
        s.pool("c")


def test_reclaim_orphans_removes_dead_and_reused_pids_only(store: FrameStore) -> None:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    dead = os.path.join(SHM_DIR, f"flowrt_{proc.pid}_0_cam_0")
    reused = os.path.join(SHM_DIR, "flowrt_1_0_cam_0")  # pid 1 is alive, but started at boot
    live = os.path.join(SHM_DIR, "flowrt_1_0_cam_1")
    for path in (dead, reused, live):
        Path(path).write_bytes(b"x")
    os.utime(reused, (1.0, 1.0))  # created long before pid 1 started: its creator is gone
    fill(store.pool("mine"), 1).release()
    try:
        FrameStore.reclaim_orphans()  # (a concurrent runtime's start may reclaim them too)
        assert not os.path.exists(dead)
        assert not os.path.exists(reused)
        assert os.path.exists(live)
        assert len(own_segments()) == 4  # never our own
    finally:
        for path in (dead, reused, live):
            if os.path.exists(path):
                os.unlink(path)


SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, time
    import numpy as np
    from flowrt.frames import FrameStore
    store = FrameStore()
    f = store.pool("cam").reserve((8, 8, 3), np.uint8)
    print(len([n for n in os.listdir("/dev/shm") if n.startswith(store.prefix)]), flush=True)
    mode = sys.argv[1]
    if mode == "exception":
        raise RuntimeError("boom")
    if mode == "sigint":
        os.kill(os.getpid(), signal.SIGINT)
    if mode == "sigkill":
        time.sleep(30)
    """
)


@pytest.mark.parametrize("mode", ["normal", "exception", "sigint", "sigkill"])
def test_no_segment_outlives_the_process(mode: str) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, mode],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        cwd=REPO,
        text=True,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "4"
    if mode == "sigkill":
        proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    prefix = f"flowrt_{proc.pid}_"
    left = [n for n in os.listdir(SHM_DIR) if n.startswith(prefix)]
    if mode == "sigkill":
        # Nobody could clean up (unless a concurrent runtime's start reclaimed them already):
        # the next start reclaims them.
        FrameStore.reclaim_orphans()
        left = [n for n in os.listdir(SHM_DIR) if n.startswith(prefix)]
    assert left == []


def _resident_pages(frame: Frame) -> int:
    """How many pages of ``frame``'s slot are in memory (mincore), without touching them."""
    import ctypes
    import mmap

    assert frame._slot is not None
    mm = frame._slot.mm
    pages = (len(mm) + mmap.PAGESIZE - 1) // mmap.PAGESIZE
    vec = (ctypes.c_ubyte * pages)()
    buf = ctypes.c_char.from_buffer(mm)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        assert libc.mincore(ctypes.c_void_p(ctypes.addressof(buf)), len(mm), vec) == 0
    finally:
        del buf
    return sum(v & 1 for v in vec)


def test_fresh_slots_get_their_pages_untouched_and_keep_what_was_written(
    store: FrameStore,
) -> None:
    """A new slot's pages are allocated before anyone writes it (by the prefault thread:
    the producer does not pay them on its first write), and populating never changes a byte
    already written."""
    from flowrt.frames import prefault

    pool = store.pool("cam", initial_slots=3)
    first = pool.reserve((512, 512, 3))
    assert first is not None
    first.data[:] = 7  # written at once: before or while its pages are populated
    others = [pool.reserve((512, 512, 3)) for _ in range(2)]  # the initial slots, untouched
    assert prefault.settled()
    assert all(f is not None and _resident_pages(f) * 4096 >= f.nbytes for f in others)
    assert int(first.data.min()) == int(first.data.max()) == 7
