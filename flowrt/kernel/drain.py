"""The end of a run: sources stop, the rest finishes what it holds, leftovers are counted.

A stop must not lose data silently: what a source published before the stop is delivered
(every lossless edge drains, producers blocked on a full one get their values in), within a
bound; what is still undelivered when the bound hits is counted as dropped with its reason.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Protocol

from ..clock import Clock
from ..edges import Buffer, LatestBuffer, LosslessBuffer
from ..events import Event, HealthAlert
from ..graph.spec import TimerTrigger
from .runner import NodeRunner
from .state import RunState


class DrainedGraph(Protocol):
    """What the drain reads of the scheduler: its runners and edges."""

    runners: dict[str, NodeRunner]
    buffers: list[Buffer]
    reader_of: dict[int, NodeRunner]
    loop: asyncio.AbstractEventLoop
    clock: Clock
    emit: Callable[[Event], None]

    def rel(self, t: float) -> float: ...


log = logging.getLogger("flowrt.scheduler")


class Drain:
    """Drains one scheduler's graph at stop (once; later calls return the first result)."""

    def __init__(self, sched: DrainedGraph, timeout: float) -> None:
        self._s = sched
        self.timeout = timeout  # seconds the drain at stop may take (then reported)
        self.done = False
        self.left: list[str] = []  # what a timed-out drain left undone
        self.cut = False  # cut short (a signal while draining): leftovers say "interrupted"
        self.deadline: float | None = None  # loop time the drain ends by (set as it begins)

    def over(self) -> bool:
        """Cut, or past its deadline: no activation may begin (a node whose call holds the
        loop for seconds was called again on a queued value after the deadline, and the
        drain ran a whole call late)."""
        return self.cut or (self.deadline is not None and self._s.loop.time() >= self.deadline)

    def stop_sources(self) -> None:
        """Sources (nodes without inputs, and free-running ones) are released no more and
        their in-flight activation is cancelled (a capture waiting for a frame, a paced
        source waiting for its readers). Done as the stop is asked for (so a timer already
        due behind a blocked loop does not publish after it), and again as the drain begins."""
        for r in self._s.runners.values():
            if r.source and not r.stopping:
                r.stop_releasing()
                if r.task is not None and not r.task.done():
                    r.task.add_done_callback(r.cancelled)
                    r.task.cancel()  # e.g. a capture waiting for its next frame

    async def run(self, limit: float | None = None) -> list[str]:
        """Stop the sources, then let the graph finish what it holds (at most ``limit`` s).

        Sources are released no more (:meth:`stop_sources`): nothing new is published after
        the stop request, but what a source did publish, even a value waiting on a full
        lossless edge, is delivered.
        Every other node keeps running: in-flight activations finish, every lossless edge
        delivers what it holds, producers waiting on a full lossless edge get their values in.
        Returns what was left undone when the limit hit (then reported as a ``drain-timeout``
        HealthAlert and a warning), or []. The limit is a deadline for the whole graph, not
        for one awaited call (hence no ``asyncio.timeout``).
        """
        if self.done:
            return self.left
        self.done = True
        s = self._s
        timeout = self.timeout if limit is None else limit
        loop = s.loop
        t0 = loop.time()
        self.deadline = t0 + timeout
        self.stop_sources()
        left = await self._settle(t0, timeout)
        if not left and not self.cut:
            # Timed nodes with inputs (a 1 kHz loop reading the latest wall) ran on while the
            # graph drained; they stop now, their call in flight ends and what it published is
            # delivered too, not dropped at the teardown.
            for r in s.runners.values():
                if isinstance(r.rnode.trigger, TimerTrigger) and not r.stopping:
                    r.stop_releasing()
            left = await self._settle(t0, timeout)
        self.left = left
        if left and self.cut:
            detail = "cut short by a signal: " + "; ".join(left)
            log.warning("drain: %s", detail)
            s.emit(HealthAlert(s.rel(s.clock.now()), None, "drain-interrupted", detail))
        elif left:
            detail = f"not drained within {timeout:g} s: " + "; ".join(left)
            log.warning("drain: %s", detail)
            s.emit(HealthAlert(s.rel(s.clock.now()), None, "drain-timeout", detail))
        else:
            log.debug("drained in %.1f ms", (loop.time() - t0) * 1000)
        return left

    async def _settle(self, t0: float, limit: float) -> list[str]:
        """Wait until nothing is left undrained, the deadline ``t0 + limit`` or a cut."""
        loop = self._s.loop
        while True:
            left = self.undrained()
            if not left or loop.time() - t0 >= limit or self.cut:
                return left
            for r in self._s.runners.values():
                r.catch_up()
            await asyncio.sleep(0.002)

    def undrained(self) -> list[str]:
        """What the drain still waits for, in words."""
        s = self._s
        left = []
        for r in s.runners.values():
            if (
                r.busy
                and r.backpressure.blocked
                and all(self._gone(buf) for buf, _, _ in r.backpressure.blocked)
            ):
                continue  # held for a reader that will take nothing more: counted at stop
            if r.busy:
                left.append(
                    f"{r.name} waits on a full lossless edge"
                    if r.backpressure.blocked
                    else f"{r.name} running"
                )
            elif r.state in (RunState.starting, RunState.backoff) and self._waits_for(r):
                left.append(f"{r.name} restarting")
        for buf in s.buffers:
            reader = s.reader_of.get(id(buf))
            if (
                reader is not None
                and isinstance(buf, LosslessBuffer)
                and buf.pending()
                and reader.timing.enabled
                and reader.state is not RunState.failed
                # released no more (a stopped source's reader): it takes nothing now, unless
                # the drain itself cut it short (its backlog is the drain's leftover)
                and (not reader.stopping or reader.cut_short)
            ):
                left.append(f"{buf.name} holds {buf.pending()}")
        return left

    def _gone(self, buf: Buffer) -> bool:
        """The reader of ``buf`` failed or is disabled: it will take nothing more."""
        reader = self._s.reader_of.get(id(buf))
        return reader is not None and (reader.state is RunState.failed or not reader.timing.enabled)

    @staticmethod
    def _waits_for(r: NodeRunner) -> bool:
        """A restarting node the drain waits for: it has lossless values to deliver."""
        return r.ins.backlog() and r.timing.enabled

    def discard_leftovers(self) -> None:
        """Count what a stop leaves undelivered on queue and lossless edges, with a reason."""
        s = self._s
        late = "interrupted" if self.cut and self.left else "drain timeout" if self.left else "stop"
        for r in s.runners.values():
            r.backpressure.abandon(late)
        for buf in s.buffers:
            reader = s.reader_of.get(id(buf))
            if reader is None or isinstance(buf, LatestBuffer):
                buf.clear()  # a host subscription, or a sampled/latest value: not a loss
                continue
            why = (
                "reader failed"
                if reader.state is RunState.failed
                else "reader disabled"
                if not reader.timing.enabled
                else late
            )
            n = buf.discard(why)
            if n:
                log.warning("%s: %d value(s) dropped at stop (%s)", buf.name, n, why)
