"""Pipelined worker calls: several activations in flight to a worker fed by queues.

A node at ``placement: process`` whose trigger inputs are ``queue`` or ``lossless`` edges gets
up to ``pipeline`` (default 4) activations in flight: the next input is on its way while the
worker computes. Checked here: results complete in order, a full ``lossless`` edge still holds
the producer back (nothing lost), a ``latest`` input keeps one call at a time (the worker gets
the newest value), and a worker that dies with calls in flight has them counted and recovers.
"""

from __future__ import annotations

import os
import time
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict

import flowrt
from flowrt import GraphBuilder, Input, Node, Output, Runtime

pytestmark = pytest.mark.timeout(60)


class Burst(Node):
    """Publishes ``n`` consecutive integers per activation (a fast producer)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        n: int = 10
        limit: int = 60

    value = Output(int)

    def setup(self) -> None:
        self.next = 0

    def process(self) -> None:
        for _ in range(self.params.n):
            if self.next < self.params.limit:
                self.ctx.publish("value", self.next)
                self.next += 1


class Slow(Node):
    """Takes ``ms`` per value; returns (value, pid). Dies (os._exit) on ``die_at``."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        ms: float = 2.0
        die_at: int = -1
        hang_at: int = -1

    x = Input(int)
    result = Output(object)

    def setup(self) -> None:
        self.seen: list[int] = []

    def process(self, x: int) -> tuple[int, int]:
        if x == self.params.die_at:  # sent once: the replacement never sees it
            os._exit(3)
        while x == self.params.hang_at:
            time.sleep(0.01)
        time.sleep(self.params.ms / 1000)
        return x, os.getpid()


def graph(
    policy: str,
    *,
    size: int = 10,
    n: int = 10,
    limit: int = 60,
    pipeline: int | None = None,
    watchdog: str | None = None,
    **slow: Any,
) -> flowrt.Graph:
    g = GraphBuilder("pipeline")
    g.add("src", Burst, params={"n": n, "limit": limit}, trigger={"timer": "20ms"})
    extra: dict[str, Any] = {} if pipeline is None else {"pipeline": pipeline}
    if watchdog is not None:
        extra["watchdog"] = watchdog
    g.add(
        "w",
        Slow,
        params=slow,
        trigger={"input": "x"},
        inputs={"x": {"from": "src.value", "policy": policy, "size": size}},
        placement="process",
        restart={"backoff": "20ms"},
        **extra,
    )
    return g.build()


async def _collect(
    rt: Runtime, want: int, within: float = 20.0, last: int | None = None
) -> list[Any]:
    """Results until ``want`` of them (or the value ``last``) came back, and the peak in flight."""
    sub = rt.subscribe("w.result", size=1000)
    pipe = rt.scheduler.runners["w"].pipeline
    got: list[Any] = []
    peak = 0
    start = pipe._start

    def counted(t_release: float) -> bool:
        """The calls in flight right after each one is sent (sampling between loop turns
        would miss them on a loaded machine)."""
        nonlocal peak
        sent = start(t_release)
        peak = max(peak, pipe.inflight)
        return sent

    pipe._start = counted  # type: ignore[method-assign]
    end = time.monotonic() + within
    while time.monotonic() < end and (
        len(got) < want if last is None else not any(v == last for v, _ in got)
    ):
        await rt.run(0.02)
        got += sub.drain()
    got.append(("peak", peak))
    return got


@pytest.mark.parametrize(
    ("policy", "pipeline", "window"),
    [("queue", None, 4), ("lossless", None, 4), ("queue", 2, 2), ("queue", 1, 1), ("latest", 8, 1)],
)
async def test_window_follows_the_edge_policy(
    policy: str, pipeline: int | None, window: int
) -> None:
    async with Runtime(graph(policy, limit=5, pipeline=pipeline)) as rt:
        await rt.run(0.05)
        assert rt._sched.runners["w"].window == window


async def test_results_complete_in_order_with_calls_in_flight() -> None:
    # 10 values per 20 ms tick, 1 ms each: the worker keeps up, with several in flight.
    async with Runtime(graph("queue", size=64, n=10, limit=120, ms=1)) as rt:
        got = await _collect(rt, 120)
        s = rt.stats().node("w")
    peak = got.pop()[1]
    values = [v for v, _ in got]
    assert values == list(range(120))  # every value, in order, nothing lost
    assert peak > 1  # calls were in flight together (the point of pipelining)
    assert s.completions == 120
    assert s.errors == 0
    assert s.aborted == 0
    assert s.dropped == 0


