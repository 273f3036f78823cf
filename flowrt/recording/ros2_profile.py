"""The ``ros2`` recording profile: flowrt values as ROS 2 messages (CDR, ``ros2msg`` schemas).

``flowrt record G --profile ros2`` (``profile: ros2`` on the ``recorder``) writes a rosbag2
folder: the MCAP files hold CDR messages under ``ros2msg`` schemas, each schema the type's
full definition with its dependencies (as rosbag2 writes them), so ``rosbags``'
``AnyReader``, ``mcap-ros2-support`` and the Foxglove app read every message without a ROS 2
install. A standard type is used where one fits, a flowrt definition otherwise:

=====================================  =======================================================
flowrt value                           ROS 2 message
=====================================  =======================================================
``Frame`` (BGR, RGB, GRAY, GRAY16)     ``sensor_msgs/msg/Image`` (bgr8, rgb8, mono8, mono16)
``Frame`` with ``--images jpeg|png``   ``sensor_msgs/msg/CompressedImage``
velocity command ``{v, w}`` or         ``geometry_msgs/msg/Twist`` (v/vx/vy/vz -> linear,
``{vx, vy, vz, wx, wy, wz}``           w/wx/wy/wz -> angular)
``bool``, ``int``, ``float``, ``str``  ``std_msgs/msg/Bool``, ``Int64``, ``Float64``, ``String``
``AudioBlock``                         ``flowrt_msgs/msg/AudioBlock`` (pcm s16, interleaved)
a dataclass / pydantic model           ``flowrt_msgs/msg/<ClassName>``, from its type hints
a mapping of snake_case keys           ``flowrt_msgs/msg/<Topic>``, from its first value
any other mapping (CAN signals)        ``flowrt_msgs/msg/KeyValues`` (key, value, text)
=====================================  =======================================================

In flowrt definitions ``X | None`` is an array of zero or one ``X`` (``centroid`` of a
detection that found nothing is ``[]``), a mapping is ``KeyValue[]``, a float ``timestamp``
(the runtime clock: a dataclass's, or a mapping's such as a sync set's index) is a
``builtin_interfaces/msg/Time`` in Unix time, and a value of no ROS type is its JSON text.
Detections are not drawn as annotations in this profile. Topics are ROS 2 names
(:func:`ros2_topic`).

Read back by flowrt (the ``replay`` node, so ``flowrt replay BAG --graph G``), a message is
the value it was written from again (:func:`value_restorer`), so that a replayed source's
typed outputs take it: flowrt's own ``KeyValue[]`` the mapping (:func:`mapping_restorer`: a
``can`` node gets ``{"LeftSpeed": 0.25}``, not ``{"items": [...]}``), a ``std_msgs`` scalar
the scalar (a ``counter`` gets ``3``, not ``{"data": 3}``), an ``AudioBlock`` the block
(:func:`audio_block_of`), a flowrt message's ``timestamp`` Unix nanoseconds (as a ``flowrt``
recording's JSON has it; the replay moves it onto its clock). Other readers see the
messages as written.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import struct
import types
import typing
from collections.abc import Callable
from typing import Any

import numpy as np

from ..audio import AudioBlock
from ..frames import Frame
from .encoding import (
    FRAME_ENCODINGS,
    Encoded,
    Overlay,
    StreamSchema,
    plain_value,
    sec_nsec,
    to_jsonable,
)
from .streams import image_format_of

__all__ = [
    "Ros2Encoder",
    "audio_block_of",
    "mapping_restorer",
    "mappings_of",
    "ros2_topic",
    "value_restorer",
]

SEP = "=" * 80 + "\n"
TIME = "builtin_interfaces/msg/Time"
DEFS: dict[str, str] = {
    TIME: "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/msg/Image": "std_msgs/Header header\nuint32 height\nuint32 width\n"
    "string encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "std_msgs/msg/Bool": "bool data\n",
    "std_msgs/msg/Int64": "int64 data\n",
    "std_msgs/msg/Float64": "float64 data\n",
    "std_msgs/msg/String": "string data\n",
    "flowrt_msgs/msg/KeyValue": "string key\nfloat64 value\nstring text\n",
    "flowrt_msgs/msg/KeyValues": "flowrt_msgs/KeyValue[] items\n",
    "flowrt_msgs/msg/AudioBlock": "builtin_interfaces/Time stamp\nuint32 sample_rate\n"
    "uint32 channels\nint64 seq\nint16[] data\n",
}
_SCALAR_TYPES = {
    bool: "std_msgs/msg/Bool",
    int: "std_msgs/msg/Int64",
    float: "std_msgs/msg/Float64",
}
_VELOCITY = {"v": ("linear", "x"), "vx": ("linear", "x"), "vy": ("linear", "y")}
_VELOCITY |= {"vz": ("linear", "z"), "w": ("angular", "z"), "wz": ("angular", "z")}
_VELOCITY |= {"wx": ("angular", "x"), "wy": ("angular", "y")}
_FIELD = re.compile(r"^[a-z][a-z0-9_]*$")
_PRIMITIVE = {"bool", "int64", "float64", "string", "uint8", "int16", "uint32", "int32"}


def _definition(name: str, defs: dict[str, str]) -> str:
    """``name``'s definition followed by every type it uses, as rosbag2 writes a schema."""
    out, seen, todo = [defs[name]], {name}, _uses(defs[name])
    while todo:
        dep = todo.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        pkg, _, short = dep.partition("/msg/")
        out.append(f"{SEP}MSG: {pkg}/{short}\n{defs[dep]}")
        todo.extend(_uses(defs[dep]))
    return "".join(out)


