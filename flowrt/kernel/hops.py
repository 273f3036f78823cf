"""Direct hops between workers: a reader's call sent ahead, its input coming from the writer.

A node in a worker that feeds a node in another worker costs the hop two wake-ups and the
loop's turn between: the writer's reply wakes the loop, which publishes, releases the reader
and writes its call, which wakes the reader's worker. On the 8-relay pipe of the peer
benchmark (30 Hz, a frame copied at each hop) that is ~400 us a hop, of which ~110 us is the
loop's Python and ~60 us the wake-ups (benchmarks/RESULTS.md). Here the loop decides the
reader's release *ahead*, when it sends the writer's call: the reader's call goes out at once
with its input marked to come from the writer's worker, which sends its frame there as soon
as it has it (:mod:`flowrt.workers.hops`); readers of readers are armed the same way, so a
chain of workers runs at the speed of its workers while the loop follows behind.

What does not change: the loop still publishes the writer's value to every reader (the armed
one included), from the writer's reply; the reader's activation begins when that value is
published, as it would have been released, and takes it from its buffer, so its counters,
statistics, recordings and the determinism log see what they always saw. Arming is the
release decided early, under the same rules a release obeys at that instant: the reader is
idle, enabled, not stopping, its input holds nothing newer (an activation already decided
runs to its end when the node is disabled meanwhile, as one already running does).

When the hop does not happen (the writer fails, publishes nothing, or its value is not a
stamped frame), the writer's worker sends a skip: the reader's call returns not run, and its
activation, if the writer published after all, sends it the usual way. A reader armed by a
call whose writer never published is let go (its worker told to stop waiting); if it had run
on the value meanwhile, its result is dropped and counted ``aborted``. Nodes with a deadline,
a watchdog, ``spin``, ``timing: precise`` or pipelined calls are never armed or fed, nor any
while an observer (the determinism log) watches.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Awaitable, Coroutine, Iterable, Mapping
from typing import Any, Protocol

from ..edges import Buffer, LatestBuffer
from ..frames import Frame, release_handoffs
from ..graph._resolve import Edge, ResolvedNode
from ..graph.spec import InputTrigger, Placement
from .counters import Counters
from .disabling import DisableHook
from .executor import Executor, HopTo
from .ports import SchedulerPort
from .state import RunState
from .swapping import Swapper
from .timing import Timing


class HopRunner(Protocol):
    """What hops read of their runner, and the runner's methods that apply what they
    decide (its call sent ahead: ``started``; its activation: ``run_async``; ``idle``)."""

    @property
    def sched(self) -> SchedulerPort: ...
    @property
    def executor(self) -> Executor: ...
    @property
    def rnode(self) -> ResolvedNode: ...
    @property
    def timing(self) -> Timing: ...
    @property
    def counts(self) -> Counters: ...
    @property
    def inputs(self) -> dict[str, Buffer]: ...
    @property
    def outputs(self) -> dict[str, list[Buffer]]: ...
    @property
    def trigger_inputs(self) -> list[str]: ...
    @property
    def busy(self) -> bool: ...
    @property
    def state(self) -> RunState: ...
    @property
    def stopping(self) -> bool: ...
    @property
    def deferred(self) -> float | None: ...
    @property
    def window(self) -> int: ...
    @property
    def swapper(self) -> Swapper: ...
    @property
    def disable_hook(self) -> DisableHook: ...
    @property
    def hops(self) -> Hops: ...

    def started(self, task: asyncio.Task[None] | None = None) -> None: ...
    def idle(self) -> None: ...
    def run_async(self, t_release: float) -> Coroutine[Any, Any, None]: ...


_tags = itertools.count(1)  # one per hop armed: what the reader's worker waits for
# Readers armed down a chain by one call (the peer benchmark's 8 relays at 30 Hz, p50: 4
# ahead 3.2-3.5 ms, 8 or 16 ahead 2.7-3.0 ms, none 3.4-3.5 ms)
AHEAD = 16


class Hops:
    """One runner's direct hops: the reader its worker may feed, its own call sent ahead.

    Invariants: ``armed`` is set only while the runner is busy (``started``) with no task of
    its own yet, or a task that has not taken it; ``begun`` only while ``armed`` is set;
    ``fed`` is the reader armed by this runner's call in flight (None between calls).
    """

    def __init__(self, runner: HopRunner) -> None:
        self.r = runner
        self.reader: Hops | None = None  # wired (wire_hops): the one reader it may feed directly
        self.writer: Hops | None = None  # wired: the one writer that may feed it directly
        self.port: str | None = None  # the output port feeding it (None: the node's only one)
        self.in_port = ""  # as a reader: the input the writer feeds
        self.armed: tuple[int, asyncio.Future[Any]] | None = None  # tag, call sent ahead
        self.begun = False  # its activation has begun on the value (task created)
        self.fed: tuple[Hops, int] | None = None
        # True from its hop call's result until the end of that loop turn: its publication
        # (what an armed reader's activation waits for, not a host's Runtime.publish)
        self.publishing = False

    # -- the writer's side ---------------------------------------------------------------

    def call(self, inputs: dict[str, Any]) -> Awaitable[Any]:
        """The activation's call: sent ahead already (armed), or sent now, arming the
        readers down the chain that may run on its output."""
        r = self.r
        armed = self.armed
        if armed is not None:
            self.armed, self.begun = None, False
            return self._armed(armed[1], inputs)
        plan = self._plan()
        if not plan:
            return r.executor.call(inputs)
        reader, tag, address = plan[0]
        fut = self._result(r.executor.call_hop(inputs, (address, tag, self.port)))
        self.fed = (reader, tag)
        # The readers' output slots are lent with their calls, before their input exists:
        # sized as the writer's input frames (a filter's output is usually its input's size).
        size = max((v.nbytes for v in inputs.values() if isinstance(v, Frame)), default=0)
        for i, (h, tag, _) in enumerate(plan):
            nxt = plan[i + 1] if i + 1 < len(plan) else None
            h.arm(tag, None if nxt is None else (nxt[2], nxt[1], h.port), size)
            h.fed = None if nxt is None else (nxt[0], nxt[1])
        return fut

    def _plan(self) -> list[tuple[Hops, int, str]]:
        """The readers to arm down the chain: each with its hop's tag and its worker's
        address."""
        if not self._may_feed():
            return []
        plan: list[tuple[Hops, int, str]] = []
        h: Hops = self
        while (reader := h.reader) is not None and len(plan) < AHEAD:
            address = reader._arm_address()
            if address is None:
                break
            plan.append((reader, next(_tags), address))
            if not reader._may_feed():
                break
            h = reader
        return plan

    def _may_feed(self) -> bool:
        r = self.r
        sched = r.sched
        return (
            self.reader is not None
            and r.executor.hop_address is not None  # (a worker of its own, running)
            and sched.observer is None  # (a stop due, --duration's, is no reason: it stops
            and r.timing.deadline is None  # sources, and a reader armed before it runs)
            and r.window == 1
        )

    def ended(self) -> None:
        """The writer's call ended (however): a reader it armed and did not feed, once the
        result is published (next turn), is let go."""
        fed, self.fed = self.fed, None
        if fed is not None:
            self.r.sched.loop.call_soon(fed[0].unfed, fed[1])

    # -- the reader's side ---------------------------------------------------------------

    def _arm_address(self) -> str | None:
        """Its worker's address if it may be armed now (None: it may not)."""
        r = self.r
        may = (
            self.armed is None
            and not r.busy
            and r.state is RunState.idle
            and r.timing.enabled
            and not r.stopping
            and r.deferred is None
            and r.swapper.pending is None
            and not r.disable_hook.due
            and r.timing.deadline is None
            and r.window == 1
            and not r.inputs[self.in_port].pending()
        )
        return r.executor.hop_address if may else None

    def arm(self, tag: int, to: HopTo, size: int) -> None:
        """Send this node's call now, its input to come from its writer's worker (hop
        ``tag``, a frame of about ``size`` bytes), its output to go on ``to``: its release,
        decided ahead."""
        r = self.r
        fut = r.executor.call_hop({self.in_port: None}, to, (self.in_port, tag, size))
        self.armed, self.begun = (tag, fut), False
        r.started()

    def arrived(self) -> None:
        """The writer published: the activation begins (and takes the value), as a release
        would have begun it. A newer value, or one published by someone else (a host's
        ``Runtime.publish``), waits in the buffer for the next activation."""
        if self.begun or self.writer is None or not self.writer.publishing:
            return
        self.begun = True
        r = self.r
        r.counts.activations += 1
        r.started(r.sched.loop.create_task(r.run_async(r.sched.clock.now())))

    async def _armed(self, fut: asyncio.Future[Any], inputs: dict[str, Any]) -> Any:
        ran, result = await self._result(fut, keep=True)
        if ran:
            self.r.counts.direct_hops += 1
            return result
        return await self.r.executor.call(inputs)  # the value did not come: the usual way

    async def _result(self, fut: asyncio.Future[Any], keep: bool = False) -> Any:
        """The call's result; what the activation does with it in this turn (its
        publication) is this node's publishing."""
        got = await fut
        self.publishing = True
        self.r.sched.loop.call_soon(self._published)
        return got if keep else got[1]

    def _published(self) -> None:
        self.publishing = False

    def unfed(self, tag: int) -> None:
        """The writer's call that armed this one ended without its value reaching it."""
        armed = self.armed
        if armed is None or armed[0] != tag or self.begun:
            return
        self.drop()
        armed[1].add_done_callback(lambda _f: self.r.idle())

    def drop(self) -> None:
        """Let the call sent ahead go (its activation will not take it): its worker stops
        waiting; if it ran, its result is dropped and counted aborted. Its own reader too."""
        armed, begun = self.armed, self.begun
        self.armed, self.begun = None, False
        if armed is None:
            return
        r = self.r
        r.executor.skip_hop(armed[0])
        self.ended()

        def gone(f: asyncio.Future[Any]) -> None:
            if f.cancelled() or f.exception() is not None:
                return
            ran, result = f.result()
            if ran:
                if not begun:  # (an activation that began is counted already)
                    r.counts.activations += 1
                r.counts.aborted += 1
                release_handoffs(result)

        armed[1].add_done_callback(gone)


