"""The health node: stream statistics, machine state and alerts (in events, table and RTDB)."""

from __future__ import annotations

import asyncio
import os
import time
from typing import Any

import numpy as np
import psutil
import pytest
from conftest import drained, wait_until
from flowrt.nodes.health import HealthReport
from rich.console import Console

import flowrt
from flowrt import (
    Frame,
    GraphBuilder,
    HealthAlert,
    Node,
    Output,
    Runtime,
    TimerTrigger,
    VirtualClock,
)
from flowrt.monitors.status import render


class Source(Node):
    """A frame source on a timer (10 ms: 100 fps unless throttled)."""

    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=10.0)

    def setup(self) -> None:
        self.seq = 0

    def process(self) -> Frame:
        self.seq += 1
        f = Frame(np.zeros((24, 32, 3), np.uint8), source=self.ctx.name, seq=self.seq)
        f.timestamp = self.ctx.now()
        return f


def alerts(rt: Runtime, kind: str | None = None) -> list[HealthAlert]:
    return [
        e for e in rt.events if isinstance(e, HealthAlert) and (kind is None or e.alert == kind)
    ]


def reports(sub: flowrt.Subscription) -> list[HealthReport]:
    return sub.drain()


async def test_throttled_source_raises_one_fps_drop_alert() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("cam", Source, priority=50)
    g.add("health", "health", params={"interval_ms": 200}, inputs={"cam": "cam.frame"})
    async with Runtime(g.build(), clock=clock) as rt:
        sub = rt.subscribe("health.report")
        await clock.advance(1.0)
        steady = reports(sub)[-1]
        (cam,) = steady.streams
        assert cam.name == "cam"
        assert cam.source == "cam"
        assert cam.fps == pytest.approx(100, rel=0.06)
        assert cam.delta_ms == pytest.approx(10, rel=0.06)
        assert cam.frame_bytes == 24 * 32 * 3
        assert cam.shape == (24, 32, 3)
        assert cam.lost == 0
        assert not alerts(rt)
        rt.set_timing("cam", timer=40)  # throttled: 25 fps
        await clock.advance(1.0)
        drops = alerts(rt, "fps_drop")
        assert len(drops) == 1  # alerted when it started, not at every report since
        assert drops[0].node == "cam"
        assert drops[0].detail.startswith("cam: 100.0 -> ")
        since = reports(sub)
        assert [a.alert for r in since for a in r.alerts] == ["fps_drop"]  # in its report too
        (cam,) = since[-1].streams
        assert cam.fps == pytest.approx(25, rel=0.06)
        assert cam.fps_max == pytest.approx(100, rel=0.06)
        assert cam.fps_min == pytest.approx(25, rel=0.1)
        assert cam.expected > cam.received
        assert cam.lost > 50
        # the runtime keeps alerts in the RTDB, the node its last report
        rec = rt.rtdb.read("flowrt.alerts")
        assert rec is not None
        assert rec.value == drops[0]
        report = rt.rtdb.read("health")
        assert report is not None
        assert isinstance(report.value, HealthReport)
        # and the status table shows it, even after other events
        console = Console(record=True, width=200)
        console.print(render(rt.stats(), [], rt.qos_status(), drops))
        assert f"fps_drop cam {drops[0].detail}" in console.export_text()
        rt.set_timing("cam", timer=10)  # recovers: no alert, and the condition clears
        await clock.advance(0.6)
        assert len(alerts(rt, "fps_drop")) == 1
        assert "fps_drop cam" not in reports(sub)[-1].active


async def test_expected_fps_counts_lost_frames_from_the_start() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("cam", Source, trigger={"timer": "20ms"})
    params = {"interval_ms": 500, "expected_fps": {"cam": 100}, "machine": False}
    g.add("health", "health", params=params, inputs={"cam": "cam.frame"})
    async with Runtime(g.build(), clock=clock) as rt:
        sub = rt.subscribe("health.report")
        await clock.advance(2.0)
        (cam,) = reports(sub)[-1].streams
    assert cam.fps == pytest.approx(50, rel=0.05)
    assert cam.received == pytest.approx(100, abs=2)
    assert cam.expected == pytest.approx(200, abs=3)
    assert cam.lost == cam.expected - cam.received


class Hang(Node):
    async def process(self) -> None:
        await asyncio.Event().wait()


