"""An import's counting and liveness, without a network (issue 38 item 7, issue 40 item 3).

A refused plain sample takes no sequence number (it is counted once, as refused); an import
with ``stale_after: never`` never goes stale; with ``stale: state`` a link that drops is a
state (one alert per outage, time down counted, no error), with ``stale: error`` the node's
error state. The ImportLink is driven directly with fake samples and a hand-moved clock.
"""

from __future__ import annotations

import json
import time
import types
from typing import Any

import pytest

from flowrt.events import HealthAlert
from flowrt.graph._loading import load_text
from flowrt.graph._resolve import resolve
from flowrt.graph.diagnostics import GraphError
from flowrt.remote._importer import ImportLink
from flowrt.remote.wire import Header, PlainFormat, own_timestamp


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


class _PlainSample:
    attachment = None

    def __init__(self, payload: bytes) -> None:
        self.payload = _Bytes(payload)


class _Ctx:
    """What check_liveness uses of a node's context: the error state and events."""

    def __init__(self) -> None:
        self.error: str | None = None
        self.errors = 0
        self.events: list[Any] = []

    def set_error(self, reason: str) -> None:
        self.error = reason
        self.errors += 1

    def clear_error(self) -> None:
        self.error = None

    def emit(self, event: Any) -> None:
        self.events.append(event)

    def elapsed(self) -> float:
        return 0.0


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _link(stale_after: float | None, stale_is: str = "error") -> tuple[ImportLink, _Clock]:
    clock = _Clock()
    calls: list[Any] = []
    host = types.SimpleNamespace(
        # call_soon: at once (the loop would run it right after the delivery)
        loop=types.SimpleNamespace(
            call_soon_threadsafe=calls.append, call_soon=lambda f, *a: f(*a)
        ),
        now_mono=clock,
        publish=lambda *a: None,
        record=lambda *a: None,
    )
    bridge = types.SimpleNamespace(
        host=host, clock_probe=lambda zid: None, offset=lambda z: 0.0, clock_known=lambda z: True
    )
    imp = ImportLink(bridge, "cmd", "demo/cmd", 50.0, stale_after, 16, stale_is)  # type: ignore[arg-type]
    return imp, clock


def test_a_refused_plain_sample_takes_no_sequence_number() -> None:
    """Issue 38.7: 60 sent, 30 bad: published 60, dropped 30 undecodable, no invented gap."""
    imp, _ = _link(5.0)
    imp.plain = PlainFormat("json", None, "uint8")
    for i in range(60):
        imp.on_sample(_PlainSample(b'{"vx": 0.1}' if i % 2 == 0 else b"{not json"))
        if len(imp.pending) >= 8:  # the loop takes them now and then
            imp.pending.clear()
    assert imp.link.drop_reasons == {"undecodable": 30}
    assert imp.link.published == 60
    assert imp.link.dropped == 30
    assert imp.plain_seq == 30


def test_stale_after_never_never_goes_stale() -> None:
    imp, clock = _link(None)
    ctx = _Ctx()
    for t in (0.5, 60.0, 3600.0):
        clock.t = t
        imp.check_liveness(ctx)
    assert not imp.stale
    assert ctx.error is None
    assert ctx.events == []
    assert imp.live.validity_ms() is None


def _arrive(imp: ImportLink) -> None:
    imp.on_sample(_PlainSample(b"1"))
    imp.deliver()


def test_stale_as_a_state_is_one_alert_per_outage_and_counts_the_time_down() -> None:
    imp, clock = _link(5.0, "state")  # 50 ms period: stale after 250 ms
    imp.plain = PlainFormat("json", None, "uint8")
    states: list[Any] = []
    imp.bridge.host.publish = lambda node, port, v: port == "state" and states.append(v)  # type: ignore[attr-defined]
    ctx = _Ctx()
    _arrive(imp)
    for step in range(1, 41):  # 2 s of silence, checked every 50 ms
        clock.t = step * 0.05
        imp.check_liveness(ctx)
    assert imp.stale
    assert ctx.error is None  # a state, not an error
    alerts = [e for e in ctx.events if isinstance(e, HealthAlert)]
    assert [a.alert for a in alerts] == ["import-stale"]
    assert imp.report()["down_s"] == pytest.approx(2.0, abs=0.01)  # since the last contact
    _arrive(imp)
    assert not imp.stale
    assert [e.alert for e in ctx.events] == ["import-stale", "import-resumed"]
    report = imp.report()
    assert report["outages"] == 1
    assert report["stale"] is False
    assert report["down_s"] == pytest.approx(2.0, abs=0.01)
    assert report["last_contact"] is not None
    # the state output marks the gap in a recording: stale since the last contact, back after
    assert [(st["stale"], st["silent_s"]) for st in states] == [(True, 0.3), (False, 2.0)]


