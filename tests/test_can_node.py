"""The ``can`` node on python-can's virtual bus: receive, transmit, supervise, recover.

The test plays the other ECUs with a plain python-can ``virtual`` bus on the same channel
(a fresh channel per test). "Interface gone" uses a virtual bus that can be unplugged (the
``flaky`` interface registered below), as an adapter pulled from its USB port would: reads
fail, and opening fails until it is plugged back.
"""

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
from can.interfaces import BACKENDS
from can.interfaces.virtual import VirtualBus
from flowrt.nodes.can.node import Can, CanMessage, checksum

from flowrt import GraphBuilder, GraphError, HealthAlert, Runtime, VirtualClock

pytestmark = pytest.mark.timeout(30)

DBC = str(Path(__file__).resolve().parent.parent / "nodes" / "robot.dbc")
db = cantools.database.load_file(DBC)
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"test-can-{time.monotonic_ns()}-{next(_channels)}"


@pytest.fixture
def peer(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


async def until(cond: Callable[[], Any], within: float = 5.0) -> None:
    """Wait in real time for frames to cross the reader thread (not a timing assertion)."""
    end = time.monotonic() + within
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached")
        await asyncio.sleep(0.005)


def frame(name: str, **signals: Any) -> can.Message:
    m = db.get_message_by_name(name)
    values = {s.name: 0 for s in m.signals} | signals
    return can.Message(arbitration_id=m.frame_id, data=m.encode(values), is_extended_id=False)


def wheels(counter: int, good_sum: bool = True, **signals: Any) -> can.Message:
    msg = frame("WheelSpeeds", Counter=counter, **signals)
    data = bytearray(msg.data)
    data[7] = checksum("xor", bytes(data), 7) ^ (0 if good_sum else 0xFF)
    msg.data = data
    return msg


def node(rt: Runtime, name: str = "chassis") -> Can:
    n = rt.scheduler.runners[name].executor.node  # type: ignore[attr-defined]
    assert isinstance(n, Can)
    return n


def graph(channel: str, inputs: dict[str, str] | None = None, **params: Any) -> GraphBuilder:
    g = GraphBuilder()
    p = {"interface": "virtual", "channel": channel, "dbc": DBC, **params}
    g.add("chassis", "can", params=p, inputs=inputs or {})
    return g


async def opened(rt: Runtime, name: str = "chassis") -> Can:
    await until(lambda: rt.scheduler.runners[name].executor.node is not None)
    n = node(rt, name)
    await until(lambda: n.bus is not None)
    return n


async def test_receive_decodes_and_counts_unknown_ids(channel: str, peer: can.BusABC) -> None:
    async with Runtime(graph(channel, unknown_output=True).build()) as rt:
        speeds = rt.subscribe("chassis.WheelSpeeds")
        raw = rt.subscribe("chassis.unknown")
        n = await opened(rt)
        peer.send(frame("WheelSpeeds", LeftSpeed=1.25, RightSpeed=-0.5, Heading=90.0))
        peer.send(can.Message(arbitration_id=0x7FF, data=[1, 2], is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x100, data=[0] * 8, is_extended_id=True))
        await until(lambda: n.unknown_count == 2)
        msg = speeds.get_nowait()
        assert isinstance(msg, CanMessage)
        assert msg.valid
        assert msg.id == 0x100
        assert msg["LeftSpeed"] == pytest.approx(1.25)
        assert msg["RightSpeed"] == pytest.approx(-0.5)
        assert msg["Heading"] == pytest.approx(90.0)
        assert len(msg.data) == 8
        assert msg.timestamp <= rt.clock.now()
        unknown = [raw.get_nowait(), raw.get_nowait()]
        assert [(u.id, u.extended) for u in unknown] == [(0x7FF, False), (0x100, True)]
        assert [u.dlc for u in unknown] == [2, 8]  # (was 0: the frames output's was right)
        assert n.snapshot().unknown == 2


async def test_wrong_length_is_counted_not_decoded(channel: str, peer: can.BusABC) -> None:
    async with Runtime(graph(channel).build()) as rt:
        speeds = rt.subscribe("chassis.WheelSpeeds")
        n = await opened(rt)
        peer.send(can.Message(arbitration_id=0x100, data=[1, 2, 3], is_extended_id=False))
        peer.send(frame("Infrared", Front=33))  # a good one after it, to know we are past
        await until(lambda: n.msgs["Infrared"].received == 1)
        assert n.msgs["WheelSpeeds"].bad_length == 1
        with pytest.raises(LookupError):
            speeds.get_nowait()
        row = {r.name: r for r in n.snapshot().messages}["WheelSpeeds"]
        assert row.bad_length == 1


async def test_counter_skips_and_bad_checksums_invalidate_until_good_return(
    channel: str, peer: can.BusABC
) -> None:
    opts = {"WheelSpeeds": {"counter": "Counter", "checksum": "Checksum"}}
    async with Runtime(graph(channel, messages=opts, max_bad=3).build()) as rt:
        speeds = rt.subscribe("chassis.WheelSpeeds", size=64)
        n = await opened(rt)
        st = n.msgs["WheelSpeeds"]

        async def send(*msgs: can.Message) -> list[CanMessage]:
            before = st.received
            for m in msgs:
                peer.send(m)
            await until(lambda: st.received == before + len(msgs))
            return [speeds.get_nowait() for _ in msgs]

        out = await send(*(wheels(c) for c in range(4)))
        assert [m.valid for m in out] == [True] * 4
        out = await send(wheels(6), wheels(6), wheels(8, good_sum=False))  # skip, repeat, sum
        assert st.bad_counter == 3  # 3->6 skipped, 6 repeated, 6->8 skipped
        assert st.bad_checksum == 1
        assert [m.valid for m in out] == [True, True, False]  # the 3rd bad one: invalid
        assert out[-1].reason in ("checksum", "counter")
        out = await send(wheels(8, good_sum=False), wheels(9, good_sum=False))
        assert [m.valid for m in out] == [False, False]  # still bad: stays invalid
        out = await send(wheels(10))
        assert out[0].valid  # a good frame returns (opendbc: each good one takes one off)
        out = await send(wheels(11), wheels(13))
        assert [m.valid for m in out] == [True, True]  # one bad among good ones: tolerated
        assert {r.name: r for r in n.snapshot().messages}[
            "WheelSpeeds"
        ].bad_counter == 5  # + 8 repeated, 11->13


async def test_timeout_marks_invalid_and_alerts(channel: str, peer: can.BusABC) -> None:
    clock = VirtualClock()
    opts = {"WheelSpeeds": {"timeout_ms": 100}}
    async with Runtime(graph(channel, messages=opts).build(), clock=clock) as rt:
        speeds = rt.subscribe("chassis.WheelSpeeds")
        infrared = rt.subscribe("chassis.Infrared")
        n = await opened(rt)
        await clock.advance(0.05)
        peer.send(frame("WheelSpeeds", LeftSpeed=0.3))
        await until(lambda: n.msgs["WheelSpeeds"].received == 1)
        assert speeds.get_nowait().valid
        await clock.advance(0.09)
        with pytest.raises(LookupError):
            speeds.get_nowait()  # 90 ms: not yet
        await clock.advance(0.03)
        stale = speeds.get_nowait()
        assert not stale.valid
        assert stale.reason == "timeout"
        assert stale["LeftSpeed"] == pytest.approx(0.3)  # the last values, marked invalid
        await clock.advance(0.5)
        with pytest.raises(LookupError):
            speeds.get_nowait()  # alerted and published once, not at every tick
        alerts = [e for e in rt.events if isinstance(e, HealthAlert) and e.alert == "can-timeout"]
        wheel_alerts = [a for a in alerts if "WheelSpeeds" in a.detail]
        assert len(wheel_alerts) == 1
        # Infrared (20 ms cycle, 10 x = 200 ms) never came at all: timed out too, stamped
        # at its timeout (it was 0.0: the machine's boot in a recording's Unix time)
        assert any("Infrared" in a.detail for a in alerts)
        never = infrared.get_nowait()
        assert (never.valid, never.reason, never.signals) == (False, "timeout", {})
        assert never.timestamp == pytest.approx(0.2, abs=0.03)
        assert n.msgs["WheelSpeeds"].timeouts == 1
        peer.send(frame("WheelSpeeds", LeftSpeed=0.4))
        await until(lambda: n.msgs["WheelSpeeds"].received == 2)
        assert speeds.get_nowait().valid


async def test_error_frames_and_bus_off_are_counted_and_survived(
    channel: str, peer: can.BusABC
) -> None:
    async with Runtime(graph(channel, reopen_ms=10).build()) as rt:
        n = await opened(rt)
        peer.send(can.Message(arbitration_id=0x004, is_error_frame=True, data=[0] * 8))
        await until(lambda: n.error_frames == 1)
        assert n.bus_off == 0
        peer.send(can.Message(arbitration_id=0x040, is_error_frame=True, data=[0] * 8))
        await until(lambda: n.bus_off == 1)
        assert n.link.lost_count == 1
        await until(lambda: n.link.reopens == 1 and n.bus is not None)  # reopened, clean state
        assert rt.scheduler.runners["chassis"].error_reason is None
        peer.send(frame("Infrared", Front=10))
        await until(lambda: n.msgs["Infrared"].received == 1)
        assert n.snapshot().error_frames == 2


class FlakyBus(VirtualBus):
    """A virtual bus whose adapter can be pulled out (``FlakyBus.plugged = False``)."""

    plugged = True

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        if not FlakyBus.plugged:
            raise can.CanInitializationError("no such device")
        super().__init__(channel=channel, **kwargs)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not FlakyBus.plugged:
            raise can.CanOperationError("device unplugged")
        return super()._recv_internal(timeout)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not FlakyBus.plugged:
            raise can.CanOperationError("device unplugged")
        super().send(msg, timeout)


@pytest.fixture
def flaky(monkeypatch: pytest.MonkeyPatch) -> Iterator[type[FlakyBus]]:
    BACKENDS["flaky"] = (__name__, "FlakyBus")
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"flaky"})
    FlakyBus.plugged = True
    yield FlakyBus
    FlakyBus.plugged = True
    del BACKENDS["flaky"]


