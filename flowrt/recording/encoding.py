"""How a flowrt value becomes an MCAP message, and back: the schemas Foxglove knows.

Frames become ``foxglove.RawImage`` (or ``foxglove.CompressedImage`` when a stream asks for
JPEG/PNG), protobuf-encoded by foxglove-sdk with its own schema descriptors, so the Foxglove
app shows them as images. Everything else (detections, health, numbers) is JSON with a JSON
schema: a dataclass or pydantic model gets the schema pydantic derives from its type, any
other value a permissive one, and Foxglove plots any numeric field.

Detections also become ``foxglove.ImageAnnotations`` (protobuf, like the images) on a topic
of their camera's, ``CAMERA/annotations/DETECTIONS`` (:func:`annotations_topic`): a circle at
the centroid, the bounding box, a label, stamped with the timestamp of the frame the detection
was computed on, so that Foxglove's image panel, with that topic ticked, draws each detection
on its own frame.

Why protobuf for images and not JSON: a JSON RawImage carries its pixels in base64, measured
at 4x the CPU of the protobuf encoding for 1936x1216 BGR frames (see docs/DESIGN-NOTES.md).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import struct
import sys
import types
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from ..frames import Frame
from .gilfree import join
from .jsonschema import app_schema, conform

__all__ = [
    "ANNOTATIONS_SCHEMA",
    "FRAME_ENCODINGS",
    "Decoder",
    "Encoded",
    "Overlay",
    "StreamSchema",
    "annotations_topic",
    "encode_annotations",
    "encode_frame",
    "encode_json",
    "is_detection",
    "schema_for",
]

# flowrt pixel format -> foxglove.RawImage encoding (and back)
FRAME_ENCODINGS: dict[str, str] = {"BGR": "bgr8", "RGB": "rgb8", "GRAY": "mono8"}
_PIXEL_FORMATS = {v: k for k, v in FRAME_ENCODINGS.items()}
_PIXEL_FORMATS["mono16"] = "GRAY"


@dataclass(frozen=True)
class StreamSchema:
    """What an MCAP channel needs: schema name/encoding/data and the message encoding."""

    name: str
    encoding: str  # schema encoding: protobuf | jsonschema
    data: bytes
    message_encoding: str  # protobuf | json
    #: a JSON schema guessed from a sample (a plain mapping), not derived from a type: values
    #: are then written as they are (never coerced to a guess), only ``None`` left out
    guessed: bool = field(default=False, compare=False)


@dataclass(frozen=True)
class Encoded:
    """One message ready to write: its schema and its bytes."""

    schema: StreamSchema
    data: bytes


def epoch_ns(t: float) -> int:
    """Unix time ``t`` (float seconds) in integer nanoseconds, the one conversion of the
    recording: log times, stamps and ``timestamp`` fields agree to the nanosecond (a stamp
    was truncated from ``t - floor(t)`` while the log time was ``round(t * 1e9)``, tens of
    ns apart, where the README says the capture time is the log time). The fraction is
    rounded on its own: ``t * 1e9`` near 1.7e18 is a multiple of 256 (.25 s as 249999872)."""
    if t <= 0:
        return 0
    sec = math.floor(t)
    return sec * 1_000_000_000 + round((t - sec) * 1e9)


def sec_nsec(t: float) -> tuple[int, int]:
    """Unix time ``t`` as (seconds, nanoseconds), :func:`epoch_ns`'s."""
    sec, nsec = divmod(epoch_ns(t), 1_000_000_000)
    return sec, nsec


def _timestamp(t: float) -> Any:
    from foxglove.messages import Timestamp

    sec, nsec = sec_nsec(t)
    return Timestamp(sec=sec, nsec=nsec)


def image_schema(compressed: bool) -> StreamSchema:
    """The foxglove-sdk's own schema of RawImage / CompressedImage (protobuf descriptors)."""
    from foxglove.messages import CompressedImage, RawImage

    s = (CompressedImage if compressed else RawImage).get_schema()
    return StreamSchema(s.name, s.encoding, bytes(s.data), "protobuf")


