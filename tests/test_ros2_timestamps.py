"""In the ``ros2`` profile every float ``timestamp`` is a ``builtin_interfaces/Time`` in Unix
time, a mapping's as a dataclass's; a replay gives it back on its own clock.

Found by the audit: a ``sync`` node's set index (``pair.set``: its members' references, its
``stamp`` written as ``timestamp``) was written as ``float64 timestamp`` of the run's
monotonic clock (65983.13), where the README says a float ``timestamp`` is a Time in Unix time
(and the ``flowrt`` profile writes Unix nanoseconds). Only a dataclass's fields were typed
from their hints; a mapping's were guessed from its first value, a float. A mapping's float
``timestamp`` is now the runtime clock as a dataclass's is.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from pathlib import Path
from typing import Any

import flowrt.nodes.replay as replay_mod
import numpy as np
import pytest
from flowrt.nodes.replay import Replay
from mcap.records import Schema
from mcap_ros2._dynamic import generate_dynamic

from flowrt import Frame
from flowrt.recording.decoding import MessageDecoder
from flowrt.recording.ros2_profile import Ros2Encoder, ros2_topic
from flowrt.recording.streams import split_set
from flowrt.recording.writer.threads import RecordingWriter
from flowrt.testing import NodeHarness

pytestmark = pytest.mark.timeout(120)

OFFSET = 1_700_000_000.0  # runtime clock + OFFSET = Unix time
T = 2.5  # runtime clock, s


@dataclasses.dataclass
class Det:
    found: bool
    object: str
    timestamp: float


def _frame(name: str) -> Frame:
    return Frame(np.zeros((4, 4, 3), np.uint8), source=name, seq=3, timestamp=T)


SET_INDEX = split_set(
    "pair.set", {"a": _frame("a"), "b": _frame("b"), "stamp": T, "spread_ms": 1.5}
)[0]

# (case, value, whether its timestamp is the runtime clock: a Time in Unix time)
VALUES: list[tuple[str, Any, bool]] = [
    ("sync_set_index", SET_INDEX, True),
    ("snake_case_mapping", {"axes": [0.1, -0.5], "buttons": {"a": True}, "timestamp": T}, True),
    ("numpy_float_timestamp", {"level": 0.5, "timestamp": np.float64(T)}, True),
    ("dataclass", Det(True, "ball", T), True),
    ("an_int_timestamp_is_not_the_clock", {"count": 1, "timestamp": 3}, False),
]


def _official(enc: Any) -> Any:
    """mcap-ros2-support's message (the official reader of the written definition)."""
    s = enc.schema
    return generate_dynamic(s.name, s.data.decode())[s.name](enc.data)


@pytest.mark.parametrize(("value", "is_clock"), [pytest.param(v, c, id=n) for n, v, c in VALUES])
def test_a_float_timestamp_is_a_time_in_unix_time(value: Any, is_clock: bool) -> None:
    enc = Ros2Encoder({}, epoch_offset=OFFSET).encode("pair.set", value)
    assert enc.schema.name.startswith("flowrt_msgs/msg/")
    lines = enc.schema.data.decode().splitlines()
    msg = _official(enc)
    if is_clock:
        assert "builtin_interfaces/Time timestamp" in lines
        assert (msg.timestamp.sec, msg.timestamp.nanosec) == (int(OFFSET) + 2, 500_000_000)
    else:
        assert "float64 timestamp" in lines
        assert msg.timestamp == 3.0


def test_rosbags_reads_the_sync_set_s_timestamp_as_a_time() -> None:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    enc = Ros2Encoder({}, epoch_offset=OFFSET).encode("pair.set", SET_INDEX)
    store = get_typestore(Stores.EMPTY)
    text = enc.schema.data.decode()
    store.register(get_types_from_msg(text, enc.schema.name))
    for part in text.split("=" * 80 + "\n")[1:]:
        head, _, body = part.partition("\n")
        store.register(get_types_from_msg(body, head.removeprefix("MSG: ").replace("/", "/msg/")))
    msg = store.deserialize_cdr(enc.data, enc.schema.name)
    assert msg.timestamp.__msgtype__ == "builtin_interfaces/msg/Time"
    assert msg.timestamp.sec + msg.timestamp.nanosec / 1e9 == pytest.approx(OFFSET + T)
    assert msg.spread_ms == 1.5


