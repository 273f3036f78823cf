"""``timing: precise``: the release logic of flowrt/kernel/precise.py, without its thread.

The fast tests drive :meth:`PreciseRelease.fire` by hand on a virtual-time runtime (the
thread would call it at each instant) and check what the loop does with what it hands
over: counters, published values, skips, failures, swaps. The slow one runs a real graph
with a precise node for two seconds and checks that its statistics are filled in.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import wait_until

from flowrt import Frame, GraphBuilder, Input, Node, Output, Runtime, VirtualClock
from flowrt.edges import LatestBuffer
from flowrt.kernel.precise import PreciseNodeRunner, PreciseRelease, due, guard, why_not_thread
from flowrt.kernel.state import RunState


class Count(Node):
    """0, 1, 2, ... and the thread each call ran in."""

    value = Output(int)

    def setup(self) -> None:
        self.n = 0
        self.threads: list[int] = []

    def process(self) -> int:
        self.threads.append(threading.get_ident())
        self.n += 1
        return self.n - 1


class FailOnce(Node):
    value = Output(int)

    def setup(self) -> None:
        self.calls = 0

    def process(self) -> int:
        self.calls += 1
        if self.calls == 1:
            raise ValueError("first call fails")
        return self.calls


class AsyncCount(Node):
    value = Output(int)

    async def process(self) -> int:
        return 1


class Keep(Node):
    input = Input(int)

    def setup(self) -> None:
        self.seen: list[int] = []

    def process(self, input: int) -> None:
        self.seen.append(input)


def graph(kind: type[Node] = Count, **spec: Any) -> GraphBuilder:
    g = GraphBuilder("precise")
    g.add("tick", kind, trigger={"timer": "1000ms"}, timing="precise", **spec)
    g.add("keep", Keep, inputs={"input": "tick.value"})
    return g


def precise(rt: Runtime, name: str = "tick") -> tuple[PreciseNodeRunner, PreciseRelease]:
    """The node's release logic, with no thread: the test calls ``fire`` at its instants."""
    r = rt.scheduler.runners[name]
    assert isinstance(r, PreciseNodeRunner)
    assert r.timer is not None  # virtual time: the clock's own timer (never fires here)
    r.timer.cancel()
    return r, r.start_precise(0.0, thread=False)


def node(rt: Runtime, name: str) -> Any:
    return rt.scheduler.runners[name].executor.node  # type: ignore[attr-defined]


async def settle() -> None:
    for _ in range(8):
        await asyncio.sleep(0)


def test_a_late_wake_serves_the_latest_instant_and_counts_the_rest() -> None:
    assert due(10.0, 0.001, 10.0) == (10.0, 0, 10.001)
    release, missed, nxt = due(10.0, 0.001, 10.0025)
    assert missed == 2
    assert release == pytest.approx(10.002)
    assert nxt == pytest.approx(10.003)


