"""A write-only file with direct I/O: the writer's bytes go to the disk without the page cache.

Why: on the development VM, writing through the page cache runs at 150-220 MB/s while the
same disk takes 900+ MB/s with ``O_DIRECT`` (``dd``, measured in the same run; see
benchmarks/RESULTS.md), and two 1936x1216 cameras at 20 fps need 282 MB/s. ``mcap``'s
writer only needs ``write``, ``tell`` and ``flush`` from its stream, so this class gives it
those over an ``O_DIRECT`` descriptor: bytes are gathered in a page-aligned buffer and
written in whole blocks. ``flush`` writes the partial last block padded with zeros (zeroed
explicitly: the buffer is reused; it is written again, complete, later); ``close`` cuts the
file to its length. A killed writer
leaves at most one block of zero padding after the last record, which readers report as the
end of a truncated file.
"""

from __future__ import annotations

import contextlib
import fcntl
import mmap
import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from .gilfree import Gathered, copy_into

__all__ = ["DirectFile", "open_direct"]

BLOCK = 4096
BUFFER = 8 << 20


class DirectFile:
    """``write``/``tell``/``flush``/``close`` over an ``O_DIRECT`` file descriptor.

    Double buffered: a full buffer is written by a thread of its own (``pwrite`` releases the
    GIL) while the caller fills the other, so the disk works while the writer copies and
    computes CRCs instead of after (a direct write of 8 MB blocks ~5 ms). A write error of the
    background thread is raised by the next ``write``, ``flush`` or ``close``.
    Invariant: at most one buffer is being written; ``_done`` counts the bytes handed to
    ``pwrite`` (whole buffers), so ``tell`` is the logical position whatever is in flight.
    """

    def __init__(self, fd: int, capacity: int = BUFFER) -> None:
        self._fd = fd
        # page aligned, as O_DIRECT requires
        self._bufs = (mmap.mmap(-1, capacity), mmap.mmap(-1, capacity))
        self._buf = self._bufs[0]
        self._cap = capacity
        self._fill = 0
        self._done = 0  # bytes in whole buffers handed to the disk (a multiple of capacity)
        self._buffered = False  # O_DIRECT dropped after a short write
        self._disk = ThreadPoolExecutor(1, thread_name_prefix="flowrt-direct-io")
        self._inflight: Future[None] | None = None
        self.closed = False

    gathers = True  # write() takes a Gathered list of buffers (.chunking: chunks not joined)

    def write(self, data: Any) -> int:
        if isinstance(data, Gathered):
            return sum(self.write(part) for part in data)
        mv = memoryview(data).cast("B")
        total = len(mv)
        while mv:
            n = min(len(mv), self._cap - self._fill)
            copy_into(self._buf, self._fill, mv[:n])  # the GIL released: see .gilfree
            self._fill += n
            mv = mv[n:]
            if self._fill == self._cap:
                self._wait()
                full, at = self._buf, self._done
                self._inflight = self._disk.submit(self._pwrite, full, self._cap, at)
                self._done += self._cap
                self._fill = 0
                self._buf = self._bufs[1] if full is self._bufs[0] else self._bufs[0]
        return total

    def _wait(self) -> None:
        """The buffer in flight is on disk (its error, if any, raised here)."""
        pending, self._inflight = self._inflight, None
        if pending is not None:
            pending.result()

    def tell(self) -> int:
        return self._done + self._fill

    def flush(self) -> None:
        """Put what is buffered on disk (the last block padded); the buffer keeps it."""
        self._wait()
        if self._fill:
            end = -(-self._fill // BLOCK) * BLOCK
            # The buffer is reused: past the data it holds bytes of an earlier buffer. They
            # are zeroed, so a writer killed now leaves zeros after its last record, never
            # stale records a stream reader would try to parse ("record length too large").
            self._buf[self._fill : end] = bytes(end - self._fill)
            self._pwrite(self._buf, end, self._done)

    def fileno(self) -> int:
        return self._fd

    def _pwrite(self, buf: mmap.mmap, length: int, at: int) -> None:
        with memoryview(buf) as whole, whole[:length] as view:
            written = 0
            while written < length:
                n = os.pwrite(self._fd, view[written:], at + written)
                if 0 < n < length - written and not self._buffered:
                    # A short direct write (the disk or the size limit is reached): the rest
                    # is unaligned, so go on without O_DIRECT, and the real error shows.
                    flags = fcntl.fcntl(self._fd, fcntl.F_GETFL)
                    fcntl.fcntl(self._fd, fcntl.F_SETFL, flags & ~os.O_DIRECT)
                    self._buffered = True
                written += n

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.flush()
            os.ftruncate(self._fd, self.tell())
        finally:
            with contextlib.suppress(OSError):
                self._wait()  # the error, if any, was raised by flush
            self._disk.shutdown(wait=True)
            os.close(self._fd)
            for buf in self._bufs:
                with contextlib.suppress(BufferError):  # a view held by a traceback
                    buf.close()


def open_direct(path: str | os.PathLike[str]) -> DirectFile | None:
    """Create ``path`` for direct I/O, or None where the file system refuses it (tmpfs)."""
    flag = getattr(os, "O_DIRECT", 0)
    if not flag:
        return None
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | flag, 0o644)
    except OSError as e:
        if e.errno == 22:  # EINVAL: no direct I/O here
            return None
        raise
    return DirectFile(fd)
