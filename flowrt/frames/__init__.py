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
(read-only, except the slots lent to a worker for the frames it makes:
:mod:`flowrt.frames.lending`).

Threading: link counting happens on the event-loop thread of the main process (edges and
activations call ``acquire``/``release``). ``reserve`` and slot recycling take a lock, so a
capture thread may reserve and fill slots while the loop releases others.
"""

from .frame import (
    SHM_DIR,
    SHM_PREFIX,
    Frame,
    StaleFrameError,
    WorkerOutputs,
    release_handoffs,
    set_worker_outputs,
    worker_frame,
)
from .pool import FramePool, FramePoolStats, FrameStore

__all__ = [
    "SHM_DIR",
    "SHM_PREFIX",
    "Frame",
    "FramePool",
    "FramePoolStats",
    "FrameStore",
    "StaleFrameError",
    "WorkerOutputs",
    "release_handoffs",
    "set_worker_outputs",
    "worker_frame",
]