def wire_hops(runners: Mapping[str, HopRunner], edges: Iterable[Edge]) -> None:
    """Each writer's one reader it may feed directly: both in workers of their own, the
    reader fed by that edge alone, triggered by it, through a latest-value buffer, on a
    frame output, and neither with a watchdog, ``spin`` or ``timing: precise``."""
    edges = list(edges)
    into: dict[str, int] = {}
    for e in edges:
        into[e.dst] = into.get(e.dst, 0) + 1
    for e in edges:
        w, rd = runners[e.src], runners[e.dst]
        if w.hops.reader is not None or not (_plain(w) and _plain(rd)) or into[e.dst] != 1:
            continue
        if rd.rnode.spec.watchdog is not None or not isinstance(rd.rnode.trigger, InputTrigger):
            continue
        if rd.trigger_inputs != [e.dst_port] or not isinstance(rd.inputs[e.dst_port], LatestBuffer):
            continue
        port = w.rnode.cls.outputs.get(e.src_port)
        if port is None or port.type is not Frame:
            continue
        w.hops.reader = rd.hops
        rd.hops.writer = w.hops
        w.hops.port = None if len(w.outputs) == 1 else e.src_port
        rd.hops.in_port = e.dst_port


def _plain(r: HopRunner) -> bool:
    spec = r.rnode.spec
    return spec.placement is Placement.process and spec.timing == "normal" and spec.spin is None
