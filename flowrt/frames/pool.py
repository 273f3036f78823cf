"""Shared-memory slots and pools: one producer reserves, readers hold by link, slots recycle.

CAMBADA's Shared Data Buffers (see the package's docstring): a pool grows up to its bound and
then drops and counts; the store owns every pool of a runtime and reclaims what a killed
runtime left in ``/dev/shm``.
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
from dataclasses import dataclass
from itertools import count
from typing import Any

import numpy as np

from .frame import ALIGN, HEADER, NAME_RE, SHM_DIR, SHM_PREFIX, Frame, occupants
from .prefault import prefault

# --------------------------------------------------------------------------------------------
# Slots and pools


class Slot:
    """One shared-memory segment holding one frame at a time."""

    __slots__ = ("capacity", "generation", "index", "mm", "name", "pool", "size")

    def __init__(self, pool: FramePool, index: int, name: str, capacity: int) -> None:
        self.pool = pool
        self.index = index
        self.name = name
        self.capacity = capacity  # bytes available for pixels
        self.size = _round_up(HEADER + capacity, ALIGN)
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
        # Pre-allocated buffers: the first frame written into a fresh slot must not pay tmpfs
        # page allocation on the capture path; a thread has the pages allocated meanwhile.
        prefault(self.mm)

    def view(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
        n = math.prod(shape) if shape else 1
        return np.frombuffer(self.mm, dtype=dtype, count=n, offset=HEADER).reshape(shape)

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
        self._slots: list[Slot] = []
        self._free: list[Slot] = []
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
        occupants[slot.name] = frame
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

    def _take(self, nbytes: int) -> Slot | None:
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

    def _new_slot(self, nbytes: int) -> Slot:
        index = len(self._slots)
        slot = Slot(self, index, self._segment_name(), nbytes)
        self._slots.append(slot)
        return slot

    def _replace(self, old: Slot, nbytes: int) -> Slot:
        slot = Slot(self, old.index, self._segment_name(), nbytes)
        self._slots[old.index] = slot
        old.destroy()
        return slot

    def _segment_name(self) -> str:
        return f"{self._store.prefix}{self._tag}_{next(self._names)}"

    def recycle(self, slot: Slot) -> None:
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
            m = NAME_RE.match(name)
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
