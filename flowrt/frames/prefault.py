"""Slot pages allocated off the capture path: a thread asks the kernel for them ahead of use.

A fresh shared-memory slot has no pages yet: the first frame written into it pays a page
fault per 4 KiB (the kernel allocates and zeroes each page: about 1 ms per megabyte, far more
on a loaded machine), on whichever thread writes it, usually the event loop. Writing zeros
when the slot is made only moves that cost to its creation, still on the loop: the first
reserve of a pool creates several slots at once, before its first frame is published.

So a slot is made without its pages and queued here; one daemon thread per process asks the
kernel to populate them (``madvise(MADV_POPULATE_WRITE)``, Linux 5.14: pages allocated
writable, contents untouched) through ctypes, which releases the GIL. A producer that writes
the slot before the thread got to it faults the missing pages itself, as it would have anyway:
populating never changes a byte, so the two may overlap safely. Where the kernel refuses
(older kernels, other systems) the slot is zero-filled on the spot, as before.
"""

from __future__ import annotations

import contextlib
import ctypes
import mmap
import queue
import threading

import numpy as np

__all__ = ["prefault", "settled"]

_MADV_POPULATE_WRITE = 23  # linux/mman.h; not in Python's mmap module before 3.13

_libc: ctypes.CDLL | None = None
_supported: bool | None = None  # None: not tried yet
_todo: queue.SimpleQueue[mmap.mmap | threading.Event] = queue.SimpleQueue()
_thread: threading.Thread | None = None
_lock = threading.Lock()


def prefault(mm: mmap.mmap) -> None:
    """Have ``mm``'s pages allocated soon, off the calling thread (else now, by writing)."""
    if _supported is None:
        _probe(mm)
    if not _supported:
        np.frombuffer(mm, dtype=np.uint8)[:] = 0
        return
    _start()
    _todo.put(mm)


def settled(timeout: float = 5.0) -> bool:
    """Wait until every slot queued so far has its pages (for tests and benchmarks)."""
    if _thread is None or not _thread.is_alive():
        return _todo.empty()
    done = threading.Event()
    _todo.put(done)
    return done.wait(timeout)


def _probe(mm: mmap.mmap) -> None:
    """Whether the kernel populates on request (tried on the first slot, synchronously)."""
    global _libc, _supported
    try:
        _libc = ctypes.CDLL(None, use_errno=True)
        _supported = _populate(mm)
    except (OSError, AttributeError):
        _supported = False


def _populate(mm: mmap.mmap) -> bool:
    if mm.closed or _libc is None:
        return True
    buf = ctypes.c_char.from_buffer(mm)
    try:
        address = ctypes.addressof(buf)
    finally:
        del buf  # no export left behind: the slot may close its mapping
    size = ctypes.c_size_t(len(mm))
    return int(_libc.madvise(ctypes.c_void_p(address), size, _MADV_POPULATE_WRITE)) == 0


def _start() -> None:
    global _thread
    with _lock:
        if _thread is None or not _thread.is_alive():
            _thread = threading.Thread(target=_run, name="flowrt-prefault", daemon=True)
            _thread.start()


def _run() -> None:
    while True:
        mm = _todo.get()
        if isinstance(mm, threading.Event):
            mm.set()
            continue
        # A slot closed meanwhile (its pool gone): nothing to do. A mapping closed during the
        # call makes it fail harmlessly (the range is unmapped), never write anything.
        with contextlib.suppress(ValueError, BufferError, OSError):
            _populate(mm)