def _uses(text: str) -> list[str]:
    found = []
    for line in text.splitlines():
        typ = line.split()[0].removesuffix("[]") if line.strip() else ""
        if "/" in typ:
            pkg, _, short = typ.partition("/")
            found.append(f"{pkg}/msg/{short}")
    return found


def ros2_topic(name: str) -> str:
    """A flowrt stream's name as a valid ROS 2 topic: ``front_cam.frame`` -> ``/front_cam/frame``.

    ROS 2 refuses a dot in a topic name (``ros2 bag play`` could not publish it); the channel's
    ``source`` metadata keeps the flowrt name, so flowrt's replay finds the node again.
    """
    parts = [re.sub(r"[^A-Za-z0-9_]", "_", p) for p in re.split(r"[./]+", name) if p]
    return "/" + "/".join(p if not p[0].isdigit() else f"_{p}" for p in parts)


class Ros2Encoder:
    """A value to the CDR bytes of its ROS 2 message (the writer's encoder in this profile)."""

    def __init__(self, image_formats: dict[str, str], epoch_offset: float) -> None:
        self._formats = image_formats
        self._offset = epoch_offset
        self._defs = dict(DEFS)
        self._streams: dict[str, tuple[type, StreamSchema, Any, Any]] = {}
        self._serializers: dict[str, Any] = {}

    def encode(self, topic: str, v: Any) -> Encoded:
        if isinstance(v, Encoded):
            return v
        if isinstance(v, Overlay):
            raise ValueError("annotations are not recorded in the ros2 profile")
        if isinstance(v, Frame) and self._format(topic, "raw") == "raw":
            return self._raw_image(v)
        got = self._streams.get(topic)  # a channel has one schema: its first value's
        if got is None:
            got = self._streams[topic] = (type(v), *self._stream(topic, v))
        first, schema, convert, write = got
        if type(v) is not first and not (_number(v) and _number_type(first)):
            raise ValueError(f"a {type(v).__name__} on a stream of {first.__name__}")
        return Encoded(schema, write(convert(v)))

    def _schema(self, name: str) -> StreamSchema:
        return StreamSchema(name, "ros2msg", _definition(name, self._defs).encode(), "cdr")

    def _writer(self, name: str) -> Any:
        from mcap_ros2._dynamic import serialize_dynamic

        fn = serialize_dynamic(name, _definition(name, self._defs))[name]
        return fn

    def _stream(self, topic: str, v: Any) -> tuple[StreamSchema, Any, Any]:
        """(schema, value -> dict, dict -> CDR) for the stream's first value."""
        name: str
        if isinstance(v, Frame):
            name, convert = "sensor_msgs/msg/CompressedImage", self._compressed(topic)
        elif isinstance(v, AudioBlock):
            name, convert = "flowrt_msgs/msg/AudioBlock", self._audio
        elif isinstance(v, bool | np.bool_):
            name, convert = "std_msgs/msg/Bool", lambda x: {"data": bool(x)}
        elif isinstance(v, int | np.integer):
            name, convert = "std_msgs/msg/Int64", _integral
        elif isinstance(v, float | np.floating):
            name, convert = "std_msgs/msg/Float64", lambda x: {"data": float(x)}
        elif isinstance(v, str):
            name, convert = "std_msgs/msg/String", lambda x: {"data": x}
        elif _is_velocity(v):
            name, convert = "geometry_msgs/msg/Twist", _twist
        else:
            name, field = self._define(topic, v)
            convert = lambda x: field(x)  # noqa: E731
        return self._schema(name), convert, self._writer(name)

    # --- images and audio -------------------------------------------------------------

    def _stamp(self, t: float) -> dict[str, int]:
        sec, nsec = sec_nsec(t + self._offset)  # (its log time's ns)
        return {"sec": sec, "nanosec": nsec}

    def _format(self, topic: str, default: str) -> str:
        return image_format_of(self._formats, topic, default)

    def _raw_image(self, frame: Frame) -> Encoded:
        """sensor_msgs/msg/Image, its CDR written by hand: the pixels copied once."""
        data = np.ascontiguousarray(frame.data)
        enc = FRAME_ENCODINGS.get(frame.pixel_format)
        if data.dtype == np.uint16 and data.ndim == 2:
            enc = "mono16"
        if enc is None or data.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"no sensor_msgs/msg/Image encoding for {frame.pixel_format}")
        h, w = data.shape[:2]
        stamp = self._stamp(frame.timestamp)
        out = _CdrOut()
        out.u32(0x00000100)  # encapsulation: CDR little-endian (bytes 00 01 00 00)
        out.i32(stamp["sec"])
        out.u32(stamp["nanosec"])
        out.string(frame.source)
        out.u32(h)
        out.u32(w)
        out.string(enc)
        out.u8(0)
        out.u32(int(data.strides[0]))
        out.u32(data.nbytes)
        body = b"".join((out.bytes(), memoryview(data.reshape(-1).view(np.uint8))))  # type: ignore[arg-type]
        return Encoded(self._schema("sensor_msgs/msg/Image"), body)

    def _compressed(self, topic: str) -> Any:
        fmt = self._format(topic, "jpeg")

        def convert(frame: Frame) -> dict[str, Any]:
            import cv2

            img = frame.data
            if frame.pixel_format == "RGB":
                img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
            ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", img)
            if not ok:
                raise ValueError(f"cannot encode a {frame.pixel_format} frame as {fmt}")
            header = {"stamp": self._stamp(frame.timestamp), "frame_id": frame.source}
            return {"header": header, "format": fmt, "data": buf.tobytes()}

        return convert

    def _audio(self, block: AudioBlock) -> dict[str, Any]:
        pcm = np.frombuffer(block.pcm16(), dtype="<i2")
        return {
            "stamp": self._stamp(block.timestamp),
            "sample_rate": int(block.rate),
            "channels": int(block.channels),
            "seq": int(block.seq),
            "data": pcm.tolist(),
        }

    # --- flowrt definitions ------------------------------------------------------------

    def _define(self, topic: str, v: Any) -> tuple[str, Any]:
        """A flowrt_msgs type for ``v`` (registered in ``self._defs``) and its converter."""
        if isinstance(v, dict) and not all(isinstance(k, str) and _FIELD.match(k) for k in v):
            return "flowrt_msgs/msg/KeyValues", lambda x: {"items": _key_values(x)}
        if (dataclasses.is_dataclass(v) and not isinstance(v, type)) or hasattr(v, "model_fields"):
            hints = _hints(type(v))
            base = type(v).__name__
        elif isinstance(v, dict):
            hints = {k: _sample_type(x) for k, x in v.items()}
            if isinstance(v.get("timestamp"), float):  # the runtime clock, as a field's is
                hints["timestamp"] = _Stamp  # (a sync set's index, a joystick's state)
            base = "".join(p.capitalize() for p in re.split(r"[^A-Za-z0-9]+", topic) if p)
        else:
            hints = {"data": Any}
            base = type(v).__name__
        name = f"flowrt_msgs/msg/{_type_name(base)}"
        fields = [(k, _field_name(k), self._field_type(t)) for k, t in hints.items()]
        if len({f for _, f, _ in fields}) < len(fields):
            raise ValueError(f"{base}: field names that differ only in case or punctuation")
        self._defs[name] = "".join(f"{typ} {f}\n" for _, f, (typ, _) in fields) or "uint8 empty\n"

        def convert(x: Any) -> dict[str, Any]:
            if not isinstance(x, dict) and not hasattr(x, "__dict__") and hints == {"data": Any}:
                x = {"data": x}
            out = {}
            for k, f, (_, conv) in fields:
                raw = x.get(k) if isinstance(x, dict) else getattr(x, k, None)
                out[f] = conv(raw)
            if isinstance(x, dict):
                extra = set(x) - {k for k, _, _ in fields}
                if extra:
                    raise ValueError(f"keys not in its definition: {', '.join(sorted(extra))}")
            return out

        return name, convert

    def _field_type(self, hint: Any) -> tuple[str, Any]:
        """(ros2msg field type, Python value -> what the serializer takes) for a type hint."""
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin in (typing.Union, types.UnionType):
            inner = [a for a in args if a is not type(None)]
            if len(inner) == 1 and len(inner) < len(args):  # X | None: zero or one X
                typ, conv = self._field_type(inner[0])
                if typ.endswith("[]"):
                    return typ, lambda x: [] if x is None else conv(x)
                return f"{typ}[]", lambda x: [] if x is None else [conv(x)]
            if all(a in (int, float) for a in inner):
                return "float64", _float
            return "string", _json_text
        if hint is bool:
            return "bool", lambda x: bool(x)
        if hint is int:
            return "int64", lambda x: int(x or 0)
        if hint is float:
            return "float64", _float
        if hint is str:
            return "string", lambda x: "" if x is None else str(x)
        if hint is bytes:
            return "uint8[]", lambda x: bytes(x or b"")
        if hint is _Stamp:
            return "builtin_interfaces/Time", lambda x: self._stamp(float(x or 0.0))
        if origin in (tuple, list) and args:
            item = args[0]
            if all(a in (int, float, Ellipsis) for a in args) and item in (int, float):
                typ, conv = (
                    ("int64", int) if set(args) - {Ellipsis} == {int} else ("float64", float)
                )
                return f"{typ}[]", lambda x: [conv(i) for i in (x or ())]
        if origin is dict or hint is dict:
            return "flowrt_msgs/KeyValue[]", _key_values
        return "string", _json_text


