"""One description per stream: what a stream is on every wire, decided once.

A stream (an output ``node.port``, declared on its node's class or made at run time: a
``can`` node's per-message outputs, a ``sync`` node's set) has one :class:`StreamDescription`:
its message encoding, schema (name, encoding, data), message shape and time base. It is
decided from the stream's first value by :func:`describe` and kept by a :class:`StreamBook`;
the recorder (thread or process writer) and the live Foxglove server each hold a book and
encode through it, so a stream is the same channel in a recording and live, and a consumer
that needs to know a stream's channel (Zenoh export, replay, ``flowrt info``) reads it here.

The shapes (see the README, "Recording and replay", "The message shapes"):

- a :class:`~flowrt.frames.Frame`: ``foxglove.RawImage`` (protobuf), or
  ``foxglove.CompressedImage`` when the stream's image format is ``jpeg``/``png``;
- an :class:`~flowrt.AudioBlock`: ``foxglove.RawAudio`` (protobuf, pcm-s16, interleaved);
- a detection's overlay: ``foxglove.ImageAnnotations`` (protobuf);
- anything else: JSON under the JSON schema of its type (:func:`.encoding.schema_for`), the
  value in the shape of its schema (:func:`.jsonschema.conform`).

A *set* (a mapping holding frames or audio blocks: a ``sync`` node's output) is several
streams (:func:`split_set`): each frame or block is a stream of its own, ``TOPIC/KEY``, with
the shape above (so the app shows each camera of the set as an image), and ``TOPIC`` carries
the set's index: ``{KEY: {"topic": "TOPIC/KEY", "seq": N}, ..., "timestamp": ...}`` with the
set's other fields (``spread_ms``); a set's ``stamp`` is written as its ``timestamp``.
:func:`join_set` puts a replayed set back together.

The time base is Unix time for every stream: log times, and a value's own ``timestamp``
(epoch nanoseconds in JSON, a ``Timestamp`` in protobuf).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..audio import AudioBlock
from ..frames import Frame
from .encoding import (
    Encoded,
    Overlay,
    StreamSchema,
    annotations_schema,
    audio_schema,
    encode_annotations,
    encode_audio,
    encode_frame,
    encode_json,
    flat_json,
    image_schema,
    schema_for,
)

__all__ = [
    "TIME_BASE",
    "StreamBook",
    "StreamDescription",
    "describe",
    "is_set",
    "join_set",
    "split_set",
]

TIME_BASE = "unix"
"""Every time a stream carries (log time, a value's ``timestamp``): since the Unix epoch."""


@dataclass(frozen=True)
class StreamDescription:
    """What one stream is on every wire.

    ``shape``: ``image``, ``audio``, ``annotations`` (protobuf, foxglove-sdk's schemas) or
    ``json`` (a value's type's JSON schema); ``value_type``: the Python type it was decided
    from (a JSON stream whose values change type gets a description per type).
    """

    topic: str
    shape: str
    schema: StreamSchema
    value_type: type
    time_base: str = TIME_BASE

    @property
    def message_encoding(self) -> str:
        return self.schema.message_encoding


def describe(topic: str, value: Any, image_format: str = "raw") -> StreamDescription:
    """The description of ``topic`` from one of its values."""
    if isinstance(value, Frame):
        return StreamDescription(topic, "image", image_schema(image_format != "raw"), Frame)
    if isinstance(value, AudioBlock):
        return StreamDescription(topic, "audio", audio_schema(), AudioBlock)
    if isinstance(value, Overlay):
        return StreamDescription(topic, "annotations", annotations_schema(), Overlay)
    return StreamDescription(topic, "json", schema_for(value), type(value))


class StreamBook:
    """The streams seen so far, each described once, and each value encoded by its stream's
    description. Not thread-safe: one encoder thread owns a book.

    Args:
        image_formats: per topic ``raw`` (default), ``jpeg`` or ``png``.
        default_image_format: for a frame topic not in ``image_formats``.
        epoch_offset: added to the runtime clock to get Unix time.
        gil_free: a RawImage's pixels copied with the GIL released (:mod:`.gilfree`).
    """

    def __init__(
        self,
        image_formats: dict[str, str] | None = None,
        epoch_offset: float = 0.0,
        *,
        default_image_format: str = "raw",
        gil_free: bool = False,
    ) -> None:
        self.image_formats = dict(image_formats or {})
        self.default_image_format = default_image_format
        self.epoch_offset = epoch_offset
        self.gil_free = gil_free
        self._streams: dict[tuple[str, type], StreamDescription] = {}

    def description(self, topic: str, value: Any) -> StreamDescription:
        kind = type(value)
        key = (topic, Frame if isinstance(value, Frame) else kind)
        d = self._streams.get(key)
        if d is None:
            d = self._streams[key] = describe(topic, value, self.image_format(topic))
        return d

    def image_format(self, topic: str) -> str:
        """The format of ``topic``'s images (:func:`image_format_of`)."""
        return image_format_of(self.image_formats, topic, self.default_image_format)

    def streams(self) -> list[StreamDescription]:
        """Every description made so far, in order."""
        return list(self._streams.values())

    def encode_flat(self, topic: str, value: Any) -> Encoded | None:
        """``encode(topic, value)`` for a flat mapping (text keys, scalar values: never a
        set) of a stream already described by a guessed schema; None for anything else.
        One walk of the value instead of three calls: the exporter's message path runs
        cold at 20 Hz and pays every one."""
        d = self._streams.get((topic, dict))
        if d is None or not d.schema.guessed or type(value) is not dict:
            return None
        data = flat_json(value, self.epoch_offset)
        return None if data is None else Encoded(d.schema, data)

    def encode(self, topic: str, value: Any) -> Encoded:
        """``value`` as a message of ``topic``'s channel (time in Unix time)."""
        if isinstance(value, Encoded):  # encoded already (a writer process's messages)
            return value
        d = self.description(topic, value)
        off = self.epoch_offset
        if d.shape == "image":
            fmt = self.image_format(topic)
            return encode_frame(value, value.timestamp + off, fmt, gil_free=self.gil_free)
        if d.shape == "audio":  # its first sample's time
            return encode_audio(value, value.timestamp + off)
        if d.shape == "annotations":  # stamped like the frame: the same float, the same offset
            return encode_annotations(value.detection, value.detection.timestamp + off)
        return encode_json(value, d.schema, off)


def image_format_of(formats: dict[str, str], topic: str, default: str) -> str:
    """The format of ``topic``'s images by ``formats``; a sync set's member (``TOPIC/KEY``)
    takes its set's (``--images jpeg`` left a set's frames raw: 6.3 MiB against 123 KiB)."""
    fmt = formats.get(topic)
    if fmt is None and "/" in topic:
        fmt = formats.get(topic.rpartition("/")[0])
    return fmt or default


def is_set(value: Any) -> bool:
    """True for a mapping that holds frames or audio blocks (a ``sync`` node's set)."""
    if not isinstance(value, dict):
        return False
    for v in value.values():  # noqa: SIM110 (not any(): this runs cold per message, 7 -> 4 us)
        if isinstance(v, _SET_MEMBERS):
            return True
    return False


_SET_MEMBERS = (Frame, AudioBlock)


def split_set(topic: str, value: dict[str, Any]) -> tuple[dict[str, Any], list[tuple[str, Any]]]:
    """(the set's index, its members as ``(TOPIC/KEY, value)``): see the module docstring."""
    index: dict[str, Any] = {}
    members: list[tuple[str, Any]] = []
    for key, v in value.items():
        if isinstance(v, Frame | AudioBlock):
            sub = f"{topic}/{key}"
            members.append((sub, v))
            index[str(key)] = {"topic": sub, "seq": int(v.seq)}
        elif key == "stamp" and isinstance(v, float) and "timestamp" not in value:
            index["timestamp"] = v  # the recording's time base, like every timestamp
        else:
            index[str(key)] = v
    return index, members


def join_set(
    topic: str,
    index: Any,
    members: dict[str, Any],
    channel: Callable[[str], str] | None = None,
) -> Any:
    """A replayed set: the index's references replaced by the member values last read
    (``members``: TOPIC/KEY -> value); ``timestamp`` also as ``stamp``. Anything else is
    returned as it is. ``channel``: the name a member's channel has in the file, from the
    flowrt name the index holds (the ``ros2`` profile's :func:`ros2_topic`; ``topic`` and
    ``members`` are then channel names too)."""
    if not isinstance(index, dict):
        return index
    out: dict[str, Any] = {}
    joined = False
    for key, v in index.items():
        ref = v.get("topic") if isinstance(v, dict) and set(v) == {"topic", "seq"} else None
        if isinstance(ref, str) and channel is not None:
            ref = channel(ref)
            expected = channel(f"{topic}/{key}")
        else:
            expected = f"{topic}/{key}"
        if isinstance(ref, str) and ref == expected and ref in members:
            out[key] = members[ref]
            joined = True
        else:
            out[key] = v
    if joined and "timestamp" in out and "stamp" not in out:
        out["stamp"] = out["timestamp"]  # kept too: a replay maps both onto its clock
    return out