def test_stale_as_an_error_sets_and_clears_the_node_error() -> None:
    imp, clock = _link(5.0, "error")
    imp.plain = PlainFormat("json", None, "uint8")
    ctx = _Ctx()
    _arrive(imp)
    clock.t = 1.0
    imp.check_liveness(ctx)
    assert ctx.error is not None
    assert "stale on demo/cmd since " in ctx.error  # when it began: true while it lasts
    _arrive(imp)
    assert ctx.error is None
    assert imp.report()["outages"] == 1


def test_the_graph_file_takes_never_and_the_stale_choice() -> None:
    text = """
name: g
zenoh: {listen: ["tcp/127.0.0.1:0"]}
import:
  cmd: {key: demo/cmd, format: json, stale_after: never}
  det: {key: robot1/det, stale: state}
nodes: {}
"""
    graph = resolve(*load_text(text))
    assert graph.nodes["cmd"].params.stale_after is None
    assert graph.nodes["det"].params.stale == "state"
    with pytest.raises(GraphError, match="stale"):
        resolve(*load_text(text.replace("stale: state", "stale: maybe")))


class _Sample:
    def __init__(self, header: Header, payload: bytes) -> None:
        self.attachment = _Bytes(header.encode())
        self.payload = _Bytes(payload)


def test_a_refused_flowrt_sample_is_counted_once_not_again_as_a_gap() -> None:
    """Its header was read: its sequence number is taken, so the next sample sees no gap."""
    imp, _ = _link(5.0)
    for seq in range(6):
        payload = b"{not json" if seq % 2 else b'{"v": 1}'
        imp.on_sample(_Sample(Header("s", "z", seq, time.time(), time.time(), "json"), payload))
        imp.pending.clear()
    assert imp.link.published == 6
    assert imp.link.drop_reasons == {"undecodable": 3}
    assert imp.link.dropped == 3


def test_a_message_timestamp_is_mapped_onto_the_importer_clock() -> None:
    """Issue 40 item 5: a detection's own timestamp (the exporter's monotonic clock) arrives
    as the importer's monotonic time of the same instant, through the measured offset."""
    imp, clock = _link(5.0)
    clock.t = 1000.0
    published: list[Any] = []
    imp.bridge.host.publish = lambda node, port, value: published.append(value)  # type: ignore[attr-defined]
    imp.bridge.offset = lambda zid: -5.0  # type: ignore[attr-defined]  # its clock 5 s behind
    captured = time.time() - 5.0 - 0.010  # 10 ms ago, on the exporter's clock
    header = Header("s", "z", 0, captured + 0.002, captured, "json")
    payload = json.dumps({"__type__": "FrameDetection", "seq": 7, "timestamp": 42.0}).encode()
    imp.on_sample(_Sample(header, payload))
    imp.deliver()
    (det,) = published
    assert det.seq == 7
    assert det.timestamp == pytest.approx(1000.0 - 0.010, abs=0.002)


def test_the_exporter_sends_a_message_timestamp_as_its_capture_time() -> None:
    assert own_timestamp({"v": 1.0, "timestamp": 12.5}) == 12.5
    assert own_timestamp(types.SimpleNamespace(timestamp=3.0)) == 3.0
    for none in ({"timestamp": 0.0}, {"timestamp": "x"}, 5, types.SimpleNamespace()):
        assert own_timestamp(none) is None


def test_before_the_exporter_clock_is_measured_the_arrival_time_is_used() -> None:
    """A guess of 0 offset would put a first detection 5 s off; its arrival is ms off."""
    imp, clock = _link(5.0)
    clock.t = 1000.0
    published: list[Any] = []
    imp.bridge.host.publish = lambda node, port, value: published.append(value)  # type: ignore[attr-defined]
    imp.bridge.clock_known = lambda zid: False  # type: ignore[attr-defined]
    header = Header("s", "z", 0, time.time() - 5.0, time.time() - 5.01, "json")
    imp.on_sample(_Sample(header, json.dumps({"timestamp": 42.0, "v": 1.0}).encode()))
    imp.deliver()
    assert published[0]["timestamp"] == 1000.0
    # nor has it an age: 0 offset read "age max 5001 ms" (a new-user pass, 5 s off)
    assert imp.link.delivered == 1
    assert imp.link.age.count == 0
    imp.bridge.clock_known = lambda zid: True  # type: ignore[attr-defined]
    imp.bridge.offset = lambda zid: -5.0  # type: ignore[attr-defined]
    imp.on_sample(_Sample(Header("s", "z", 1, time.time() - 5.0, time.time() - 5.0, "json"), b"{}"))
    imp.deliver()
    assert imp.link.age.count == 1
    assert imp.link.age.max < 100  # ms: its clock known, the age holds