class _Stamp:
    """The type hint of a float ``timestamp`` field: runtime-clock seconds -> Time."""


def _hints(cls: type) -> dict[str, Any]:
    try:
        hints = typing.get_type_hints(cls)
    except Exception:
        hints = {}
    names = (
        [f.name for f in dataclasses.fields(cls)]
        if dataclasses.is_dataclass(cls)
        else list(getattr(cls, "model_fields", {}))
    )
    out = {n: hints.get(n, Any) for n in names}
    if out.get("timestamp") is float:
        out["timestamp"] = _Stamp
    return out


def _sample_type(x: Any) -> Any:
    if isinstance(x, bool):
        return bool
    if isinstance(x, int | float):
        return float  # a number that is 0 first may be 0.5 next
    if isinstance(x, str):
        return str
    if isinstance(x, list | tuple) and all(
        isinstance(i, int | float) and not isinstance(i, bool) for i in x
    ):
        return tuple[float, ...]
    if isinstance(x, dict):
        return dict
    return Any


def _field_name(key: str) -> str:
    """A valid ROS 2 field name for ``key``: lower case, ``_`` for anything else."""
    name = re.sub(r"[^a-z0-9_]", "_", re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", key).lower())
    name = re.sub(r"_+", "_", name).strip("_")
    return name if name and name[0].isalpha() else f"f_{name}"


def _type_name(base: str) -> str:
    name = re.sub(r"[^A-Za-z0-9]", "", base) or "Message"
    return name[0].upper() + name[1:] if name[0].isalpha() else f"M{name}"


def _number(v: Any) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(
        v, bool | np.bool_
    )


def _number_type(t: type) -> bool:
    return issubclass(t, int | float | np.integer | np.floating) and not issubclass(
        t, bool | np.bool_
    )


def _integral(x: Any) -> dict[str, int]:
    """An Int64 stream's value: a float is taken only when it is a whole number."""
    if float(x) != int(x):
        raise ValueError(f"{x!r} on a stream of integers")
    return {"data": int(x)}


def _float(x: Any) -> float:
    return float(x) if x is not None else math.nan


def _json_text(x: Any) -> str:
    return json.dumps(to_jsonable(x), separators=(",", ":"))


def _key_values(x: Any) -> list[dict[str, Any]]:
    out = []
    for k, v in (x or {}).items():
        number = isinstance(v, int | float | np.number) and not isinstance(v, bool)
        text = "" if number else (v if isinstance(v, str) else _json_text(v))
        out.append({"key": str(k), "value": float(v) if number else math.nan, "text": text})
    return out


# --- read back: flowrt's KeyValue[] as the mapping it was written from --------------------

KEY_VALUE = "flowrt_msgs/KeyValue"
_KEY_VALUE_FIELDS = [
    ("string", False, "key"),
    ("float64", False, "value"),
    ("string", False, "text"),
]
_KEY_VALUES_FIELDS = [(KEY_VALUE, True, "items")]
_MSG_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "string", "wstring"}
_MSG_PRIMITIVES |= {f"{s}int{n}" for s in ("", "u") for n in (8, 16, 32, 64)}
_JSON_STARTS = tuple('[{"tfn')  # JSON of a non-number: array, object, string, true/false/null


