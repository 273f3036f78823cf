"""Scalars and audio recorded with the ``ros2`` profile come back from flowrt's replay as the
values recorded.

Found by the audit: a ``--profile ros2`` recording replayed into its own graph (``flowrt
replay BAG --graph G``) failed at the first source publishing a scalar or audio. ``int``,
``float``, ``bool`` and ``str`` are written as ``std_msgs`` ``Int64``, ``Float64``, ``Bool``
and ``String`` and came back as ``{"data": 1}``; an ``AudioBlock``, written as
``flowrt_msgs/AudioBlock``, came back as a dict; the replayed node's typed output refused
both ("output 'value' expects int, got dict": the built-in ``counter``, avsync's ``mic``).
The ``flowrt`` profile replays the same graphs. The replay now publishes the scalar and the
``AudioBlock``; other readers still see the messages as written.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.records import Schema
from test_ros2_replay_mappings import replayed

from flowrt import AudioBlock, Node, Output
from flowrt.recording.decoding import MessageDecoder
from flowrt.recording.reader import iter_messages
from flowrt.recording.writer.threads import RecordingWriter

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[1]
INF, NAN = math.inf, math.nan
JSON = '{"data":1}'  # a string that reads as a message: still the string

# (case, the output's type, values recorded, values replayed)
SCALARS: list[tuple[str, type, list[Any], list[Any]]] = [
    ("int", int, [0, -7, 2**40, np.int64(3)], [0, -7, 2**40, 3]),
    ("float", float, [0.25, -1e-9, INF, math.nan, np.float32(0.5)], [0.25, -1e-9, INF, NAN, 0.5]),
    ("bool", bool, [True, False, True], [True, False, True]),
    ("str", str, ["n1", "", "ß → ü", JSON, "true"], ["n1", "", "ß → ü", JSON, "true"]),
    # a stream keeps its first type: an int on a Float64 stream is written (and read) a float
    ("ints_on_a_float_stream", float, [0.5, 2, 3], [0.5, 2.0, 3.0]),
    # flowrt_msgs Bytes and Tuple (their JSON as text): read back as mappings before
    ("bytes", bytes, [b"\x00\x01bytes", b""], [b"\x00\x01bytes", b""]),
    ("tuple", tuple, [(1.0, 2.5), ("x", 3)], [(1.0, 2.5), ("x", 3)]),
]  # fmt: skip

RATE = 48_000
# (case, samples recorded, their block's seq)
AUDIO: list[tuple[str, np.ndarray, int]] = [
    ("mono_float32", np.linspace(-1.0, 1.0, 480, dtype=np.float32).reshape(-1, 1), 0),
    ("stereo_int16", np.arange(-512, 512, dtype=np.int16).reshape(-1, 2) * 31, 7),
    ("out_of_range", np.array([[1.5], [-2.0], [0.25]], dtype=np.float32), 2**40),
]


def same(a: Any, b: Any) -> bool:
    """Equal with the same type (``3.0`` is not ``3``), NaN equal to NaN."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b)


def source(port_type: type) -> type[Node]:
    """A source node of one typed output ``value`` (a ``counter``, a ``mic``)."""
    return type(f"{port_type.__name__.title()}Source", (Node,), {"value": Output(port_type)})


def as_written(samples: np.ndarray) -> np.ndarray:
    """What a block's samples are once written (pcm s16) and read as float32."""
    block = AudioBlock(samples, RATE, 0.0, 0)
    pcm = np.frombuffer(block.pcm16(), dtype="<i2").reshape(-1, block.channels)
    return pcm.astype(np.float32) / 32768.0


EPOCH = time.time()


def write(path: Path, profile: str) -> Path:
    """Every case of SCALARS and AUDIO on node ``case_<name>``'s ``value``, written by the
    recording writer (the recorder's own, on threads)."""
    w = RecordingWriter(path, profile=profile, epoch_offset=EPOCH)
    w.open({})
    for name, _, values, _ in SCALARS:
        topic = f"case_{name}.value"
        w.declare(topic, source=topic)
        for i, v in enumerate(values):
            assert w.submit(topic, v, 0.01 * i, i)
    for name, samples, seq in AUDIO:
        topic = f"case_{name}.value"
        w.declare(topic, source=topic)
        assert w.submit(topic, AudioBlock(samples, RATE, 0.5, seq, "mic"), 0.52, seq)
    w.close()
    assert w.error is None
    assert not w.notes
    return path


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("values")
    return {p: write(tmp / f"{p}.mcap", p) for p in ("flowrt", "ros2")}


