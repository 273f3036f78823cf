"""Precise release (``timing: precise``): a timer node released from a thread of its own.

Why: the loop's timers (one timerfd per loop, :mod:`flowrt.clock`) wake the loop, and the
loop wakes later than a thread sleeping to the instant, by whatever it was doing (an
activation, a socket, a garbage collection): tens of microseconds idle, milliseconds under
load. A node whose value is its instant (a CAN transmitter, a 1 kHz haptic loop) asks for a
thread that sleeps to each release with an absolute ``clock_nanosleep`` (no drift, no
accumulated latency), optionally spins the last ``spin`` of it, and then either

- runs the activation there ("thread" mode: an inline node whose ``process`` is a plain
  function, with no frame and no lossless edge: its inputs are taken and ``process`` is
  called in the thread), the runner counting and publishing on the loop afterwards; or
- hands the release to the loop ("loop" mode: a coroutine, a worker, frames, lossless
  inputs, or a node whose calls turned out long), with the nominal release time kept.

The cost, written where users read it (README, "Graph files / timing"): one thread per
precise node; CPU for ``spin`` per release; while a precise thread runs, the interpreter's
switch interval is lowered to :data:`SWITCH_INTERVAL` so that the thread gets the GIL within
that of its instant when the loop is busy in Python (the default, 5 ms, would make it wait),
and the loop's timers due at a precise instant wait for its call (:func:`_timers_wait`).

Thread safety, what is shared and how:

- the runner's fields, its counters, statistics, deadlines, supervisor and outputs: owned
  by the loop. The thread never writes them: an activation's outcome (release, start, end,
  result or exception) is handed over with ``call_soon_threadsafe``
  (:meth:`PreciseNodeRunner.threaded_done`), and so is a release it could not run
  (:meth:`PreciseNodeRunner.skipped_release`);
- whether the thread may start a call: the runner's state (down: starting, backoff, failed),
  its backpressure, a swap under way (``Swapper.swapping``: the swap sets it then reads
  ``busy``, the thread counts its call in then reads it: one sees the other), and under
  :attr:`PreciseRelease.lock` ``inflight``, the calls whose outcome the loop has not taken
  yet (the runner is busy while there are any). The thread counts a call in when it starts
  it, the loop counts it out (:meth:`PreciseRelease.landed`). The next call may start before
  the loop has taken the previous outcome (the loop may be late: the thread is not), except
  after a call that raised: then the thread waits until the loop has taken it (and the
  supervisor has put the node in backoff), so a failed instance is never called again;
- the node's input buffers: guarded by the same (re-entrant) lock on both sides
  (:func:`guard`), since the thread takes from them while the loop's producers put; the
  exception: a value of a type the port refuses is counted (``errors``) by the thread,
  the one counter it writes (``Inputs.take``; rare, and a lost increment at worst);
- the node instance: owned by the thread during a call; the loop never calls a
  thread-mode node itself, and a swap or teardown waits for the call in flight;
- ``ctx`` calls from the thread (publish, emit, set_error...): forwarded to the loop by
  :class:`flowrt.kernel.context.RunnerContext`; ``ctx.new_frame`` is refused there;
- the schedule (period, phase) and the stop flag: written by the loop under the lock,
  read by the thread at each wake-up (at most :data:`SLICE` apart);
- the calls running in threads and each thread's next instant (``_calls``, ``_due``):
  written by the threads under the ``_quiet`` condition, read there by the loop's timer
  wheel (:func:`_timers_wait`), which waits on it with the GIL released.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from ..clock import next_release, set_before_timers, spin_until
from ..edges import Buffer, LosslessBuffer
from ..graph._resolve import Graph
from ..graph.spec import Placement
from ..stats import NodeStats
from ..system._priorities import rt_priority_for
from .runner import NodeRunner
from .state import RunState

log = logging.getLogger("flowrt.scheduler")

_DOWN = frozenset((RunState.starting, RunState.backoff, RunState.failed))
SLICE = 0.05
"""Longest single sleep (s): a stop or a new period is seen within this."""
SWITCH_INTERVAL = 0.00002
"""The interpreter's switch interval while a precise thread runs (``sys.setswitchinterval``)."""
LONG_CALLS = 3
"""Calls in a row longer than half the period after which a node leaves its thread."""
QUIET_LEAD = 0.00005
QUIET_LATE = 0.0003
QUIET_MAX = 0.001
"""The loop's timers due within ``QUIET_LEAD`` before or ``QUIET_LATE`` after a precise
thread's release wait for its call, at most ``QUIET_MAX`` (s): see :func:`_timers_wait`."""


