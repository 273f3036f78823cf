"""Mappings recorded with the ``ros2`` profile come back from flowrt's replay as mappings.

Found by a new user: ``flowrt record graphs/can.yaml --profile ros2`` then ``flowrt replay
BAG --graph graphs/can.yaml`` gave the ``can`` nodes ``{"items": [{key, value, text}]}``
instead of their signals (``no signal 'items'``, then can-timeout alerts): a mapping is written
as ``flowrt_msgs/msg/KeyValues`` (a number in ``value``, anything else as ``text``) and was
replayed as that message. The replay now gives back the mapping it was written from; other
readers still see ``KeyValues`` (the written format is unchanged).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import flowrt.nodes.replay as replay_mod
import numpy as np
import pytest
from flowrt.nodes.replay import Replay
from mcap.records import Schema
from mcap_ros2._dynamic import generate_dynamic

import flowrt
from flowrt import Input, Node, Output, TimerTrigger
from flowrt.recording.decoding import MessageDecoder
from flowrt.recording.ros2_profile import Ros2Encoder, mapping_restorer
from flowrt.recording.writer.threads import RecordingWriter
from flowrt.testing import NodeHarness

pytestmark = pytest.mark.timeout(120)

INF = math.inf

# (case, mapping recorded, mapping replayed): a number comes back a float (KeyValue.value is
# a float64), everything else as it was.
ROUND_TRIP: list[tuple[str, dict[Any, Any], dict[str, Any]]] = [
    (
        "can_signals",
        {"LeftSpeed": 0.25, "RightSpeed": -0.4, "Heading": 359.0, "Counter": 3},
        {"LeftSpeed": 0.25, "RightSpeed": -0.4, "Heading": 359.0, "Counter": 3.0},
    ),
    ("ints", {"Zero": 0, "Neg": -7, "Big": 2**40}, {"Zero": 0.0, "Neg": -7.0, "Big": 2.0**40}),
    ("floats", {"Tiny": 1e-9, "Inf": INF, "Neg": -INF}, {"Tiny": 1e-9, "Inf": INF, "Neg": -INF}),
    ("bools", {"On": True, "Off": False}, {"On": True, "Off": False}),
    (
        "strings",
        {"Mode": "drive", "Digits": "42", "Padded": " true", "Text": "ß → ü", "Brace": "{x"},
        {"Mode": "drive", "Digits": "42", "Padded": " true", "Text": "ß → ü", "Brace": "{x"},
    ),
    ("none", {"Fault": None, "Speed": 1.0}, {"Fault": None, "Speed": 1.0}),
    (
        "nested",
        {"Cfg": {"a": 1, "b": [1, 2.5, None, "x"], "c": {"d": False}}, "Pair": (1, 2), "Empty": {}},
        {"Cfg": {"a": 1, "b": [1, 2.5, None, "x"], "c": {"d": False}}, "Pair": [1, 2], "Empty": {}},
    ),
    (
        "numpy",
        {"F": np.float32(0.5), "I": np.int64(3), "B": np.bool_(True), "A": np.array([1, 2])},
        {"F": 0.5, "I": 3.0, "B": True, "A": [1, 2]},
    ),
    # what the format does not keep, as mappings_of's docstring says
    ("int_keys", {1: 2.0, "A": 1}, {"1": 2.0, "A": 1.0}),
    ("json_strings", {"T": "true", "N": "null", "L": "[1,2]"}, {"T": True, "N": None, "L": [1, 2]}),
    ("nan_and_empty_text", {"Nan": math.nan, "Empty": ""}, {"Nan": math.nan, "Empty": math.nan}),
]  # fmt: skip


def same(a: Any, b: Any) -> bool:
    """Equal with the same types (``3.0`` is not ``3``), NaN equal to NaN."""
    if isinstance(a, dict) and isinstance(b, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b)


class Signals(Node):
    """A CAN-signals-like source: a mapping of signal names every 20 ms."""

    values = Output(dict, doc="signal name -> value")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=20)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> dict[str, Any]:
        self.n += 1
        n = self.n
        return {"LeftSpeed": n * 0.25, "Counter": n, "Mode": "drive", "Ok": n % 2 == 0, "X": None}


class Drive(Node):
    """Reads signals by name, as a ``can`` node does: a KeyError on ``{"items": [...]}``."""

    values = Input(dict)
    seen = Output(dict)

    def process(self, values: dict[str, Any]) -> dict[str, Any]:
        assert "items" not in values, values
        _ = values["LeftSpeed"] * 2.0, values["Mode"].upper()
        return values


def as_replayed(live: dict[str, Any]) -> dict[str, Any]:
    return {k: float(v) if type(v) is int else v for k, v in live.items()}


# --- through the profile's writer and the replay node ---------------------------------------


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every case of ROUND_TRIP as node ``case_<name>``'s ``values``, written by the recording
    writer with the ros2 profile (the recorder's own, on threads), plus two flowrt
    definitions with a mapping field."""
    path = tmp_path_factory.mktemp("kv") / "kv.mcap"
    w = RecordingWriter(path, profile="ros2", epoch_offset=time.time())
    w.open({})
    for i, (name, value, _) in enumerate(ROUND_TRIP):
        topic = f"case_{name}.values"
        w.declare(topic, source=topic)
        assert w.submit(topic, value, 0.01 * i, 0)
    for topic, value in NESTED.items():
        w.declare(topic, source=topic)
        assert w.submit(topic, value, 1.0, 0)
    w.close()
    assert w.error is None
    assert not w.notes
    return path


