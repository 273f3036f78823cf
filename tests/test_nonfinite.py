"""Infinity and NaN in the flowrt profile's JSON messages (and over Zenoh, which sends them).

JSON has neither: a non-finite float is left out of an object (and ``null`` in an array), as
Foxglove's SDKs write it, and every message stays valid against its schema. Read back it was
a mapping (``{}`` for a float stream: a typed port refused it, the replaying node failed at
every message) or the field's default: it is ``NaN`` now, the one float that says "not a
number here"; ``--profile ros2`` (CDR) keeps such floats exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from flowrt.recording.encoding import Decoder, encode_json, schema_for
from flowrt.remote._streams import decode_json


@dataclass
class Reading:
    range_m: float
    gain: float = 1.0
    label: str | None = None


def _both(value: Any) -> tuple[Any, Any]:
    """``value`` written as the recorder writes it, read back by the replay's decoder and
    by a Zenoh import's."""
    schema = schema_for(value)
    data = encode_json(value, schema, 0.0).data
    return Decoder().message(schema.name, data), decode_json(data, schema.name)


def _same(a: Any, b: Any) -> bool:
    return (isinstance(a, float) and math.isnan(a) and math.isnan(b)) or a == b


# (what, value written, value read back)
CASES: list[tuple[str, Any, Any]] = [
    ("finite-float", 1.5, 1.5),
    ("inf", math.inf, math.nan),
    ("minus-inf", -math.inf, math.nan),
    ("nan", math.nan, math.nan),
    ("int", 3, 3),
    ("a-mapping-stays-a-mapping", {"a": 1.0}, {"a": 1.0}),
    # the same joint for the other plain values whose JSON shape is not their type: bytes
    # were base64 text, a tuple a list (a typed reader refused both)
    ("bytes", b"\x00\x01bytes", b"\x00\x01bytes"),
    ("tuple", (1.0, 2.5), (1.0, 2.5)),
    ("mixed-tuple", ("x", 3), ("x", 3)),
]


@pytest.mark.parametrize(("value", "back"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_plain_streams_value_reads_back_in_its_type(value: Any, back: Any) -> None:
    replayed, imported = _both(value)
    assert _same(replayed, back), replayed
    assert _same(imported, back), imported
    assert type(replayed) is type(back)


def test_a_dataclasss_non_finite_float_fields_read_back_as_nan() -> None:
    """A required float field and one with a default: NaN, not None nor the default (1.0);
    an optional field that was None stays None."""
    replayed, imported = _both(Reading(math.inf, math.nan, None))
    assert isinstance(replayed, Reading)
    assert math.isnan(replayed.range_m)
    assert math.isnan(replayed.gain)
    assert replayed.label is None
    assert math.isnan(imported.range_m)
    assert math.isnan(imported.gain)
    assert imported.label is None
    finite, _ = _both(Reading(2.0))
    assert finite == Reading(2.0)


GRAPH = """
name: nonfinite
nodes:
  src: {kind: 'values:Src', trigger: {timer: 20ms}}
  sink: {kind: 'values:Sink', inputs: {v: {from: src.out}}}
"""

NODES = """
import math
from flowrt import Input, Node, Output

class Src(Node):
    out = Output(float)

    def setup(self) -> None:
        self.i = 0

    def process(self) -> float:
        self.i += 1
        return [1.5, math.inf, -math.inf, math.nan][self.i % 4]

class Sink(Node):
    v = Input(float)

    def process(self, v: float) -> None:
        print("got", v, flush=True)
"""


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_float_stream_with_infinities_replays_into_its_typed_port(
    tmp_path: Path, flowrt_cli: Any
) -> None:
    """The user's case: recorded in the flowrt profile and replayed into its own graph, the
    source replaced by the recording: the sink gets every value (NaN for the non-finite
    ones), no node fails (before: "output 'out' expects float, got dict", in a loop)."""
    (tmp_path / "values.py").write_text(NODES)
    (tmp_path / "g.yaml").write_text(GRAPH)
    env = {"PYTHONPATH": str(tmp_path)}
    quiet = ("--no-ui", "--no-display")
    r = flowrt_cli(
        "record", "g.yaml", "-o", "out", "--topics", "src.*", "--duration", "1", *quiet,
        cwd=tmp_path, env=env,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    (rec,) = (tmp_path / "out").glob("rec_*/*.mcap")
    r = flowrt_cli("replay", str(rec), "--graph", "g.yaml", *quiet, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    got = [line.split()[1] for line in r.stdout.splitlines() if line.startswith("got ")]
    assert len(got) >= 20, r.stdout[-2000:]
    assert set(got) == {"1.5", "nan"}
    assert "expects float" not in r.stderr
