"""The reader thread of a capture device: opens, reads ahead and releases it off the loop.

A driver call can block for seconds or for good (an unplugged camera, a stalled network
share). The node's event loop therefore never calls a device: a daemon thread per device
does, and hands items to the loop through a deque -- ``("frame", (image, dims, position))``,
``("eof", None)``, ``("error", message)``, ``("alert", (alert, detail))`` or
``("log", lines)`` (what the C libraries printed while the device opened).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from .capture_sources import Device, SourceError
from .capture_stderr import native_stderr

__all__ = ["ALERT", "EOF", "ERROR", "FRAME", "LOG", "Opener", "Reader"]

FRAME, EOF, ERROR, ALERT, LOG = "frame", "eof", "error", "alert", "log"

Opener = Callable[[Callable[[str, str], None], int], Device]
"""Opens the device (in the reader thread): given the thread's alert callback and the stream
position to resume at."""


class Reader:
    """A daemon thread that owns one device: opens, reads ahead and releases it.

    Items go to a deque that the event loop takes from; ``latest`` keeps only the newest
    (cameras: an old frame is worthless), otherwise the thread reads at most ``depth`` frames
    ahead (files: decoding is smoothed, nothing is skipped). The thread alone touches the
    device, so abandoning a reader stuck in a driver call is safe: it releases the device
    whenever the call returns.
    """

    def __init__(
        self,
        name: str,
        opener: Opener,
        loop: asyncio.AbstractEventLoop,
        *,
        latest: bool,
        depth: int = 2,
        rewind: bool = False,
        start: int = 0,
    ) -> None:
        self._opener = opener
        self._start = start
        self._loop = loop
        self._latest = latest
        self._depth = depth
        self._rewind = rewind
        self._items: deque[tuple[str, Any]] = deque()
        self._cond = threading.Condition()
        self._waiter: asyncio.Future[None] | None = None
        self._stop = False
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
        try:
            dev = self._open(self._start)
            while self._room():
                img = dev.read()
                if img is None:
                    if not (self._rewind and dev.rewindable):
                        self._push(EOF, None)
                        return
                    dev.release()
                    dev = None
                    dev = self._open(0)
                    continue
                self._push(FRAME, (img, dev.dims, dev.position))
        except SourceError as e:
            self._push(ERROR, str(e))
        except Exception as e:  # a driver or decoder error: report it, never kill silently
            self._push(ERROR, f"{type(e).__name__}: {e}")
        finally:
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.release()

    # -- loop side

    def take(self) -> tuple[str, Any] | None:
        with self._cond:
            if not self._items:
                return None
            item = self._items.popleft()
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