def mappings_of(items: Any) -> dict[str, Any]:
    """The mapping a ``KeyValue[]`` (decoded to dicts) was written from: ``_key_values``
    inverted, so a replayed ``can`` node gets its signals by name.

    A number is its ``value``; anything else has a NaN ``value`` and its ``text``: a string
    as it is, any other value as its JSON. Comes back as written: text keys, numbers,
    strings, bools, None, and lists and mappings nested in a value. Does not round-trip:

    - an ``int`` comes back a ``float`` (``3`` -> ``3.0``, equal; past 2**53 rounded):
      ``value`` is a float64 and the type is not written;
    - a key that was not a string comes back as its text (``str(key)``);
    - a NaN number and the empty string are written alike (NaN, ``""``): read as NaN;
    - a string that is exactly the JSON written for another value (``"true"``, ``"null"``,
      ``"[1,2]"``, ``'"x"'``) comes back as that value (``True``, ``None``, ``[1, 2]``,
      ``"x"``);
    - inside a nested value, what JSON loses: tuples come back as lists, keys as text,
      NaN and infinities as None, bytes as base64 text, other objects as their ``repr``.
    """
    out: dict[str, Any] = {}
    for item in items or ():
        value, text = item.get("value"), item.get("text") or ""
        if isinstance(value, int | float) and not math.isnan(value):
            out[str(item.get("key"))] = float(value)
        else:
            out[str(item.get("key"))] = _from_text(text) if text else math.nan
    return out


