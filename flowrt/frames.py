"""Frames: images with capture metadata, held by link count (the Shared Data Buffers).

A :class:`Frame` is a numpy array plus where and when it was captured. It is either a plain
heap frame (made by tests, host programs, or returned by a worker) or a view of a slot in a
shared-memory :class:`FramePool`.

The pool is CAMBADA's Shared Data Buffers: one producer reserves a free slot, fills it and
publishes it; readers hold the frame by a link count; the slot returns to the free list only
when the count reaches zero, so a slow reader's frame is never overwritten under it. The
producer never waits: when every slot is held the pool grows up to ``max_slots``, and beyond
that the frame is dropped and counted.

Why shared memory: a worker process that receives a pooled frame maps the same pages. A pooled
frame pickles to a small descriptor (segment name, offset, shape, dtype, metadata) and unpickles
in the worker to a *read-only* numpy view of the producer's memory — no pixel is copied between
capture and trackers, whatever the resolution. The descriptor is valid only while the main
process holds a link (an activation holds one for the duration of a worker call).

Each slot is its own ``/dev/shm`` file named ``flowrt_{pid}_...`` so that segments left by a
SIGKILLed runtime are recognisable and reclaimed by :meth:`FrameStore.reclaim_orphans` at the
next start. Segments are created and unlinked only by the main process; workers just map them
(read-only, except the slots lent to a worker for the frames it makes: :mod:`flowrt.grants`).

Threading: link counting happens on the event-loop thread of the main process (edges and
activations call ``acquire``/``release``). ``reserve`` and slot recycling take a lock, so a
capture thread may reserve and fill slots while the loop releases others.
"""

from __future__ import annotations

import atexit
import contextlib
import math
import mmap
import os
import re
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from itertools import count
from typing import Any, Protocol

import numpy as np

__all__ = [
    "SHM_DIR",
    "SHM_PREFIX",
    "Frame",
    "FramePool",
    "FramePoolStats",
    "FrameStore",
    "StaleFrameError",
    "WorkerOutputs",
]

SHM_DIR = "/dev/shm"
SHM_PREFIX = "flowrt_"

