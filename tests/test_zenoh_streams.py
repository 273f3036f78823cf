"""A stream's values over Zenoh (flowrt/remote/_streams.py): the payload is the recording's
message, a flowrt import gets the value back. No Zenoh session: the bytes an exporter puts."""

from __future__ import annotations

import json
import types
from dataclasses import dataclass, field

import jsonschema
import numpy as np
import pytest

from flowrt import AudioBlock
from flowrt.recording.streams import StreamBook
from flowrt.remote._streams import decode_audio, decode_json, encoding_of, schema_of_sample


@dataclass
class Part:
    name: str
    where: tuple[float, float]


@dataclass
class Seen:
    found: bool
    centroid: tuple[float, float] | None
    bbox: tuple[int, int, int, int] | None
    mixed: tuple[str, int]
    parts: dict[str, Part] = field(default_factory=dict)
    raw: bytes = b""
    history: list[float] = field(default_factory=list)
    timestamp: float = 0.0


def _wire(value: object, topic: str = "n.out") -> tuple[bytes, str, bytes]:
    """(payload, schema name, schema) as the exporter sends them: the recorder's encoding."""
    msg = StreamBook(epoch_offset=1000.0).encode(topic, value)
    return msg.data, msg.schema.name, msg.schema.data


def test_a_typed_value_is_the_recorded_message_and_comes_back_exact() -> None:
    value = Seen(
        True, (1.5, 2.0), (1, 2, 3, 4), ("a", 3), {"x": Part("x", (0.5, 1.0))}, b"\x00\xff",
        [1.0, 2.5], 12.25,
    )  # fmt: skip
    payload, name, schema = _wire(value)
    assert name == f"{__name__}.Seen"
    body = json.loads(payload)
    jsonschema.validate(body, json.loads(schema))  # what a plain program reads: valid
    assert body["mixed"] == {"_0": "a", "_1": 3}  # a mixed tuple: a positional object
    assert body["timestamp"] == round((12.25 + 1000.0) * 1e9)  # epoch ns, as recorded
    back = decode_json(payload, name)
    assert isinstance(back, types.SimpleNamespace)
    assert back._type == name
    assert back.centroid == (1.5, 2.0)
    assert back.bbox == (1, 2, 3, 4)
    assert back.mixed == ("a", 3)
    assert back.parts["x"].where == (0.5, 1.0)
    assert back.parts["x"]._type.endswith(".Part")
    assert back.raw == b"\x00\xff"
    assert back.history == [1.0, 2.5]  # a list stays a list
    assert back.timestamp == pytest.approx(1012.25)  # Unix seconds; the import restamps it


def test_a_none_field_is_left_out_on_the_wire_and_none_again_after() -> None:
    payload, name, schema = _wire(Seen(False, None, None, ("b", 1)))
    body = json.loads(payload)
    assert "centroid" not in body
    assert "bbox" not in body
    jsonschema.validate(body, json.loads(schema))
    back = decode_json(payload, name)
    assert back.centroid is None
    assert back.bbox is None
    assert back.found is False


def test_plain_values_and_mappings() -> None:
    payload, name, _ = _wire(7)
    assert (json.loads(payload), name) == ({"value": 7}, "builtins.int")
    assert decode_json(payload, name) == 7
    payload, name, _ = _wire({"value": 1, "b": (1, "x")})
    assert name == "builtins.dict"
    assert decode_json(payload, name) == {"value": 1, "b": [1, "x"]}


def test_an_unknown_type_keeps_its_fields_and_name() -> None:
    back = decode_json(b'{"a": 1, "p": {"_0": 1, "_1": "x"}}', "elsewhere.mod.Thing")
    assert back._type == "elsewhere.mod.Thing"
    assert back.a == 1
    assert back.p == (1, "x")


def test_an_older_exporter_is_still_read() -> None:
    back = decode_json(b'{"__type__": "Det", "found": true, "centroid": [1, 2]}', "")
    assert back._type == "Det"
    assert back.centroid == [1, 2]


def test_audio_goes_as_the_recordings_raw_audio() -> None:
    block = AudioBlock(np.linspace(-0.5, 0.5, 64, dtype=np.float32).reshape(32, 2), 48000, 3.0, 9)
    payload, name, _ = _wire(block)
    assert name == "foxglove.RawAudio"
    back = decode_audio(payload, 4, 1000.0)
    assert back.rate == 48000
    assert back.samples.shape == (32, 2)
    assert back.seq == 4
    assert np.allclose(back.samples, block.samples, atol=2 / 32768)
    assert back.timestamp == pytest.approx(3.0)  # its Unix time, back on this clock


