"""A frame: pixels and capture metadata, held by link count; its descriptor across processes.

A pooled frame pickles to a small descriptor of its shared-memory slot and unpickles in a
worker to a read-only view of the same pages (``attach_frame``); a frame a worker makes goes
to a slot lent for the call (the lending state below, filled by :mod:`.lending`).
"""

from __future__ import annotations

import math
import mmap
import os
import re
import weakref
from collections import OrderedDict
from typing import Any, Protocol

import numpy as np

SHM_DIR = "/dev/shm"
SHM_PREFIX = "flowrt_"

# Every slot starts with a small header holding the slot's generation (bumped at each reserve),
# so that a worker can check that the slot still holds the frame it was sent. 64 bytes keeps
# the pixel data cache-line aligned.
HEADER = 64
ALIGN = 4096
NAME_RE = re.compile(r"^flowrt_(\d+)_")


class SlotView(Protocol):
    """What a frame reads of the slot it occupies (:class:`.pool.Slot`)."""

    name: str
    size: int
    capacity: int  # bytes of pixels it holds
    pool: Any  # its FramePool: ``recycle(slot)`` when the last link goes

    def view(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray: ...


class StaleFrameError(RuntimeError):
    """A frame descriptor refers to a slot that has been recycled since it was sent.

    Cannot happen while the sender holds a link, which the runtime guarantees for the duration
    of a worker call; raised rather than silently reading another frame's pixels.
    """


class Frame:
    """An image plus where and when it was captured.

    Link counted: every buffer and activation that holds a frame calls ``acquire`` and
    ``release``. A pooled frame's slot returns to its pool only when the count reaches zero,
    and releasing it once more is an error (it would recycle a slot someone else now owns). A
    heap frame's count is informative only: its memory belongs to the garbage collector.

    The constructor makes a heap frame with link count 1 (the creator's link).
    """

    __slots__ = (
        "__weakref__",
        "_gen",
        "_grant",
        "_handoff",
        "_origin",
        "_refs",
        "_slot",
        "data",
        "pixel_format",
        "seq",
        "source",
        "timestamp",
    )

    def __init__(
        self,
        data: np.ndarray,
        *,
        source: str = "",
        seq: int = 0,
        timestamp: float = 0.0,
        pixel_format: str = "BGR",
    ) -> None:
        self.data = data
        self.source = source
        self.seq = seq
        self.timestamp = timestamp
        self.pixel_format = pixel_format
        self._refs = 1
        self._slot: SlotView | None = None
        self._gen = 0
        # In a worker: the descriptor of the slot this frame views, and the very array, so
        # that the frame passed on unchanged goes back as a descriptor too (no pixel copied).
        self._origin: tuple[tuple[Any, ...], np.ndarray] | None = None
        # In the main process: the grant holder while this slot is lent to a worker to write
        # a frame into (see flowrt.frames.lending), and whether this frame, just back from a worker,
        # carries that grant's link for whoever takes the result (``take_link``).
        self._grant: GrantHolder | None = None
        self._handoff = False

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape)

    @property
    def dtype(self) -> np.dtype[Any]:
        return self.data.dtype

    @property
    def nbytes(self) -> int:
        return int(self.data.nbytes)

    @property
    def refs(self) -> int:
        """Current link count (for tests and statistics)."""
        return self._refs

    @property
    def shared(self) -> bool:
        """True when the pixels live in a pool slot (pickling sends a descriptor, not pixels)."""
        return self._slot is not None

    def acquire(self) -> None:
        """Take one more link; the slot cannot be recycled until it is released."""
        self._refs += 1

    def take_link(self) -> None:
        """Hold this frame: take the link it carries, if any, else a new one.

        A frame that a worker wrote into a granted slot comes back carrying the grant's link
        (nobody else holds it yet); the first holder takes that one instead of adding its own,
        so the slot returns to its pool when the last reader lets go.
        """
        if self._handoff:
            self._handoff = False
        else:
            self.acquire()

    def release(self) -> None:
        """Drop one link; the last release returns a pooled slot to its pool."""
        slot = self._slot
        if slot is None:
            self._refs -= 1
            return
        if self._refs <= 0:
            raise RuntimeError(f"{self!r} released more often than acquired")
        self._refs -= 1
        if self._refs == 0:
            slot.pool.recycle(slot)

    def __reduce__(self) -> tuple[Any, ...]:
        slot = self._slot
        origin = self._origin
        out = _worker_out
        if slot is None and out is not None:
            # A worker's result: a frame it made goes into a writable slot granted by the
            # main process (written in place, or copied once), not through the socket.
            desc = out.place(self)
            if desc is not None:
                return (attach_frame, desc)
        if slot is None and origin is not None and self.data is origin[1]:
            # A frame attached in a worker, passed on with its pixels untouched (they are
            # read-only there): it goes back to the owner as the same descriptor.
            return (
                attach_frame,
                (*origin[0], self.source, self.seq, self.timestamp, self.pixel_format),
            )
        if slot is None:
            # Heap frames (and new arrays made in a worker) travel with their pixels.
            return (
                heap_frame,
                (self.data, self.source, self.seq, self.timestamp, self.pixel_format),
            )
        if self._refs <= 0:
            raise RuntimeError(f"{self!r} was released: its slot may already hold another frame")
        return (
            attach_frame,
            (
                slot.name,
                slot.size,
                self._gen,
                self.shape,
                self.dtype.str,
                self.source,
                self.seq,
                self.timestamp,
                self.pixel_format,
            ),
        )

    def __repr__(self) -> str:
        kind = "shm" if self._slot is not None else "heap"
        return f"Frame({self.source}#{self.seq} {self.shape} {self.pixel_format} {kind})"


