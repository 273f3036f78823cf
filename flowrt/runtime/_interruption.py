"""A run interrupted at any phase: what a signal cuts, and how a cut start is undone.

A signal (Ctrl-C, SIGTERM, SIGHUP; see :mod:`flowrt.cli.signals`) may come while the
runtime starts (workers spawning, nodes in ``setup()``), runs, drains or tears down. Each
phase has one answer, so that a run always ends within about 2 s of it:

- set-up: the start is cancelled and undone (:meth:`Interruptible.start`): nodes torn down
  at once in parallel, workers killed after a short grace, shared memory freed. Before, a
  signal here only took effect once every ``setup()`` had returned (25 s of a slow worker),
  then blamed a camera that "never delivered a frame";
- the run: an orderly stop (the drain, then teardown);
- once the stop is asked for: the drain is cut short, what it holds counted as dropped
  (reason ``interrupted``);
- teardown: nothing more (each node's stop is bounded by its grace time).

A stop request is an instant (``mark_stop``, ``request_stop``, ``run``'s ``then_stop``): no
source is released after it, even a timer due before it that a loop held by a slow call
serves after it (uvloop runs expired timers before the callbacks it was handed).

:class:`Interruptible` is the part of :class:`flowrt.Runtime` that does this.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..clock import Clock
    from ..kernel import Scheduler
    from ..system._cpu_latency import CpuLatencyRequest
    from ..system._loop_cpus import LoopCpus
    from ..system._loop_share import LoopShare
    from ._event_hub import Monitor
    from ._resources import RunResources


class Interruptible:
    """The runtime's start, undone when cancelled, and its answer to a signal by phase."""

    _starting: asyncio.Task[Any] | None = None  # the task in start(), while it runs
    clock: Clock
    _sched: Scheduler | None
    _stop: asyncio.Event
    _bridge: Any
    _loop_share: LoopShare
    _loop_cpus: LoopCpus
    _cpu_latency: CpuLatencyRequest
    started: bool
    ended: bool
    resources: RunResources | None
    monitors: list[Monitor]

    async def _start(self) -> None:
        raise NotImplementedError

    async def run(self, duration: float | None = None, *, then_stop: bool = False) -> None:
        """Run until ``duration`` seconds have passed or ``request_stop`` is called.

        ``then_stop``: the duration's end is a stop request (``flowrt run --duration``):
        no source is released after it, even a release due before it that a loop held by a
        slow call serves after it, and a later ``run`` returns at once."""
        if not self.started:
            await self.start()
        if duration is None:
            await self._stop.wait()
            return
        if not then_stop:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), timeout=duration)
            return
        assert self._sched is not None
        self._sched.stop_due(self.clock.now() + duration)
        handle = asyncio.get_running_loop().call_later(duration, self.request_stop)
        try:
            await self._stop.wait()
        finally:
            handle.cancel()

    def mark_stop(self) -> None:
        """A stop is asked for now (a signal's handler, which may run while a slow call holds
        the loop): no source is released from this instant, before the loop acts on it.
        Safe in a signal handler: it only writes a time."""
        sched = self._sched
        if sched is not None and sched.stage == "running":
            sched.stop_due(self.clock.now())

    def request_stop(self) -> None:
        """Ask ``run`` to return, and the sources to publish nothing more from now on (on
        the loop's thread). The rest stops as the runtime does (the drain): a timer already
        due behind a loop held by a slow call published after the stop otherwise."""
        self._stop.set()
        if self._sched is not None:
            self._sched.stop_sources()

    async def start(self) -> None:
        """Start workers and frames, set every node up, arm the triggers.

        Cancelled (:meth:`interrupt` during set-up) or failing, it undoes what it did before
        the exception goes on: nodes torn down, workers ended, shared memory freed.
        """
        if self.ended:  # its stop tore everything down: run() after it did nothing, silently
            raise RuntimeError(
                "the runtime has stopped: a Runtime runs once (make a new one to run again)"
            )
        if self.started or self._starting is not None:
            return
        self._starting = asyncio.current_task()
        try:
            await self._start()
        except BaseException:
            self._starting = None  # a second signal must not cancel the undoing
            await self._undo_start()
            raise
        finally:
            self._starting = None

    async def _undo_start(self) -> None:
        try:
            if self._sched is not None:
                await self._sched.abort()
        finally:
            was_started, self.started = self.started, False
            if self.resources is not None:
                await self.resources.stop_workers()
                self.resources.close()
            for m in self.monitors if was_started else ():
                with contextlib.suppress(Exception):
                    m.stopped(self)
            if self._bridge is not None:
                with contextlib.suppress(Exception):
                    await self._bridge.close()
                self._bridge = None
            self._give_back_the_system()

    def _give_back_the_system(self) -> None:
        """What the start took of the process and the machine, given back (at stop, or when
        the start is undone): the loop's nice level and CPUs, the CPU latency request, the
        frozen heap."""
        self._loop_share.restore()
        self._loop_cpus.restore()
        self._cpu_latency.release()
        gc.unfreeze()

    def interruption(self) -> str:
        """What a signal would interrupt now, in words: ``set-up (in setup() of cam)``,
        ``the run``, ``the drain``, ``teardown``. Reads only: safe in a signal handler, which
        says it at once even while the loop is held (an inline node's teardown)."""
        sched = self._sched
        if self._starting is not None:
            if sched is None:
                return "set-up (starting the worker processes)"
            waiting = list(sched.setting_up)
            return "set-up" + (f" (in setup() of {', '.join(waiting)})" if waiting else "")
        if sched is None or sched.stage == "setting up":
            return "the start"
        if not self._stop.is_set():
            return "the run"
        if sched.stage in ("running", "draining") and not sched.drain_cut:
            return "the drain"
        return "teardown"

    def interrupt(self) -> str:
        """A signal arrived: act on it by phase (the module's docstring), on the loop's
        thread; returns what it cut, as :meth:`interruption` says it."""
        what = self.interruption()
        if what.startswith("set-up") and self._starting is not None:
            self._starting.cancel()
        elif what == "the run":
            self.request_stop()
        elif what == "the drain" and self._sched is not None:
            self._sched.cut_drain()
        return what


async def in_daemon_thread(fn: Callable[[], None]) -> None:
    """``fn`` in a daemon thread: unlike ``asyncio.to_thread``, an interrupted start does not
    wait for it at the loop's close (starting the forkserver takes seconds on a busy
    machine), and the process can exit while it runs."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()

    def settle(exc: BaseException | None) -> None:
        if done.done():
            return
        if exc is None:
            done.set_result(None)
        else:
            done.set_exception(exc)

    def target() -> None:
        outcome: BaseException | None = None
        try:
            fn()
        except BaseException as e:
            outcome = e
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody waits any more
            loop.call_soon_threadsafe(settle, outcome)

    threading.Thread(target=target, name=fn.__name__, daemon=True).start()
    await done
