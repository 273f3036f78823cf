"""Every JSON channel can be read by the Foxglove and Lichtblick apps (issue 26).

Their ``parseJsonSchema`` drops a topic whose schema has a field without a ``type``, an array
without ``items``, an object without ``properties``, or ``anyOf``/``$ref``: no detection,
statistic or CAN signal could be plotted. Recordings of each example graph, and the live
server's own channels, are walked channel by channel.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from conftest import FlowrtCli

import flowrt
from flowrt.recording.jsonschema import app_schema, schema_problems

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("graph", ["cambada", "agent", "can", "video"])
def test_every_json_channel_of_a_recording_passes_the_apps_rules(
    graph: str, tmp_path: Path, flowrt_cli: FlowrtCli
) -> None:
    from mcap.reader import make_reader

    r = flowrt_cli(
        "record",
        f"graphs/{graph}.yaml",
        "-o",
        str(tmp_path),
        "--duration",
        "1",
        "--no-ui",
        "--no-display",
    )
    assert r.returncode == 0, r.stderr
    (path,) = tmp_path.glob("*/*.mcap")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    json_channels = 0
    for ch in summary.channels.values():
        schema = summary.schemas.get(ch.schema_id)
        if schema is None or schema.encoding != "jsonschema":
            continue
        json_channels += 1
        assert schema_problems(json.loads(schema.data)) == [], (ch.topic, schema.name)
    assert json_channels >= 1


def test_the_live_servers_own_channels_pass_too() -> None:
    from flowrt.recording.live import _json_schema

    for name in ("flowrt.RuntimeStats", "flowrt.Event"):
        assert schema_problems(json.loads(_json_schema(name).data)) == [], name


@pytest.mark.parametrize(
    "event",
    [
        flowrt.HealthAlert(1.0, "can", "can-timeout", "Gear (0x200) not received", "warning"),
        flowrt.DeadlineMissed(1.0, "ball", 20.0, True, False),
        flowrt.NodeFailed(1.0, "ball", "ValueError: x", "Traceback ..."),
        flowrt.ModeChanged(1.0, None, "attack", "defend"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_every_field_of_an_event_is_typed_in_the_events_schema(event: object) -> None:
    """The live ``/flowrt/events`` schema typed only ``t``, ``node`` and ``kind``: an alert's
    ``alert``, ``detail`` and ``severity`` could not be plotted or filtered."""
    import dataclasses

    import jsonschema

    from flowrt.recording.encoding import to_jsonable
    from flowrt.recording.live import _json_schema

    schema = json.loads(_json_schema("flowrt.Event").data)
    body = {"kind": type(event).__name__, **to_jsonable(event)}
    body = {k: v for k, v in body.items() if v is not None}  # None is left out (README)
    names = {f.name for f in dataclasses.fields(event)}  # type: ignore[arg-type]
    assert names <= set(schema["properties"])
    jsonschema.validate(body, schema)


@pytest.mark.parametrize(
    ("schema", "expected"),
    [
        (
            {
                "type": "object",
                "properties": {"a": {"anyOf": [{"type": "number"}, {"type": "null"}]}},
            },
            {"type": "object", "properties": {"a": {"type": "number"}}},
        ),
        (
            {
                "type": "object",
                "properties": {
                    "p": {"type": "array", "prefixItems": [{"type": "number"}, {"type": "number"}]}
                },
            },
            {
                "type": "object",
                "properties": {
                    "p": {
                        "type": "array",
                        "items": {"type": "number"},
                        "minItems": 2,
                        "maxItems": 2,
                    }
                },
            },
        ),
        (
            {
                "type": "object",
                "properties": {"m": {"$ref": "#/$defs/M"}},
                "$defs": {"M": {"type": "object", "properties": {"x": {"type": "integer"}}}},
            },
            {
                "type": "object",
                "properties": {"m": {"type": "object", "properties": {"x": {"type": "integer"}}}},
            },
        ),
        (
            {
                "type": "object",
                "properties": {"d": {"type": "object", "additionalProperties": {"type": "number"}}},
            },
            {
                "type": "object",
                "properties": {
                    "d": {
                        "type": "object",
                        "properties": {},
                        "additionalProperties": {"type": "number"},
                    }
                },
            },
        ),
        (
            {"type": "object", "properties": {"any": {}}},
            {"type": "object", "properties": {"any": {"type": "string"}}},
        ),
        ({"type": "number"}, {"type": "object", "properties": {"value": {"type": "number"}}}),
        (
            {
                "type": "object",
                "properties": {
                    "u": {
                        "type": "array",
                        "items": {
                            "type": "array",
                            "prefixItems": [{"type": "string"}, {"type": "integer"}],
                        },
                    }
                },
            },
            {
                "type": "object",
                "properties": {
                    "u": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "properties": {"_0": {"type": "string"}, "_1": {"type": "integer"}},
                        },
                    }
                },
            },
        ),
        (
            {"type": "object", "properties": {"d": {"type": "string", "format": "binary"}}},
            {
                "type": "object",
                "properties": {"d": {"type": "string", "contentEncoding": "base64"}},
            },
        ),
    ],
    ids=["optional", "tuple", "ref", "mapping", "any", "plain-value", "mixed-tuples", "bytes"],
)
def test_app_schema_rewrites_what_the_apps_refuse(
    schema: dict[str, object], expected: dict[str, object]
) -> None:
    assert (
        schema_problems(schema) != [] or schema.get("type") != "object" or "format" in str(schema)
    )
    assert app_schema(schema) == expected
    assert schema_problems(app_schema(schema)) == []


@pytest.mark.slow
@pytest.mark.subprocess
def test_can_signals_are_recorded_as_plottable_json(tmp_path: Path, flowrt_cli: FlowrtCli) -> None:
    """Issue 26: `--topics chassis.WheelSpeeds` matched nothing (a CAN node's messages are
    outputs of its params) and raw data was a Python repr; now each message is a channel with
    its signals as schema fields and the frame's data as base64 bytes."""
    import base64

    from mcap.reader import make_reader

    r = flowrt_cli(
        "record",
        "graphs/can.yaml",
        "-o",
        str(tmp_path),
        "--duration",
        "1",
        "--no-ui",
        "--topics",
        "chassis.WheelSpeeds",
    )
    assert r.returncode == 0, r.stderr
    (path,) = tmp_path.glob("*/*.mcap")
    with open(path, "rb") as f:
        got = list(make_reader(f).iter_messages(topics=["chassis.WheelSpeeds"]))
    assert len(got) >= 50  # of 100 in the fixed 1 s (10 ms): room for a loaded machine's skips
    schema, _, message = got[0]
    signals = json.loads(schema.data)["properties"]["signals"]["properties"]
    assert {"LeftSpeed", "RightSpeed", "Heading"} <= set(signals)
    assert signals["LeftSpeed"] == {"type": "number"}
    body = json.loads(message.data)
    assert len(base64.b64decode(body["data"])) == 8


