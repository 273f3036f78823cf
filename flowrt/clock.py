"""Clocks: where the scheduler gets time and timers, so tests can run on virtual time.

``SystemClock`` drives periodic timers with a Linux timerfd registered on the event loop:
asyncio/libuv sleeps have ~1 ms granularity and drift under load, a timerfd with absolute
expiry times has neither (≈0.03 ms std at 20 Hz on the dev machine). All the periodic timers
of a loop share one timerfd, and those due at the same instant fire in the order they were
made (the scheduler's priority order), after a single wake-up. Elsewhere it falls back to
``loop.call_at`` on absolute times, which does not drift but is coarser.

``VirtualClock`` holds time still until a test advances it, firing due callbacks in order.
"""

from __future__ import annotations

import asyncio
import ctypes
import heapq
import itertools
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Protocol

TickCallback = Callable[[float, int], None]
"""Called with the nominal release time of a periodic tick and the number of ticks missed."""


class Handle(Protocol):
    def cancel(self) -> None: ...


class PeriodicTimer(Protocol):
    def cancel(self) -> None: ...

    def reset(self, period: float, phase: float) -> None:
        """New period/phase (seconds) from the next tick on, aligned to the clock's origin."""
        ...


class Clock(Protocol):
    origin: float

    def now(self) -> float: ...

    def call_at(self, when: float, callback: Callable[[], None]) -> Handle: ...

    def periodic(self, period: float, phase: float, callback: TickCallback) -> PeriodicTimer: ...


def next_release(origin: float, period: float, phase: float, after: float) -> tuple[float, int]:
    """First ``origin + phase + k*period`` strictly after ``after``, and its k."""
    k = max(0, math.floor((after - origin - phase) / period) + 1)
    return origin + phase + k * period, k


# --- the system clock -------------------------------------------------------------------

_CLOCK_MONOTONIC = 1
_TFD_NONBLOCK = 0o4000
_TFD_CLOEXEC = 0o2000000
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _load_libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        # libc's own timerfd, not one a preloaded library interposes (libfaketime, which the
        # clock-offset tests use to put a machine's wall clock off, shifts monotonic timers too)
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
        except OSError:  # not glibc (musl): the process's own symbols
            libc = ctypes.CDLL(None, use_errno=True)
        libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.timerfd_settime.argtypes = [
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_Itimerspec),
            ctypes.c_void_p,
        ]
        return libc
    except (OSError, AttributeError):
        return None


_LIBC = _load_libc()


def _ns(seconds: float) -> int:
    return round(seconds * 1e9)


def _ts(seconds: float) -> _Timespec:
    sec = math.floor(seconds)
    return _Timespec(sec, round((seconds - sec) * 1e9))


class _TimerfdTimer:
    """A periodic timer on its clock's shared timerfd (:class:`_TimerfdWheel`)."""

    __slots__ = ("_callback", "_clock", "_next", "_wheel", "dead", "index", "period", "version")

    def __init__(
        self, clock: SystemClock, period: float, phase: float, callback: TickCallback
    ) -> None:
        self._clock = clock
        self._callback = callback
        self._wheel = clock._wheel()
        self.index = self._wheel.add()
        self.version = 0
        self.dead = False
        self.reset(period, phase)

    def reset(self, period: float, phase: float) -> None:
        if self.dead:
            return
        self.period = period
        self._next, _ = next_release(self._clock.origin, period, phase, time.monotonic())
        self.version += 1
        self._wheel.push(self)

    def cancel(self) -> None:
        if not self.dead:
            self.dead = True
            self._wheel.remove()