@dataclasses.dataclass
class Message:
    """A ``CanMessage``-like value: a dataclass with a mapping field."""

    name: str
    signals: dict[str, Any]
    valid: bool


NESTED: dict[str, Any] = {
    "can_message.values": Message("WheelSpeeds", {"LeftSpeed": 0.5, "Counter": 7}, True),
    "status.values": {"mode": "run", "signals": {"Voltage": 24.2, "Note": "ok"}},
}


class _NoSleep:
    """``asyncio`` for the replay module, its sleeps not slept: a replay as fast as it reads."""

    async def sleep(self, seconds: float) -> None:
        return None

    def __getattr__(self, name: str) -> Any:
        return getattr(asyncio, name)


def replayed(
    path: Path, node: str, monkeypatch: pytest.MonkeyPatch, cls: type[Node] | None = None
) -> list[Any]:
    """What a replay node standing in for ``node`` (of ``cls``: a Signals source by default)
    publishes (tests/test_ros2_replay_values.py too)."""
    monkeypatch.setattr(replay_mod, "asyncio", _NoSleep())
    kind = Replay.standing_in_for(Signals if cls is None else cls, node)
    h = NodeHarness(kind, {"path": str(path), "node": node, "on_end": "idle"}, name=node)

    async def every() -> list[Any]:
        out, n = [], h.node
        while not n.ended:  # type: ignore[attr-defined]
            v = await n.process()  # type: ignore[misc]
            if v is not None:
                out.append(v)
        await n.teardown()  # type: ignore[misc]
        return out

    return asyncio.run(every())


