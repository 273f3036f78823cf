"""Edge buffers: one per connected input, so a slow reader never slows a fast one.

- ``LatestBuffer``: the cyclic asynchronous buffer. The writer never waits and the reader
  always gets the newest value. A value replaced before anyone read it is ``unread`` when the
  reader samples (a period-4 reader runs on one frame in four by design) and ``dropped`` when
  the reader wanted it: an input-triggered reader, or a sampling reader whose release for that
  value was skipped (overrun, restart).
- ``QueueBuffer``: bounded FIFO that drops the oldest when full (counted).
- ``LosslessBuffer``: bounded FIFO whose producer waits when it is full (for recorders).

Frames are link counted: a buffer holds one link on every frame it stores and gives it up
when the frame is replaced, dropped or handed over to an activation.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Any

from .frames import Frame
from .stats import EdgeStats, Running


class _Empty:
    def __repr__(self) -> str:
        return "EMPTY"


EMPTY: Any = _Empty()
OVERWRITTEN = "overwritten"
"""A latest edge's value replaced before a reader that wanted it took it."""
QUEUE_FULL = "queue full"
"""A queue edge's oldest value dropped for a new one (the writer never waits)."""


def hold(value: Any) -> None:
    """Take a link on a frame (other values need none)."""
    if isinstance(value, Frame):
        value.acquire()


def _drop(value: Any) -> None:
    if isinstance(value, Frame):
        value.release()


class Buffer:
    """Common counters and the reader's wake-up hook."""

    policy = "queue"

    def __init__(self, name: str, size: int = 1, clock: Callable[[], float] | None = None) -> None:
        import time

        self.name = name
        self.size = size
        self.published = 0
        self.delivered = 0
        self.dropped = 0  # values lost: the reader wanted them (see the module docstring)
        self.unread = 0  # values a sampling reader never needed: by design, not a loss
        self.sampled = False
        self.age = Running()
        self.now = clock or time.monotonic
        self.on_put: Callable[[], None] | None = None
        # every drop by its reason (their sum is ``dropped``): overwritten / queue full while
        # running, the stop's and the drain's at the end (a burst behind a queue of 8 was
        # counted with no reason)
        self.drop_reasons: dict[str, int] = {}
        self._last_seq = -1
        # Runtime-clock time at which the value last returned by take() was published here:
        # what freshness is judged on (NodeContext.input_time), never the value's identity.
        self.taken_t: float | None = None
        # The sequence number (1, 2, ... per edge: the n-th value its producer published) of
        # the value last returned by take(), or None when take() returned EMPTY: what a
        # deterministic recording says each activation held (flowrt.determinism).
        self.taken_seq: int | None = None

    def put(self, value: Any, t: float) -> bool:
        """Store a value published at time ``t``; False when a lossless buffer is full."""
        raise NotImplementedError

    def take(self) -> Any:
        """The value for an activation (the caller owns one link on a frame), or EMPTY."""
        raise NotImplementedError

    def pending(self) -> int:
        """Values not yet delivered."""
        raise NotImplementedError

    def clear(self) -> None:
        raise NotImplementedError

    def discard(self, reason: str) -> int:
        """Drop every value still waiting (at stop), counted as dropped with ``reason``."""
        n = self.pending()
        if n:
            self.dropped += n
            self.drop_reasons[reason] = self.drop_reasons.get(reason, 0) + n
        self.clear()
        return n

    def abandon(self, value: Any, reason: str) -> None:
        """A value its producer could not put (a lossless edge full at stop): published, lost.

        Keeps ``published == delivered + dropped`` true for values that never got in.
        """
        self.published += 1
        self.dropped += 1
        self.drop_reasons[reason] = self.drop_reasons.get(reason, 0) + 1
        _drop(value)

    def reader_skipped(self) -> None:
        """The reader was released for the value now held but could not run (overrun, down).

        A queue keeps the value for the next run; a latest buffer counts it as dropped, not
        unread, if it is replaced before being read.
        """

    def _delivered(self, seq: int, t: float) -> None:
        assert seq >= self._last_seq, "a reader saw an older message after a newer one"
        self._last_seq = seq
        self.delivered += 1
        self.age.add(self.now() - t)

    def stats(self) -> EdgeStats:
        return EdgeStats(
            name=self.name,
            policy=self.policy,
            size=self.size,
            published=self.published,
            delivered=self.delivered,
            dropped=self.dropped,
            drop_reasons=dict(self.drop_reasons),
            unread=self.unread,
            sampled=self.sampled,
            age=self.age.summary(),
        )