class _TimerfdWheel:
    """Every periodic timer of a clock on one loop, on one timerfd armed for the earliest.

    Why one: timers that fall due together (a 10 ms CAN transmitter and eight 100 ms signal
    sources every tenth tick) each had a timerfd of their own, and the loop read them in
    whatever order epoll gave, so the most important node's activation was queued behind the
    reads and releases of the others (~0.15 ms every tenth tick on the dev machine: the CAN
    transmitter's p99). Here the due timers fire in their creation order, which the scheduler
    makes its priority order (higher first), after a single wake-up and read; the first one's
    activation comes before the others are released (``loop.call_soon``); a heap keeps
    the next releases, so a wake-up costs O(log n) per timer due, whatever the number of
    timers. The kernel keeps the expiry as an absolute time, so nothing drifts.
    """

    def __init__(self, clock: SystemClock, loop: asyncio.AbstractEventLoop) -> None:
        assert _LIBC is not None
        self._clock = clock
        self._loop = loop
        # (next release in ns, creation index, version, timer): in ns, so that the same
        # instant reached by two periods (10 x 10 ms, 1 x 100 ms) ties, and the index decides
        self._heap: list[tuple[int, int, int, _TimerfdTimer]] = []
        self._live = 0
        self._count = itertools.count()
        self._armed = math.inf
        self._fd = _LIBC.timerfd_create(_CLOCK_MONOTONIC, _TFD_NONBLOCK | _TFD_CLOEXEC)
        if self._fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create failed")
        loop.add_reader(self._fd, self._on_readable)

    def add(self) -> int:
        self._live += 1
        return next(self._count)

    def push(self, timer: _TimerfdTimer) -> None:
        heapq.heappush(self._heap, (_ns(timer._next), timer.index, timer.version, timer))
        if timer._next < self._armed:
            self._arm(timer._next)

    def remove(self) -> None:
        self._live -= 1
        if self._live <= 0:
            self.close()

    def close(self) -> None:
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1
        self._heap.clear()
        if self._clock._wheels.get(self._loop) is self:
            del self._clock._wheels[self._loop]

    def _top(self) -> float:
        """The earliest live release (stale heap entries dropped on the way)."""
        heap = self._heap
        while heap:
            _, _, version, t = heap[0]
            if not t.dead and version == t.version:
                return t._next
            heapq.heappop(heap)
        return math.inf

    def _arm(self, first: float) -> None:
        """Arm the timerfd for ``first`` (``spin`` early: the loop spins the rest)."""
        assert _LIBC is not None
        if self._fd < 0:
            return
        self._armed = first
        when = _ts(first - self._clock.spin) if first < math.inf else _Timespec(0, 0)
        spec = _Itimerspec(_Timespec(0, 0), when)
        if _LIBC.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            raise OSError(ctypes.get_errno(), "timerfd_settime failed")

    def _on_readable(self) -> None:
        try:
            os.read(self._fd, 8)
        except BlockingIOError:
            return
        self._armed = math.inf
        if self._clock.spin:
            first = self._top()
            if first < math.inf:
                spin_until(first)
        if before_timers is not None:
            before_timers()  # a precise node's call at this instant goes first (kernel/precise)
        now = time.monotonic()
        due = _ns(now)
        heap = self._heap
        pop, push = heapq.heappop, heapq.heappush
        first = True
        rest: list[tuple[_TimerfdTimer, float, int]] = []
        while heap and heap[0][0] <= due:
            _, index, version, t = pop(heap)
            if t.dead or version != t.version:
                continue
            when = t._next
            if when > now:  # within the rounding of a nanosecond: never early
                push(heap, (_ns(when), index, version, t))
                break
            missed = int((now - when) // t.period)
            release = when + missed * t.period
            t._next = release + t.period
            push(heap, (_ns(t._next), index, version, t))
            # In (release, creation) order, the heap's. The first at once; the others after
            # what it starts (the scheduler queues the activation it releases), in one batch:
            # the most important node's activation does not wait for the others' releases.
            if first:
                first = False
                t._callback(release, missed)
            else:
                rest.append((t, release, missed))
        if rest:
            self._loop.call_soon(self._fire, rest)
        # Armed again after what the callbacks started (the activations they released are
        # queued first): the timerfd_settime call (~30 us cold, through ctypes) must not sit
        # between a release and its activation. A timer a callback resets arms on its own.
        self._loop.call_soon(self._rearm)

    @staticmethod
    def _fire(due: list[tuple[_TimerfdTimer, float, int]]) -> None:
        for t, release, missed in due:
            if not t.dead:
                t._callback(release, missed)

    def _rearm(self) -> None:
        if self._armed == math.inf:
            self._arm(self._top())


class _LoopTimer:
    """Fallback periodic timer on ``loop.call_at`` with absolute release times (no drift)."""

    def __init__(
        self, clock: SystemClock, period: float, phase: float, callback: TickCallback
    ) -> None:
        self._clock = clock
        self._callback = callback
        self._loop = asyncio.get_running_loop()
        self._handle: asyncio.TimerHandle | None = None
        self.reset(period, phase)

    def reset(self, period: float, phase: float) -> None:
        self.cancel()
        self.period = period
        self._phase = phase
        self._next, _ = next_release(self._clock.origin, period, phase, time.monotonic())
        self._arm()

    def _arm(self) -> None:
        delay = self._next - time.monotonic()
        self._handle = self._loop.call_later(max(0.0, delay), self._fire)

    def _fire(self) -> None:
        now = time.monotonic()
        missed = max(0, math.floor((now - self._next) / self.period))
        release = self._next + missed * self.period
        self._next = release + self.period
        self._arm()
        self._callback(release, missed)

    def cancel(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None


class _LoopHandle:
    def __init__(self, handle: asyncio.TimerHandle) -> None:
        self._handle = handle

    def cancel(self) -> None:
        self._handle.cancel()


before_timers: Callable[[], None] | None = None
"""Called by the loop's timerfd wheel before it fires due timers: set by
:mod:`flowrt.kernel.precise` while precise nodes run, so that the loop's timers falling due
at a precise node's instant wait for its call (bounded) instead of taking turns with it on
the GIL."""


def set_before_timers(hook: Callable[[], None] | None) -> None:
    """Set (None: clear) :data:`before_timers`: one writer, by name, for the kernel."""
    global before_timers
    before_timers = hook


def spin_until(when: float) -> None:
    """Busy-wait until ``when`` (monotonic seconds); returns at once if it has passed."""
    now = time.monotonic
    while now() < when:
        pass


class SystemClock:
    """Monotonic time (CLOCK_MONOTONIC), timerfd periodic timers, loop one-shot timers.

    ``spin`` (seconds) trades CPU for wake-up precision: periodic timers fire that long before
    each release and the loop busy-waits the rest. A sleeping CPU takes tens to hundreds of
    microseconds to wake, and more under a hypervisor, varying from tick to tick; a spinning
    one is already awake. The cost is ``spin`` of CPU per release.
    """

    def __init__(self, use_timerfd: bool = True, spin: float = 0.0) -> None:
        self.origin = time.monotonic()
        self.use_timerfd = use_timerfd and _LIBC is not None
        if not 0.0 <= spin < 0.1:
            raise ValueError(f"spin must be in [0, 100 ms), got {spin * 1e3:g} ms")
        self.spin = spin
        self._wheels: dict[asyncio.AbstractEventLoop, _TimerfdWheel] = {}

    def _wheel(self) -> _TimerfdWheel:
        loop = asyncio.get_running_loop()
        wheel = self._wheels.get(loop)
        if wheel is None:
            wheel = self._wheels[loop] = _TimerfdWheel(self, loop)
        return wheel

    def now(self) -> float:
        return time.monotonic()

    def call_at(self, when: float, callback: Callable[[], None]) -> Handle:
        loop = asyncio.get_running_loop()
        return _LoopHandle(loop.call_later(max(0.0, when - time.monotonic()), callback))

    def periodic(self, period: float, phase: float, callback: TickCallback) -> PeriodicTimer:
        if self.use_timerfd:
            try:
                return _TimerfdTimer(self, period, phase, callback)
            except OSError:
                self.use_timerfd = False
        return _LoopTimer(self, period, phase, callback)


# --- virtual time -------------------------------------------------------------------------


class _VirtualEntry:
    __slots__ = ("callback", "cancelled")

    def __init__(self, callback: Callable[[], None]) -> None:
        self.callback = callback
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class _VirtualPeriodic:
    def __init__(
        self, clock: VirtualClock, period: float, phase: float, callback: TickCallback
    ) -> None:
        self._clock = clock
        self._callback = callback
        self._entry: _VirtualEntry | None = None
        self.reset(period, phase)

    def reset(self, period: float, phase: float) -> None:
        self.cancel()
        self.period = period
        # A tick due exactly now still fires: virtual time does not move on its own.
        self._next, _ = next_release(self._clock.origin, period, phase, self._clock.now() - 1e-12)
        self._entry = self._clock._schedule(self._next, self._fire)

    def _fire(self) -> None:
        release = self._next
        self._next = release + self.period
        self._entry = self._clock._schedule(self._next, self._fire)
        self._callback(release, 0)

    def cancel(self) -> None:
        if self._entry is not None:
            self._entry.cancel()
            self._entry = None


class VirtualClock:
    """Time that moves only when ``advance`` is awaited: deterministic scheduler tests.

    Between due callbacks the event loop gets a few turns, so tasks the callbacks started
    (activations, publications) run before time moves on.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.origin = start
        self._now = start
        self._heap: list[tuple[float, int, _VirtualEntry]] = []
        self._seq = itertools.count()

    def now(self) -> float:
        return self._now

    def _schedule(self, when: float, callback: Callable[[], None]) -> _VirtualEntry:
        entry = _VirtualEntry(callback)
        heapq.heappush(self._heap, (when, next(self._seq), entry))
        return entry

    def call_at(self, when: float, callback: Callable[[], None]) -> Handle:
        return self._schedule(when, callback)

    def periodic(self, period: float, phase: float, callback: TickCallback) -> PeriodicTimer:
        return _VirtualPeriodic(self, period, phase, callback)

    async def advance(self, seconds: float, settle: int = 8) -> None:
        """Move time forward, firing every callback due on the way, in time order."""
        end = self._now + seconds
        await _settle(settle)
        while self._heap and self._heap[0][0] <= end + 1e-12:
            when, _, entry = heapq.heappop(self._heap)
            if entry.cancelled:
                continue
            self._now = max(self._now, when)
            entry.callback()
            await _settle(settle)
        self._now = end
        await _settle(settle)


async def _settle(turns: int) -> None:
    for _ in range(turns):
        await asyncio.sleep(0)