# --- sleeping to an instant ---------------------------------------------------------------


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


_CLOCK_MONOTONIC = 1
_TIMER_ABSTIME = 1


def _libc_nanosleep() -> Callable[[float], None] | None:
    """``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`` through ctypes (which releases the
    GIL while it sleeps); None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.clock_nanosleep
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Timespec), ctypes.c_void_p]

    def sleep_until(when: float) -> None:
        sec = math.floor(when)
        ts = _Timespec(sec, min(999_999_999, round((when - sec) * 1e9)))
        fn(_CLOCK_MONOTONIC, _TIMER_ABSTIME, ctypes.byref(ts), None)  # EINTR: woken early

    return sleep_until


def _thread_priority(priority: int) -> str:
    """SCHED_FIFO for the calling thread alone, where the process may have it: the node asked
    for its instant, and under the fair scheduler a woken thread may wait for another task's
    slice (a 1 kHz haptic loop missed its 1 ms deadline 7-9 times in 5 s so, none with it;
    RESULTS.md). The loop and the workers keep their own scheduling; with ``--realtime`` the
    thread has the loop's policy already (said so: "SCHED_FIFO 90, the loop's"). Returns
    what the thread runs at ("" when it stays at the normal policy).

    The priority is the node's, capped below the loop's (``rt_priority_for``); the thread
    mostly sleeps, waits for the GIL without spinning, and a node whose calls grow long leaves
    the thread (``LONG_CALLS``), so it cannot take a CPU for long; the kernel's RT throttling
    bounds it in any case."""
    if not hasattr(os, "sched_setscheduler"):
        return ""
    try:
        policy = os.sched_getscheduler(0)
        if policy != os.SCHED_OTHER:  # inherited from the loop (--realtime)
            names = {os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_RR: "SCHED_RR"}
            if policy not in names:
                return ""
            return f"{names[policy]} {os.sched_getparam(0).sched_priority}, the loop's"
        rt = rt_priority_for(priority)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt))  # 0: this thread
    except OSError:
        return ""
    return f"SCHED_FIFO {rt}"


def _relative_sleep(when: float) -> None:
    delay = when - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def _sleeper() -> Callable[[float], None]:
    native = getattr(time, "clock_nanosleep", None)  # not in CPython 3.11; kept if it comes
    if native is not None:
        clock = time.CLOCK_MONOTONIC
        flags = getattr(time, "TIMER_ABSTIME", _TIMER_ABSTIME)
        return lambda when: native(clock, flags, when)
    return _libc_nanosleep() or _relative_sleep


sleep_until: Callable[[float], None] = _sleeper()
"""Sleep until ``when`` (monotonic seconds), absolute where the system allows (no drift)."""


def due(next_t: float, period: float, now: float) -> tuple[float, int, float]:
    """The release to serve at ``now`` (``>= next_t``), the releases passed unserved before
    it, and the next one: a thread woken late serves the latest instant, never a burst."""
    missed = max(0, math.floor((now - next_t) / period))
    release = next_t + missed * period
    return release, missed, release + period


# --- which nodes run in the thread --------------------------------------------------------


def why_not_thread(runner: NodeRunner, graph: Graph) -> str | None:
    """Why ``runner``'s activations are handed to the loop rather than run in its thread
    (None: they run in the thread). Decided once the node is set up (``executor.sync``)."""
    spec = graph.nodes[runner.name].spec
    if spec.placement is not Placement.inline:
        return f"placement {spec.placement.value}: its worker runs it"
    if not runner.executor.sync:
        return "its process is a coroutine: it runs on the loop"
    if runner.tick_ports:
        return "it publishes frames (the frame pool belongs to the loop)"
    for e in graph.edges:
        if e.dst != runner.name:
            continue
        src = graph.nodes.get(e.src)
        if src is not None and e.src_port in src.cls.frame_ports():
            return f"input {e.dst_port} carries frames (their links belong to the loop)"
    if any(isinstance(b, LosslessBuffer) for b in runner.ins.buffers.values()):
        return "a lossless input (its backlog is served from the loop)"
    return None


_GUARDED: dict[type[Buffer], type[Buffer]] = {}
_GUARDED_METHODS = (
    "put",
    "take",
    "take_new",
    "pending",
    "reader_skipped",
    "clear",
    "discard",
    "abandon",
    "stats",
)


def _guarded_class(cls: type[Buffer]) -> type[Buffer]:
    g = _GUARDED.get(cls)
    if g is None:
        ns: dict[str, Any] = {}
        for name in _GUARDED_METHODS:
            base = getattr(cls, name, None)
            if base is None:
                continue

            def method(self: Any, *args: Any, _base: Any = base) -> Any:
                with self._guard:
                    return _base(self, *args)

            ns[name] = method
        g = _GUARDED[cls] = type(f"Guarded{cls.__name__}", (cls,), ns)
    return g


def guard(buf: Buffer, lock: threading.RLock) -> None:
    """Make ``buf``'s methods hold ``lock`` (the producer on the loop, the reader in the
    thread). The same object: its producer keeps the reference it has."""
    if not hasattr(buf, "_guard"):
        buf._guard = lock  # type: ignore[attr-defined]
        buf.__class__ = _guarded_class(type(buf))


# --- the loop's side of an instant ---------------------------------------------------------

_switch_users = 0
_switch_saved = 0.005
_quiet = threading.Condition()
_calls = 0  # precise calls running in their threads now (under _quiet)
_due: dict[int, float] = {}  # a thread-mode release thread -> its next instant (under _quiet)


def _timers_wait() -> None:
    """On the loop, before its timerfd wheel fires due timers: while a precise thread's call
    runs, or its release is due about now and not started yet, wait for it (the GIL
    released), at most :data:`QUIET_MAX`.

    Why: timers falling due at a precise node's instant woke the loop at the same time as
    the thread, and the two took turns on the GIL every switch interval: a CAN transmitter's
    p99 went from 0.06-0.08 ms to 0.47 ms when eight signal nodes shared its instants
    (benchmarks/RESULTS.md). A precise node's instant goes first, as a higher priority does.
    """
    if not _calls and not _due:
        return
    end = time.monotonic() + QUIET_MAX
    with _quiet:
        while True:
            now = time.monotonic()
            if now >= end:
                return
            soon = any(d - QUIET_LEAD <= now < d + QUIET_LATE for d in _due.values())
            if not _calls and not soon:
                return
            _quiet.wait(end - now)


def _calls_begin(key: int, nxt: float | None) -> None:
    """A thread's call starts (and its next instant is ``nxt``): the loop's timers wait."""
    global _calls
    with _quiet:
        _calls += 1
        if nxt is not None:
            _due[key] = nxt


def _calls_end() -> None:
    global _calls
    with _quiet:
        _calls -= 1
        _quiet.notify_all()


def _lower_switch_interval() -> None:
    global _switch_users, _switch_saved
    if _switch_users == 0:
        _switch_saved = sys.getswitchinterval()
        sys.setswitchinterval(min(_switch_saved, SWITCH_INTERVAL))
        set_before_timers(_timers_wait)
    _switch_users += 1


def _restore_switch_interval() -> None:
    global _switch_users
    _switch_users -= 1
    if _switch_users == 0:
        sys.setswitchinterval(_switch_saved)
        set_before_timers(None)


# --- the release thread -----------------------------------------------------------------


class PreciseRelease:
    """The release thread of one ``timing: precise`` node (a :class:`PeriodicTimer`).

    Invariants: ``inflight`` counts the calls started by the thread whose outcome the loop
    has not taken, written under ``lock``; ``_after_error`` is true from a call that raised
    to the loop taking it, and no call starts meanwhile; ``thread_mode`` is written by the
    thread only (it leaves for the loop after :data:`LONG_CALLS` long calls, for good, or
    while a swap has made it a coroutine: ``_for_coroutine``, and comes back when a swap makes
    it sync again); ``_loop_epoch`` (under ``lock``) numbers the stretches of releases handed
    to the loop: one posted in an earlier stretch is not run (the thread took over), and
    ``_on_loop`` (under ``lock``) is true while one runs there, when the thread may not.
    """

    def __init__(
        self,
        runner: PreciseNodeRunner,
        loop: asyncio.AbstractEventLoop,
        origin: float,
        period: float,
        phase: float,
        spin: float,
        thread_mode: bool,
    ) -> None:
        self._r = runner
        self._loop = loop
        self._origin = origin
        self.lock = threading.RLock()
        self._period, self._phase, self._version = period, phase, 0
        self.spin = spin
        self.thread_mode = thread_mode
        self.inflight = 0
        self._after_error = False
        self._stopped = False
        self._long = 0
        self._for_coroutine = False  # left the thread for a coroutine: back once sync (thread)
        self._loop_epoch = 0
        self._on_loop = False
        # what the thread got from the OS (written once by the thread as it starts, then read)
        self.os_grant = ""
        self._exited: asyncio.Future[None] = loop.create_future()
        if thread_mode:
            for buf in runner.ins.buffers.values():
                guard(buf, self.lock)
        self._thread = threading.Thread(
            target=self._main, name=f"flowrt-precise-{runner.name}", daemon=True
        )

    def start(self) -> None:
        """Start the thread (apart from construction: the release logic is tested without)."""
        _lower_switch_interval()
        self._thread.start()

    # --- the loop's side --------------------------------------------------------------

    def reset(self, period: float, phase: float) -> None:
        """New period/phase from the next release on (``PeriodicTimer.reset``)."""
        with self.lock:
            self._period, self._phase = period, phase
            self._version += 1

    def cancel(self) -> None:
        """No release after this; a call in flight still ends (await :meth:`stopped`)."""
        with self.lock:
            self._stopped = True

    async def stopped(self) -> None:
        """The thread has exited: nothing of it runs from now on (teardown may follow)."""
        if self._thread.ident is not None:  # started
            await asyncio.shield(self._exited)
            # it told the loop as its last act; its end follows at once (a loaded machine may
            # take a while to run it): no thread of the runtime's outlives its stop
            await asyncio.to_thread(self._thread.join, 1.0)

    def landed(self) -> None:
        """The loop has taken the outcome of the oldest call in flight."""
        with self.lock:
            self.inflight -= 1
            self._after_error = False

    # --- the thread -------------------------------------------------------------------

    def _main(self) -> None:
        self.os_grant = _thread_priority(self._r.rnode.spec.priority)
        try:
            self._run()
        except Exception:  # a bug here must not leave the node silently unreleased
            log.exception("node %s: precise release thread failed", self._r.name)
        finally:
            self._announce(None)
            self._post(self._exit)

    def _exit(self) -> None:
        _restore_switch_interval()
        if not self._exited.done():
            self._exited.set_result(None)

    def _post(self, fn: Callable[..., None], *args: Any) -> bool:
        try:
            self._loop.call_soon_threadsafe(fn, *args)
            return True
        except RuntimeError:  # the loop is closed: nobody left to tell
            return False

    def _run(self) -> None:
        version = -1
        nxt = period = 0.0
        now = time.monotonic
        while True:
            with self.lock:
                if self._stopped:
                    return
                if version != self._version:
                    version, period = self._version, self._period
                    nxt, _ = next_release(self._origin, period, self._phase, now())
                    self._announce(nxt)
            wake = nxt - self.spin
            t = now()
            if t < wake:
                sleep_until(min(wake, t + SLICE))
                continue
            spin_until(nxt)
            release, missed, nxt = due(nxt, period, now())
            self.fire(release, missed, nxt)

    def _announce(self, nxt: float | None) -> None:
        """Tell the loop's timers the next instant to leave to this thread (None: none)."""
        with _quiet:
            if nxt is None or not self.thread_mode:
                _due.pop(id(self), None)
            else:
                _due[id(self)] = nxt
            _quiet.notify_all()

    def fire(self, release: float, missed: int, nxt: float | None = None) -> None:
        """One release at its instant: run it here, or hand it to the loop; ``nxt``: the
        instant after it, announced to the loop's timers (see :func:`_timers_wait`)."""
        r = self._r
        if self.thread_mode and not r.executor.sync:
            self.thread_mode = False  # swapped for a coroutine: the loop runs it meanwhile
            self._for_coroutine = True
            self._announce(None)
        elif self._for_coroutine and r.executor.sync:
            self._back_to_thread()  # swapped back to a sync kind: here again, once it may
        if not self.thread_mode:
            with self.lock:
                epoch = self._loop_epoch
            self._post(self._release_on_loop, epoch, release, missed)
            return
        with self.lock:
            go = (
                not self._after_error
                and not self._stopped
                and r.state not in _DOWN
                and not r.backpressure.blocked
                and r.timing.enabled
                and not r.stopping
            )
            if go:
                self.inflight += 1
        if go and r.swapper.swapping:  # counted in first: the swap saw it busy, or we see it
            with self.lock:
                self.inflight -= 1
            go = False
        if go:
            _calls_begin(id(self), nxt)
            try:
                self._call(release, missed)
            finally:
                _calls_end()
            return
        if nxt is not None:
            self._announce(nxt)
        if r.timing.enabled and not r.stopping:
            self._post(r.skipped_release, missed)  # an overrun, or the node is down: counted

    def _back_to_thread(self) -> None:
        """Take the node's releases back from the loop, when none of them runs there now;
        those already handed over are then not run (a new stretch: ``_loop_epoch``), so the
        node never runs on both at once."""
        with self.lock:
            if self._on_loop or self._r._busy:
                return  # one runs on the loop: next release
            self._loop_epoch += 1
            self._for_coroutine, self._long = False, 0
            self.thread_mode = True

    def _release_on_loop(self, epoch: int, release: float, missed: int) -> None:
        """On the loop: a release the thread handed over, unless the thread took the node
        back since (then it is not run: counted skipped)."""
        r = self._r
        with self.lock:
            stale = epoch != self._loop_epoch
            self._on_loop = not stale
        if stale:
            r.skipped_release(missed)
            return
        try:
            r.release_timer(release, missed)
        finally:
            with self.lock:
                self._on_loop = False

    def _call(self, release: float, missed: int) -> None:
        r = self._r
        start = time.monotonic()
        inputs: dict[str, Any] | None = None
        result: Any = None
        error: Exception | None = None
        try:
            with self.lock:  # once for every input (re-entrant): one wait at most, not one each
                inputs = r.ins.take()
            if inputs is not None:
                result = r.executor.call_sync(inputs)
        except Exception as e:
            error = e
        end = time.monotonic()
        with self.lock:
            self._after_error = error is not None
        if not self._post(r.threaded_done, release, missed, start, end, inputs, result, error):
            return
        with self.lock:
            period = self._period
        self._long = self._long + 1 if end - start > period / 2 else 0
        if self._long >= LONG_CALLS:
            self.thread_mode = False
            self._announce(None)
            self._post(_left_thread, r.name, (end - start) * 1000, period * 1000)