def _from_text(text: str) -> Any:
    """A ``KeyValue``'s ``text``: the value whose JSON it is exactly (as ``_json_text``
    writes it), else the string itself. Numbers are never written as text: ``"1"`` is a
    string."""
    if not text.startswith(_JSON_STARTS):
        return text
    try:
        parsed = json.loads(text)
    except ValueError:
        return text
    if isinstance(parsed, int | float) and not isinstance(parsed, bool):
        return text
    return parsed if json.dumps(parsed, separators=(",", ":")) == text else text


def mapping_restorer(name: str, encoding: str, data: bytes) -> Callable[[Any], Any] | None:
    """For the decoded messages of a schema: a function giving their ``KeyValue[]`` fields
    back as mappings (:func:`mappings_of`; a whole ``KeyValues`` message becomes the mapping
    itself), or None when the schema has no such field (its messages stay as decoded).

    Only flowrt's own type counts: ``flowrt_msgs/KeyValue`` defined in the schema as this
    profile writes it (``string key``, ``float64 value``, ``string text``); a foreign type
    keeps its fields. Built once per schema (cached): a replay calls it for every message.
    """
    if encoding != "ros2msg" or KEY_VALUE.encode() not in data:
        return None
    return _restorer_of(name, data)


@functools.lru_cache(maxsize=256)
def _restorer_of(name: str, data: bytes) -> Callable[[Any], Any] | None:
    try:
        defs = _msg_types(name, data.decode())
    except UnicodeDecodeError:
        return None
    if defs.get(KEY_VALUE) != _KEY_VALUE_FIELDS:
        return None
    root = _type_key(name)
    if defs.get(root) == _KEY_VALUES_FIELDS and root == "flowrt_msgs/KeyValues":
        return lambda v: mappings_of(v.get("items")) if isinstance(v, dict) else v
    return _fields_restorer(defs, root, frozenset({root}))