class LatestBuffer(Buffer):
    """Newest value only. A reader may read the same value again if nothing newer came."""

    policy = "latest"

    def __init__(self, name: str, size: int = 1, clock: Callable[[], float] | None = None) -> None:
        super().__init__(name, 1, clock)
        self._value: Any = EMPTY
        self._t = 0.0
        self._seq = -1
        self._read = True
        self._due = False  # the reader was released for the value held and skipped it

    def put(self, value: Any, t: float) -> bool:
        self.published += 1
        old = self._value
        if old is not EMPTY:
            if not self._read:
                if self.sampled and not self._due:
                    self.unread += 1
                else:
                    self.dropped += 1
                    self.drop_reasons[OVERWRITTEN] = self.drop_reasons.get(OVERWRITTEN, 0) + 1
            _drop(old)
        self._due = False
        hold(value)
        self._value, self._t, self._seq, self._read = value, t, self.published, False
        if self.on_put is not None:
            self.on_put()
        return True

    def take(self) -> Any:
        if self._value is EMPTY:
            self.taken_seq = None
            return EMPTY
        if not self._read:
            self._read = True
            self._delivered(self._seq, self._t)
        hold(self._value)
        self.taken_t = self._t
        self.taken_seq = self._seq
        return self._value

    def reader_skipped(self) -> None:
        self._due = not self._read and self._value is not EMPTY

    def take_new(self) -> Any:
        """Like take, but EMPTY when the newest value was already delivered."""
        if self._read:
            self.taken_seq = None
            return EMPTY
        return self.take()

    def pending(self) -> int:
        return 0 if self._read or self._value is EMPTY else 1

    def clear(self) -> None:
        if self._value is not EMPTY:
            _drop(self._value)
        self._value = EMPTY
        self._read = True


class QueueBuffer(Buffer):
    """Bounded FIFO; when full the oldest value is dropped and counted (the writer never waits)."""

    policy = "queue"

    def __init__(self, name: str, size: int = 8, clock: Callable[[], float] | None = None) -> None:
        super().__init__(name, size, clock)
        self._q: deque[tuple[int, float, Any]] = deque()

    def put(self, value: Any, t: float) -> bool:
        self.published += 1
        if len(self._q) >= self.size:
            _, _, old = self._q.popleft()
            self.dropped += 1
            self.drop_reasons[QUEUE_FULL] = self.drop_reasons.get(QUEUE_FULL, 0) + 1
            _drop(old)
        hold(value)
        self._q.append((self.published, t, value))
        if self.on_put is not None:
            self.on_put()
        return True

    def take(self) -> Any:
        if not self._q:
            self.taken_seq = None
            return EMPTY
        seq, t, value = self._q.popleft()
        self._delivered(seq, t)
        self.taken_t = t
        self.taken_seq = seq
        return value

    def take_new(self) -> Any:
        return self.take()

    def pending(self) -> int:
        return len(self._q)

    def clear(self) -> None:
        while self._q:
            _drop(self._q.popleft()[2])


class LosslessBuffer(QueueBuffer):
    """Bounded FIFO that never drops: ``put`` refuses when full and the producer waits."""

    policy = "lossless"

    def __init__(self, name: str, size: int = 8, clock: Callable[[], float] | None = None) -> None:
        super().__init__(name, size, clock)
        self._space = asyncio.Event()
        # Called when a put finds the buffer full: the reader must take now, whatever its
        # trigger says, or the waiting producer (and every tick it would make) stops for good.
        self.on_full: Callable[[], None] | None = None

    def put(self, value: Any, t: float) -> bool:
        if len(self._q) >= self.size:
            if self.on_full is not None:
                self.on_full()
            return False
        return super().put(value, t)

    async def wait_space(self) -> None:
        while len(self._q) >= self.size:
            self._space.clear()
            await self._space.wait()

    def take(self) -> Any:
        value = super().take()
        if value is not EMPTY:
            self._space.set()
        return value

    def clear(self) -> None:
        super().clear()
        self._space.set()


def make_buffer(
    policy: str, name: str, size: int, clock: Callable[[], float] | None = None
) -> Buffer:
    cls = {"latest": LatestBuffer, "queue": QueueBuffer, "lossless": LosslessBuffer}[policy]
    return cls(name, size, clock)
