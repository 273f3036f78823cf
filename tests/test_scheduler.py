"""Scheduler behaviour on virtual time: activation patterns, buffers, deadlines, supervision."""

from __future__ import annotations

import asyncio
import os
import re
from typing import Any

import numpy as np
import pytest

import flowrt
from flowrt import Frame, FrameTrigger, GraphBuilder, Input, Node, Output, Runtime, VirtualClock


class Camera(Node):
    """A frame source the test drives by publishing on its output."""

    frame = Output(Frame)


class Recorder(Node):
    """Records the sequence number of every frame it is activated with."""

    frame = Input(Frame)

    def setup(self) -> None:
        self.seen: list[int] = []

    def process(self, frame: Frame) -> None:
        self.seen.append(frame.seq)


class Gate(Node):
    """An async consumer that waits on a test-controlled gate: a slow reader."""

    value = Input(object)
    out = Output(object)
    gates: dict[str, asyncio.Event] = {}
    log: dict[str, list[Any]] = {}

    async def process(self, value: Any) -> Any:
        Gate.log.setdefault(self.ctx.name, []).append(value)
        await Gate.gates[self.ctx.name].wait()
        Gate.gates[self.ctx.name].clear()
        return value


class Hang(Node):
    async def process(self) -> None:
        await asyncio.Event().wait()


class Flaky(Node):
    """Raises on every call whose count is odd: an exception to isolate."""

    tick = Output(int)
    calls = 0

    def process(self) -> int:
        Flaky.calls += 1
        if Flaky.calls % 2:
            raise ValueError(f"boom {Flaky.calls}")
        return Flaky.calls


class Count(Node):
    tick = Output(int)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> int:
        self.n += 1
        return self.n


def frame(seq: int) -> Frame:
    return Frame(np.zeros((4, 4, 3), np.uint8), source="cam", seq=seq)


def recorder(rt: Runtime, name: str) -> Recorder:
    node = rt.scheduler.runners[name].executor.node  # type: ignore[attr-defined]
    assert isinstance(node, Recorder)
    return node


async def publish_frames(rt: Runtime, clock: VirtualClock, seqs: range) -> None:
    for k in seqs:
        rt.publish("cam.frame", frame(k))
        await clock.advance(0.05)


def cambada_like() -> GraphBuilder:
    g = GraphBuilder("pattern")
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add(
        "every",
        Recorder,
        trigger=FrameTrigger(frame="cam"),
        inputs={"frame": "cam.frame"},
        priority=45,
    )
    g.add(
        "p4ph1",
        Recorder,
        trigger=FrameTrigger(frame="cam", period=4, phase=1),
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "p4ph3",
        Recorder,
        trigger=FrameTrigger(frame="cam", period=4, phase=3),
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "p8",
        Recorder,
        trigger=FrameTrigger(frame="cam.frame", period=8),
        inputs={"frame": "cam.frame"},
    )
    return g


async def test_period_phase_pattern_over_hyperperiods() -> None:
    clock = VirtualClock()
    g = cambada_like()
    async with Runtime(g.build(), clock=clock) as rt:
        await publish_frames(rt, clock, range(16))
        assert recorder(rt, "every").seen == list(range(16))
        assert recorder(rt, "p4ph1").seen == [1, 5, 9, 13]
        assert recorder(rt, "p4ph3").seen == [3, 7, 11, 15]
        assert recorder(rt, "p8").seen == [0, 8]
        stats = rt.stats()
    assert stats.node("p4ph1").activations == 4
    assert stats.node("every").skipped == 0
    # a reader that samples every 4th frame leaves 3 of 4 unread: expected, not loss
    edge = stats.edge("p4ph1.frame")
    assert edge.sampled
    assert edge.delivered == 4


async def test_timing_change_takes_effect_on_next_tick_only_for_that_node() -> None:
    clock = VirtualClock()
    async with Runtime(cambada_like().build(), clock=clock) as rt:
        await publish_frames(rt, clock, range(8))
        rt.set_timing("p4ph1", period=2, phase=0)
        await publish_frames(rt, clock, range(8, 16))
        assert recorder(rt, "p4ph1").seen == [1, 5, 8, 10, 12, 14]
        assert recorder(rt, "p4ph3").seen == [3, 7, 11, 15]  # undisturbed
        assert recorder(rt, "every").seen == list(range(16))
        events = [e for e in rt.events if isinstance(e, flowrt.TimingChanged)]
        assert events
        assert events[-1].node == "p4ph1"
        assert "period 4 -> 2" in events[-1].change
        with pytest.raises(ValueError, match="phase"):
            rt.set_timing("p4ph3", period=2, phase=3)
        rt.set_timing("p8", enabled=False)
        await publish_frames(rt, clock, range(16, 25))
        assert recorder(rt, "p8").seen == [0, 8]


