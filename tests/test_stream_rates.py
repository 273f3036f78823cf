"""Stream expectations from the stream's own rate (issue 38 item 8).

The recording's stream table expected every output at its node's tick rate: a CAN node
ticking at 100 Hz was expected to publish its once-a-second ``status`` 100 times a second
(``expected 800 received 4 missing 796``), and an event output to publish on every tick.
An output now declares its rate (``Output(rate_hz=...)``, or ``Node.output_rates`` when it
depends on the params); the statistics carry it (``output_hz``) and the table reads it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from flowrt.nodes.can.node import Can

from flowrt import GraphBuilder, Node, Output, Runtime, TimerTrigger, VirtualClock
from flowrt.recording import build_report, nominal_rates
from flowrt.recording.writer import StreamCounters

pytestmark = pytest.mark.timeout(30)

DBC = str(Path(__file__).resolve().parent.parent / "nodes" / "robot.dbc")


class Beacon(Node):
    """Ticks at 10 Hz: ``tick`` every activation, ``slow`` twice a second, ``alarm`` on events."""

    tick = Output(int)
    slow = Output(int, rate_hz=2.0)
    alarm = Output(str, rate_hz=None)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=100.0)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> None:
        self.n += 1
        self.ctx.publish("tick", self.n)
        if self.n % 5 == 1:
            self.ctx.publish("slow", self.n)
        if self.n == 3:
            self.ctx.publish("alarm", "once")


def test_the_default_reads_each_outputs_declared_rate() -> None:
    assert Beacon.output_rates(Beacon.Params()) == {"slow": 2.0, "alarm": None}


@dataclass
class _Written:
    """What a report reads of a writer: streams, as the recorder's writer counts them."""

    streams: dict[str, StreamCounters]
    files: list[Path] = field(default_factory=list)
    path: Path = Path("rec.mcap")
    error: str | None = None
    notes: list[str] = field(default_factory=list)


def _counters(source: str, received: int, first: float, last: float) -> StreamCounters:
    return StreamCounters(
        topic=f"/{source}", source=source, received=received, written=received,
        first_seen=first, last_seen=last,
    )  # fmt: skip


async def test_the_stream_table_expects_each_output_at_its_own_rate() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("beacon", Beacon)
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(1.05)
        stats = rt.stats()
    (row,) = [n for n in stats.nodes if n.name == "beacon"]
    assert row.output_hz == {"slow": 2.0, "alarm": None}
    rates = nominal_rates(stats)
    assert rates["beacon"] == pytest.approx(10.0)
    assert rates["beacon.slow"] == 2.0
    assert rates["beacon.alarm"] is None
    writer = _Written(
        {
            "tick": _counters("beacon.tick", 11, 0.0, 1.0),
            "slow": _counters("beacon.slow", 3, 0.0, 1.0),
            "alarm": _counters("beacon.alarm", 1, 0.2, 0.2),
        }
    )
    report = build_report(writer, "rec_001", "2026-01-01T00:00:00", 1.0, rates)
    by = {s.source: s for s in report.streams}
    assert (by["beacon.tick"].expected, by["beacon.tick"].missing) == (11, 0)
    assert (by["beacon.slow"].nominal_hz, by["beacon.slow"].expected) == (2.0, 3)
    assert by["beacon.slow"].missing == 0
    assert by["beacon.alarm"].expected is None  # no rate: nothing expected, nothing missing
    assert by["beacon.alarm"].missing == 0


async def test_a_can_nodes_outputs_at_their_cycle_and_status_ms() -> None:
    """robot.dbc: WheelSpeeds every 10 ms, Battery 100 ms, Kick on events; ``status`` every
    ``status_ms``; raw frames on events. The node ticks every 10 ms."""
    clock = VirtualClock()
    channel = f"rates-{time.monotonic_ns()}"
    g = GraphBuilder()
    g.add(
        "chassis",
        "can",
        params={"interface": "virtual", "channel": channel, "dbc": DBC, "status_ms": 250},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.1)
        stats = rt.stats()
    (row,) = [n for n in stats.nodes if n.name == "chassis"]
    assert row.output_hz["status"] == 4.0
    assert row.output_hz["WheelSpeeds"] == 100.0
    assert row.output_hz["Battery"] == 10.0
    assert row.output_hz["Kick"] is None
    assert row.output_hz["unknown"] is None
    assert row.output_hz["frames"] is None
    rates = nominal_rates(stats)
    assert rates["chassis"] == pytest.approx(100.0)  # its tick: the gcd of the cycles
    writer = _Written({"s": _counters("chassis.status", 33, 0.0, 8.0)})
    (status,) = build_report(writer, "r", "t", 8.0, rates).streams
    assert status.expected == 33  # 4 Hz x 8 s + 1: not 801
    assert status.missing == 0


def test_receive_limits_which_messages_are_expected() -> None:
    params = Can.Params(dbc=DBC, receive=["WheelSpeeds"])
    rates = Can.output_rates(params)
    assert rates["WheelSpeeds"] == 100.0
    assert rates["Battery"] is None  # filtered out at the interface: never received