def _fields_restorer(
    defs: dict[str, list[tuple[str, bool, str]]], typ: str, seen: frozenset[str]
) -> Callable[[Any], Any] | None:
    """Restores the ``KeyValue[]`` fields of ``typ``, also inside its nested messages."""
    convs: list[tuple[str, Callable[[Any], Any]]] = []
    for base, array, field in defs.get(typ, []):
        if base == KEY_VALUE and array:
            convs.append((field, mappings_of))
        elif base in defs and base not in seen:
            inner = _fields_restorer(defs, base, seen | {base})
            if inner is not None:
                convs.append((field, _each(inner) if array else inner))
    if not convs:
        return None

    def restore(v: Any) -> Any:
        if not isinstance(v, dict):
            return v
        out = dict(v)
        for field, conv in convs:
            if field in out:
                out[field] = conv(out[field])
        return out

    return restore


def _each(conv: Callable[[Any], Any]) -> Callable[[Any], Any]:
    return lambda xs: [conv(x) for x in xs] if isinstance(xs, list) else xs


# --- read back: the other values the profile writes, as they were -------------------------

_STD_SCALARS = {  # std_msgs' one-field wrappers of a primitive: the four flowrt writes, and
    f"std_msgs/{name}": typ  # their siblings, so a bag's Int32 is not read unlike its Int64
    for name, typ in (
        ("Bool", "bool"), ("Byte", "byte"), ("Char", "char"), ("String", "string"),
        ("Float32", "float32"), ("Float64", "float64"),
        *((f"{u}Int{n}", f"{u.lower()}int{n}") for u in ("", "U") for n in (8, 16, 32, 64)),
    )
}  # fmt: skip
AUDIO_BLOCK = "flowrt_msgs/AudioBlock"
_TIME_KEY = "builtin_interfaces/Time"
_TIME_FIELDS = [("int32", False, "sec"), ("uint32", False, "nanosec")]
_AUDIO_FIELDS = [
    (_TIME_KEY, False, "stamp"),
    ("uint32", False, "sample_rate"),
    ("uint32", False, "channels"),
    ("int64", False, "seq"),
    ("int16", True, "data"),
]


