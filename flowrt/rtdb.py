"""The real-time database: named records of the latest value, shared with worker processes.

CAMBADA's RTDB holds the robot's view of the world — the objects the trackers found, with
when they were seen — so that any process reads the newest state without asking anyone.
Here a record holds the latest value, its timestamp, a validity window and a short history
ring; a read past the validity window is flagged ``stale`` instead of silently returning old
data as if it were current.

Layout: one shared-memory segment (a ``/dev/shm`` file named ``flowrt_{pid}_rtdb...``, so
that what a SIGKILLed runtime leaves behind is reclaimed like frame segments) with a fixed
directory of record names and a fixed-size slot per record. Values are pickled into the
slot, up to ``max_value`` bytes each.

Concurrency, without round trips to the main process:
- readers take no lock: each record has a seqlock (odd while a write is in progress) and
  each history entry a CRC32 of its payload, so a read that overlapped a write is detected
  and retried, whatever the memory ordering of the machine;
- writers of the same record exclude each other with a POSIX byte-range lock on the record
  (``fcntl.lockf``), which the kernel releases if the writer dies, plus a thread lock for
  writers within one process;
- a new name is allocated under a lock on the segment header and published by bumping the
  record count last, so a reader never sees a half-written name.

Only the creating process (the runtime) unlinks the segment; workers attach through the
picklable :class:`RtdbHandle` that their node factory carries.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import itertools
import math
import mmap
import os
import pickle
import struct
import tempfile
import threading
import time
import weakref
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["RTDB", "Record", "RtdbHandle"]

#: The records through which a ``recorder`` node is commanded and answers, each followed by
#: the node's name; owned here, where the control endpoint, ``flowrt ctl record``, the
#: operator's page and the node itself (any node could) all find them.
RECORD_COMMAND = "flowrt.record."
"""``flowrt.record.NODE`` = ``"start"`` | ``"stop"`` | ``{"action": "start", "name": N}``."""
RECORDING_SESSION = "flowrt.recording."
"""``flowrt.recording.NODE``: the recorder's current session folder, "" when stopped."""
RECORDING_FOLDER = "flowrt.recordings."
"""``flowrt.recordings.NODE``: the folder the recorder creates its sessions in."""

_MAGIC = b"FLOWRTDB"
_VERSION = 1
_PAGE = 4096
# header: magic, version, max_records, history, max_value, n_records, origin
_HEADER = struct.Struct("<8sIIIIId")
_N_RECORDS_OFF = 8 + 4 * 4
_NAME_BYTES = 126
_DIR_ENTRY = 128  # u16 length + name
# record header: seq (seqlock), count (writes so far), default validity (s, NaN = none)
_REC = struct.Struct("<QQd")
_REC_HEADER = 64
# history entry: timestamp (s since origin), validity (s, NaN = none), length, crc32
_ENTRY = struct.Struct("<ddII")
_READ_SPINS = 200


def _shm_dir() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()


def _align(n: int, to: int) -> int:
    return (n + to - 1) // to * to


@dataclass(frozen=True)
class Record:
    """One value read from the RTDB, with how old it is and whether it is still valid."""

    name: str
    value: Any
    timestamp: float  # runtime clock, seconds since the runtime started
    age: float  # seconds between the write's timestamp and the read
    stale: bool  # older than its validity window
    seq: int  # write number of this record, from 1
    validity: float | None  # seconds; None = valid forever


@dataclass(frozen=True)
class RtdbHandle:
    """A picklable reference to an RTDB segment, to attach to it from another process."""

    path: str


_ids = itertools.count()
_live: weakref.WeakSet[RTDB] = weakref.WeakSet()
_attached: dict[tuple[int, str], RTDB] = {}