# Every slot starts with a small header holding the slot's generation (bumped at each reserve),
# so that a worker can check that the slot still holds the frame it was sent. 64 bytes keeps
# the pixel data cache-line aligned.
_HEADER = 64
_ALIGN = 4096
_NAME_RE = re.compile(r"^flowrt_(\d+)_")


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
        self._slot: _Slot | None = None
        self._gen = 0
        # In a worker: the descriptor of the slot this frame views, and the very array, so
        # that the frame passed on unchanged goes back as a descriptor too (no pixel copied).
        self._origin: tuple[tuple[Any, ...], np.ndarray] | None = None
        # In the main process: the grant holder while this slot is lent to a worker to write
        # a frame into (see flowrt.grants), and whether this frame, just back from a worker,
        # carries that grant's link for whoever takes the result (``take_link``).
        self._grant: _GrantHolder | None = None
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
            slot.pool._recycle(slot)

    def __reduce__(self) -> tuple[Any, ...]:
        slot = self._slot
        origin = self._origin
        out = _worker_out
        if slot is None and out is not None:
            # A worker's result: a frame it made goes into a writable slot granted by the
            # main process (written in place, or copied once), not through the socket.
            desc = out.place(self)
            if desc is not None:
                return (_attach_frame, desc)
        if slot is None and origin is not None and self.data is origin[1]:
            # A frame attached in a worker, passed on with its pixels untouched (they are
            # read-only there): it goes back to the owner as the same descriptor.
            return (
                _attach_frame,
                (*origin[0], self.source, self.seq, self.timestamp, self.pixel_format),
            )
        if slot is None:
            # Heap frames (and new arrays made in a worker) travel with their pixels.
            return (
                _heap_frame,
                (self.data, self.source, self.seq, self.timestamp, self.pixel_format),
            )
        if self._refs <= 0:
            raise RuntimeError(f"{self!r} was released: its slot may already hold another frame")
        return (
            _attach_frame,
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
    frames the node makes go (:mod:`flowrt.grants` implements it; this module only calls)."""

    def take(
        self, shape: tuple[int, ...], dtype: np.dtype[Any], source: str, pixel_format: str
    ) -> Frame | None:
        """A writable frame in a granted slot, or None (no slot fits)."""

    def place(self, frame: Frame) -> tuple[Any, ...] | None:
        """The slot descriptor ``frame`` goes back as (its pixels in a granted slot), or None."""


class _GrantHolder(Protocol):
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


def _heap_frame(
    data: np.ndarray, source: str, seq: int, timestamp: float, pixel_format: str
) -> Frame:
    return Frame(data, source=source, seq=seq, timestamp=timestamp, pixel_format=pixel_format)


# --------------------------------------------------------------------------------------------
# Attaching in a worker process


class _MappingCache:
    """Per-process cache of segment mappings, so each slot is mapped once per worker.

    Read-only for the frames a worker receives; writable (``writable=True``) for the slots
    granted to it to write its own frames into (:mod:`flowrt.grants`).

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


_mappings = _MappingCache()

# In the process that owns the pools: the frame that occupies each slot (by segment name), so
# that a descriptor coming back from a worker resolves to that frame, not to a second view.
_occupants: weakref.WeakValueDictionary[str, Frame] = weakref.WeakValueDictionary()


def _attach_frame(
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
    owned = _occupants.get(name)
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
    m = _mappings.get(name, size)
    header = np.frombuffer(m, dtype=np.uint64, count=1)
    if int(header[0]) != generation:
        raise StaleFrameError(
            f"slot {name} holds generation {int(header[0])}, expected {generation} "
            f"({source}#{seq}): the sender released the frame before it was read"
        )
    dt = np.dtype(dtype)
    n = math.prod(shape) if shape else 1
    data = np.frombuffer(m, dtype=dt, count=n, offset=_HEADER).reshape(shape)
    # A frame attached in a worker is not link counted there (the main process holds the link);
    # returned unchanged it goes back as this descriptor (see Frame.__reduce__).
    frame = Frame(data, source=source, seq=seq, timestamp=timestamp, pixel_format=pixel_format)
    frame._origin = ((name, size, generation, shape, dtype), data)
    return frame


# --------------------------------------------------------------------------------------------
# Slots and pools


class _Slot:
    """One shared-memory segment holding one frame at a time."""

    __slots__ = ("capacity", "generation", "index", "mm", "name", "pool", "size")

    def __init__(self, pool: FramePool, index: int, name: str, capacity: int) -> None:
        self.pool = pool
        self.index = index
        self.name = name
        self.capacity = capacity  # bytes available for pixels
        self.size = _round_up(_HEADER + capacity, _ALIGN)
        self.generation = 0
        path = os.path.join(SHM_DIR, name)
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o600)
        try:
            os.ftruncate(fd, self.size)
            self.mm = mmap.mmap(fd, self.size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        except BaseException:
            os.close(fd)
            os.unlink(path)
            raise
        os.close(fd)
        # Touch every page now (pre-allocated buffers): the first frame written into a fresh
        # slot must not pay tmpfs page allocation on the capture path.
        np.frombuffer(self.mm, dtype=np.uint8)[:] = 0

    def view(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
        n = math.prod(shape) if shape else 1
        return np.frombuffer(self.mm, dtype=dtype, count=n, offset=_HEADER).reshape(shape)

    def stamp(self) -> None:
        """Start a new generation: the slot now holds a new frame."""
        self.generation += 1
        np.frombuffer(self.mm, dtype=np.uint64, count=1)[0] = self.generation

    def destroy(self) -> None:
        # A frame view still alive somewhere keeps the mapping (BufferError); the name is
        # unlinked regardless, so nothing outlives the process.
        with contextlib.suppress(BufferError):
            self.mm.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(SHM_DIR, self.name))


def _round_up(n: int, to: int) -> int:
    return (n + to - 1) // to * to


@dataclass(frozen=True, slots=True)
class FramePoolStats:
    """Counters of one pool; ``dropped`` frames are those refused because every slot was held."""

    owner: str
    slots: int
    slots_in_use: int
    max_slots: int
    reserved: int
    grown: int
    dropped: int
    reallocated: int
    bytes: int


class FramePool:
    """Shared-memory slots for one producer (the Shared Data Buffers of one source).

    ``initial_slots`` slots are allocated at the first ``reserve`` (the frame size is not known
    before). A slot is sized for the frame it receives; a larger frame reallocates a free slot.
    Free slots are reused most-recently-freed first, which keeps their pages hot in cache.
    Create pools through :meth:`FrameStore.pool`, which owns their cleanup.
    """

    def __init__(
        self, store: FrameStore, owner: str, *, max_slots: int = 16, initial_slots: int = 4
    ) -> None:
        if max_slots < 1:
            raise ValueError("max_slots must be >= 1")
        self.owner = owner
        self.max_slots = max_slots
        self.initial_slots = max(1, min(initial_slots, max_slots))
        self._store = store
        self._tag = re.sub(r"[^A-Za-z0-9_-]", "-", owner)[:40]
        self._slots: list[_Slot] = []
        self._free: list[_Slot] = []
        self._lock = threading.Lock()
        self._names = count()
        self._reserved = 0
        self._grown = 0
        self._dropped = 0
        self._reallocated = 0
        self._closed = False

    # -- producer side ----------------------------------------------------------------------

    def reserve(
        self,
        shape: tuple[int, ...],
        dtype: Any = np.uint8,
        *,
        source: str = "",
        seq: int = 0,
        timestamp: float = 0.0,
        pixel_format: str = "BGR",
        count_drop: bool = True,
    ) -> Frame | None:
        """Return a writable frame in a free slot with link count 1 (the producer's), or None.

        None means every slot is held and the pool is at ``max_slots``: the frame is dropped
        and counted, because the producer (a camera) must never wait for a slow reader. The
        producer fills ``frame.data``, publishes, then releases its own link.
        ``count_drop=False``: the caller counts the refusal itself (a slot to lend to a
        worker is not a frame dropped: the worker's frame takes the socket instead).
        """
        dt = np.dtype(dtype)
        shape = tuple(int(s) for s in shape)
        nbytes = math.prod(shape) * dt.itemsize if shape else dt.itemsize
        with self._lock:
            if self._closed:
                raise RuntimeError(f"frame pool {self.owner!r} is closed")
            slot = self._take(nbytes)
            if slot is None:
                if count_drop:
                    self._dropped += 1
                return None
            slot.stamp()
            self._reserved += 1
        frame = Frame(
            slot.view(shape, dt),
            source=source,
            seq=seq,
            timestamp=timestamp,
            pixel_format=pixel_format,
        )
        frame._slot = slot
        frame._gen = slot.generation
        _occupants[slot.name] = frame
        return frame

    def publish_array(
        self,
        array: np.ndarray,
        *,
        source: str = "",
        seq: int = 0,
        timestamp: float = 0.0,
        pixel_format: str = "BGR",
    ) -> Frame | None:
        """Copy ``array`` into a reserved slot (for producers that cannot decode in place)."""
        frame = self.reserve(
            array.shape,
            array.dtype,
            source=source,
            seq=seq,
            timestamp=timestamp,
            pixel_format=pixel_format,
        )
        if frame is not None:
            np.copyto(frame.data, array)
        return frame

    def _take(self, nbytes: int) -> _Slot | None:
        # Prefer the most recently freed slot that is large enough; else reallocate a free one.
        for i in range(len(self._free) - 1, -1, -1):
            if self._free[i].capacity >= nbytes:
                return self._free.pop(i)
        if self._free:
            old = self._free.pop()
            self._reallocated += 1
            return self._replace(old, nbytes)
        if len(self._slots) < self.max_slots:
            if not self._slots:
                # First reserve: allocate the initial slots at this size.
                for _ in range(self.initial_slots - 1):
                    self._free.append(self._new_slot(nbytes))
            elif len(self._slots) >= self.initial_slots:
                self._grown += 1
            return self._new_slot(nbytes)
        return None

    def _new_slot(self, nbytes: int) -> _Slot:
        index = len(self._slots)
        slot = _Slot(self, index, self._segment_name(), nbytes)
        self._slots.append(slot)
        return slot

    def _replace(self, old: _Slot, nbytes: int) -> _Slot:
        slot = _Slot(self, old.index, self._segment_name(), nbytes)
        self._slots[old.index] = slot
        old.destroy()
        return slot

    def _segment_name(self) -> str:
        return f"{self._store.prefix}{self._tag}_{next(self._names)}"

    def _recycle(self, slot: _Slot) -> None:
        with self._lock:
            if self._closed or self._slots[slot.index] is not slot:
                return
            self._free.append(slot)

    # -- inspection and cleanup -------------------------------------------------------------

    def stats(self) -> FramePoolStats:
        with self._lock:
            return FramePoolStats(
                owner=self.owner,
                slots=len(self._slots),
                slots_in_use=len(self._slots) - len(self._free),
                max_slots=self.max_slots,
                reserved=self._reserved,
                grown=self._grown,
                dropped=self._dropped,
                reallocated=self._reallocated,
                bytes=sum(s.size for s in self._slots),
            )

    def segment_names(self) -> list[str]:
        with self._lock:
            return [s.name for s in self._slots]

    def close(self) -> None:
        """Unlink every segment. Frames still held keep their (now anonymous) mapping."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            slots, self._slots, self._free = self._slots, [], []
        for slot in slots:
            slot.destroy()


# --------------------------------------------------------------------------------------------
# The store: runtime-wide owner of all pools


_store_ids = count()
_live_stores: weakref.WeakSet[FrameStore] = weakref.WeakSet()


class FrameStore:
    """Owns every frame pool of a runtime and guarantees that no segment outlives it.

    ``close()`` (called by the runtime on every exit path, and by ``atexit`` after an exception
    or Ctrl-C) unlinks all segments. Only the process that created the store unlinks: a forked
    child running its own ``atexit`` must not pull the segments from under its parent. What a
    SIGKILL leaves behind is reclaimed by :meth:`reclaim_orphans` at the next start.
    """

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.prefix = f"{SHM_PREFIX}{self.pid}_{next(_store_ids)}_"
        self._pools: dict[str, FramePool] = {}
        self._closed = False
        _live_stores.add(self)

    def pool(self, owner: str, *, max_slots: int = 16, initial_slots: int = 4) -> FramePool:
        """The pool of ``owner`` (a producer node's port), created on first use."""
        if self._closed:
            raise RuntimeError("frame store is closed")
        pool = self._pools.get(owner)
        if pool is None:
            pool = FramePool(self, owner, max_slots=max_slots, initial_slots=initial_slots)
            self._pools[owner] = pool
        return pool

    def pools(self) -> list[FramePool]:
        return list(self._pools.values())

    def stats(self) -> list[FramePoolStats]:
        return [p.stats() for p in self._pools.values()]

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Unlink every segment of every pool (idempotent)."""
        if self._closed or os.getpid() != self.pid:
            return
        self._closed = True
        for pool in self._pools.values():
            pool.close()
        self._pools.clear()
        _live_stores.discard(self)

    def __enter__(self) -> FrameStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @staticmethod
    def reclaim_orphans() -> int:
        """Unlink flowrt segments whose creating process is gone; return how many.

        A segment counts as orphaned when its pid is not alive, or when a live process with
        that pid started after the segment was created (the pid was reused).
        """
        try:
            names = os.listdir(SHM_DIR)
        except FileNotFoundError:
            return 0
        me = os.getpid()
        removed = 0
        for name in names:
            m = _NAME_RE.match(name)
            if m is None:
                continue
            pid = int(m.group(1))
            if pid == me:
                continue
            path = os.path.join(SHM_DIR, name)
            if _pid_alive(pid):
                started = _process_start_time(pid)
                try:
                    created = os.stat(path).st_mtime
                except FileNotFoundError:
                    continue
                if started is None or started <= created + 1.0:
                    continue
            try:
                os.unlink(path)
                removed += 1
            except FileNotFoundError:
                pass
        return removed


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _process_start_time(pid: int) -> float | None:
    """Wall-clock start time of ``pid`` from /proc, or None if unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
        with open("/proc/stat") as f:
            btime = next(int(line.split()[1]) for line in f if line.startswith("btime"))
    except (OSError, StopIteration, ValueError):
        return None
    fields = stat[stat.rfind(")") + 2 :].split()
    ticks = int(fields[19])  # field 22 of /proc/pid/stat, counted after "pid (comm)"
    return btime + ticks / os.sysconf("SC_CLK_TCK")


@atexit.register
def _close_all_stores() -> None:
    for store in list(_live_stores):
        store.close()