async def test_interface_gone_and_back(
    channel: str, peer: can.BusABC, flaky: type[FlakyBus]
) -> None:
    g = graph(channel, interface="flaky", reopen_ms=20, reopen_max_ms=40)
    async with Runtime(g.build()) as rt:
        runner = rt.scheduler.runners["chassis"]
        try:
            n = await opened(rt)
        except AssertionError:
            raise AssertionError(runner.error_reason) from None
        peer.send(frame("Infrared", Front=1))
        await until(lambda: n.msgs["Infrared"].received == 1)
        flaky.plugged = False
        await until(lambda: n.link.lost_count == 1)
        assert runner.error_reason is not None
        assert "lost" in runner.error_reason
        assert "unplugged" in runner.error_reason
        await until(
            lambda: runner.error_reason is not None and "cannot open" in runner.error_reason
        )
        assert n.bus is None
        flaky.plugged = True
        await until(lambda: n.bus is not None)
        await until(lambda: runner.error_reason is None)
        assert n.link.reopens == 1
        peer.send(frame("Infrared", Front=2))
        await until(lambda: n.msgs["Infrared"].received == 2)
        kinds = [e.alert for e in rt.events if isinstance(e, HealthAlert)]
        assert "node-error" in kinds
        assert "node-recovered" in kinds
        assert runner.state != "failed"
        assert runner.counts.errors == 0  # nothing raised out of the node