async def test_lossless_holds_the_producer_back_with_calls_in_flight() -> None:
    # 30 values per 20 ms tick into a lossless edge of 2: the worker (2 ms each) cannot keep
    # up within a tick, so the producer must wait; nothing may be dropped.
    async with Runtime(graph("lossless", size=2, n=30, limit=90)) as rt:
        got = await _collect(rt, 90)
        stats = rt.stats()
    peak = got.pop()[1]
    assert [v for v, _ in got] == list(range(90))
    assert peak > 1
    assert stats.edge("w.x").dropped == 0
    assert stats.node("src").skipped > 0  # ticks while it waited for the reader: back-pressure


async def test_latest_keeps_one_call_and_the_freshest_value() -> None:
    # 10 values per tick into a latest edge, 15 ms per call: the worker must skip to the newest.
    async with Runtime(graph("latest", n=10, limit=200, pipeline=8, ms=15)) as rt:
        got = await _collect(rt, 8)
        runner = rt._sched.runners["w"]
        assert runner.window == 1
    peak = got.pop()[1]
    values = [v for v, _ in got]
    assert peak <= 1
    assert values == sorted(values)
    assert all(v % 10 == 9 for v in values)  # always the last value of its burst: the newest


async def test_crash_with_calls_in_flight_is_counted_and_recovered() -> None:
    async with Runtime(graph("queue", size=64, n=10, limit=100, ms=1, die_at=30)) as rt:
        got = await _collect(rt, 100, within=10, last=99)
        stats = rt.stats()
        s = stats.node("w")
        failures = [e for e in rt.events if isinstance(e, flowrt.NodeFailed) and e.node == "w"]
    got.pop()
    values = [v for v, _ in got if isinstance(v, int)]
    pids = {p for _, p in got if isinstance(p, int)}
    assert len(pids) == 2  # the first worker, then its replacement
    assert failures
    assert "exited with code 3" in failures[0].error
    assert s.errors == 1
    assert s.restarts == 1
    lost = set(range(100)) - set(values)
    assert 30 in lost
    assert values == sorted(values)  # in order, before and after the crash
    assert values[-1] == 99  # recovered: the rest of the queue was processed
    # Every value that never came back is counted: the crashing call (the error), the calls in
    # flight behind it (aborted), values the queue dropped while the worker restarted, no more.
    assert len(lost) == 1 + s.aborted + stats.edge("w.x").dropped
    assert s.aborted >= 1


async def test_watchdog_measures_each_call_not_its_wait_in_the_window() -> None:
    # 40 ms per call, 4 in flight: the last waits ~120 ms behind the others, more than the
    # 100 ms watchdog. The watchdog starts when a call starts running, so none is hung.
    async with Runtime(
        graph("queue", size=64, n=4, limit=12, ms=40, watchdog="100ms", pipeline=4)
    ) as rt:
        got = await _collect(rt, 12)
        s = rt.stats().node("w")
    peak = got.pop()[1]
    assert [v for v, _ in got] == list(range(12))
    assert peak > 1
    assert s.errors == 0


async def test_hung_call_with_calls_in_flight_is_killed_and_counted() -> None:
    async with Runtime(
        graph("queue", size=64, n=10, limit=40, ms=1, hang_at=5, watchdog="200ms")
    ) as rt:
        got = await _collect(rt, 40, within=10, last=39)
        stats = rt.stats()
        failures = [e for e in rt.events if isinstance(e, flowrt.NodeFailed) and e.node == "w"]
    got.pop()
    s = stats.node("w")
    values = [v for v, _ in got]
    assert failures
    assert "hung" in failures[0].error
    assert s.restarts == 1
    assert values == sorted(values)
    assert values[-1] == 39
    lost = set(range(40)) - set(values)
    assert 5 in lost
    assert len(lost) == 1 + s.aborted + stats.edge("w.x").dropped


async def test_swap_of_a_pipelined_worker_node_loses_nothing() -> None:
    # A swap waits for the node's idle step: the pipeline stops taking new values, the calls
    # in flight finish on the old instance, the new one takes the queue from there.
    async with Runtime(graph("queue", size=64, n=10, limit=400, ms=1)) as rt:
        sub = rt.subscribe("w.result", size=1000)
        await rt.run(0.1)
        await rt.swap("w", Slow, {"ms": 1.0})
        got = sub.drain()
        end = time.monotonic() + 10
        while len(got) < 400 and time.monotonic() < end:
            await rt.run(0.05)
            got += sub.drain()
        s = rt.stats().node("w")
    values = [v for v, _ in got]
    pids = [p for _, p in got]
    assert values == list(range(400))
    assert len(set(pids)) == 2  # the old instance's worker, then the new one's
    assert pids.index(pids[-1]) > 0  # ... in that order, each a contiguous run
    assert len(set(pids[pids.index(pids[-1]) :])) == 1
    assert s.aborted == 0