class _Sample:
    def __init__(self, encoding: object) -> None:
        self.encoding = encoding


def test_the_zenoh_encoding_names_the_schema() -> None:
    enc = encoding_of("json", "flowrt.nodes.tracker.Detection")
    assert str(enc) == "application/json;flowrt.nodes.tracker.Detection"
    assert schema_of_sample(_Sample(enc)) == "flowrt.nodes.tracker.Detection"
    assert str(encoding_of("protobuf", "foxglove.RawAudio")).startswith("application/protobuf")
    assert schema_of_sample(_Sample("application/json")) == ""


@pytest.mark.parametrize(
    "value",
    [
        {"t": 1.5, "p": "12345678", "n": 3, "ok": True},  # flat: the short path
        {"timestamp": 12.25, "x": -1},  # flat, with its time moved to epoch ns
        {"a": None, "b": 1},  # not flat: None dropped by the walk
        {"a": float("nan"), "b": [1, (2, 3)], "c": {"d": np.int64(4)}},  # not flat
        {1: "key not text"},
    ],
)
def test_a_message_is_the_same_bytes_on_the_short_path(value: dict[object, object]) -> None:
    """The flat-mapping path of the JSON encoding writes what the general walk writes."""
    from flowrt.recording.encoding import conform, encode_json, schema_for, to_jsonable

    schema = schema_for(value)
    obj = to_jsonable(value)
    if isinstance(obj.get("timestamp"), float):
        obj["timestamp"] = round((obj["timestamp"] + 100.0) * 1e9)
    walked = conform(obj, json.loads(schema.data), coerce=not schema.guessed)
    assert (
        encode_json(value, schema, 100.0).data == json.dumps(walked, separators=(",", ":")).encode()
    )


def test_a_message_header_packs_as_the_header_class() -> None:
    from flowrt.remote.wire import Header, MessageHeaders, header_ids

    ids = header_ids("0123456789abcdef", "f" * 32)
    made = MessageHeaders(ids, "protobuf")(7, 1.25, 0.5)
    assert made == Header("0123456789abcdef", "f" * 32, 7, 1.25, 0.5, "protobuf").encode()
    assert Header.decode(made).kind == "protobuf"
    with pytest.raises(ValueError, match="longer"):
        header_ids("x" * 17, "z")


def test_a_frame_header_packs_as_the_header_class() -> None:
    import numpy as np

    from flowrt import Frame
    from flowrt.remote.wire import FrameHeaders, Header, frame_meta

    headers = FrameHeaders("0123456789abcdef", "f" * 32)
    for shape, pf in (((480, 640, 3), "BGR"), ((120, 160), "GRAY"), ((480, 640, 3), "RGB")):
        frame = Frame(np.zeros(shape, np.uint8), pixel_format=pf)
        frame.seq = 41
        meta = frame_meta(frame, "raw")
        whole = Header("0123456789abcdef", "f" * 32, 7, 1.25, 0.5, "frame", meta).encode()
        assert headers(frame, 7, 1.25, 0.5) == whole
        assert Header.decode(whole).frame == {**meta, "shape": list(shape)}


@pytest.mark.parametrize(
    ("payload", "schema", "expected"),
    [
        (b'{"t":1.5,"p":"x","n":3}', "builtins.dict", {"t": 1.5, "p": "x", "n": 3}),
        (b'{"_0":1,"_1":2}', "builtins.dict", (1, 2)),  # positional: a tuple, as before
        (b'{"a":{"_0":1}}', "builtins.dict", {"a": (1,)}),  # nested: restored
        (b'{"a":{"\\u005f_type__":"T","x":1}}', "", {"a": types.SimpleNamespace(x=1, _type="T")}),
        (b"\xef\xbb\xbf" + b'{"a":1}', "builtins.dict", {"a": 1}),  # a BOM
        ('{"a":1}'.encode("utf-16"), "", {"a": 1}),
        (b' {"a": 1, "b": [2]} \n', "builtins.dict", {"a": 1, "b": [2]}),  # white space
        (b'{"a":1,"_0":2}', "builtins.dict", {"a": 1, "_0": 2}),  # not positional
    ],
)
def test_json_payloads_decode_as_the_general_restoring_does(
    payload: bytes, schema: str, expected: object
) -> None:
    assert decode_json(payload, schema) == expected
