"""Raw frames put from Zenoh shared memory: one copy of the pixels fewer on the sending side.

Zenoh takes a payload as ``bytes`` and copies it into a buffer of its own; with its default
transport optimisation a large payload bound for a peer on this host is then copied again into
Zenoh's shared memory. A buffer allocated from a :class:`zenoh.shm.ShmProvider` and filled once
is put as it is: a subscriber on this host maps it (no copy through the socket), one on another
machine gets its bytes through the socket as before (Zenoh serialises a shared buffer for a link
without shared memory). Measured on a 1920x1080 BGR frame, one host (benchmarks/RESULTS.md):
flowrt's copies and `put` 0.91 -> 0.70 ms, a plain program's frame latency 1.65 -> 1.3 ms.

Used only when the session enables shared memory (``transport/shared_memory/enabled``, Zenoh's
default) and for payloads of at least :data:`MIN_BYTES`. A buffer is not reused while a
subscriber holds it: when the pool has none free (a subscriber slower than the export) the
payload is put as bytes, counted in :attr:`ShmFrames.fallbacks` (not a loss: it is sent).
"""

from __future__ import annotations

import logging
import os
from typing import Any

__all__ = ["MIN_BYTES", "POOL_FRAMES", "ShmFrames", "shm_free"]

log = logging.getLogger("flowrt.remote._bridge")

MIN_BYTES = 64 * 1024  # smaller payloads: Zenoh's own path is as fast (allocation costs ~us)
POOL_FRAMES = 4  # frames the pool holds: one being filled, the rest still read by subscribers
_SLACK = 1 << 20  # the allocator's own room: 4 x 5 MiB do not fit in 20 MiB, they do in 21


class ShmFrames:
    """The export sender's shared-memory pool (used from the sender thread only).

    Invariant: ``size >= POOL_FRAMES * largest payload put from it + _SLACK`` (a larger
    payload makes a new, larger pool; the old one's buffers stay valid while read)."""

    def __init__(self) -> None:
        self.provider: Any = None
        self.size = 0  # bytes of the current pool
        self.fallbacks = 0  # payloads put as bytes: no buffer free, or no pool could be made
        self.failed = False  # no pool could be made (/dev/shm short): bytes from then on
        self._policy: Any = None

    def payload(self, data: bytes) -> Any:
        """``data`` in a shared buffer of Zenoh's, or ``data`` itself when none is free."""
        n = len(data)
        if n < MIN_BYTES or self.failed:
            return data
        try:
            if n * POOL_FRAMES + _SLACK > self.size:
                self._grow(n)
            buf = self.provider.alloc(n, self._policy)
        except Exception as e:  # zenoh.ZError: out of memory (every buffer still read)
            self.fallbacks += 1
            if self.provider is None:
                self.failed = True
                log.warning("zenoh shared memory unavailable, frames sent as bytes: %s", e)
            return data
        buf[0:n] = data  # one copy, into the shared buffer
        return buf

    def _grow(self, n: int) -> None:
        import zenoh.shm as zshm

        size = -(-(n * POOL_FRAMES + _SLACK) // (1 << 20)) << 20  # whole MiB
        self.provider = None  # dropped first: if no new one can be made, bytes from then on
        free = shm_free()
        if free is not None and free < 2 * size:  # a tmpfs filled past its end is a SIGBUS
            raise OSError(f"/dev/shm has {free >> 20} MiB free, the pool takes {size >> 20}")
        self.provider = zshm.ShmProvider.default_backend(size)
        self.size = size
        self._policy = zshm.GarbageCollect()  # reclaim the buffers readers let go, never wait


def shm_free() -> int | None:
    """Bytes free in /dev/shm (a container's is 64 MiB unless raised), None where there is
    none to ask: a pool is made only with room for it twice over."""
    try:
        st = os.statvfs("/dev/shm")
    except OSError:
        return None
    return st.f_bavail * st.f_frsize