def _left_thread(name: str, took_ms: float, period_ms: float) -> None:
    log.warning(
        "node %s: %d calls in a row took more than half its %g ms period (last %.2f ms): "
        "released to the loop from now on (timing: precise runs short calls in its thread)",
        name,
        LONG_CALLS,
        period_ms,
        took_ms,
    )


class PreciseNodeRunner(NodeRunner):
    """The runner of a ``timing: precise`` node: busy while its thread has calls in flight,
    and the loop's side of what the thread hands over. On virtual time it has no thread and
    is released by the clock's own timer, as any timer node."""

    precise: PreciseRelease | None  # set once by start_precise() (real time); also the timer

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.precise: PreciseRelease | None = None

    @property
    def busy(self) -> bool:
        """An activation is running here or in the release thread (or values wait)."""
        return self._busy or (self.precise is not None and self.precise.inflight > 0)

    @busy.setter
    def busy(self, value: bool) -> None:
        NodeRunner.busy.fset(self, value)  # type: ignore[attr-defined]

    def start_precise(self, spin: float, thread: bool = True) -> PreciseRelease:
        """Release from a thread of its own; ``thread=False``: the release logic without its
        thread (tests call ``fire``)."""
        tm = self.timing
        assert tm.timer is not None
        why = why_not_thread(self, self.sched.graph)
        if why is not None:
            log.info("node %s: timing: precise, activations run on the loop: %s", self.name, why)
        p = PreciseRelease(
            self, self.sched.loop, self.sched.clock.origin, tm.timer, tm.timer_phase, spin,
            thread_mode=why is None,
        )  # fmt: skip
        self.precise = p
        self.arm(p)
        if thread:
            p.start()
        return p

    def stats(self) -> NodeStats:
        """As any node's, with how it is released where the table shows scheduling
        (``inline precise thread``; ``precise release``: handed to the loop)."""
        s = super().stats()
        p = self.precise
        if p is None:
            return s
        how = "precise thread" if p.thread_mode else "precise release"
        if p.os_grant:
            how = f"{how} ({p.os_grant})"
        return s.model_copy(update={"granted": f"{how}, {s.granted}" if s.granted else how})

    async def precise_stopped(self) -> None:
        """The release thread, if any, has exited (after ``stop_releasing``)."""
        if self.precise is not None:
            await self.precise.stopped()

    def skipped_release(self, missed: int) -> None:
        """A release the thread could not run (overrun, down, swap), as release() counts it."""
        if not self.timing.enabled or self.stopping:
            return
        self.counts.activations += 1 + missed
        self.counts.skipped += 1 + missed
        for buf in self.inputs.values():
            buf.reader_skipped()
        if not self.busy and self.swapper.pending is not None:
            self.swapper.take_pending()  # the swap waited for a call the thread gave up

    def threaded_done(
        self,
        t_release: float,
        missed: int,
        start: float,
        end: float,
        inputs: dict[str, Any] | None,
        result: Any,
        error: Exception | None,
    ) -> None:
        """A call the thread made from ``start`` to ``end``: counted, published and
        supervised here, on the loop, as ``run_sync`` does for a call on the loop."""
        precise = self.precise
        assert precise is not None
        self.counts.activations += 1 + missed
        self.counts.skipped += missed
        if self.state in _DOWN:  # an earlier call failed (its output) after this one began:
            self.counts.aborted += 1  # lost with that instance, as a pipelined call is
            precise.landed()
            if not self.busy and self.swapper.pending is not None:
                self.swapper.take_pending()
            return
        self.started()  # the call is the loop's now (landed() counts it out of the thread)
        act = self.begin(t_release, (start, inputs))  # None: skipped (a required input)
        if act is None:
            precise.landed()
            self.idle()
            return
        if error is not None:
            act.close()
            self.fail(error)  # in backoff before the thread may call again
            precise.landed()
            return
        precise.landed()  # before idle(): a swap waits for the last call in flight
        self.complete(act, result, end)
