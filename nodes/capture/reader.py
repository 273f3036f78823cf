"""The reader thread of a capture device: opens, reads ahead and releases it off the loop.

A driver call can block for seconds or for good (an unplugged camera, a stalled network
share). The node's event loop therefore never calls a device: a daemon thread per device
does, and hands items to the loop through a deque -- ``("frame", (image, dims, position,
blank))``, ``("eof", None)``, ``("error", message)``, ``("alert", (alert, detail))`` or
``("log", lines)`` (what the C libraries printed while the device opened).

Blanks: the loop may :meth:`Reader.lend` the thread arrays to decode into (the pixels of
frames in shared-memory slots), each with a token of its own; a frame item names the blank it
was decoded into (or None) and :meth:`Reader.reclaim` gives its token back. A decoded frame is
then already in its slot: the loop publishes it without copying a pixel. Tokens of blanks the
thread never used come back from :meth:`Reader.unused` once it has ended (never while it may
still be writing into one).

Priority: the thread inherits the event loop's (SCHED_FIFO 90 under ``--realtime``, the
lowest nice otherwise), above every worker. A ``background`` reader (a file or image sequence
read at ``pacing: fast`` for readers in workers: the source follows them) lowers itself under
``--realtime`` before it opens the device, so that FFmpeg's decoding threads, created by the
open, inherit the lower priority too: it only has to stay a few frames ahead of trackers
that wait for every frame, and at the loop's priority it preempted them in the middle of
their calls. See :func:`lower_priority`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from .sources import Device, SourceError
from .stderr import native_stderr

__all__ = ["ALERT", "EOF", "ERROR", "FRAME", "LOG", "Opener", "Reader", "lower_priority"]

FRAME, EOF, ERROR, ALERT, LOG = "frame", "eof", "error", "alert", "log"

Opener = Callable[[Callable[[str, str], None], int], Device]
"""Opens the device (in the reader thread): given the thread's alert callback and the stream
position to resume at."""


def lower_priority() -> str:
    """Put the calling thread below the graph's workers; what it now runs at (for the log).

    Only under SCHED_FIFO (a ``--realtime`` loop): the thread takes SCHED_FIFO 1, the lowest
    real-time priority, below every worker (1..89 from their flowrt priority) and still above
    every ordinary program of the machine. Under the fair scheduler it keeps the loop's nice
    level: ten levels higher it lost to the machine's other programs at the loop's level (on
    the loaded 2-CPU machine, graphs/video.yaml with its tracker in a worker went from 0.68x
    to 0.60x of a plain OpenCV loop), and a level between is not measured. Linux applies it
    to the calling thread only; elsewhere, or when refused, nothing changes.
    """
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            return "SCHED_FIFO 1"
    except (AttributeError, OSError):
        pass
    return "inherited"


class Reader:
    """A daemon thread that owns one device: opens, reads ahead and releases it.

    Items go to a deque that the event loop takes from; ``latest`` keeps only the newest
    (cameras: an old frame is worthless), otherwise the thread reads at most ``depth`` frames
    ahead (files: decoding is smoothed, nothing is skipped) and is woken only once the loop
    has taken half of them: every wake-up makes the thread take the GIL back from the loop
    for its few lines of Python before the decoder lets go of it, and woken per frame that
    cost the loop 0.09 ms p50 per frame (the gap between a paced capture's activation and its
    tracker's, benchmarks/bench_video.py's offline run); woken per two frames, 0.001 ms. The
    thread alone touches the device, so abandoning a reader stuck in a driver call is safe: it
    releases the device whenever the call returns.
    """

    def __init__(
        self,
        name: str,
        opener: Opener,
        loop: asyncio.AbstractEventLoop,
        *,
        latest: bool,
        depth: int = 4,
        rewind: bool = False,
        start: int = 0,
        background: bool = False,
    ) -> None:
        self._opener = opener
        self._background = background
        self.priority = "inherited"  # what the thread runs at (lower_priority's answer)
        self._start = start
        self._loop = loop
        self._latest = latest
        self._depth = depth
        self._low = max(0, depth // 2)
        self._rewind = rewind
        self._items: deque[tuple[str, Any]] = deque()
        self._cond = threading.Condition()
        self._waiter: asyncio.Future[None] | None = None
        self._stop = False
        self._blanks: deque[np.ndarray] = deque()
        self._lent: dict[int, tuple[np.ndarray, Any]] = {}  # id(blank) -> (blank, token)
        self.delivered = 0
        self.thread = threading.Thread(target=self._run, name=f"flowrt-capture-{name}", daemon=True)
        self.thread.start()

    # -- thread side

    def _push(self, kind: str, value: Any) -> None:
        with self._cond:
            if self._stop:
                return
            if kind == FRAME and self._latest:
                for i, queued in enumerate(self._items):
                    if queued[0] == FRAME:  # keep only the newest frame
                        del self._items[i]
                        break
            self._items.append((kind, value))
            waiter = self._waiter
        if waiter is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nobody is waiting
                self._loop.call_soon_threadsafe(_wake, waiter)

    def _alert(self, alert: str, detail: str) -> None:
        self._push(ALERT, (alert, detail))

    def _room(self) -> bool:
        with self._cond:
            while not self._stop and not self._latest:
                if sum(1 for i in self._items if i[0] == FRAME) < self._depth:
                    break
                self._cond.wait()
            return not self._stop

    def _open(self, start: int) -> Device:
        lines: list[str] = []
        try:
            with native_stderr(lines):
                return self._opener(self._alert, start)
        finally:
            if lines:
                self._push(LOG, lines)

    def _run(self) -> None:
        dev: Device | None = None
        if self._background:  # before the open: the decoder's own threads inherit it
            self.priority = lower_priority()
        try:
            dev = self._open(self._start)
            while self._room():
                try:
                    blank: np.ndarray | None = self._blanks.popleft()
                except IndexError:
                    blank = None
                img = dev.read() if blank is None else dev.read(blank)
                if img is None:
                    if blank is not None:
                        self._blanks.appendleft(blank)
                    if not (self._rewind and dev.rewindable):
                        self._push(EOF, None)
                        return
                    dev.release()
                    dev = None
                    dev = self._open(0)
                    continue
                self._push(FRAME, (img, dev.dims, dev.position, blank))
        except SourceError as e:
            self._push(ERROR, str(e))
        except Exception as e:  # a driver or decoder error: report it, never kill silently
            self._push(ERROR, f"{type(e).__name__}: {e}")
        finally:
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.release()

    # -- loop side

    @property
    def lent(self) -> int:
        """How many blanks are out: lent and not yet reclaimed."""
        return len(self._lent)

    def lend(self, blank: np.ndarray, token: Any) -> None:
        """Give the thread ``blank`` to decode a frame into; ``token`` comes back with it."""
        self._lent[id(blank)] = (blank, token)
        self._blanks.append(blank)

    def reclaim(self, blank: np.ndarray | None) -> Any:
        """The token of the blank a frame item names (None for none)."""
        if blank is None:
            return None
        entry = self._lent.pop(id(blank), None)
        return None if entry is None else entry[1]

    def unused(self) -> list[Any]:
        """Once the thread has ended: the tokens of the blanks it never handed back (the
        rest: the frame items dropped by :meth:`stop`, or blanks never used)."""
        if self.thread.is_alive():
            return []
        tokens = [token for _, token in self._lent.values()]
        self._lent.clear()
        self._blanks.clear()
        return tokens

    def take(self) -> tuple[str, Any] | None:
        with self._cond:
            if not self._items:
                return None
            item = self._items.popleft()
            if len(self._items) <= self._low:
                self._cond.notify()
        if item[0] == FRAME:
            self.delivered += 1
        return item

    async def get(self, wait: float) -> tuple[str, Any] | None:
        """The next item, or None after ``wait`` seconds without one."""
        item = self.take()
        if item is not None or wait <= 0:
            return item
        with self._cond:
            if not self._items:
                self._waiter = self._loop.create_future()
            waiter = self._waiter
        if waiter is not None:
            try:
                await asyncio.wait_for(waiter, wait)
            except TimeoutError:
                pass
            finally:
                with self._cond:
                    self._waiter = None
        return self.take()

    def stop(self) -> None:
        """Ask the thread to end; it releases the device as soon as its current call returns."""
        with self._cond:
            self._stop = True
            self._items.clear()
            self._cond.notify_all()


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
