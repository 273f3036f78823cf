"""The ``can`` node over python-can's ``slcan`` interface, through a gateway on a pty.

The gateway (tests/slcan_device.py) paces its bytes at 115200 baud and bridges to a
virtual bus where the test plays the robot's ECUs.
"""

from __future__ import annotations

import asyncio
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from flowrt import GraphBuilder, HealthAlert, Runtime

sys.path.insert(0, str(Path(__file__).resolve().parent))
from slcan_device import SlcanDevice, max_frames_per_s

pytestmark = pytest.mark.timeout(60)

DBC = str(Path(__file__).resolve().parent.parent / "nodes" / "robot.dbc")
db = cantools.database.load_file(DBC)


async def until(cond: Callable[[], Any], within: float = 10.0) -> None:
    end = time.monotonic() + within
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached")
        await asyncio.sleep(0.01)


@pytest.fixture
def gateway(tmp_path: Path) -> Iterator[tuple[SlcanDevice, can.BusABC]]:
    channel = f"slcan-test-{time.monotonic_ns()}"
    dev = SlcanDevice(tmp_path / "ttyCAN0", channel, baud=115200)
    peer = can.Bus(interface="virtual", channel=channel)
    yield dev, peer
    peer.shutdown()
    dev.close()


def graph(dev: SlcanDevice, **extra: Any) -> GraphBuilder:
    g = GraphBuilder()
    g.add(
        "ctl",
        "can-signals",
        params={
            "rate_ms": 20,
            "signals": {"LeftSetpoint": {"value": 0.5}, "RightSetpoint": {"value": 0.25}},
        },
    )
    g.add(
        "chassis",
        "can",
        params={
            "interface": "slcan",
            "channel": str(dev.path),
            "bitrate": 250000,
            "dbc": DBC,
            "options": {"tty_baudrate": 115200, "sleep_after_open": 0},
            "reopen_ms": 50,
            "reopen_max_ms": 200,
            **extra,
        },
        inputs={"MotorSetpoints": "ctl.values"},
    )
    return g


def wheels(left: float) -> can.Message:
    m = db.get_message_by_name("WheelSpeeds")
    data = m.encode({"LeftSpeed": left, "RightSpeed": 0, "Heading": 0, "Counter": 0, "Checksum": 0})
    return can.Message(arbitration_id=m.frame_id, data=data, is_extended_id=False)


def drain(peer: can.BusABC) -> list[can.Message]:
    out = []
    while (m := peer.recv(0)) is not None:
        out.append(m)
    return out


async def test_receive_and_transmit_through_the_gateway(
    gateway: tuple[SlcanDevice, can.BusABC],
) -> None:
    dev, peer = gateway
    async with Runtime(graph(dev).build()) as rt:
        speeds = rt.subscribe("chassis.WheelSpeeds")
        await until(lambda: dev.is_open)
        assert dev.bitrate == 250000  # the node set the bus bitrate (S5) before opening
        peer.send(wheels(1.5))
        seen: list[Any] = []  # a loaded machine may first publish the message's timeout
        await until(lambda: seen.extend(speeds.drain()) or any(m.valid for m in seen))
        assert all(m.valid or m.reason == "timeout" for m in seen), seen
        msg = next(m for m in seen if m.valid)
        assert msg["LeftSpeed"] == pytest.approx(1.5)
        await until(lambda: len(dev.from_host) >= 5)
        got = [m for m in drain(peer) if m.arbitration_id == 0x80]
        assert got
        dec = db.decode_message(0x80, got[0].data)
        assert dec["LeftSetpoint"] == pytest.approx(0.5)
        assert dec["RightSetpoint"] == pytest.approx(0.25)


async def test_unplug_and_replug_are_survived(gateway: tuple[SlcanDevice, can.BusABC]) -> None:
    dev, peer = gateway
    async with Runtime(graph(dev).build()) as rt:
        runner = rt.scheduler.runners["chassis"]
        speeds = rt.subscribe("chassis.WheelSpeeds", size=256)
        await until(lambda: dev.is_open)
        peer.send(wheels(1.0))
        await until(lambda: speeds._buf.pending() > 0)
        dev.unplug()
        await until(lambda: runner.error_reason is not None)
        assert "lost" in runner.error_reason or "cannot open" in runner.error_reason
        await asyncio.sleep(0.3)  # a few reopen attempts against a missing port
        assert runner.error_reason is not None
        assert "cannot open" in runner.error_reason
        dev.replug()
        await until(lambda: dev.is_open)
        await until(lambda: runner.error_reason is None)
        sent_before = len(dev.from_host)
        peer.send(wheels(2.0))
        seen: list[Any] = []
        await until(lambda: any(abs(v["LeftSpeed"] - 2.0) < 1e-6 for v in _drain(speeds, seen)))
        await until(lambda: len(dev.from_host) > sent_before)  # transmitting again too
        assert runner.state != "failed"
        assert runner.counts.errors == 0
        kinds = [e.alert for e in rt.events if isinstance(e, HealthAlert)]
        assert "node-error" in kinds
        assert "node-recovered" in kinds


def _drain(sub: Any, seen: list[Any]) -> list[Any]:
    while True:
        try:
            seen.append(sub.get_nowait())
        except LookupError:
            return seen


def test_theoretical_ceiling() -> None:
    # an 8-byte standard frame is 22 characters on the wire: 115200 / 10 / 22 frames/s
    assert max_frames_per_s(115200, 8) == pytest.approx(523.6, abs=0.1)
    assert max_frames_per_s(115200, 1) == pytest.approx(1440.0)  # 8 characters