@pytest.mark.parametrize(
    ("name", "expected"), [pytest.param(name, e, id=name) for name, _, e in ROUND_TRIP]
)
def test_a_replayed_mapping_is_the_mapping_recorded(
    name: str, expected: dict[str, Any], bag: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    got = replayed(bag, f"case_{name}", monkeypatch)
    assert len(got) == 1
    assert same(got[0], expected), got[0]


def test_mapping_fields_of_flowrt_definitions_come_back_as_mappings(
    bag: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (msg,) = replayed(bag, "can_message", monkeypatch)
    assert msg["name"] == "WheelSpeeds"
    assert msg["valid"] is True
    assert same(msg["signals"], {"LeftSpeed": 0.5, "Counter": 7.0})
    (status,) = replayed(bag, "status", monkeypatch)
    assert same(status, {"mode": "run", "signals": {"Voltage": 24.2, "Note": "ok"}})


# --- the written format: other readers still see KeyValues ----------------------------------


def _decoded(enc: Any) -> tuple[Any, Any, Schema]:
    """(mcap-ros2-support's message, flowrt's plain value, schema) of one encoded message."""
    s = enc.schema
    schema = Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    official = generate_dynamic(s.name, s.data.decode())[s.name](enc.data)
    return official, MessageDecoder().decode("cdr", schema, enc.data).value, schema


def test_other_readers_still_see_key_values() -> None:
    enc = Ros2Encoder({}, epoch_offset=0.0).encode("w.values", {"LeftSpeed": 0.25, "Mode": "d"})
    official, plain, schema = _decoded(enc)
    assert schema.name == "flowrt_msgs/msg/KeyValues"
    first, second = official.items
    assert (first.key, first.value, first.text) == ("LeftSpeed", 0.25, "")
    assert (second.key, second.text) == ("Mode", "d")
    assert math.isnan(second.value)
    assert plain["items"][0] == {"key": "LeftSpeed", "value": 0.25, "text": ""}
    restore = mapping_restorer(schema.name, schema.encoding, schema.data)
    assert restore is not None
    assert restore(plain) == {"LeftSpeed": 0.25, "Mode": "d"}


def test_a_foreign_key_value_type_is_left_as_decoded() -> None:
    """Only flowrt's own definition is read as a mapping: another package's KeyValue, or one
    named like flowrt's with other fields, keeps its fields."""
    sep = "=" * 80 + "\n"
    kv = "string key\nstring value\n"
    other = f"flowrt_msgs/KeyValue[] items\n{sep}MSG: flowrt_msgs/KeyValue\n{kv}"
    assert mapping_restorer("flowrt_msgs/msg/KeyValues", "ros2msg", other.encode()) is None
    diag = f"diagnostic_msgs/KeyValue[] values\n{sep}MSG: diagnostic_msgs/KeyValue\n{kv}"
    assert mapping_restorer("my_msgs/msg/Status", "ros2msg", diag.encode()) is None
    twist = Ros2Encoder({}, 0.0).encode("t.cmd", {"v": 1.0, "w": 0.0}).schema
    assert mapping_restorer(twist.name, twist.encoding, twist.data) is None


# --- end to end: record a graph with the ros2 profile, replay it into the graph --------------


@pytest.mark.slow
def test_record_ros2_then_replay_into_the_graph_gives_the_mappings(tmp_path: Path) -> None:
    from flowrt.cli.record import wait_for_writers

    async def record() -> list[dict[str, Any]]:
        g = flowrt.GraphBuilder("kv")
        g.add("src", Signals)
        g.add(
            "rec",
            "recorder",
            params={"path": str(tmp_path), "name": "kv", "profile": "ros2", "writer": "thread"},
            inputs={"src.values": {"from": "src.values", "policy": "lossless", "size": 64}},
        )
        async with flowrt.Runtime(g.build()) as rt:
            sub = rt.subscribe("src.values", size=1024)
            await rt.run(0.5)
            return list(sub.drain())

    async def replay(session: Path) -> tuple[list[Any], int]:
        g = flowrt.GraphBuilder("kv")
        g.add(
            "src",
            Replay.standing_in_for(Signals, "src"),
            params={"path": str(session), "node": "src"},
        )
        edge = {"from": "src.values", "policy": "queue", "size": 64}
        g.add("drive", Drive, inputs={"values": edge})
        async with flowrt.Runtime(g.build()) as rt:
            sub = rt.subscribe("drive.seen", size=1024)
            await asyncio.wait_for(rt.run(), timeout=30)  # the replay stops the run at its end
            return list(sub.drain()), rt.stats().node("drive").errors

    live = asyncio.run(record())
    wait_for_writers()
    session = tmp_path / "kv_001"
    assert (session / "metadata.yaml").exists()  # a rosbag2 folder
    got, errors = asyncio.run(replay(session))
    assert errors == 0
    assert len(got) >= 10
    for value, before in zip(got, live, strict=False):
        assert same(value, as_replayed(before)), (value, before)