AUDIO_SCHEMA = "foxglove.RawAudio"


def audio_schema() -> StreamSchema:
    """The foxglove-sdk's own schema of RawAudio (protobuf descriptors)."""
    from foxglove.messages import RawAudio

    s = RawAudio.get_schema()
    return StreamSchema(s.name, s.encoding, bytes(s.data), "protobuf")


def encode_audio(block: Any, epoch_time: float) -> Encoded:
    """An :class:`flowrt.AudioBlock` as a foxglove RawAudio: pcm-s16, interleaved, stamped
    with its first sample's time (Unix time, the recording's time base)."""
    from foxglove.messages import RawAudio

    msg = RawAudio(
        timestamp=_timestamp(max(0.0, epoch_time)),
        data=block.pcm16(),
        format="pcm-s16",
        sample_rate=int(block.rate),
        number_of_channels=int(block.channels),
    )
    return Encoded(audio_schema(), msg.encode())


def encode_frame(
    frame: Frame, epoch_time: float, image_format: str = "raw", *, gil_free: bool = False
) -> Encoded:
    """A frame as a foxglove RawImage (``raw``) or CompressedImage (``jpeg``/``png``).

    Reads the pixels where they are (a shared-memory slot): call it from the writer thread
    while a link on the frame is held. ``gil_free``: the RawImage's bytes are a uint8 array
    copied with the GIL released (:mod:`.gilfree`), so the event loop runs meanwhile; else
    ``bytes``.
    """
    from foxglove.messages import CompressedImage

    data = np.ascontiguousarray(frame.data)
    if image_format in ("jpeg", "png"):
        import cv2

        img = data
        if frame.pixel_format == "RGB":
            img = cv2.cvtColor(data, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".jpg" if image_format == "jpeg" else ".png", img)
        if not ok:
            raise ValueError(f"cannot encode a {frame.pixel_format} frame as {image_format}")
        msg = CompressedImage(
            timestamp=_timestamp(epoch_time),
            frame_id=frame.source,
            data=buf.tobytes(),
            format=image_format,
        )
        return Encoded(image_schema(True), msg.encode())
    h, w = data.shape[:2]
    encoding = FRAME_ENCODINGS.get(frame.pixel_format)
    if data.dtype == np.uint16 and data.ndim == 2:
        encoding = "mono16"
    if encoding is None or data.dtype not in (np.uint8, np.uint16):
        raise ValueError(
            f"cannot record a {frame.pixel_format} {data.dtype} frame as a RawImage "
            f"(BGR, RGB, GRAY uint8 or GRAY uint16)"
        )
    sec, nsec = sec_nsec(epoch_time)
    head = raw_image_head(
        sec, nsec, frame.source, w, h, encoding, int(data.strides[0]), data.nbytes
    )
    pixels = memoryview(data.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
    if gil_free:
        return Encoded(image_schema(False), join(head, pixels))  # type: ignore[arg-type]
    return Encoded(image_schema(False), b"".join((head, pixels)))


ANNOTATIONS_SCHEMA = "foxglove.ImageAnnotations"


@dataclass(frozen=True)
class Overlay:
    """A detection to draw on its camera's image: written as ``foxglove.ImageAnnotations``."""

    detection: Any


def is_detection(value: Any) -> bool:
    """True for a value that says where an object is on which frame (a tracker's output).

    Duck-typed, as the runtime does not know the tracker's types: ``found``, ``centroid``,
    ``bbox``, and the ``source`` node and ``timestamp`` of the frame it was computed on.
    """
    return (
        isinstance(getattr(value, "source", None), str)
        and bool(value.source)
        and isinstance(getattr(value, "timestamp", None), float)
        and hasattr(value, "found")
        and hasattr(value, "centroid")
        and hasattr(value, "bbox")
    )


def annotations_topic(camera_topic: str, detection_topic: str) -> str:
    """``cam.frame/annotations/ball.detection``: one annotation topic per detection stream.

    One per stream, not one per camera: the image panel keeps the newest message of each
    annotation topic, and several trackers of one frame publish separately.
    """
    return f"{camera_topic}/annotations/{detection_topic}"


_PALETTE = [
    (1.0, 0.55, 0.0),  # orange
    (1.0, 0.9, 0.1),  # yellow
    (0.2, 0.5, 1.0),  # blue
    (0.9, 0.1, 0.9),  # magenta
    (0.1, 0.9, 0.9),  # cyan
    (0.3, 1.0, 0.3),  # green
]


def _colour(name: str, alpha: float = 1.0) -> Any:
    from foxglove.messages import Color

    r, g, b = _PALETTE[sum(name.encode()) % len(_PALETTE)]
    return Color(r=r, g=g, b=b, a=alpha)


def encode_annotations(det: Any, epoch_time: float) -> Encoded:
    """A detection as ``foxglove.ImageAnnotations`` stamped ``epoch_time`` (its frame's).

    Image coordinates put the origin at the top-left *corner* of the top-left pixel, so a
    centroid in pixel indices is drawn at ``+0.5``; a bbox ``x, y, w, h`` spans ``x .. x+w``.
    A detection that found nothing is an empty message: the panel clears the overlay.
    """
    from foxglove.messages import (
        CircleAnnotation,
        Color,
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
        TextAnnotation,
    )

    ts = _timestamp(max(0.0, epoch_time))
    name = str(getattr(det, "object", "") or det.source)
    circles, points, texts = [], [], []
    bbox = det.bbox
    if det.found and det.centroid is not None:
        cx, cy = (float(v) + 0.5 for v in det.centroid)
        if bbox is not None:
            diameter = float(max(bbox[2], bbox[3]))
        else:
            diameter = 2 * math.sqrt(max(float(getattr(det, "area", 0) or 0), 1.0) / math.pi)
        circles.append(
            CircleAnnotation(
                timestamp=ts,
                position=Point2(x=cx, y=cy),
                diameter=diameter,
                thickness=2.0,
                fill_color=_colour(name, 0.0),
                outline_color=_colour(name),
            )
        )
        if bbox is not None:
            x, y, w, h = (float(v) for v in bbox)
            corners = [(x, y), (x + w, y), (x + w, y + h), (x, y + h)]
            points.append(
                PointsAnnotation(
                    timestamp=ts,
                    type=PointsAnnotationType.LineLoop,
                    points=[Point2(x=px, y=py) for px, py in corners],
                    outline_color=_colour(name),
                    thickness=1.0,
                )
            )
        confidence = getattr(det, "confidence", None)
        label = name if confidence is None else f"{name} {float(confidence):.2f}"
        top = bbox[1] if bbox is not None else cy - diameter / 2
        left = bbox[0] if bbox is not None else cx - diameter / 2
        texts.append(
            TextAnnotation(
                timestamp=ts,
                position=Point2(x=float(left), y=max(0.0, float(top) - 2.0)),
                text=label,
                font_size=12.0,
                text_color=_colour(name),
                background_color=Color(r=0.0, g=0.0, b=0.0, a=0.5),
            )
        )
    # The message's own timestamp (newer schemas) says which image it belongs to, even empty.
    msg = ImageAnnotations(timestamp=ts, circles=circles, points=points, texts=texts)
    return Encoded(annotations_schema(), msg.encode())


def annotations_schema() -> StreamSchema:
    """foxglove-sdk's own protobuf schema of ``foxglove.ImageAnnotations``."""
    from foxglove.messages import ImageAnnotations

    s = ImageAnnotations.get_schema()
    return StreamSchema(s.name, s.encoding, bytes(s.data), "protobuf")


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _field(number: int, wire: int) -> bytes:
    return _varint(number << 3 | wire)


def _text(number: int, value: str) -> bytes:
    raw = value.encode()
    return _field(number, 2) + _varint(len(raw)) + raw if raw else b""


def _fixed32(number: int, value: int) -> bytes:
    return _field(number, 5) + struct.pack("<I", value) if value else b""


def raw_image_head(
    sec: int,
    nsec: int,
    frame_id: str,
    width: int,
    height: int,
    encoding: str,
    step: int,
    nbytes: int,
) -> bytes:
    """The protobuf bytes of a ``foxglove.RawImage`` up to its pixels (field 6's length).

    Why not foxglove-sdk's ``RawImage(...).encode()``: it copies the pixels three times (to
    bytes, into the message, into the encoding), measured at 3 x 10 ms per 1936x1216 frame on
    the loaded 2-core machine; here the pixels are copied once, after this head. The field
    numbers and types are those of the schema foxglove-sdk ships (a test decodes both and
    compares them).
    """
    ts = (_field(1, 0) + _varint(sec) if sec else b"") + (
        _field(2, 0) + _varint(nsec) if nsec else b""
    )
    return b"".join(
        (
            _field(1, 2) + _varint(len(ts)) + ts,  # timestamp
            _text(7, frame_id),
            _fixed32(2, width),
            _fixed32(3, height),
            _text(4, encoding),
            _fixed32(5, step),
            _field(6, 2) + _varint(nbytes),  # data: the pixels follow
        )
    )


def to_jsonable(value: Any) -> Any:
    """A JSON-ready view of a dataclass, pydantic model, numpy value or plain value."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if hasattr(value, "model_dump"):
        return value.model_dump(mode="json")
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, types.SimpleNamespace):  # a typed value received over Zenoh
        return {k: to_jsonable(v) for k, v in vars(value).items() if not k.startswith("_")}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, bytes | bytearray | memoryview):
        # bytes as base64, as Foxglove's JSON encoding has them (raw CAN data, payloads)
        import base64

        return base64.b64encode(bytes(value)).decode("ascii")
    return repr(value)


def _type_name(value: Any) -> str:
    t = type(value)
    return f"{t.__module__}.{t.__qualname__}"


def schema_for(value: Any) -> StreamSchema:
    """A JSON schema for a message value: pydantic's for typed values, permissive otherwise.

    A plain value (a number, a string, a list) is wrapped as ``{"value": ...}`` so that
    Foxglove, which plots fields of objects, can plot it.
    """
    name = _type_name(value)
    if isinstance(value, types.SimpleNamespace):  # received over Zenoh: its fields, as a dict
        name = str(getattr(value, "_type", "") or name)
        value = to_jsonable(value)
    schema: dict[str, Any]
    if (dataclasses.is_dataclass(value) and not isinstance(value, type)) or hasattr(
        value, "model_json_schema"
    ):
        try:
            from pydantic import TypeAdapter

            schema = TypeAdapter(type(value)).json_schema()
        except Exception:  # a type pydantic cannot describe: still a valid, permissive schema
            schema = {"type": "object", "properties": {}}
    elif isinstance(value, dict):
        schema = {
            "type": "object",
            "properties": _fields(value),
        }
    else:
        schema = {"type": "object", "properties": _fields({"value": value})}
    schema = app_schema(schema)  # what the Foxglove/Lichtblick apps can read (jsonschema.py)
    sample = to_jsonable(value)
    _fill_mappings(schema, sample)
    props = schema.get("properties", {})
    if isinstance(sample, dict) and isinstance(sample.get("timestamp"), float):
        props["timestamp"] = {  # written as epoch nanoseconds by encode_json
            "type": "integer",
            "description": "nanoseconds since the Unix epoch (the recording's time base)",
        }
    schema.setdefault("title", name)
    typed = dataclasses.is_dataclass(value) or hasattr(value, "model_json_schema")
    return StreamSchema(name, "jsonschema", json.dumps(schema).encode(), "json", not typed)


def _fill_mappings(schema: dict[str, Any], sample: Any) -> None:
    """Free-form mappings of a typed value (a CAN message's ``signals``) get their fields from
    the first value recorded, so each one can be plotted (the type alone says only 'dict')."""
    props = schema.get("properties")
    if not isinstance(props, dict) or not isinstance(sample, dict):
        return
    for key, sub in props.items():
        if not isinstance(sub, dict) or key not in sample:
            continue
        if (
            sub.get("type") == "object"
            and not sub.get("properties")
            and isinstance(sample[key], dict)
        ):
            sub["properties"] = _fields(sample[key])
        elif sub.get("type") == "object":
            _fill_mappings(sub, sample[key])


def _value_schema(value: Any) -> dict[str, Any]:
    """The schema of one value of a plain mapping (its type, as the apps need it), guessed
    from a sample: see :func:`_fields`."""
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int | float | np.integer | np.floating):
        return {"type": "number"}  # a later value of an int field may be a float
    if isinstance(value, dict):
        return {"type": "object", "properties": _fields(value)}
    if isinstance(value, list | tuple | np.ndarray):
        kinds = {_kind(v) for v in value}
        if len(kinds) == 1 and (kind := kinds.pop()) in ("boolean", "number", "string"):
            return {"type": "array", "items": {"type": kind}}
        if kinds == {"object"}:
            return {"type": "array", "items": _value_schema(value[0])}
        return {}  # empty, mixed or nested: left unconstrained (not a field the apps plot)
    if isinstance(value, str):
        return {"type": "string"}
    return {}  # None or an unknown type: unconstrained


def _kind(v: Any) -> str:
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, int | float | np.integer | np.floating):
        return "number"
    if isinstance(v, str):
        return "string"
    return "object" if isinstance(v, dict) else "other"


def _fields(sample: dict[Any, Any]) -> dict[str, Any]:
    """The typed fields of a plain mapping's sample; a field whose type a sample cannot tell
    (None, a mixed or nested list) is left out of the schema, so that whatever it holds later
    is valid and written unchanged (the apps do not offer it to plot)."""
    out = {}
    for k, v in sample.items():
        sub = _value_schema(v)
        if sub:
            out[str(k)] = sub
    return out


def encode_json(value: Any, schema: StreamSchema, epoch_offset: float | None = None) -> Encoded:
    """A message value as JSON under ``schema`` (from :func:`schema_for` of the stream).

    ``epoch_offset`` (added to the runtime clock for Unix time): a value's own ``timestamp``
    (runtime clock, seconds) is written as nanoseconds since the Unix epoch, the time base of
    every time in a recording (log times, image stamps); replay maps it back.
    """
    if schema.guessed and (data := flat_json(value, epoch_offset)) is not None:
        return Encoded(schema, data)  # what the two walks below would give, unchanged
    obj = to_jsonable(value)
    if not isinstance(obj, dict):
        obj = {"value": obj}
    elif epoch_offset is not None:
        ts = obj.get("timestamp")
        if isinstance(ts, float) and math.isfinite(ts):
            obj["timestamp"] = epoch_ns(ts + epoch_offset)
    # the value in the shape of its schema (jsonschema.py); a guessed schema only drops None
    obj = conform(obj, _parsed(schema.data), coerce=not schema.guessed)
    return Encoded(schema, _dumps(obj).encode())


_dumps = json.JSONEncoder(separators=(",", ":")).encode
"""``json.dumps(obj, separators=(",", ":"))`` without a new encoder object per call."""


def flat_json(value: Any, epoch_offset: float | None) -> bytes | None:
    """A flat mapping (:func:`_flat`) under a guessed schema as :func:`encode_json` writes it
    (its float ``timestamp`` in epoch nanoseconds); None when ``value`` is not flat."""
    if not _flat(value):
        return None
    ts = value.get("timestamp")
    if epoch_offset is not None and type(ts) is float:
        value = {**value, "timestamp": epoch_ns(ts + epoch_offset)}
    return _flat_dumps(value)


_flat_dumps = msgspec.json.Encoder().encode
"""A flat mapping (:func:`_flat`) as compact UTF-8 JSON. msgspec's C encoder, not ``json``'s:
a small message's path runs cold at 20 Hz, where ``json``'s encoder cost 15 us and this one
3 us (cache-evicted calls, median). Same values as ``_dumps`` (text keys, scalars, finite
floats); the bytes differ only in spelling: UTF-8 for non-ASCII text, ``1e16`` for
``1e+16``."""

_SCALARS = (str, int, bool)


def _flat(value: Any) -> bool:
    """A mapping of text keys to text, integers, booleans and finite floats (exact types):
    :func:`to_jsonable` and a guessed schema's :func:`conform` leave it as it is. A message
    path at 20 Hz runs cold (its caches evicted between messages), where each walk costs
    tens of microseconds; this check costs one pass."""
    if type(value) is not dict:
        return False
    for k, v in value.items():
        t = type(v)
        if type(k) is not str or (t not in _SCALARS and (t is not float or not math.isfinite(v))):
            return False
    return True


@functools.lru_cache(maxsize=512)
def _parsed(data: bytes) -> Any:
    return json.loads(data)


class Decoder:
    """Turns recorded messages back into flowrt values (frames as pixel arrays).

    Images are decoded with the protobuf descriptors stored in the file (mcap-protobuf-support),
    JSON messages with ``json``; a JSON message whose schema names a dataclass of a module
    already imported is rebuilt as that dataclass, so a replayed detection looks like a live one.
    """

    def __init__(self) -> None:
        from mcap_protobuf.decoder import DecoderFactory

        self._factory = DecoderFactory()
        self._decoders: dict[int, Any] = {}
        self._types: dict[str, Any] = {}

    def is_image(self, schema_name: str) -> bool:
        return schema_name in ("foxglove.RawImage", "foxglove.CompressedImage")

    def protobuf(self, schema: Any, data: bytes) -> Any:
        """A protobuf message (images, audio) decoded with the descriptors stored in the file,
        one decoder per schema."""
        dec = self._decoders.get(schema.id)
        if dec is None:
            dec = self._factory.decoder_for("protobuf", schema)
            if dec is None:
                raise ValueError(f"no protobuf decoder for schema {schema.name}")
            self._decoders[schema.id] = dec
        return dec(data)

    def image(self, schema: Any, data: bytes) -> tuple[np.ndarray, str]:
        """(pixels, flowrt pixel format) of a RawImage/CompressedImage message."""
        return self.pixels(schema.name, self.protobuf(schema, data))

    def pixels(self, schema_name: str, msg: Any) -> tuple[np.ndarray, str]:
        """(pixels, flowrt pixel format) of a decoded RawImage/CompressedImage (its other
        fields, the timestamp, stay the caller's to read)."""
        if schema_name == "foxglove.CompressedImage":
            import cv2

            img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"cannot decode a {msg.format} image")
            return img, "GRAY" if img.ndim == 2 else "BGR"
        enc = msg.encoding
        fmt = _PIXEL_FORMATS.get(enc)
        if fmt is None:
            raise ValueError(f"unsupported RawImage encoding {enc!r}")
        dtype = np.uint16 if enc == "mono16" else np.uint8
        channels = 1 if fmt == "GRAY" else 3
        itemsize = np.dtype(dtype).itemsize
        flat = np.frombuffer(msg.data, dtype=np.uint8)
        rows = flat[: msg.step * msg.height].reshape(msg.height, msg.step)
        px = rows[:, : msg.width * channels * itemsize].view(dtype)
        shape = (msg.height, msg.width) if channels == 1 else (msg.height, msg.width, channels)
        return px.reshape(shape), fmt

    def audio(self, schema: Any, data: bytes, seq: int, epoch_offset: float) -> Any:
        """A RawAudio message as an :class:`flowrt.AudioBlock` (float32 samples), its time
        moved by ``epoch_offset`` (recorded Unix time minus the replaying clock)."""
        from ..audio import AudioBlock

        msg = self.protobuf(schema, data)
        ch = max(1, int(msg.number_of_channels))
        pcm = np.frombuffer(msg.data, dtype="<i2")
        samples = (pcm.reshape(-1, ch).astype(np.float32) / 32768.0).copy()
        t = msg.timestamp.seconds + msg.timestamp.nanos / 1e9 - epoch_offset
        return AudioBlock(samples, int(msg.sample_rate), t, seq)

    def message(self, schema_name: str, data: bytes) -> Any:
        """A JSON message as its dataclass when importable, else as a dict (or bare value)."""
        obj = json.loads(data)
        cls = self._type(schema_name)
        if cls is not None and isinstance(obj, dict):
            try:
                fields = dataclasses.fields(cls)
                kw: dict[str, Any] = {f.name: None for f in fields if _required(f)}  # was None
                kw.update({f.name: math.nan for f in fields if f.type in (float, "float")})
                names = {f.name for f in fields}
                kw.update({k: _tuples(v) for k, v in obj.items() if k in names})
                return cls(**kw)
            except Exception:
                return obj
        if isinstance(obj, dict) and set(obj) == {"value"}:
            return plain_value(schema_name, obj["value"])
        if obj == {} and schema_name in FLOAT_TYPES:  # a non-finite float (see FLOAT_TYPES)
            return math.nan
        return obj

    def _type(self, name: str) -> Any:
        if name in self._types:
            return self._types[name]
        cls = None
        module, _, qual = name.rpartition(".")
        # Only modules already imported: a file never makes this process import code.
        mod = sys.modules.get(module) if module else None
        if mod is not None:
            cls = getattr(mod, qual, None)
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            cls = None
        self._types[name] = cls
        return cls


FLOAT_TYPES = frozenset(["builtins.float", "numpy.float64", "numpy.float32", "numpy.float16"])
"""Schema names of plain float streams. JSON has no infinity nor NaN: a non-finite float is
written as an absent field (objects) or ``null`` (arrays), as Foxglove's SDKs write it; read
back, a float stream's value or a ``float`` field of a dataclass so left out is ``NaN``
(its sign and infinity lost: ``--profile ros2`` keeps floats exactly), not a mapping a typed
port refuses nor the field's default."""


def plain_value(schema_name: str, v: Any) -> Any:
    """A plain stream's value (``{"value": v}``, schema ``schema_name``) back in its type
    where JSON changed it: bytes (written as base64 text) and a tuple (an array). The
    replay's decoder, a Zenoh import's and the ros2 profile's restorer all read it so."""
    if schema_name in ("builtins.bytes", "builtins.bytearray") and isinstance(v, str):
        import base64

        try:
            return base64.b64decode(v, validate=True)
        except ValueError:
            return v
    if schema_name == "builtins.tuple" and isinstance(v, list):
        return _tuples(v)
    return v


def _required(f: dataclasses.Field[Any]) -> bool:
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _tuples(v: Any) -> Any:
    """JSON has no tuples: give back fixed-size sequences (bbox, centroid) as tuples, and the
    positional objects (``_0``, ``_1`` ...) a mixed tuple is written as (jsonschema.py)."""
    if isinstance(v, list):
        return tuple(_tuples(x) for x in v)
    if isinstance(v, dict) and v and all(k == f"_{i}" for i, k in enumerate(v)):
        return tuple(_tuples(x) for x in v.values())
    return v
