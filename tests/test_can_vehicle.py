"""The ``can`` node with whole vehicles' databases (issue 38): opendbc's largest DBCs, CAN FD
included, on python-can's ``virtual`` bus at default params.

Before, the node kept its whole status table in the RTDB record ``<node>.can``; with 40 or
more messages the value was over the RTDB's 4096-byte limit, ``process`` raised at every
``status_ms`` and the node restarted, losing frames (179 of 331 decoded). Now the record
holds a bounded summary and the table goes on ``status`` only. A message cantools cannot
unpack whole (overlapping signals: 177 of the GM database's 367) was a decode error at every
frame; it is now decoded signal by signal, each signal as cantools decodes it alone.
"""

from __future__ import annotations

import asyncio
import pickle
import random
import time
from typing import Any

import can
import cantools
import pytest
from _can_dbcs import VEHICLE_DBCS, opendbc
from cantools.database.can import Message
from flowrt.nodes.can.dbc import load_dbc, message_is_fd
from flowrt.nodes.can.node import Can, CanBusStatus, CanBusSummary, CanMessage
from flowrt.nodes.can.values import SUMMARY_NAMES, MessageStatus, summarise

from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.analysis.can_frames import fd_payload_length

pytestmark = pytest.mark.timeout(120)


async def until(cond: Any, within: float = 30.0) -> None:
    """Wait in real time for frames to cross the reader thread (not a timing assertion)."""
    end = time.monotonic() + within
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached")
        await asyncio.sleep(0.01)


def frames_of(db: Any, seed: int) -> list[tuple[Any, can.Message]]:
    """One frame per message, random payload (every signal some value), FD where the DBC
    says so, padded to the FD length the wire carries."""
    rnd = random.Random(seed)
    out = []
    for m in db.messages:
        fd = message_is_fd(m)
        n = fd_payload_length(m.length) if fd else m.length
        data = bytes(rnd.getrandbits(8) for _ in range(m.length)) + bytes(n - m.length)
        msg = can.Message(
            arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame, is_fd=fd, data=data
        )
        out.append((m, msg))
    return out


def cantools_decode(db: Any, m: Any, data: bytes) -> dict[str, Any]:
    """What cantools makes of a frame: the message whole; or, where cantools cannot unpack
    it whole (gm's ``...Group`` signals overlap their parts: 177 of 367 messages), each
    signal alone, as a one-signal cantools message decodes it."""
    try:
        return dict(db.decode_message(m.frame_id, data, decode_choices=False))
    except cantools.database.DecodeError:
        if m.is_multiplexed():
            raise
    out: dict[str, Any] = {}
    for sig in m.signals:
        one = Message(
            m.frame_id, m.name, m.length, [sig], is_extended_frame=m.is_extended_frame, strict=False
        )
        out.update(one.decode(data, decode_choices=False))
    return out


@pytest.mark.slow  # 2-3 s a database (the reader thread takes hundreds of frames)
@pytest.mark.parametrize("name", VEHICLE_DBCS)
async def test_every_message_of_a_vehicle_dbc_decodes_as_cantools_does(name: str) -> None:
    path = opendbc(name)
    db = load_dbc(path)
    channel = f"vehicle-{time.monotonic_ns()}"
    g = GraphBuilder()
    g.add("car", "can", params={"interface": "virtual", "channel": channel, "dbc": path})
    clock = VirtualClock()
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        async with Runtime(g.build(), clock=clock) as rt:
            subs = {m.name: rt.subscribe(f"car.{m.name}", size=4) for m in db.messages}
            status = rt.subscribe("car.status", size=16)
            runner = rt.scheduler.runners["car"]
            await until(lambda: getattr(runner.executor, "node", None) is not None)
            node = runner.executor.node  # type: ignore[attr-defined]
            assert isinstance(node, Can)
            await until(lambda: node.bus is not None)
            sent = frames_of(db, seed=len(name))
            expected: dict[str, Any] = {}
            refused = 0
            for m, msg in sent:
                try:
                    expected[m.name] = cantools_decode(db, m, bytes(msg.data[: m.length]))
                except Exception:  # cantools refuses it too (a multiplexer with no branch)
                    refused += 1
                peer.send(msg)
            assert refused <= 2  # hyundai_2015_ccan's multiplexed messages at random values
            await until(lambda: node.received == len(sent))
            await clock.advance(3.5)  # three status periods, at default params
            for m, msg in sent:
                if m.name not in expected:  # counted as a decode error, not published
                    continue
                got = subs[m.name].get_nowait()  # the frame's, before any timeout
                assert isinstance(got, CanMessage)
                assert got.id == m.frame_id
                assert got.data == bytes(msg.data)
                assert got.valid, m.name
                assert got.signals == expected[m.name], m.name
            assert len(expected) + refused == len(db.messages)
            assert node.decode_errors == refused
            assert node.unknown_count == 0
            counts = runner.counts
            assert counts.restarts == 0
            assert counts.errors == 0
            last: CanBusStatus | None = None
            while True:
                try:
                    last = status.get_nowait()
                except LookupError:
                    break
            assert last is not None
            assert len(last.messages) == len(db.messages)  # the full table on the output
            kept = rt.rtdb.read("car.can")
            assert kept is not None
            summary = kept.value
            assert isinstance(summary, CanBusSummary)
            assert summary.messages == len(db.messages)
            assert summary.received == len(sent)
            assert summary.t == last.t
    finally:
        peer.shutdown()