def release_handoffs(result: Any) -> None:
    """Drop the links carried by frames of a worker's result that nobody will take (the result
    is discarded: its caller gave up, or the node instance that made it has failed)."""
    from collections.abc import Mapping

    values = result.values() if isinstance(result, Mapping) else (result,)
    for v in values:
        if isinstance(v, Frame) and v._handoff:
            v._handoff = False
            v.release()


class WorkerOutputs(Protocol):
    """In a worker process, during a node's call and the pickling of its result: where the
    frames the node makes go (:mod:`flowrt.frames.lending` implements it; this only calls)."""

    def take(
        self, shape: tuple[int, ...], dtype: np.dtype[Any], source: str, pixel_format: str
    ) -> Frame | None:
        """A writable frame in a granted slot, or None (no slot fits)."""

    def place(self, frame: Frame) -> tuple[Any, ...] | None:
        """The slot descriptor ``frame`` goes back as (its pixels in a granted slot), or None."""


class GrantHolder(Protocol):
    """In the main process: who lent a slot to a worker (takes it back with a frame in it)."""

    def returned(
        self,
        frame: Frame,
        shape: tuple[int, ...],
        dtype: str,
        source: str,
        seq: int,
        timestamp: float,
        pixel_format: str,
    ) -> Frame: ...


_worker_out: WorkerOutputs | None = None  # set by a worker process around each call


def set_worker_outputs(out: WorkerOutputs | None) -> None:
    """Install (or clear, ``None``) the lent slots of the worker's current call."""
    global _worker_out
    _worker_out = out


def worker_frame(shape: tuple[int, ...], dtype: Any, source: str, pixel_format: str) -> Frame:
    """A new writable frame for a node: in a granted shared-memory slot inside a worker's call
    (zero copy to the main process), else on the heap."""
    out = _worker_out
    dt = dtype if isinstance(dtype, np.dtype) else np.dtype(dtype)
    shape = tuple(map(int, shape))
    if out is not None:
        frame = out.take(shape, dt, source, pixel_format)
        if frame is not None:
            return frame
    return Frame(np.empty(shape, dtype=dt), source=source, pixel_format=pixel_format)


def heap_frame(
    data: np.ndarray, source: str, seq: int, timestamp: float, pixel_format: str
) -> Frame:
    return Frame(data, source=source, seq=seq, timestamp=timestamp, pixel_format=pixel_format)