@pytest.mark.slow
@pytest.mark.subprocess
def test_one_time_base_values_are_stamped_in_epoch_nanoseconds(
    tmp_path: Path, flowrt_cli: FlowrtCli
) -> None:
    """Issue 26: a detection's own timestamp was the run's monotonic seconds beside epoch log
    times; now it is epoch nanoseconds too, the frame's time: at or before its log time."""
    from mcap.reader import make_reader

    r = flowrt_cli(
        "record",
        "graphs/cambada.yaml",
        "-o",
        str(tmp_path),
        "--duration",
        "1",
        "--no-ui",
        "--no-display",
        "--topics",
        "ball_fr.detection",
    )
    assert r.returncode == 0, r.stderr
    (path,) = tmp_path.glob("*/*.mcap")
    with open(path, "rb") as f:
        got = list(make_reader(f).iter_messages(topics=["ball_fr.detection"]))
    assert got
    for _schema, _, message in got:
        ts = json.loads(message.data)["timestamp"]
        assert isinstance(ts, int)
        assert 0 <= message.log_time - ts < 1_000_000_000  # the frame's time, <1 s before
    assert json.loads(got[0][0].data)["properties"]["timestamp"]["type"] == "integer"


@pytest.mark.slow
@pytest.mark.subprocess
def test_raw_can_frames_are_a_channel_of_their_own(tmp_path: Path, flowrt_cli: FlowrtCli) -> None:
    """Issue 26: raw frames as their own channel (id, extended, fd, remote, dlc, data)."""
    import base64

    from mcap.reader import make_reader

    text = (REPO / "graphs" / "can.yaml").read_text()
    text = text.replace(
        "      bitrate: 250000\n", "      bitrate: 250000\n      raw_output: true\n"
    )
    graph = REPO / "graphs" / f"_raw_{os.getpid()}.yaml"  # beside robot.dbc's folder
    graph.write_text(text)
    try:
        r = flowrt_cli(
            "record",
            str(graph),
            "-o",
            str(tmp_path),
            "--duration",
            "1",
            "--no-ui",
            "--topics",
            "chassis.frames",
        )
    finally:
        graph.unlink()
    assert r.returncode == 0, r.stderr
    (path,) = tmp_path.glob("*/*.mcap")
    with open(path, "rb") as f:
        got = list(make_reader(f).iter_messages(topics=["chassis.frames"]))
    assert len(got) >= 100  # of ~210 in the fixed 1 s: room for a loaded machine's skips
    schema, _, message = got[0]
    props = json.loads(schema.data)["properties"]
    assert {"id", "extended", "fd", "remote", "dlc", "data"} <= set(props)
    assert schema_problems(json.loads(schema.data)) == []
    body = json.loads(message.data)
    assert len(base64.b64decode(body["data"])) == body["dlc"]