def value_restorer(name: str, encoding: str, data: bytes) -> Callable[[Any], Any] | None:
    """For the decoded messages of a schema: a function giving back the value this profile
    wrote them from, or None when they stay as decoded. What the replay node publishes, so
    that a graph replayed from a ``ros2`` bag gets what a ``flowrt`` recording gives it
    (a typed output refuses ``{"data": 1}`` where it declares ``int``):

    - a ``std_msgs`` scalar (``Bool``, ``Int64``, ``Float64``, ``String``, and the other
      one-field wrappers ``Int32``, ``UInt8``, ``Float32``...): its ``data``, the Python
      scalar. Also from a bag flowrt did not write: the message is the same;
    - flowrt's ``AudioBlock``: an :class:`~flowrt.AudioBlock` (:func:`audio_block_of`);
    - ``KeyValue[]`` fields and ``KeyValues`` messages: mappings (:func:`mapping_restorer`);
    - flowrt's ``Bytes`` and ``Tuple`` wrappers (``string data``, the value's JSON): the
      bytes, the tuple;
    - the ``builtin_interfaces/Time timestamp`` of a ``flowrt_msgs`` message (a float
      ``timestamp`` when written): nanoseconds since the epoch, as a ``flowrt`` recording
      has it in JSON, which replay moves onto its own clock.

    A type is recognised by its definition in the schema, as this profile writes it; one of
    the same name with other fields keeps them. Built once per schema (cached).
    """
    if encoding != "ros2msg":
        return None
    return _value_restorer(name, bytes(data))


@functools.lru_cache(maxsize=256)
def _value_restorer(name: str, data: bytes) -> Callable[[Any], Any] | None:
    try:
        defs = _msg_types(name, data.decode())
    except UnicodeDecodeError:
        return None
    root = _type_key(name)
    fields = defs.get(root)
    time_ok = defs.get(_TIME_KEY) == _TIME_FIELDS
    if root in _STD_SCALARS and fields == [(_STD_SCALARS[root], False, "data")]:
        return _scalar
    if root in _TEXT_WRAPPED and fields == [("string", False, "data")]:
        return functools.partial(_unwrapped, _TEXT_WRAPPED[root])
    if root == AUDIO_BLOCK and fields == _AUDIO_FIELDS and time_ok:
        return audio_block_of
    mappings = mapping_restorer(name, "ros2msg", data)
    stamped = root.startswith("flowrt_msgs/") and time_ok
    if not (stamped and (_TIME_KEY, False, "timestamp") in (fields or [])):
        return mappings
    if mappings is None:
        return _epoch_timestamp
    return lambda v: _epoch_timestamp(mappings(v))


def _scalar(v: Any) -> Any:
    return v["data"] if isinstance(v, dict) and "data" in v else v


def _unwrapped(schema_name: str, v: Any) -> Any:
    """A ``flowrt_msgs`` one-field wrapper (``string data``, the value's JSON) as the plain
    value it was written from (:func:`~flowrt.recording.encoding.plain_value`); ``v`` when
    it is not that."""
    text = v.get("data") if isinstance(v, dict) else None
    try:
        parsed = json.loads(text) if isinstance(text, str) else v
    except ValueError:
        return v
    out = plain_value(schema_name, parsed)
    return v if out is parsed else out


# flowrt_msgs wrappers whose JSON shape is not their type's -> the flowrt schema they stand for
_TEXT_WRAPPED = {
    "flowrt_msgs/Bytes": "builtins.bytes",
    "flowrt_msgs/Bytearray": "builtins.bytearray",
    "flowrt_msgs/Tuple": "builtins.tuple",
}


def _epoch_timestamp(v: Any) -> Any:
    ts = v.get("timestamp") if isinstance(v, dict) else None
    if not isinstance(ts, dict):
        return v
    return {**v, "timestamp": int(ts.get("sec", 0)) * 1_000_000_000 + int(ts.get("nanosec", 0))}


