"""One description per stream, values shaped like their schemas (issue 38 items 2, 5, 6).

Fast and process-free: the schema rewriting, the value shaping, the apps' rules, a sync set
split into streams and joined back, and the decoder giving back what was encoded.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import jsonschema
import numpy as np
import pytest

from flowrt import AudioBlock, Frame
from flowrt.recording.encoding import Decoder, Overlay, encode_json, schema_for
from flowrt.recording.jsonschema import app_schema, conform, schema_problems
from flowrt.recording.streams import StreamBook, describe, is_set, join_set, split_set


@dataclass(frozen=True)
class Seen:
    """A value with every shape the apps refuse as pydantic writes it."""

    found: bool
    centroid: tuple[float, float] | None
    pairs: tuple[tuple[str, int], ...]
    grid: tuple[tuple[float, float], ...]
    data: bytes
    label: int | str
    timestamp: float
    note: str | None = None


def _validate(value: object) -> tuple[dict[str, object], dict[str, object]]:
    schema = schema_for(value)
    body = json.loads(encode_json(value, schema, 0.0).data)
    parsed = json.loads(schema.data)
    jsonschema.Draft202012Validator(parsed).validate(body)
    assert schema_problems(parsed) == []
    return parsed, body


def test_a_value_with_absent_fields_and_tuples_validates_and_comes_back() -> None:
    v = Seen(False, None, (("can0", 3),), ((1.0, 2.0),), b"\x01\x02", 7, 1.5)
    schema, body = _validate(v)
    assert "centroid" not in body  # absent, not null
    assert "note" not in body
    assert body["pairs"] == [{"_0": "can0", "_1": 3}]
    assert body["grid"] == [{"_0": 1.0, "_1": 2.0}]
    assert body["label"] == "7"  # int | str: text, the one type both can be
    assert schema["properties"]["data"]["contentEncoding"] == "base64"
    back = Decoder().message(schema_for(v).name, json.dumps(body).encode())
    assert isinstance(back, Seen)
    assert back.centroid is None
    assert back.pairs == (("can0", 3),)


def test_a_found_value_keeps_its_typed_arrays() -> None:
    v = Seen(True, (3.0, 4.0), (), (), b"", "a", 2.0, "x")
    schema, body = _validate(v)
    assert body["centroid"] == [3.0, 4.0]
    c = schema["properties"]["centroid"]
    assert c == {
        "type": "array",
        "items": {"type": "number"},
        "minItems": 2,
        "maxItems": 2,
        **{k: c[k] for k in ("title",) if k in c},
    }


@pytest.mark.parametrize(
    ("schema", "problem"),
    [
        ({"type": "array"}, "expected type object"),
        ({"type": "object"}, "without properties"),
        (
            {"type": "object", "properties": {"a": {"type": "array", "items": {"type": "array"}}}},
            "unsupported array item type 'array'",
        ),
        (
            {"type": "object", "properties": {"s": {"type": "string", "contentEncoding": "hex"}}},
            "contentEncoding 'hex'",
        ),
        ({"type": "object", "properties": {"n": {"type": "null"}}}, "unsupported type 'null'"),
        ({"type": "object", "properties": {"n": {"anyOf": []}}}, "anyOf"),
    ],
)
def test_the_apps_rules_refuse_what_parse_json_schema_throws_on(
    schema: dict[str, object], problem: str
) -> None:
    assert any(problem in p for p in schema_problems(schema)), schema_problems(schema)


def test_conform_follows_the_schema_alone() -> None:
    schema = app_schema(
        {
            "type": "object",
            "properties": {
                "xs": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
                "n": {"type": "integer"},
            },
        }
    )
    assert schema_problems(schema) == []
    out = conform({"xs": [[1.0], [2.0, 3.0]], "n": 4.0, "gone": None}, schema)
    assert out == {"xs": [{"values": [1.0]}, {"values": [2.0, 3.0]}], "n": 4}


def test_a_sync_set_is_streams_and_joins_back() -> None:
    a = Frame(np.zeros((4, 4, 3), np.uint8), source="cam", seq=5, timestamp=10.0)
    block = AudioBlock(np.zeros((8, 1), np.float32), 48000, 10.0, 2)
    value = {"a": a, "m": block, "stamp": 10.0, "spread_ms": 1.0}
    assert is_set(value)
    assert not is_set({"x": 1})
    index, members = split_set("pair.set", value)
    assert [t for t, _ in members] == ["pair.set/a", "pair.set/m"]
    assert index == {
        "a": {"topic": "pair.set/a", "seq": 5},
        "m": {"topic": "pair.set/m", "seq": 2},
        "timestamp": 10.0,
        "spread_ms": 1.0,
    }
    book = StreamBook(epoch_offset=1000.0)
    body = json.loads(book.encode("pair.set", index).data)
    assert body["timestamp"] == 1010 * 10**9  # Unix time, as every recorded time
    assert book.description("pair.set/a", a).schema.name == "foxglove.RawImage"
    assert book.description("pair.set/m", block).schema.name == "foxglove.RawAudio"
    joined = join_set("pair.set", index, dict(members))
    assert joined["a"] is a
    assert joined["m"] is block
    assert joined["stamp"] == joined["timestamp"] == 10.0


def test_one_description_per_stream_and_kind() -> None:
    f = Frame(np.zeros((2, 2, 3), np.uint8), source="c", seq=0, timestamp=1.0)
    assert describe("c.frame", f).shape == "image"
    assert describe("c.frame", f, "jpeg").schema.name == "foxglove.CompressedImage"
    assert describe("x", Overlay(None)).shape == "annotations"
    d = describe("x.v", {"a": 1})
    assert (d.shape, d.message_encoding, d.time_base) == ("json", "json", "unix")
    book = StreamBook()
    assert book.description("x.v", 1) is book.description("x.v", 2)
    assert len(book.streams()) == 1


def test_a_plain_mapping_is_written_as_it_is_under_its_guessed_schema() -> None:
    """The deterministic log's records: a schema guessed from the first sample must not
    coerce later values (``["src", "value", 3]`` once became a string) nor drop a None the
    reader needs where the guess has no type."""
    first = {"node": "a", "inputs": {"x": None, "y": ["src", "value", 3]}, "t": 1.0}
    schema = schema_for(first)
    assert schema.guessed
    parsed = json.loads(schema.data)
    assert schema_problems(parsed) == []
    assert "x" not in parsed["properties"]["inputs"]["properties"]  # unknown: unconstrained
    later = {"node": "a", "inputs": {"x": ["src", "value", 4], "y": None}, "t": 2.0}
    body = json.loads(encode_json(later, schema).data)
    assert body["inputs"]["x"] == ["src", "value", 4]
    jsonschema.Draft202012Validator(parsed).validate(body)
    assert body["inputs"] == {"x": ["src", "value", 4], "y": None}  # y's guess had no type