@pytest.mark.parametrize(
    ("name", "port_type", "expected"),
    [pytest.param(name, t, e, id=name) for name, t, _, e in SCALARS],
)
def test_a_replayed_scalar_is_the_scalar_recorded(
    name: str,
    port_type: type,
    expected: list[Any],
    bags: dict[str, Path],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    got = replayed(bags["ros2"], f"case_{name}", monkeypatch, source(port_type))
    assert all(isinstance(v, port_type) for v in got), got  # what the typed output takes
    assert len(got) == len(expected)
    assert all(same(g, e) for g, e in zip(got, expected, strict=True)), got


@pytest.mark.parametrize(
    ("name", "samples", "seq"), [pytest.param(n, s, q, id=n) for n, s, q in AUDIO]
)
def test_a_replayed_audio_block_is_the_block_recorded(
    name: str, samples: np.ndarray, seq: int, bags: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    cls = source(AudioBlock)
    (got,) = replayed(bags["ros2"], f"case_{name}", monkeypatch, cls)
    assert isinstance(got, AudioBlock)
    assert (got.rate, got.seq, got.channels) == (RATE, seq, samples.shape[1])
    assert got.samples.dtype == np.float32
    assert np.array_equal(got.samples, as_written(samples))
    (flowrt_profile,) = replayed(bags["flowrt"], f"case_{name}", monkeypatch, cls)
    assert np.array_equal(got.samples, flowrt_profile.samples)  # as a flowrt recording gives
    assert (got.rate, got.channels, got.source) == (
        flowrt_profile.rate,
        flowrt_profile.channels,
        flowrt_profile.source,
    )


def test_an_audio_block_s_time_is_its_first_sample_s_unix_time(bags: dict[str, Path]) -> None:
    """Read back without a replay: the block's stamp, Unix time to the nanosecond (a replay
    moves it onto its own clock, as old against its log time as when recorded)."""
    from flowrt.recording.ros2_profile import value_restorer

    dec = MessageDecoder()
    blocks = []
    for m in iter_messages(bags["ros2"]):
        if m.schema.name == "flowrt_msgs/msg/AudioBlock":
            restore = value_restorer(m.schema.name, m.schema.encoding, m.schema.data)
            assert restore is not None
            blocks.append(restore(dec.decode(m.encoding, m.schema, m.data).value))
    assert len(blocks) == len(AUDIO)
    for b in blocks:
        assert b.timestamp == pytest.approx(EPOCH + 0.5, abs=1e-6)


# --- which definitions are read back as values ------------------------------------------------

SEP = "=" * 80 + "\n"
AUDIO_DEF = (
    "builtin_interfaces/Time stamp\nuint32 sample_rate\nuint32 channels\nint64 seq\n"
    f"int16[] data\n{SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
# (case, schema name, definition, a decoded message, what replay gives; None: as decoded)
RESTORED: list[tuple[str, str, str, Any, Any]] = [
    ("int64", "std_msgs/msg/Int64", "int64 data\n", {"data": 5}, 5),
    ("another_bag_s_int32", "std_msgs/msg/Int32", "int32 data\n", {"data": -3}, -3),
    ("uint8", "std_msgs/msg/UInt8", "uint8 data\n", {"data": 7}, 7),
    ("float32", "std_msgs/msg/Float32", "float32 data\n", {"data": 0.5}, 0.5),
    (
        "string_with_comments",  # as ROS 2 ships std_msgs/String
        "std_msgs/msg/String",
        "# This was originally provided as an example message.\nstring data\n",
        {"data": "hi"},
        "hi",
    ),
    ("ros1_style_name", "std_msgs/Bool", "bool data\n", {"data": True}, True),
    ("another_field", "std_msgs/msg/Int64", "int64 data\nstring note\n", None, None),
    ("another_package", "my_msgs/msg/Int64", "int64 data\n", None, None),
    ("a_multi_array", "std_msgs/msg/Float64MultiArray", "float64[] data\n", None, None),
    ("audio_with_other_fields", "flowrt_msgs/msg/AudioBlock", "int16[] data\n", None, None),
]


@pytest.mark.parametrize(
    ("name", "definition", "message", "expected"),
    [pytest.param(n, d, m, e, id=c) for c, n, d, m, e in RESTORED],
)
def test_which_messages_come_back_as_values(
    name: str, definition: str, message: Any, expected: Any
) -> None:
    from flowrt.recording.ros2_profile import value_restorer

    restore = value_restorer(name, "ros2msg", definition.encode())
    if message is None:
        assert restore is None
        return
    assert restore is not None
    assert same(restore(message), expected)


def test_an_audio_block_message_as_flowrt_writes_it_comes_back_as_a_block() -> None:
    from flowrt.recording.ros2_profile import value_restorer

    schema = Schema(id=1, name="flowrt_msgs/msg/AudioBlock", encoding="ros2msg", data=b"")
    restore = value_restorer(schema.name, schema.encoding, AUDIO_DEF.encode())
    assert restore is not None
    msg = {
        "stamp": {"sec": 1_700_000_000, "nanosec": 250_000_000},
        "sample_rate": 16_000,
        "channels": 2,
        "seq": 9,
        "data": [0, 16384, -32768, 32767, 5],  # a partial last frame is dropped
    }
    block = restore(msg)
    assert isinstance(block, AudioBlock)
    assert (block.rate, block.seq, block.channels, block.frames) == (16_000, 9, 2, 2)
    assert block.timestamp == 1_700_000_000.25
    assert block.samples.tolist() == [[0.0, 0.5], [-1.0, 32767 / 32768]]


# --- end to end: record a graph with the ros2 profile, replay it into the graph --------------

SCALARS_MODULE = """
from flowrt import Input, Node, Output


class Scalars(Node):
    i = Output(int)
    f = Output(float)
    b = Output(bool)
    s = Output(str)

    def setup(self):
        self.n = 0

    def process(self):
        self.n += 1
        return {"i": self.n, "f": self.n / 4, "b": self.n % 2 == 0, "s": f"n{self.n}"}


class Check(Node):
    i = Input(int)
    f = Input(float)
    b = Input(bool)
    s = Input(str)
    out = Output(str)

    def process(self, i=None, f=None, b=None, s=None):
        return f"{i!r} {f!r} {b!r} {s!r}"
"""

SCALARS_GRAPH = """\
name: scalars
nodes:
  src:
    kind: scalkind:Scalars
    trigger: {timer: 100ms}
  tick:
    kind: counter
    trigger: {timer: 100ms}
  chk:
    kind: scalkind:Check
    trigger: {timer: 100ms}
    inputs: {i: src.i, f: src.f, b: src.b, s: src.s}
"""


@pytest.mark.slow
@pytest.mark.parametrize("graph", ["scalars", "avsync"])
def test_record_ros2_then_replay_into_the_graph(
    graph: str, tmp_path: Path, flowrt_cli: Any
) -> None:
    (tmp_path / "scalkind.py").write_text(SCALARS_MODULE)
    (tmp_path / "scalars.yaml").write_text(SCALARS_GRAPH)
    path = tmp_path / "scalars.yaml" if graph == "scalars" else REPO / "graphs" / "avsync.yaml"
    env = {"PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    r = flowrt_cli(
        "record", str(path), "-o", str(tmp_path / "bags"), "--name", "b", "--profile", "ros2",
        "--duration", "2", "--no-ui", "--no-display", cwd=tmp_path, env=env, timeout=150,
    )  # fmt: skip
    assert r.returncode == 0 or "message(s) lost" in r.stderr, r.stderr
    again = flowrt_cli(
        "replay", str(tmp_path / "bags" / "b_001"), "--graph", str(path), "--duration", "2",
        "--no-ui", "--no-display", cwd=tmp_path, env=env, timeout=120,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert "OutputError" not in again.stderr
    assert "expects" not in again.stderr


def test_every_reason_a_stream_refuses_values_is_said(tmp_path: Path) -> None:
    """An int stream given text and NaN floats in the ros2 profile: 12 refused, counted,
    but the note said only the text ("cannot encode str"), the floats' reason unsaid."""
    w = RecordingWriter(tmp_path / "r.mcap", profile="ros2", epoch_offset=EPOCH)
    w.open({})
    w.declare("src.value", source="src.value")
    values: list[object] = [1, 2, "a", float("nan"), "b", float("nan"), 3]
    for i, v in enumerate(values):
        w.submit("src.value", v, 0.01 * i, i)
    w.close()
    kinds = sorted(n.split("cannot encode ")[1].split(":")[0] for n in w.notes)
    assert kinds == ["float", "str"], w.notes
    assert w.streams["src.value"].unwritten == 4
