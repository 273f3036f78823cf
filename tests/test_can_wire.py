"""The ``can`` node with CAN FD and multiplexed messages on python-can's virtual bus, the
trace it writes, ``flowrt can stats`` over channels and FD frames, and replay as recorded."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from _can_dbcs import FD_DBC, write
from flowrt.nodes.can.dbc import EncodeProblem, encode_signals
from flowrt.nodes.can.node import Can, CanMessage
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt import GraphBuilder, HealthAlert, Runtime, VirtualClock

pytestmark = pytest.mark.timeout(30)
_FD_DB = cantools.database.load_string(FD_DBC, strict=False)
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"test-can-wire-{time.monotonic_ns()}-{next(_channels)}"


@pytest.fixture
def peer(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


@pytest.fixture
def dbc(tmp_path: Path) -> str:
    return write(tmp_path, FD_DBC)


async def until(cond: Callable[[], Any], within: float = 5.0) -> None:
    """Wait in real time for frames to cross the reader thread (not a timing assertion)."""
    end = time.monotonic() + within
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached")
        await asyncio.sleep(0.005)


async def opened(rt: Runtime, name: str = "bus") -> Can:
    await until(lambda: rt.scheduler.runners[name].executor.node is not None)
    n = rt.scheduler.runners[name].executor.node  # type: ignore[attr-defined]
    assert isinstance(n, Can)
    await until(lambda: n.bus is not None)
    return n


def drain(bus: can.BusABC) -> list[can.Message]:
    got = []
    while (m := bus.recv(0)) is not None:
        got.append(m)
    return got


def sender(
    channel: str, dbc: str, sources: dict[str, dict[str, float]], **params: Any
) -> GraphBuilder:
    g = GraphBuilder()
    inputs = {}
    for k, (msg, signals) in enumerate(sources.items()):
        g.add(
            f"src{k}",
            "can-signals",
            params={"rate_ms": 10, "signals": {s: {"value": v} for s, v in signals.items()}},
        )
        inputs[msg] = f"src{k}.values"
    p = {"interface": "virtual", "channel": channel, "dbc": dbc, **params}
    g.add("bus", "can", params=p, inputs=inputs)
    return g


async def test_fd_messages_go_out_as_fd_frames_and_decode(
    channel: str, peer: can.BusABC, dbc: str
) -> None:
    clock = VirtualClock()
    g = sender(
        channel,
        dbc,
        {"Fd64": {"Lead": 7, "Tail": 9}, "Fd8NoBrs": {"X": 5}, "Classic": {"C": 1}},
        fd=True,
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await opened(rt)
        await clock.advance(0.1)
        await asyncio.sleep(0.1)
        got = drain(peer)
    db = cantools.database.load_file(dbc, strict=False)
    fd64 = [m for m in got if m.arbitration_id == 256]
    assert len(fd64) >= 9
    assert all(m.is_fd and m.bitrate_switch and len(m.data) == 64 for m in fd64)
    assert db.decode_message(256, fd64[0].data) == {"Lead": 7, "Tail": 9}
    nobrs = [m for m in got if m.arbitration_id == 258]
    assert nobrs
    assert all(m.is_fd and not m.bitrate_switch for m in nobrs)  # CANFD_BRS 0
    classic = [m for m in got if m.arbitration_id == 768]
    assert all(not m.is_fd and len(m.data) == 8 for m in classic)


async def test_fd_frames_are_received_and_decoded(channel: str, peer: can.BusABC, dbc: str) -> None:
    db = cantools.database.load_file(dbc, strict=False)
    g = GraphBuilder()
    g.add("bus", "can", params={"interface": "virtual", "channel": channel, "dbc": dbc, "fd": True})
    async with Runtime(g.build()) as rt:
        sub = rt.subscribe("bus.Fd12", size=8)
        n = await opened(rt)
        data = db.get_message_by_name("Fd12").encode({"Value": 123456})
        peer.send(
            can.Message(
                arbitration_id=257, data=data, is_fd=True, bitrate_switch=True, is_extended_id=False
            )
        )
        await until(lambda: n.msgs["Fd12"].received == 1)
        msg = await asyncio.wait_for(sub.get(), 2)
    assert isinstance(msg, CanMessage)
    assert msg["Value"] == 123456
    assert msg.fd
    assert msg.brs
    assert msg.channel == channel


async def test_fd_message_on_a_classic_node_is_one_counted_cause(
    channel: str, peer: can.BusABC, dbc: str
) -> None:
    clock = VirtualClock()
    g = sender(channel, dbc, {"Fd64": {"Lead": 1, "Tail": 2}})
    async with Runtime(g.build(), clock=clock) as rt:
        n = await opened(rt)
        await clock.advance(0.5)
        await asyncio.sleep(0.05)
        status = n.snapshot()
        assert drain(peer) == []
        row = next(m for m in status.messages if m.name == "Fd64")
        assert row.encode_errors >= 45
        assert status.encode_errors == (
            ("Fd64", "a CAN FD message on a node without fd: true", row.encode_errors),
        )
        kinds = [e.alert for e in rt.events if isinstance(e, HealthAlert)]
        assert kinds.count("can-encode") == 1


async def test_multiplexed_message_encodes_only_the_selected_branch(
    channel: str, peer: can.BusABC, dbc: str, caplog: pytest.LogCaptureFixture
) -> None:
    clock = VirtualClock()
    # values for both branches: page 1 selects Temp and Flags, Speed waits for page 0
    g = sender(channel, dbc, {"Mux": {"Page": 1, "Temp": 21, "Flags": 3, "Speed": 50}})
    async with Runtime(g.build(), clock=clock) as rt:
        n = await opened(rt)
        await clock.advance(0.1)
        await asyncio.sleep(0.1)
        got = [m for m in drain(peer) if m.arbitration_id == 512]
        assert n.msgs["Mux"].encode_errors == 0
    assert len(got) >= 9
    db = cantools.database.load_file(dbc, strict=False)
    assert db.decode_message(512, got[0].data) == {"Page": 1, "Temp": 21, "Flags": 3}
    assert "cannot encode" not in caplog.text


async def test_multiplexed_frames_decode_their_branch(
    channel: str, peer: can.BusABC, dbc: str
) -> None:
    db = cantools.database.load_file(dbc, strict=False)
    g = GraphBuilder()
    g.add("bus", "can", params={"interface": "virtual", "channel": channel, "dbc": dbc})
    async with Runtime(g.build()) as rt:
        sub = rt.subscribe("bus.Mux", size=8)
        await opened(rt)
        mux = db.get_message_by_name("Mux")
        peer.send(
            can.Message(
                arbitration_id=512,
                data=mux.encode({"Page": 0, "Speed": 12.5}),
                is_extended_id=False,
            )
        )
        peer.send(
            can.Message(
                arbitration_id=512,
                data=mux.encode({"Page": 1, "Temp": -5, "Flags": 9}),
                is_extended_id=False,
            )
        )
        first = await asyncio.wait_for(sub.get(), 2)
        second = await asyncio.wait_for(sub.get(), 2)
    assert first.signals == {"Page": 0, "Speed": 12.5}
    assert second.signals == {"Page": 1, "Temp": -5, "Flags": 9}


async def test_value_out_of_range_is_one_event_per_cause_not_per_tick(
    channel: str, peer: can.BusABC, dbc: str, caplog: pytest.LogCaptureFixture
) -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add(
        "src",
        "can-signals",
        params={
            "rate_ms": 10,
            "signals": {
                "Page": {"value": 1},
                "Flags": {"value": 1},
                "Temp": {"wave": "ramp", "value": 400, "amplitude": 50},
            },
        },
    )
    g.add(
        "bus",
        "can",
        params={"interface": "virtual", "channel": channel, "dbc": dbc},
        inputs={"Mux": "src.values"},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        n = await opened(rt)
        await clock.advance(2.0)
        await asyncio.sleep(0.05)
        status = n.snapshot()
        alerts = [e for e in rt.events if isinstance(e, HealthAlert) and e.alert == "can-encode"]
    row = next(m for m in status.messages if m.name == "Mux")
    assert row.encode_errors >= 190  # every tick of 2 s, none sent
    assert row.sent == 0
    assert len(status.encode_errors) == 1  # one cause, whatever the value each tick
    assert status.encode_errors[0][2] == row.encode_errors
    assert len(alerts) == 1
    assert "Temp" in alerts[0].detail
    assert caplog.text.count("Mux not sent") == 1


async def test_node_statistics_keep_ids_per_channel(channel: str, dbc: str) -> None:
    """One interface delivering two channels (as multi-channel adapters do): the node's
    status counts the same id on each channel apart."""
    g = GraphBuilder()
    g.add("bus", "can", params={"interface": "virtual", "channel": channel, "dbc": dbc})
    async with Runtime(g.build()) as rt:
        n = await opened(rt)
        for ch in ("left", "right", "right"):
            n._on_frame(
                can.Message(arbitration_id=0x300, data=bytes(8), is_extended_id=False, channel=ch)
            )
        status = n.snapshot()
    assert status.ids_by_channel == (("left", 0x300, False, 1), ("right", 0x300, False, 2))
    assert status.channels == ("left", "right")


def test_params_know_the_node_outputs() -> None:
    from flowrt.nodes.can.params import NODE_OUTPUTS

    assert set(Can.outputs) == NODE_OUTPUTS  # no DBC message may shadow them


@settings(max_examples=80, deadline=None)
@given(
    page=st.sampled_from([0, 1]),
    speed=st.integers(0, 1000).map(lambda x: x / 10),
    temp=st.integers(-40, 150),
    flags=st.integers(0, 255),
)
def test_multiplexed_roundtrip_keeps_only_the_selected_branch(
    page: int, speed: float, temp: int, flags: int
) -> None:
    mux = _FD_DB.get_message_by_name("Mux")
    every = {"Page": page, "Speed": speed, "Temp": temp, "Flags": flags}
    decoded = mux.decode(encode_signals(mux, every))
    branch = (
        {"Page": page, "Speed": speed} if page == 0 else {"Page": 1, "Temp": temp, "Flags": flags}
    )
    assert decoded == pytest.approx(branch)


@pytest.mark.parametrize(
    ("values", "cause"),
    [
        ({"Page": 3, "Speed": 1}, 'multiplexer selector signal "Page"'),  # no branch for 3
        ({"Page": 1, "Temp": 900, "Flags": 1}, "Temp"),
        ({"Page": 1, "Temp": 901.5, "Flags": 1}, "Temp"),
    ],
)
def test_encode_causes_leave_the_numbers_out(values: dict[str, float], cause: str) -> None:
    mux = _FD_DB.get_message_by_name("Mux")
    with pytest.raises(EncodeProblem) as e:
        encode_signals(mux, values)
    assert not any(ch.isdigit() for ch in e.value.cause.replace("#", ""))
    assert cause in e.value.cause