async def test_timer_trigger_period_and_phase_on_virtual_time() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("a", Count, trigger={"timer": "50ms", "phase": "10ms"})
    g.add("b", Count, trigger={"timer": "20ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.2)
        a, b = rt.stats().node("a"), rt.stats().node("b")
    # a: 10, 60, 110, 160 ms; b: 0, 20, ..., 200 ms
    assert a.activations == 4
    assert b.activations == 11
    assert a.interval.mean == pytest.approx(50.0)
    assert a.interval.std == pytest.approx(0.0, abs=1e-6)


async def test_latest_only_under_slow_consumer_never_goes_back_in_time() -> None:
    clock = VirtualClock()
    Gate.gates["slow"] = asyncio.Event()
    Gate.log.clear()
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": 3_600_000}, enabled=False)
    g.add("slow", Gate, inputs={"value": {"from": "src.tick", "policy": "latest"}})
    async with Runtime(g.build(), clock=clock) as rt:
        rt.publish("src.tick", 1)
        await clock.advance(0.001)
        for v in (2, 3, 4):  # arrive while the reader is busy with 1
            rt.publish("src.tick", v)
        await clock.advance(0.001)
        Gate.gates["slow"].set()
        await clock.advance(0.001)
        Gate.gates["slow"].set()
        await clock.advance(0.001)
        edge = rt.stats().edge("slow.value")
    assert Gate.log["slow"] == [1, 4]  # newest only, never 2 or 3 after 4
    assert edge.dropped == 2
    assert edge.delivered == 2
    assert edge.published == 4


async def test_queue_drops_oldest_and_counts() -> None:
    clock = VirtualClock()
    Gate.gates["q"] = asyncio.Event()
    Gate.log.clear()
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": 3_600_000}, enabled=False)
    g.add("q", Gate, inputs={"value": {"from": "src.tick", "policy": "queue", "size": 2}})
    async with Runtime(g.build(), clock=clock) as rt:
        for v in range(1, 7):  # 1 is taken at once; 2..6 queue into 2 slots
            rt.publish("src.tick", v)
            await clock.advance(0.0)
        for _ in range(3):
            Gate.gates["q"].set()
            await clock.advance(0.001)
        edge = rt.stats().edge("q.value")
    assert Gate.log["q"] == [1, 5, 6]
    assert edge.dropped == 3
    assert edge.published == 6
    assert edge.delivered == 3


async def test_lossless_edge_makes_the_producer_wait() -> None:
    clock = VirtualClock()
    Gate.gates["rec"] = asyncio.Event()
    Gate.log.clear()
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    g.add("rec", Gate, inputs={"value": {"from": "src.tick", "policy": "lossless", "size": 2}})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.1)  # 11 timer ticks; the reader holds 1, the buffer 2, the producer 1
        src = rt.stats().node("src")
        assert src.completions == 4
        assert src.skipped == src.activations - 4  # overrun while waiting, counted
        for _ in range(20):
            Gate.gates["rec"].set()
            await clock.advance(0.001)
        edge = rt.stats().edge("rec.value")
    assert edge.dropped == 0
    assert Gate.log["rec"] == sorted(Gate.log["rec"])
    assert len(set(Gate.log["rec"])) == len(Gate.log["rec"])
    assert Gate.log["rec"][:4] == [1, 2, 3, 4]


async def test_deadline_miss_of_a_hung_node_is_detected_at_the_deadline_instant() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("hang", Hang, trigger={"timer": "100ms"}, deadline="10ms")
    g.add("ok", Count, trigger={"timer": "20ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.009)
        assert rt.stats().node("hang").deadline_misses == 0
        await clock.advance(0.002)
        misses = [e for e in rt.events if isinstance(e, flowrt.DeadlineMissed)]
        assert len(misses) == 1
        assert misses[0].still_running
        assert misses[0].t == pytest.approx(0.010)
        await clock.advance(0.3)
        s = rt.stats()
    assert s.node("hang").deadline_misses == 1  # one activation, one miss
    assert s.node("hang").skipped == 3  # ticks at 100/200/300 ms: still running
    assert s.node("ok").completions == 16  # others unaffected


class LateValue(Node):
    out = Output(int)

    async def process(self) -> int:
        await asyncio.sleep(0)  # completes on the loop, but the test clock has moved on
        return 7


async def test_firm_deadline_discards_the_late_result() -> None:
    clock = VirtualClock()

    class Slow(Node):
        out = Output(int)

        async def process(self) -> int:
            fut = asyncio.get_running_loop().create_future()
            clock.call_at(clock.now() + 0.02, lambda: fut.set_result(None))
            await fut
            return 1

    g = GraphBuilder()
    g.add("firm", Slow, trigger={"timer": "100ms"}, deadline="10ms", miss_policy="discard")
    g.add("soft", Slow, trigger={"timer": "100ms"}, deadline="10ms")
    async with Runtime(g.build(), clock=clock) as rt:
        firm = rt.subscribe("firm.out")
        soft = rt.subscribe("soft.out")
        await clock.advance(0.05)
        s = rt.stats()
        assert s.node("firm").discarded == 1
        assert s.node("firm").deadline_misses == 1
        assert s.node("soft").discarded == 0
        assert s.node("soft").deadline_misses == 1
        with pytest.raises(LookupError):
            firm.get_nowait()
        assert soft.get_nowait() == 1


async def test_exception_is_isolated_and_node_restarts_with_backoff() -> None:
    clock = VirtualClock()
    Flaky.calls = 0
    g = GraphBuilder()
    g.add("flaky", Flaky, trigger={"timer": "10ms"}, restart={"backoff": "20ms"})
    g.add("steady", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.5)
        s = rt.stats()
        failures = [e for e in rt.events if isinstance(e, flowrt.NodeFailed)]
        restarts = [e for e in rt.events if isinstance(e, flowrt.NodeRestarted)]
    assert s.node("steady").completions == 51
    assert s.node("steady").errors == 0
    flaky = s.node("flaky")
    assert flaky.errors >= 5
    assert flaky.restarts in (flaky.errors - 1, flaky.errors)
    assert flaky.completions >= 5
    assert "ValueError: boom 1" in failures[0].error
    assert "Traceback" in failures[0].traceback
    assert restarts[0].backoff_ms == pytest.approx(20.0)  # the consecutive count resets on success


async def test_restart_never_leaves_node_failed_but_runtime_running() -> None:
    clock = VirtualClock()
    Flaky.calls = 0
    g = GraphBuilder()
    g.add("flaky", Flaky, trigger={"timer": "10ms"}, restart={"policy": "never"})
    g.add("steady", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.1)
        s = rt.stats()
    assert s.node("flaky").state == "failed"
    assert s.node("flaky").errors == 1
    assert s.node("steady").completions == 11
    assert any(isinstance(e, flowrt.NodeGaveUp) for e in rt.events)


@pytest.mark.realtime
async def test_overrun_is_skipped_and_counted() -> None:
    clock = VirtualClock()
    Gate.gates["busy"] = asyncio.Event()
    g = GraphBuilder()
    g.add("busy", Gate, trigger={"timer": "10ms"}, inputs={"value": {"from": "src.tick"}})
    g.add("src", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.045)
        s = rt.stats().node("busy")
    assert s.completions == 0
    assert s.activations == 5
    assert s.skipped == 4


async def test_host_publish_and_subscribe_through_input_triggered_chain() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("a", "relay", inputs={"input": "b.output"})
    g.add("b", "relay", inputs={"input": "c.output"})
    g.add("c", "relay", inputs={"input": "src.tick"})
    g.add("src", Count, trigger={"timer": 3_600_000}, enabled=False)
    async with Runtime(g.build(), clock=clock) as rt:
        sub = rt.subscribe("a.output")
        for v in range(5):
            rt.publish("src.tick", v)
        await clock.advance(0.0)
        got = [await asyncio.wait_for(sub.get(), 1) for _ in range(5)]
        with pytest.raises(KeyError, match="did you mean"):
            rt.publish("a.outptu", 1)
    assert got == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    ("policy", "size", "said"),
    [
        ("queue", 0, "size must be a whole number >= 1, not 0"),  # the source stalled, silently
        ("queue", -1, "not -1"),
        ("latest", 2.5, "not 2.5"),  # stats() failed (EdgeStats size), and so did the exit
        ("queue", True, "not True"),
        ("lossless", 2, "would let this program stall the source"),  # 3 of 50 releases ran
        ("bogus", 2, "'bogus' is not a valid EdgePolicy"),
    ],
)
async def test_a_subscription_that_could_stall_or_break_the_graph_is_refused(
    policy: str, size: Any, said: str
) -> None:
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        with pytest.raises(ValueError, match=re.escape(said)):
            rt.subscribe("src.tick", policy=policy, size=size)
        await rt.clock.advance(0.05)  # type: ignore[attr-defined]
        assert rt.stats().node("src").completions >= 5


async def test_a_subscription_ends_with_the_run() -> None:
    """A reader waiting on ``async for`` or ``get()`` waited for ever once the runtime had
    stopped: the iteration ends, ``get`` raises."""
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    seen: list[int] = []

    async def read_all(sub: flowrt.Subscription) -> None:
        async for v in sub:
            seen.append(v)

    async with Runtime(g.build(), clock=clock) as rt:
        reader = asyncio.create_task(read_all(rt.subscribe("src.tick")))
        late = rt.subscribe("src.tick")
        await clock.advance(0.045)
    await asyncio.wait_for(reader, 1)
    assert seen == list(range(1, len(seen) + 1))
    assert len(seen) >= 4
    with pytest.raises(LookupError, match="the run has ended"):
        await asyncio.wait_for(late.get(), 1)


@pytest.mark.parametrize(
    ("given", "said"),
    [
        ("graph.yaml", "Runtime.from_file(path) loads a graph file"),
        (GraphBuilder(), "call .build() on a GraphBuilder"),
        (42, "not int: build one with GraphBuilder"),
    ],
)
def test_runtime_of_something_else_than_a_graph_says_what_to_do(given: Any, said: str) -> None:
    """(an AttributeError: 'str' object has no attribute 'imports')"""
    with pytest.raises(TypeError, match=re.escape(said)):
        Runtime(given)


async def test_a_value_published_by_the_host_is_checked_as_a_nodes() -> None:
    """``rt.publish("src.tick", "hello")`` on an ``int`` port was taken, and failed at the
    reader (counted on it, as its error)."""
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        with pytest.raises(TypeError, match=re.escape("output 'tick' expects int, got str")):
            rt.publish("src.tick", "hello")
        rt.publish("src.tick", 3)


@pytest.mark.parametrize(
    ("call", "error", "said"),
    [
        (lambda rt: rt.subscribe(3), TypeError, "a port is named 'node.port' (text), got 3"),
        (lambda rt: rt.publish(None, 1), TypeError, "a port is named 'node.port' (text)"),
        (
            lambda rt: rt.set_timing("src", enabled="no"),
            ValueError,
            "src: enabled must be True or False, got 'no'",
        ),
    ],
)
async def test_misuse_of_the_embedding_api_says_what_is_wrong(
    call: Any, error: type[Exception], said: str
) -> None:
    """(``rt.subscribe(3)``: AttributeError 'int' object has no attribute 'partition';
    ``enabled="no"`` disabled the node)"""
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        with pytest.raises(error, match=re.escape(said)):
            call(rt)
        assert rt.stats().node("src").enabled


async def _maybe_awaited(call: Any, rt: Runtime) -> None:
    result = call(rt)
    if asyncio.iscoroutine(result):
        await result


@pytest.mark.parametrize(
    ("call", "said"),
    [
        (lambda rt: rt.run(0.1), "a Runtime runs once"),  # ran nothing, stats wiped
        (lambda rt: rt.start(), "a Runtime runs once"),  # `async with rt` again: the same
        (lambda rt: rt.publish("src.tick", 3), "publish: the runtime has stopped"),
        (lambda rt: rt.subscribe("src.tick"), "subscribe: the runtime has stopped"),
    ],
)
async def test_a_stopped_runtime_refuses_to_run_again(call: Any, said: str) -> None:
    g = GraphBuilder()
    g.add("src", Count, trigger={"timer": "10ms"})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.05)
    before = rt.stats().node("src").completions
    with pytest.raises(RuntimeError, match=re.escape(said)):
        await _maybe_awaited(call, rt)
    assert rt.stats().node("src").completions == before >= 5


async def test_monitors_are_scheduled_in_the_widest_gap_between_timer_releases() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("a", Count, trigger={"timer": "50ms"})
    g.add("b", Count, trigger={"timer": "50ms", "phase": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        # releases at 0 and 10 ms of every 50: the widest gap is 10..50, its middle 30 ms
        delay = rt.quiet_delay(0.25)
        assert (clock.now() + delay - clock.origin) % 0.05 == pytest.approx(0.030)
        assert delay >= 0.25


async def test_loop_process_asks_the_fair_scheduler_for_a_short_slice() -> None:
    """Without --realtime the loop still wakes promptly: a 100 us EEVDF slice (Linux >= 6.12)."""
    import ctypes
    import platform

    from flowrt.system._priorities import _SchedAttr, lowest_nice

    g = GraphBuilder()
    g.add("a", Count, trigger={"timer": "50ms"})
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    async with Runtime(g.build()) as rt:
        if not rt.latency_hint.endswith("slice 100 us"):
            pytest.skip("the kernel does not take a custom slice here")
        assert rt.latency_hint == f"nice {lowest_nice()}, slice 100 us"
        assert rt.stats().loop_scheduling == rt.latency_hint
        if platform.machine() == "x86_64":
            attr = _SchedAttr()
            libc = ctypes.CDLL(None, use_errno=True)
            assert libc.syscall(315, 0, ctypes.byref(attr), ctypes.sizeof(attr), 0) == 0
            assert attr.sched_runtime == 100_000
    # an embedding program gets its own scheduling back
    assert os.getpriority(os.PRIO_PROCESS, 0) == nice
    if platform.machine() == "x86_64":
        assert libc.syscall(315, 0, ctypes.byref(attr), ctypes.sizeof(attr), 0) == 0
        assert attr.sched_runtime != 100_000