def test_a_mappings_values_are_typed_and_written_in_their_shape() -> None:
    """A typed message's mapping (keys known at run time) keeps its values' schema as
    ``additionalProperties``, rewritten as a field's; each value is written in that shape,
    so the message still validates: a tuple as its positional object, a union as text. The
    keys of a later message, not in the first one's guessed ``properties``, rely on it."""
    from dataclasses import dataclass, field

    import jsonschema

    from flowrt.recording.encoding import encode_json, schema_for

    @dataclass
    class Counts:
        by_reason: dict[str, int] = field(default_factory=dict)
        rate: dict[str, float | None] = field(default_factory=dict)
        last: dict[str, tuple[str, int]] = field(default_factory=dict)
        label: dict[str, int | str] = field(default_factory=dict)
        free: dict[str, object] = field(default_factory=dict)

    stream = schema_for(Counts({"queue full": 3}, {"a": 2.5}, {}, {"k": "x"}, {"n": 1}))
    schema = json.loads(stream.data)
    values = {k: p.get("additionalProperties") for k, p in schema["properties"].items()}
    assert values == {
        "by_reason": {"type": "integer"},
        "rate": {"type": "number"},
        "last": {
            "type": "object",
            "properties": {"_0": {"type": "string"}, "_1": {"type": "integer"}},
        },
        "label": {"type": "string"},
        "free": None,  # any value: nothing to say of it
    }
    assert schema_problems(schema) == []
    later = Counts({"stop": 1}, {"b": None, "c": 4}, {"can0": ("x", 1)}, {"j": 7}, {"m": [1, None]})
    message = json.loads(encode_json(later, stream).data)
    assert message == {
        "by_reason": {"stop": 1},
        "rate": {"c": 4},
        "last": {"can0": {"_0": "x", "_1": 1}},
        "label": {"j": "7"},
        "free": {"m": [1, None]},
    }
    assert list(jsonschema.Draft202012Validator(schema).iter_errors(message)) == []