# --------------------------------------------------------------------------------------------
# Attaching in a worker process


class MappingCache:
    """Per-process cache of segment mappings, so each slot is mapped once per worker.

    Read-only for the frames a worker receives; writable (``writable=True``) for the slots
    granted to it to write its own frames into (:mod:`flowrt.frames.lending`).

    Bounded (LRU): a slot reallocated with a larger size gets a new segment name, and the old
    mapping must not pin unlinked memory forever. Dropping an entry does not unmap memory a
    live array still views: the array keeps the mmap alive through its base.
    """

    def __init__(self, capacity: int = 256, *, writable: bool = False) -> None:
        self.capacity = capacity
        self.writable = writable
        self._maps: OrderedDict[str, mmap.mmap] = OrderedDict()

    def get(self, name: str, size: int) -> mmap.mmap:
        m = self._maps.get(name)
        if m is not None and len(m) == size:
            self._maps.move_to_end(name)
            return m
        w = self.writable
        fd = os.open(os.path.join(SHM_DIR, name), os.O_RDWR if w else os.O_RDONLY)
        try:
            prot = mmap.PROT_READ | (mmap.PROT_WRITE if w else 0)
            m = mmap.mmap(fd, size, mmap.MAP_SHARED, prot)
        finally:
            os.close(fd)
        self._maps[name] = m
        while len(self._maps) > self.capacity:
            self._maps.popitem(last=False)
        return m

    def forget(self, name: str) -> None:
        self._maps.pop(name, None)

    def clear(self) -> None:
        self._maps.clear()


mappings = MappingCache()

# In the process that owns the pools: the frame that occupies each slot (by segment name), so
# that a descriptor coming back from a worker resolves to that frame, not to a second view.
occupants: weakref.WeakValueDictionary[str, Frame] = weakref.WeakValueDictionary()


def attach_frame(
    name: str,
    size: int,
    generation: int,
    shape: tuple[int, ...],
    dtype: str,
    source: str,
    seq: int,
    timestamp: float,
    pixel_format: str,
) -> Frame:
    """Rebuild a pooled frame from its descriptor: a read-only view, no pixel copied.

    In the process that owns the slot (a worker's result handing back a frame it received),
    it is the frame that occupies the slot, the same object: link counted as it always was
    (the caller takes its own link, see ``NodeRunner._adopt``). If the worker changed its
    metadata, a heap copy carries the new metadata instead (the original is shared).
    """
    owned = occupants.get(name)
    if owned is not None and owned._slot is not None and owned._slot.name == name:
        if owned._gen != generation or owned._refs <= 0:
            raise StaleFrameError(
                f"slot {name} holds generation {owned._gen}, expected {generation} "
                f"({source}#{seq}): the frame was released before its result came back"
            )
        if owned._grant is not None:  # a slot lent to a worker, back with its new frame
            return owned._grant.returned(owned, shape, dtype, source, seq, timestamp, pixel_format)
        if (owned.source, owned.seq, owned.timestamp, owned.pixel_format) == (
            source,
            seq,
            timestamp,
            pixel_format,
        ):
            return owned
        return Frame(
            owned.data.copy(),
            source=source,
            seq=seq,
            timestamp=timestamp,
            pixel_format=pixel_format,
        )
    m = mappings.get(name, size)
    header = np.frombuffer(m, dtype=np.uint64, count=1)
    if int(header[0]) != generation:
        raise StaleFrameError(
            f"slot {name} holds generation {int(header[0])}, expected {generation} "
            f"({source}#{seq}): the sender released the frame before it was read"
        )
    dt = np.dtype(dtype)
    n = math.prod(shape) if shape else 1
    data = np.frombuffer(m, dtype=dt, count=n, offset=HEADER).reshape(shape)
    # A frame attached in a worker is not link counted there (the main process holds the link);
    # returned unchanged it goes back as this descriptor (see Frame.__reduce__).
    frame = Frame(data, source=source, seq=seq, timestamp=timestamp, pixel_format=pixel_format)
    frame._origin = ((name, size, generation, shape, dtype), data)
    return frame