async def test_periodic_transmit_from_the_scheduler(channel: str, peer: can.BusABC) -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add(
        "ctl",
        "can-signals",
        params={
            "rate_ms": 20,
            "signals": {"LeftSetpoint": {"value": 0.25}, "RightSetpoint": {"value": -1}},
        },
    )
    g.add("kick", "can-signals", params={"rate_ms": 250, "signals": {"Power": {"value": 80}}})
    g.add(
        "chassis",
        "can",
        params={
            "interface": "virtual",
            "channel": channel,
            "dbc": DBC,
            "messages": {"MotorSetpoints": {"counter": "Counter", "checksum": "Checksum"}},
        },
        inputs={"MotorSetpoints": "ctl.values", "Kick": "kick.values"},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await opened(rt)
        await clock.advance(1.0)
        await asyncio.sleep(0.1)
        got: list[can.Message] = []
        while (m := peer.recv(0)) is not None:
            got.append(m)
        sp = [m for m in got if m.arbitration_id == 0x80]
        kicks = [m for m in got if m.arbitration_id == 0x90]
        # 20 ms cycle over 1 s; the first value arrives on the first tick
        assert len(sp) in (49, 50, 51)
        assert len(kicks) == 5  # event message: once per new value (t = 0, .25, ... 1.0)
        dec = [db.decode_message(0x80, m.data) for m in sp]
        assert all(d["LeftSetpoint"] == pytest.approx(0.25) for d in dec)
        assert all(d["RightSetpoint"] == pytest.approx(-1) for d in dec)
        counters = [int(d["Counter"]) for d in dec]
        assert counters == [k % 16 for k in range(len(counters))]
        assert all(m.data[5] == checksum("xor", bytes(m.data), 5) for m in sp)
        assert node(rt).msgs["MotorSetpoints"].late == 0


def test_dbc_that_does_not_parse_is_one_error_at_validate(tmp_path: Path) -> None:
    bad = tmp_path / "bad.dbc"
    bad.write_text('VERSION ""\nBO_ 1 X: 9 Y\n garbage\n')
    g = GraphBuilder()
    g.add("bus", "can", params={"dbc": str(bad)})
    with pytest.raises(GraphError) as e:
        g.build()
    (err,) = e.value.errors
    assert "not a valid CAN database" in str(err)
    assert "\n" not in str(err)


@pytest.mark.parametrize(
    ("params", "inputs", "needle"),
    [
        ({"dbc": "nope.dbc"}, {}, "no such file"),
        ({"dbc": DBC, "interface": "nosuch"}, {}, "unknown python-can interface"),
        ({"dbc": DBC, "interface": "virtal"}, {}, "'virtal' (did you mean 'virtual'?)"),
        ({"dbc": DBC, "messages": {"Nope": {}}}, {}, "'Nope' is not a message"),
        ({"dbc": DBC, "messages": {"WheelSpeed": {}}}, {}, "(did you mean 'WheelSpeeds'?)"),
        ({"dbc": DBC, "messages": {"Infrared": {"counter": "X"}}}, {}, "counter signal 'X'"),
        ({"dbc": DBC, "messages": {"Battery": {"checksum": "Voltage"}}}, {}, "one whole byte"),
        ({"dbc": DBC}, {"MotorSetpoint": "src.values"}, "has no input 'MotorSetpoint'"),
    ],
)
def test_bad_params_are_graph_errors(
    params: dict[str, Any], inputs: dict[str, str], needle: str
) -> None:
    g = GraphBuilder()
    g.add("src", "can-signals", params={"signals": {"a": {}}})
    g.add("bus", "can", params=params, inputs=inputs)
    with pytest.raises(GraphError) as e:
        g.build()
    assert needle in str(e.value)


def test_outputs_by_message_name_are_checked() -> None:
    g = GraphBuilder()
    g.add("bus", "can", params={"dbc": DBC})
    g.add("world", "rtdb", inputs={"w": "bus.WheelSpeed"})
    with pytest.raises(GraphError, match="did you mean 'WheelSpeeds'"):
        g.build()


async def test_replay_a_trace_at_its_timing(channel: str, peer: can.BusABC, tmp_path: Path) -> None:
    trace = tmp_path / "t.asc"
    with can.ASCWriter(str(trace)) as w:
        for k in range(5):
            w.on_message_received(
                can.Message(
                    timestamp=50 + 0.1 * k, arbitration_id=0x123, data=[k], is_extended_id=False
                )
            )
    clock = VirtualClock()
    async with Runtime(graph(channel, replay=str(trace), tick_ms=10).build(), clock=clock) as rt:
        await opened(rt)
        await clock.advance(0.25)
        await asyncio.sleep(0.05)
        got = []
        while (m := peer.recv(0)) is not None:
            got.append(m)
        assert [m.data[0] for m in got] == [0, 1, 2]  # t = 0, 0.1, 0.2 of the trace
        await clock.advance(0.3)
        await asyncio.sleep(0.05)
        while (m := peer.recv(0)) is not None:
            got.append(m)
        assert [m.data[0] for m in got] == [0, 1, 2, 3, 4]


async def test_input_that_does_not_fit_is_counted_not_raised(
    channel: str, peer: can.BusABC
) -> None:
    clock = VirtualClock()
    g = graph(channel, inputs={"MotorSetpoints": "ctl.values"})
    g.add("ctl", "can-signals", params={"rate_ms": 20, "signals": {"Nope": {"value": 1}}})
    async with Runtime(g.build(), clock=clock) as rt:
        n = await opened(rt)
        await clock.advance(0.2)
        await asyncio.sleep(0.05)
        assert n.msgs["MotorSetpoints"].bad_inputs >= 10
        assert n.msgs["MotorSetpoints"].sent == 0
        assert peer.recv(0) is None
        assert rt.scheduler.runners["chassis"].counts.errors == 0
        row = {r.name: r for r in n.snapshot().messages}["MotorSetpoints"]
        assert row.bad_inputs == n.msgs["MotorSetpoints"].bad_inputs


async def test_status_is_published_and_kept_in_the_rtdb(channel: str, peer: can.BusABC) -> None:
    clock = VirtualClock()
    async with Runtime(graph(channel, status_ms=100).build(), clock=clock) as rt:
        status = rt.subscribe("chassis.status")
        n = await opened(rt)
        peer.send(frame("Infrared", Front=5))
        await until(lambda: n.msgs["Infrared"].received == 1)
        await clock.advance(0.25)
        last = status.get_nowait()
        while True:
            try:
                last = status.get_nowait()
            except LookupError:
                break
        assert last.open
        assert last.received == 1
        rows = {r.name: r for r in last.messages}
        assert rows["Infrared"].received == 1
        assert 200 <= rows["Infrared"].age_ms <= 250  # the status of the last 100 ms tick
        assert rows["Infrared"].timeouts == 1  # 20 ms cycle: 200 ms without it is a timeout
        assert not rows["Infrared"].valid
        kept = rt.rtdb.read("chassis.can")
        assert kept is not None
        assert kept.value.received == 1


async def test_an_unchanged_periodic_value_is_not_encoded_again(
    channel: str, peer: can.BusABC, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 31: a periodic message without counter or checksum is encoded once per new
    value, not at every send (the encode sat between the timer's release and bus.send);
    a new value goes out from the next send on."""
    import flowrt.nodes.can.transmit as can_transmit

    encodes: list[dict[str, Any]] = []
    real = can_transmit.encode_signals

    def counting(msg: Any, values: Any) -> bytes:
        encodes.append(dict(values))
        return real(msg, values)

    monkeypatch.setattr(can_transmit, "encode_signals", counting)
    clock = VirtualClock()
    g = graph(channel, {"Battery": "host.values"})
    g.add("host", "can-signals", params={"signals": {"Voltage": {}}}, enabled=False)
    async with Runtime(g.build(), clock=clock) as rt:
        await opened(rt)
        rt.publish("host.values", {"Voltage": 12.0})  # the host program plays the source
        await clock.advance(0.55)  # 100 ms cycle: 6 sends
        rt.publish("host.values", {"Voltage": 13.0})
        await clock.advance(0.5)
        await asyncio.sleep(0.1)
        sent = []
        while (m := peer.recv(0)) is not None:
            sent.append(db.decode_message(m.arbitration_id, m.data)["Voltage"])
    assert len(sent) >= 10
    assert len(encodes) == 2  # one per value
    assert sent[0] == pytest.approx(12.0)
    assert sent[-1] == pytest.approx(13.0)
    assert sorted(set(sent), key=sent.index) == pytest.approx([12.0, 13.0])


@pytest.mark.realtime
async def test_a_precise_can_node_sends_and_recovers_from_its_release_thread(
    channel: str, peer: can.BusABC, flaky: type[FlakyBus]
) -> None:
    """``timing: precise``: ``process`` (the sends, a failed send, the reopen) runs in the
    node's release thread; what the link does on the loop is handed over there."""
    g = GraphBuilder()
    signals = {"LeftSetpoint": {"value": 0.25}, "RightSetpoint": {"value": -1}}
    g.add("ctl", "can-signals", params={"rate_ms": 20, "signals": signals})
    p = {"interface": "flaky", "channel": channel, "dbc": DBC, "reopen_ms": 20, "reopen_max_ms": 40}
    g.add("chassis", "can", params=p, inputs={"MotorSetpoints": "ctl.values"}, timing="precise")
    got: list[can.Message] = []

    def setpoints() -> int:
        while (m := peer.recv(0)) is not None:
            got.append(m)
        return sum(m.arbitration_id == 0x80 for m in got)

    async with Runtime(g.build()) as rt:
        runner = rt.scheduler.runners["chassis"]
        n = await opened(rt)
        await until(lambda: setpoints() >= 5)
        flaky.plugged = False
        await until(lambda: n.link.lost_count == 1)
        await until(
            lambda: runner.error_reason is not None and "cannot open" in runner.error_reason
        )
        flaky.plugged = True
        await until(lambda: n.bus is not None and runner.error_reason is None)
        before = setpoints()
        await until(lambda: setpoints() >= before + 5)
        st = rt.stats().node("chassis")
    assert st.granted.startswith("precise thread")
    assert runner.counts.errors == 0  # nothing raised out of the node
    assert n.link.reopens == 1