def audio_block_of(v: Any) -> Any:
    """A decoded ``flowrt_msgs/AudioBlock`` as the :class:`~flowrt.AudioBlock` it was written
    from, as a ``flowrt`` recording's ``RawAudio`` is replayed: float32 samples in [-1, 1)
    (the int16 PCM / 32768), shape (frames, channels), its rate and ``seq``, and its
    ``timestamp`` the first sample's Unix time (replay moves it onto its own clock).

    Does not round-trip: ``source`` (not written: ``""``), the samples' type (an int16 block
    comes back float32), their precision (16 bits) and range (clipped to [-1, 1] when
    written).
    """
    if not isinstance(v, dict):
        return v
    channels = max(1, int(v.get("channels") or 1))
    pcm = np.asarray(v.get("data") or [], dtype=np.int16)
    pcm = pcm[: len(pcm) - len(pcm) % channels]  # a partial last frame is not a frame
    stamp = v.get("stamp")
    stamp = stamp if isinstance(stamp, dict) else {}
    return AudioBlock(
        (pcm.reshape(-1, channels).astype(np.float32) / 32768.0),
        int(v.get("sample_rate") or 0),
        int(stamp.get("sec", 0)) + int(stamp.get("nanosec", 0)) / 1e9,
        int(v.get("seq") or 0),
    )


def _msg_types(name: str, text: str) -> dict[str, list[tuple[str, bool, str]]]:
    """type -> [(field type, is an array, field name)] of a ``ros2msg`` schema: the message
    first, then each type it uses after a line of ``=`` and ``MSG: pkg/Name``."""
    out: dict[str, list[tuple[str, bool, str]]] = {}
    current = _type_key(name)
    fields = out.setdefault(current, [])
    lines = iter(text.splitlines())
    for line in lines:
        if line.startswith("===") and not line.strip().strip("="):
            head = next(lines, "").strip()
            current = _type_key(head.removeprefix("MSG:").strip()) if head[:4] == "MSG:" else ""
            fields = out.setdefault(current, [])
            continue
        bits = line.split("#", 1)[0].split()
        if len(bits) < 2 or "=" in bits[1] or (len(bits) > 2 and bits[2].startswith("=")):
            continue  # blank, a comment or a constant
        typ, bracket, _ = bits[0].partition("[")
        fields.append((_resolve(typ.partition("<=")[0], current), bool(bracket), bits[1]))
    return out


def _resolve(typ: str, owner: str) -> str:
    """A field's type as ``pkg/Name``: a bare name is of its owner's package (``Header``:
    ``std_msgs``), a primitive stays as it is."""
    if typ in _MSG_PRIMITIVES or "/" in typ:
        return _type_key(typ) if "/" in typ else typ
    if typ == "Header":
        return "std_msgs/Header"
    return f"{owner.partition('/')[0]}/{typ}"


def _type_key(name: str) -> str:
    """``pkg/msg/Name`` or ``pkg/Name`` -> ``pkg/Name``."""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else name


def _is_velocity(v: Any) -> bool:
    if not isinstance(v, dict) or not v:
        return False
    keys = set(v) - {"timestamp"}
    return (
        bool(keys)
        and keys <= set(_VELOCITY)
        and all(isinstance(v[k], int | float) and not isinstance(v[k], bool) for k in keys)
    )


def _twist(v: dict[str, Any]) -> dict[str, Any]:
    out = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
    for k, (part, axis) in _VELOCITY.items():
        if k in v:
            out[part][axis] = float(v[k])
    return out


class _CdrOut:
    """Little-endian CDR, aligned from the first byte after the encapsulation header."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def _align(self, n: int) -> None:
        pad = (-(len(self._buf) - 4)) % n if len(self._buf) >= 4 else 0
        self._buf += b"\x00" * pad

    def u8(self, v: int) -> None:
        self._buf += struct.pack("<B", v)

    def u32(self, v: int) -> None:
        self._align(4)
        self._buf += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self._align(4)
        self._buf += struct.pack("<i", v)

    def string(self, s: str) -> None:
        raw = s.encode() + b"\x00"
        self.u32(len(raw))
        self._buf += raw

    def bytes(self) -> bytes:
        return bytes(self._buf)