async def test_a_call_in_the_thread_is_counted_and_published_on_the_loop() -> None:
    async with Runtime(graph().build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        assert p.thread_mode
        p.fire(0.0, 0)
        p.fire(0.001, 0)  # the loop has not taken the first outcome yet: both in flight
        assert p.inflight == 2
        assert r.busy
        await settle()
        assert p.inflight == 0
        assert not r.busy
        assert r.state is RunState.idle
        assert node(rt, "keep").seen == [0, 1]
        p.fire(0.004, 2)  # woke two periods late
        await settle()
        st = rt.stats().node("tick")
    assert (st.activations, st.completions, st.skipped) == (5, 3, 2)
    assert st.interval.count == 2
    assert st.execution.count == 3


async def test_no_call_on_a_failed_instance_until_the_loop_has_taken_the_failure() -> None:
    g = graph(FailOnce, restart={"backoff": "1000ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        calls = node(rt, "tick")
        p.fire(0.0, 0)  # raises
        p.fire(0.001, 0)  # the loop has not seen it: this release waits, skipped
        assert calls.calls == 1
        await settle()
        assert r.state is RunState.backoff
        p.fire(0.002, 0)  # in backoff: skipped
        await settle()
        st = rt.stats().node("tick")
    assert calls.calls == 1
    assert (st.activations, st.errors, st.skipped, st.completions) == (3, 1, 2, 0)


class BadFirstOutput(Node):
    """Its first call returns what its output cannot carry (the node's failure, found on the
    loop), without raising: the thread does not wait for the loop before its next call."""

    value = Output(int)

    def setup(self) -> None:
        self.calls = 0

    def process(self) -> Any:
        self.calls += 1
        return "not an int" if self.calls == 1 else self.calls


async def test_a_call_in_flight_when_an_earlier_output_fails_the_node_is_lost_with_it() -> None:
    g = graph(BadFirstOutput, restart={"backoff": "1000ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        p.fire(0.0, 0)
        p.fire(0.001, 0)  # the loop has not taken the first outcome: both in flight
        assert p.inflight == 2
        await settle()
        assert p.inflight == 0  # both landed: the thread is not held by a lost call
        assert r.state is RunState.backoff  # not "running" on an instance given up
        assert not r.busy
        assert node(rt, "keep").seen == []  # nothing published by the lost instance
        st = rt.stats().node("tick")
    assert (st.activations, st.errors, st.aborted, st.completions) == (2, 1, 1, 0)


async def test_a_swap_holds_the_thread_and_disabled_releases_count_nothing() -> None:
    async with Runtime(graph().build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        r.swapper.swapping = True  # what Swapper.swap sets while it works
        p.fire(0.0, 0)
        r.swapper.swapping = False
        await settle()
        assert node(rt, "tick").n == 0
        rt.set_timing("tick", enabled=False)
        p.fire(0.001, 0)
        await settle()
        st = rt.stats().node("tick")
    assert (st.activations, st.skipped, st.completions) == (1, 1, 0)


class CountFrom100(Count):
    def setup(self) -> None:
        super().setup()
        self.n = 100


async def test_a_swap_waits_for_the_call_the_loop_has_not_taken_yet(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async with Runtime(graph().build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        handed: list[tuple[Any, ...]] = []
        monkeypatch.setattr(p, "_post", lambda *call: handed.append(call) or True)
        p.fire(0.0, 0)  # called "in the thread"; its outcome not handed over yet
        swap = asyncio.create_task(rt.swap("tick", CountFrom100))
        await settle()
        assert r.swapper.pending is not None  # it saw the call in flight: it waits for it
        assert not swap.done()
        monkeypatch.undo()
        for fn, *args in handed:
            fn(*args)  # what the loop does when the thread's call_soon_threadsafe comes
        await settle()
        assert swap.done()
        swap.result()
        p.fire(0.001, 0)
        await settle()
        assert node(rt, "keep").seen == [0, 100]  # the old instance's value, then the new one's


async def test_a_coroutine_node_is_released_on_the_loop_with_its_time() -> None:
    async with Runtime(graph(AsyncCount).build(), clock=VirtualClock()) as rt:
        r, p = precise(rt)
        assert why_not_thread(r, rt.scheduler.graph) == (
            "its process is a coroutine: it runs on the loop"
        )
        assert not p.thread_mode
        p.fire(0.5, 0)
        await settle()
        st = rt.stats().node("tick")
    assert st.completions == 1
    assert st.response.count == 1


async def test_swapped_to_a_coroutine_and_back_the_node_runs_in_the_thread_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A swap to a coroutine hands the releases to the loop; a swap back to a sync kind
    takes them back (it stayed "precise release" for good: late ticks at 1 kHz). A release
    handed to the loop before the take-back is not run there (counted skipped): the node
    never runs on both at once."""
    async with Runtime(graph().build(), clock=VirtualClock()) as rt:
        _, p = precise(rt)
        await rt.swap("tick", AsyncCount)
        p.fire(0.0, 0)
        assert not p.thread_mode
        await settle()
        assert rt.stats().node("tick").completions == 1  # on the loop
        handed: list[tuple[Any, ...]] = []
        monkeypatch.setattr(p, "_post", lambda *call: handed.append(call) or True)
        p.fire(1.0, 0)  # handed to the loop, not run there yet ...
        monkeypatch.undo()
        await rt.swap("tick", Count)
        p.fire(2.0, 0)  # ... when the swap back makes the node sync: the thread takes it back
        assert p.thread_mode
        await settle()
        assert "precise thread" in rt.stats().node("tick").granted
        for fn, *args in handed:
            fn(*args)  # the stale release reaches the loop: not run
        await settle()
        st = rt.stats().node("tick")
        assert node(rt, "tick").n == 1  # the new instance ran once: in the thread
        assert node(rt, "keep").seen == [1, 0]
    assert (st.activations, st.completions, st.skipped) == (3, 2, 1)


class Frames(Node):
    frame = Output(Frame)

    def process(self) -> None:
        return None


class Look(Node):
    frame = Input(Frame)

    def process(self, frame: Frame) -> None:
        return None


async def test_only_a_sync_inline_node_without_frames_runs_in_the_thread() -> None:
    g = graph()
    g.add("cam", Frames, trigger={"timer": "100ms"}, timing="precise")
    g.add("look", Look, trigger={"timer": "100ms"}, timing="precise", inputs={"frame": "cam.frame"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        runners, built = rt.scheduler.runners, rt.scheduler.graph
        assert why_not_thread(runners["tick"], built) is None
        assert why_not_thread(runners["cam"], built) == (
            "it publishes frames (the frame pool belongs to the loop)"
        )
        assert why_not_thread(runners["look"], built) == (
            "input frame carries frames (their links belong to the loop)"
        )
    worker = graph(placement="process").build()
    assert why_not_thread(SimpleNamespace(name="tick"), worker) == (  # type: ignore[arg-type]
        "placement process: its worker runs it"
    )


async def test_ctx_calls_from_the_thread_are_handed_to_the_loop() -> None:
    async with Runtime(graph().build(), clock=VirtualClock()) as rt:
        ctx = node(rt, "tick").ctx
        t = threading.Thread(target=lambda: ctx.publish("value", 41))
        t.start()
        t.join()
        assert node(rt, "keep").seen == []  # not on the loop yet
        await settle()
        assert node(rt, "keep").seen == [41]
        t = threading.Thread(target=lambda: ctx.set_error("device gone"))
        t.start()
        t.join()
        await settle()
        assert rt.stats().node("tick").reason == "device gone"
        failed: list[BaseException] = []

        def frame() -> None:
            try:
                ctx.new_frame((2, 2))
            except RuntimeError as e:
                failed.append(e)

        t = threading.Thread(target=frame)
        t.start()
        t.join()
    assert "precise thread" in str(failed[0])


def test_a_guarded_buffer_keeps_its_behaviour_under_the_lock() -> None:
    buf = LatestBuffer("a->b")
    lock = threading.RLock()
    guard(buf, lock)
    assert type(buf).__name__ == "GuardedLatestBuffer"
    buf.put(1, 0.0)
    assert buf.pending() == 1
    assert buf.take() == 1
    assert buf.stats().delivered == 1
    owned: list[bool] = []
    buf.on_put = lambda: owned.append(lock._is_owned())  # type: ignore[attr-defined]
    buf.put(2, 1.0)
    assert owned == [True]  # the producer's put runs under the lock the thread takes with
    assert not lock._is_owned()  # type: ignore[attr-defined]
    assert buf.take() == 2


@pytest.mark.realtime
async def test_a_real_graph_with_a_precise_node_fills_its_statistics() -> None:
    g = GraphBuilder("precise-real")
    g.add("tick", Count, trigger={"timer": "2ms"}, timing="precise", spin="50us", deadline="5ms")
    g.add("slow", AsyncCount, trigger={"timer": "10ms"}, timing="precise")
    g.add("keep", Keep, inputs={"input": "tick.value"})
    async with Runtime(g.build()) as rt:
        await asyncio.sleep(2.0)

        def counted() -> bool:  # what is asserted below: a loaded machine may need longer
            st = rt.stats()
            tick, seen = st.node("tick"), node(rt, "keep").seen
            counts = (tick.completions, tick.interval.count, tick.execution.count, len(seen))
            return min(*counts, tick.response.count) > 100 and st.node("slow").completions > 20

        await wait_until(counted)
        threads = node(rt, "tick").threads
        seen = node(rt, "keep").seen
        names = {t.name for t in threading.enumerate()}
    st = rt.stats()
    assert "flowrt-precise-tick" in names
    assert threading.main_thread().ident not in threads  # ran in its own thread
    tick = st.node("tick")
    assert tick.granted.startswith("precise thread")
    assert st.node("slow").granted.startswith("precise release")
    if os.geteuid() == 0:  # the release threads alone at SCHED_FIFO (the loop untouched)
        assert tick.granted == "precise thread (SCHED_FIFO 10)"  # (the default priority)
        assert st.node("slow").granted == "precise release (SCHED_FIFO 10)"
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert tick.activations > 100
    assert tick.completions > 100
    assert tick.completions + tick.skipped == tick.activations
    assert tick.interval.count > 100
    assert tick.interval.p50 > 0
    assert tick.execution.count > 100
    assert tick.response.count > 100
    assert st.node("slow").completions > 20  # handed to the loop
    assert len(seen) > 100
    assert not any(t.name.startswith("flowrt-precise") for t in threading.enumerate())


@pytest.mark.realtime  # a 10 ms real-time delay, so that the call ends while the loop waits
def test_the_loops_timers_wait_for_a_precise_call_in_flight(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from flowrt.kernel import precise as pr

    pr._timers_wait()  # nothing precise: returns at once
    monkeypatch.setattr(pr, "QUIET_MAX", 5.0)  # only the call's end may release the wait
    pr._calls_begin(1, time.monotonic() + 10.0)
    order: list[str] = []

    def call() -> None:
        order.append("call ends")
        pr._calls_end()

    t = threading.Timer(0.01, call)
    t.start()
    try:
        pr._timers_wait()
        order.append("timers fire")
    finally:
        t.join()
        pr._due.clear()
    assert order == ["call ends", "timers fire"]
    pr._timers_wait()  # the next instant is 10 s away: no wait


class KeepPrecise(Node):
    """A precise node with an input: where that input comes from decides where it runs."""

    input = Input(int)

    def process(self, input: int | None) -> None:
        return None


def _with_reader(policy: str) -> GraphBuilder:
    g = graph()
    g.add(
        "reader",
        KeepPrecise,
        trigger={"timer": "100ms"},
        timing="precise",
        inputs={"input": {"from": "tick.value", "policy": policy}},
    )
    return g


def _frames() -> GraphBuilder:
    g = graph()
    g.add("cam", Frames, trigger={"timer": "100ms"}, timing="precise")
    g.add("look", Look, trigger={"timer": "100ms"}, timing="precise", inputs={"frame": "cam.frame"})
    return g


# (what, the graph, its precise nodes): flowrt check's analysis (analysis/timing.py) reads
# from the graph the rules the kernel (kernel/precise.py) decides by once the nodes are set up
AGREEMENT = [
    ("sync", lambda: graph(), ["tick"]),
    ("coroutine", lambda: graph(AsyncCount), ["tick"]),
    ("frames-out-and-in", _frames, ["tick", "cam", "look"]),
    ("latest-input", lambda: _with_reader("latest"), ["tick", "reader"]),
    ("queue-input", lambda: _with_reader("queue"), ["tick", "reader"]),
    ("lossless-input", lambda: _with_reader("lossless"), ["tick", "reader"]),
]


@pytest.mark.parametrize(
    ("build", "names"), [c[1:] for c in AGREEMENT], ids=[c[0] for c in AGREEMENT]
)
async def test_the_analysis_and_the_kernel_agree_where_a_precise_node_runs(
    build: Any, names: list[str]
) -> None:
    """Two places decide whether a precise node is called in its own thread: ``flowrt
    check`` before anything runs, the kernel once it is set up. Kept in step by this table."""
    from flowrt.analysis.timing import in_precise_thread

    async with Runtime(build().build(), clock=VirtualClock()) as rt:
        built = rt.scheduler.graph
        for name in names:
            kernel = why_not_thread(rt.scheduler.runners[name], built) is None
            assert in_precise_thread(built, name) == kernel, name


@pytest.mark.parametrize(("budget_ms", "thread"), [(300.0, True), (500.0, True), (866.0, False)])
def test_a_budget_over_half_the_period_is_analysed_on_the_loop(
    budget_ms: float, thread: bool
) -> None:
    """The runtime moves a precise node whose calls take over half its period to the loop
    (LONG_CALLS); ``flowrt check --wcet-from`` analysed a 0.866 ms p99 on a 1 ms timer in
    its thread, and found it fine."""
    from flowrt.analysis.timing import Budget, graph_timing

    built = graph().build()
    timing = graph_timing(built, {"tick": Budget(budget_ms, "stats p99")})
    assert timing["tick"].thread is thread