class Late(Node):
    """Returns 10 ms (virtual) after release: misses a 5 ms deadline every time."""

    clock: VirtualClock

    async def process(self) -> None:
        fut = asyncio.get_running_loop().create_future()
        Late.clock.call_at(Late.clock.now() + 0.010, lambda: fut.set_result(None))
        await fut


class Flaky(Node):
    calls = 0

    def process(self) -> None:
        Flaky.calls += 1
        if Flaky.calls % 3 == 0:
            raise ValueError("boom")


async def test_watchdog_deadline_and_failure_alerts() -> None:
    clock = VirtualClock()
    Late.clock = clock
    Flaky.calls = 0
    g = GraphBuilder()
    g.add("hang", Hang, trigger={"timer": "1s"})
    g.add("late", Late, trigger={"timer": "50ms"}, deadline=5)
    g.add("flaky", Flaky, trigger={"timer": "50ms"}, restart={"backoff": "10ms"})
    g.add("fine", "counter", trigger={"timer": "50ms"}, deadline=5)
    params = {"interval_ms": 200, "watchdogs": {"hang": 300}, "machine": False}
    g.add("health", "health", params=params)
    async with Runtime(g.build(), clock=clock) as rt:
        sub = rt.subscribe("health.report")
        await clock.advance(1.0)
        watchdog = alerts(rt, "watchdog")
        misses = alerts(rt, "deadline_misses")
        failed = alerts(rt, "node_failed")
        last = reports(sub)[-1]
    assert [a.node for a in watchdog] == ["hang"]  # once for the activation, at 400 ms
    assert watchdog[0].t == pytest.approx(0.4)
    assert "watchdog 300 ms" in watchdog[0].detail
    assert [a.node for a in misses] == ["late"]  # a lasting condition: one alert
    assert "missed the deadline (100%)" in misses[0].detail
    assert failed
    assert {a.node for a in failed} == {"flaky"}
    assert failed[0].severity == "error"
    assert "deadline_misses late" in last.active
    assert not [a for a in alerts(rt) if a.node == "fine"]


async def test_machine_state_is_reported() -> None:
    g = GraphBuilder()
    g.add("health", "health", params={"interval_ms": 100})
    async with Runtime(g.build()) as rt:
        sub = rt.subscribe("health.report")
        await rt.run(0.35)
        got = reports(sub)
        # a loaded machine may report later than every 100 ms: waited for (bounded)
        await wait_until(lambda: bool(drained(sub, got)) and got[-1].machine is not None)
        report = got[-1]
    m = report.machine
    assert m is not None
    assert len(m.cpu_per_core) == psutil.cpu_count()
    assert 0 <= m.cpu_percent <= 100
    assert 0 < m.memory_percent < 100
    assert m.memory_total_mb > m.memory_used_mb > 0
    assert m.net_rx_mb_s >= 0
    assert m.disk_read_mb_s >= 0


async def test_loop_lag_alert_on_a_blocked_loop() -> None:
    g = GraphBuilder()
    g.add("hog", "burn", params={"ms": 60}, trigger={"timer": "70ms"})
    g.add("health", "health", params={"interval_ms": 200, "loop_lag_ms": 5, "machine": False})
    async with Runtime(g.build()) as rt:
        end = time.monotonic() + 5
        while not alerts(rt, "loop_lag") and time.monotonic() < end:
            await rt.run(0.1)
    (lag,) = alerts(rt, "loop_lag")
    assert lag.node is None
    assert "loop lag" in lag.detail


class Crasher(Node):
    """A worker that dies (no exception: the process exits) on its second call."""

    def setup(self) -> None:
        self.n = 0

    def process(self) -> None:
        self.n += 1
        if self.n == 2:
            os._exit(3)


async def test_worker_crash_alert() -> None:
    g = GraphBuilder()
    g.add("crasher", Crasher, trigger={"timer": "50ms"}, placement="process")
    g.add("health", "health", params={"interval_ms": 100, "machine": False})
    async with Runtime(g.build()) as rt:
        end = time.monotonic() + 10
        while not alerts(rt, "worker_crash") and time.monotonic() < end:
            await rt.run(0.1)
        crash = alerts(rt, "worker_crash")
    assert crash
    assert crash[0].node == "crasher"
    assert crash[0].severity == "error"