# --- read back by a replay: on the replay's own clock ---------------------------------------


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Each value of VALUES on ``case_<name>.value``, logged at its own timestamp."""
    path = tmp_path_factory.mktemp("stamps") / "stamps.mcap"
    w = RecordingWriter(path, profile="ros2", epoch_offset=time.time())
    w.open({})
    for name, value, _ in VALUES:
        topic = f"case_{name}.value"
        w.declare(topic, source=topic)
        assert w.submit(topic, value, T, 0)
    w.close()
    assert w.error is None
    assert not w.notes
    return path


class _NoSleep:
    async def sleep(self, seconds: float) -> None:
        return None

    def __getattr__(self, name: str) -> Any:
        return getattr(asyncio, name)


NOW = 100.0  # the replaying run's clock


def replayed(path: Path, topic: str, monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """What the ``replay`` kind publishes of ``topic`` (on ``message``), its clock at NOW."""
    monkeypatch.setattr(replay_mod, "asyncio", _NoSleep())
    h = NodeHarness(Replay, {"path": str(path), "topics": [topic], "on_end": "idle"})
    h.ctx.time = NOW

    async def every() -> list[Any]:
        out, n = [], h.node
        while not n.ended:  # type: ignore[attr-defined]
            v = await n.process()  # type: ignore[misc]
            if v is not None:
                out.append(v["message"])
        await n.teardown()  # type: ignore[misc]
        return out

    return asyncio.run(every())


@pytest.mark.parametrize(("name", "is_clock"), [pytest.param(n, c, id=n) for n, _, c in VALUES])
def test_a_replayed_timestamp_is_on_the_replay_s_clock(
    name: str, is_clock: bool, bag: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Logged at its timestamp, so published as new: at the replay's ``now``."""
    (value,) = replayed(bag, ros2_topic(f"case_{name}.value"), monkeypatch)
    assert isinstance(value, dict)
    if is_clock:
        assert value["timestamp"] == pytest.approx(NOW, abs=1e-6)
    else:
        assert value["timestamp"] == 3.0


def test_other_readers_see_the_time_as_written(bag: Path) -> None:
    """flowrt's decoder (``flowrt info``, the Foxglove app): the Time message itself."""
    from flowrt.recording.reader import iter_messages

    dec = MessageDecoder()
    (m,) = [m for m in iter_messages(bag) if m.topic == "/case_sync_set_index/value"]
    schema = Schema(id=1, name=m.schema.name, encoding=m.schema.encoding, data=m.schema.data)
    stamp = dec.decode(m.encoding, schema, m.data).value["timestamp"]
    ns = stamp["sec"] * 1_000_000_000 + stamp["nanosec"]
    assert ns == pytest.approx(m.log_time, abs=1000)  # both from one float of seconds


@pytest.mark.parametrize("profile", ["flowrt", "ros2"])
@pytest.mark.parametrize("t", [0.123456789, 2.5, 1234.000000999, 7.9999999996])
def test_an_images_stamp_is_its_log_time_to_the_nanosecond(
    tmp_path: Path, profile: str, t: float
) -> None:
    """The README: the capture time is the log time. A stamp made from t - floor(t) was
    tens of ns off the log time's round(t * 1e9) (...402276309013 against ...402276308992)."""
    from mcap.reader import make_reader

    offset = time.time()
    path = tmp_path / "s.mcap"
    w = RecordingWriter(path, profile=profile, epoch_offset=offset)
    w.open({})
    w.declare("cam.frame", source="cam.frame")
    frame = Frame(np.zeros((4, 4, 3), np.uint8), source="cam", seq=1, timestamp=t)
    assert w.submit("cam.frame", frame, t, 1)
    w.close()
    decoder = MessageDecoder()
    with path.open("rb") as f:
        ((schema, channel, msg),) = list(make_reader(f).iter_messages())
    decoded = decoder.decode(channel.message_encoding, schema, msg.data)
    assert decoded.stamp == msg.log_time