def _row(i: int, name: str) -> MessageStatus:
    return MessageStatus(name, i, 1, 0, 0.0, None, 1, 0, 0, 0, 0, 0, False)


def test_the_summary_is_bounded_whatever_the_dbc() -> None:
    """3000 invalid messages with 300-character names, a long channel: the summary the RTDB
    keeps is the same few hundred bytes, the full table tens of kilobytes."""
    rows = tuple(_row(i, f"M{i}_" + "x" * 300) for i in range(3000))
    status = CanBusStatus(
        1.0, "virtual", "/dev/serial/by-id/" + "y" * 500, True, 3000, 0, 0, 0, 0, 0, 0, 0, 0,
        rows, unknown_by_channel=tuple((f"c{i}", 1) for i in range(500)),
    )  # fmt: skip
    summary = summarise(status)
    assert len(pickle.dumps(status)) > 100_000
    assert len(pickle.dumps(summary, protocol=pickle.HIGHEST_PROTOCOL)) < 2048
    assert summary.messages == 3000
    assert summary.invalid == 3000
    assert summary.timeouts == 3000
    assert len(summary.invalid_names) == SUMMARY_NAMES
    assert summary.invalid_names[0].startswith("M0_x")
    small = summarise(CanBusStatus(1.0, "virtual", None, True, 0, 0, 0, 0, 0, 0, 0, 0, 0, ()))
    assert small.invalid_names == ()
    assert small.channel is None


async def test_an_rtdb_too_small_for_the_summary_is_said_once_not_raised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    channel = f"small-rtdb-{time.monotonic_ns()}"
    g = GraphBuilder()
    params = {"interface": "virtual", "channel": channel, "dbc": "robot.dbc", "status_ms": 100}
    g.add("car", "can", params=params)
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        rt.rtdb.max_value = 64  # an RTDB made smaller than any summary
        runner = rt.scheduler.runners["car"]
        await until(lambda: getattr(runner.executor, "node", None) is not None)
        await clock.advance(0.55)
        assert runner.counts.restarts == 0
        assert runner.counts.errors == 0
        assert runner.executor.node.keep_status is False  # type: ignore[attr-defined]
    said = [r for r in caplog.records if "status not kept in the RTDB" in r.getMessage()]
    assert len(said) == 1
    assert "more than max_value 64" in said[0].getMessage()


async def test_a_quiet_vehicle_bus_is_one_alert_per_tick_not_one_per_message() -> None:
    """Nothing on the bus: every periodic message times out, each republished invalid, and
    the alerts come one per tick in which several timed out, not 331 lines."""
    from flowrt import HealthAlert

    path = opendbc("ford_lincoln_base_pt.dbc")
    db = load_dbc(path)
    channel = f"quiet-{time.monotonic_ns()}"
    g = GraphBuilder()
    g.add("car", "can", params={"interface": "virtual", "channel": channel, "dbc": path})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        runner = rt.scheduler.runners["car"]
        await until(lambda: getattr(runner.executor, "node", None) is not None)
        node = runner.executor.node  # type: ignore[attr-defined]
        await clock.advance(16.0)  # 10 x its cycles up to 1.5 s (one is 100 s)
        periodic = [m for m in db.messages if m.cycle_time and m.cycle_time <= 1500]
        assert len(periodic) == 149
        assert all(node.msgs[m.name].timeouts == 1 for m in periodic)
        alerts = [e for e in rt.events if isinstance(e, HealthAlert) and e.alert == "can-timeout"]
    assert 0 < len(alerts) <= 16  # ten distinct timeouts, a tick or two each
    grouped = [a for a in alerts if "messages not received within their timeouts" in a.detail]
    assert grouped
    assert sum(int(a.detail.split()[0]) for a in grouped) + len(alerts) - len(grouped) == len(
        periodic
    )