class RTDB:
    """Named records in shared memory: latest value, timestamp, validity, history ring.

    Create one per runtime (``RTDB()``), hand ``rtdb.handle`` to other processes, which call
    ``RTDB.attach(handle)``. Writes cost a pickle, a copy and two lock syscalls; reads a copy
    and an unpickle, never a lock (unless a writer died mid-write).

    Args:
        max_records: number of record names the segment can hold (fixed at creation).
        history: values kept per record, the newest included.
        max_value: largest pickled value, bytes; a larger value raises ``ValueError``.
        clock: the time source of timestamps (the runtime passes its clock, which is
            ``time.monotonic`` in real runs: the same in every process of the machine).
        origin: clock time of the runtime's start; timestamps are seconds since then.
    """

    def __init__(
        self,
        *,
        max_records: int = 256,
        history: int = 8,
        max_value: int = 4096,
        clock: Callable[[], float] = time.monotonic,
        origin: float | None = None,
        _path: str | None = None,
    ) -> None:
        self.clock = clock
        self._lock = threading.Lock()
        self._index: dict[str, int] = {}
        self._owner_pid = os.getpid()
        if _path is not None:  # attach
            self.path = _path
            self._fd = os.open(_path, os.O_RDWR)
            try:
                size = os.fstat(self._fd).st_size
                self._mm = mmap.mmap(self._fd, size, mmap.MAP_SHARED)
            except BaseException:
                os.close(self._fd)
                raise
            magic, version, max_records, history, max_value, _, origin_ = _HEADER.unpack_from(
                self._mm, 0
            )
            if magic != _MAGIC or version != _VERSION:
                self._mm.close()
                os.close(self._fd)
                raise ValueError(f"{_path} is not an RTDB segment of this version")
            self.origin = origin_
            self.creator = False
        else:
            if max_records < 1 or history < 1 or max_value < 16:
                raise ValueError("need max_records >= 1, history >= 1, max_value >= 16")
            self.origin = clock() if origin is None else origin
            name = f"flowrt_{os.getpid()}_rtdb{next(_ids)}"
            self.path = os.path.join(_shm_dir(), name)
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            self.creator = True
        self.max_records = max_records
        self.history_len = history
        self.max_value = max_value
        self._entry_size = _ENTRY.size + max_value
        self._rec_size = _align(_REC_HEADER + history * self._entry_size, 64)
        self._dir_off = _PAGE
        self._rec_off = _PAGE + _align(max_records * _DIR_ENTRY, _PAGE)
        if self.creator:
            try:
                size = self._rec_off + max_records * self._rec_size
                os.ftruncate(self._fd, size)  # sparse: pages are allocated when first written
                self._mm = mmap.mmap(self._fd, size, mmap.MAP_SHARED)
                _HEADER.pack_into(
                    self._mm, 0, _MAGIC, _VERSION, max_records, history, max_value, 0, self.origin
                )
            except BaseException:
                os.close(self._fd)
                os.unlink(self.path)
                raise
            _live.add(self)
        self.closed = False

    # --- lifecycle --------------------------------------------------------------------------

    @classmethod
    def attach(cls, handle: RtdbHandle, clock: Callable[[], float] = time.monotonic) -> RTDB:
        """Map an existing RTDB (e.g. in a worker process); closing it never unlinks.

        One mapping per process and segment, shared by every node of a worker: POSIX record
        locks belong to the process, and closing any descriptor of the file would drop them.
        """
        key = (os.getpid(), handle.path)
        db = _attached.get(key)
        if db is None or db.closed:
            db = _attached[key] = cls(clock=clock, _path=handle.path)
        return db

    @property
    def handle(self) -> RtdbHandle:
        return RtdbHandle(self.path)

    def close(self) -> None:
        """Unmap; the creating process also unlinks the segment. Idempotent."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(BufferError, ValueError):
            self._mm.close()
        with contextlib.suppress(OSError):
            os.close(self._fd)
        if self.creator and os.getpid() == self._owner_pid:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        _live.discard(self)
        if _attached.get((os.getpid(), self.path)) is self:
            del _attached[(os.getpid(), self.path)]

    def __enter__(self) -> RTDB:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- names ------------------------------------------------------------------------------

    def _count(self) -> int:
        return int(struct.unpack_from("<I", self._mm, _N_RECORDS_OFF)[0])

    def _name_at(self, i: int) -> str:
        off = self._dir_off + i * _DIR_ENTRY
        (n,) = struct.unpack_from("<H", self._mm, off)
        return bytes(self._mm[off + 2 : off + 2 + n]).decode()

    def _lookup(self, name: str) -> int | None:
        i = self._index.get(name)
        if i is not None:
            return i
        for j in range(len(self._index), self._count()):
            self._index[self._name_at(j)] = j
        return self._index.get(name)

    def _allocate(self, name: str) -> int:
        encoded = name.encode()
        if not name or len(encoded) > _NAME_BYTES:
            raise ValueError(f"record name must be 1..{_NAME_BYTES} bytes of UTF-8, got {name!r}")
        with self._lock, self._locked(0, 8, fcntl.LOCK_EX):
            i = self._lookup(name)  # another process may have added it meanwhile
            if i is not None:
                return i
            n = self._count()
            if n >= self.max_records:
                raise ValueError(f"RTDB full: {self.max_records} records (raise max_records)")
            off = self._dir_off + n * _DIR_ENTRY
            struct.pack_into("<H", self._mm, off, len(encoded))
            self._mm[off + 2 : off + 2 + len(encoded)] = encoded
            _REC.pack_into(self._mm, self._rec(n), 0, 0, math.nan)
            struct.pack_into("<I", self._mm, _N_RECORDS_OFF, n + 1)  # publish last
            self._index[name] = n
            return n

    def names(self) -> list[str]:
        """Every record name, in order of creation."""
        self._lookup("")
        return sorted(self._index, key=self._index.__getitem__)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self._lookup(name) is not None

    # --- writing ----------------------------------------------------------------------------

    def _rec(self, i: int) -> int:
        return self._rec_off + i * self._rec_size

    @contextlib.contextmanager
    def _locked(self, start: int, length: int, op: int) -> Any:
        fcntl.lockf(self._fd, op, length, start, os.SEEK_SET)
        try:
            yield
        finally:
            fcntl.lockf(self._fd, fcntl.LOCK_UN, length, start, os.SEEK_SET)

    def declare(self, name: str, *, validity_ms: float | None) -> None:
        """Create ``name`` if needed and set the validity window used by writes without one."""
        i = self._lookup(name)
        if i is None:
            i = self._allocate(name)
        validity = math.nan if validity_ms is None else validity_ms / 1000
        off = self._rec(i)
        with self._lock, self._locked(off, _REC_HEADER, fcntl.LOCK_EX):
            struct.pack_into("<d", self._mm, off + 16, validity)

    def write(
        self,
        name: str,
        value: Any,
        *,
        validity_ms: float | None = None,
        timestamp: float | None = None,
    ) -> int:
        """Store ``value`` as the newest of ``name``; return its write number.

        Args:
            validity_ms: how long the value stays valid; None uses the record's declared
                validity (``declare``), or valid forever.
            timestamp: when the value was true, on the RTDB's clock (e.g. the capture time
                of the frame it was computed from); default now.
        """
        if self.closed:
            raise RuntimeError("the RTDB is closed")
        payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        if len(payload) > self.max_value:
            raise ValueError(
                f"{name}: pickled value is {len(payload)} bytes, "
                f"more than max_value {self.max_value}"
            )
        i = self._lookup(name)
        if i is None:
            i = self._allocate(name)
        t = (self.clock() if timestamp is None else timestamp) - self.origin
        off = self._rec(i)
        mm = self._mm
        with self._lock, self._locked(off, self._rec_size, fcntl.LOCK_EX):
            seq, count, default_validity = _REC.unpack_from(mm, off)
            validity = default_validity if validity_ms is None else validity_ms / 1000
            seq |= 1  # odd: write in progress (also repairs a writer that died mid-write)
            struct.pack_into("<Q", mm, off, seq)
            count += 1
            e = off + _REC_HEADER + (count % self.history_len) * self._entry_size
            _ENTRY.pack_into(mm, e, t, validity, len(payload), zlib.crc32(payload))
            mm[e + _ENTRY.size : e + _ENTRY.size + len(payload)] = payload
            struct.pack_into("<Q", mm, off + 8, count)
            struct.pack_into("<Q", mm, off, seq + 1)
        return int(count)

    # --- reading ----------------------------------------------------------------------------

    def _entry(self, off: int, k: int) -> tuple[float, float, bytes] | None:
        """History entry of write number ``k``: (timestamp, validity, payload), None if torn."""
        e = off + _REC_HEADER + (k % self.history_len) * self._entry_size
        t, validity, n, crc = _ENTRY.unpack_from(self._mm, e)
        if n > self.max_value:
            return None
        payload = bytes(self._mm[e + _ENTRY.size : e + _ENTRY.size + n])
        if zlib.crc32(payload) != crc:
            return None
        return t, validity, payload

    def _snapshot(self, i: int, n: int) -> tuple[int, list[tuple[int, float, float, bytes]]]:
        """The newest ``n`` entries of record ``i``, consistent with each other."""
        off = self._rec(i)
        mm = self._mm
        for _ in range(_READ_SPINS):
            seq1 = struct.unpack_from("<Q", mm, off)[0]
            if seq1 & 1:
                time.sleep(0)
                continue
            count = struct.unpack_from("<Q", mm, off + 8)[0]
            out = []
            for k in range(count, max(0, count - n), -1):
                entry = self._entry(off, k)
                if entry is None:
                    break
                out.append((k, *entry))
            if struct.unpack_from("<Q", mm, off)[0] == seq1 and len(out) == min(n, count):
                return count, out
        # A writer is slow or died mid-write: wait for it under the lock, keep what is intact.
        with self._lock, self._locked(off, self._rec_size, fcntl.LOCK_SH):
            count = struct.unpack_from("<Q", mm, off + 8)[0]
            out = []
            for k in range(count, max(0, count - n - 1), -1):
                entry = self._entry(off, k)
                if entry is not None:
                    out.append((k, *entry))
            return count, out[:n]

    def _record(
        self, name: str, k: int, t: float, validity: float, payload: bytes, now: float
    ) -> Record:
        valid: float | None = None if math.isnan(validity) else validity
        age = max(0.0, now - t)
        return Record(
            name=name,
            value=pickle.loads(payload),
            timestamp=t,
            age=age,
            stale=valid is not None and age > valid,
            seq=k,
            validity=valid,
        )

    def read(self, name: str) -> Record | None:
        """The newest value of ``name``, flagged ``stale`` past its validity; None if unwritten."""
        i = self._lookup(name)
        if i is None:
            return None
        _, entries = self._snapshot(i, 1)
        if not entries:
            return None
        now = self.clock() - self.origin
        return self._record(name, *entries[0], now)

    def value(self, name: str, default: Any = None, *, fresh: bool = False) -> Any:
        """The newest value, or ``default`` if none (or, with ``fresh``, if it is stale)."""
        rec = self.read(name)
        if rec is None or (fresh and rec.stale):
            return default
        return rec.value

    def history(self, name: str, n: int | None = None) -> list[Record]:
        """Up to ``n`` (default: all kept) most recent values, oldest first."""
        i = self._lookup(name)
        if i is None:
            return []
        n = self.history_len if n is None else max(0, min(n, self.history_len))
        _, entries = self._snapshot(i, n)
        now = self.clock() - self.origin
        return [self._record(name, *e, now) for e in reversed(entries)]

    def records(self) -> list[Record]:
        """The newest value of every record that has one."""
        out = []
        for name in self.names():
            rec = self.read(name)
            if rec is not None:
                out.append(rec)
        return out

    def __repr__(self) -> str:
        state = "closed" if self.closed else f"{self._count()} records"
        return f"RTDB({self.path}, {state})"


@atexit.register
def _close_all() -> None:
    for db in list(_live):
        db.close()
