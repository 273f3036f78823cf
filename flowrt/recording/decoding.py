"""Every standard MCAP message encoding back into flowrt values, whoever wrote the file.

flowrt's own recordings hold JSON and foxglove protobuf (:class:`.encoding.Decoder`); a ROS 2
bag holds CDR with ``ros2msg``/``ros2idl`` schemas, a ROS 1 one ``ros1`` with ``ros1msg``, and
the Foxglove SDK writes protobuf of any schema. :class:`MessageDecoder` picks the decoder
from the channel's message encoding and schema, once per channel:

==================  ==================  =================================================
message encoding    schema encoding     decoded by
==================  ==================  =================================================
``cdr``             ``ros2msg``,        ``rosbags`` (its type system; no ROS 2 install)
                    ``ros2idl``
``ros1``            ``ros1msg``         ``mcap-ros1-support``
``protobuf``        ``protobuf``        the file's descriptors (``mcap-protobuf-support``)
``json``            any / none          ``json`` (flowrt's dataclasses rebuilt)
anything else       none                the message's bytes, as they are
==================  ==================  =================================================

Images (:mod:`.images`) become pixels for a frame, ``foxglove.RawAudio`` an
:class:`~flowrt.AudioBlock`, the rest a plain value (:mod:`.plain`). A channel that cannot
be decoded (an encoding without a decoder, a schema that does not parse) is refused with the
reason, :meth:`MessageDecoder.why_not`, before any message is read.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from .encoding import ANNOTATIONS_SCHEMA, AUDIO_SCHEMA, Decoder
from .images import is_image_schema, pixels_of, stamp_ns
from .plain import protobuf_to_plain, to_plain

__all__ = ["Decoded", "MessageDecoder", "UndecodableChannel", "undecodable"]

_FLOWRT_IMAGES = ("foxglove.RawImage", "foxglove.CompressedImage")


class UndecodableChannel(ValueError):
    """A channel none of the decoders reads: the message says why."""


@dataclass
class Decoded:
    """One message decoded: pixels (and their format), an audio block, or a plain value."""

    kind: Literal["image", "audio", "value"]
    value: Any
    stamp: int | None = None  # the message's own time, ns (images: header.stamp)


_Fn = Callable[[bytes], Decoded]


class MessageDecoder:
    """Decodes the messages of any channel; one decoder per (encoding, schema), built once."""

    def __init__(self) -> None:
        self.own = Decoder()
        self._fns: dict[tuple[str, str, str, bytes], _Fn] = {}
        self._typestore: Any = None

    def why_not(self, encoding: str, schema: Any) -> str | None:
        """None when messages of this channel can be decoded, else why not (one line)."""
        try:
            self._fn(encoding, schema)
        except Exception as e:
            return str(e) or type(e).__name__
        return None

    def decode(self, encoding: str, schema: Any, data: bytes) -> Decoded:
        """One message; raises (UndecodableChannel or the decoder's error) when it cannot."""
        return self._fn(encoding, schema)(data)

    # --- choosing the decoder -----------------------------------------------------------

    def _fn(self, encoding: str, schema: Any) -> _Fn:
        name = schema.name if schema is not None else ""
        key = (
            encoding,
            name,
            schema.encoding if schema is not None else "",
            bytes(schema.data) if schema is not None else b"",
        )
        fn = self._fns.get(key)
        if fn is None:
            fn = self._fns[key] = self._build(encoding, schema)
        return fn

    def _build(self, encoding: str, schema: Any) -> _Fn:
        name = schema.name if schema is not None else ""
        if name == ANNOTATIONS_SCHEMA:
            raise UndecodableChannel("annotations are drawn from the detections")
        if encoding == "json":
            return self._json(name)
        if encoding == "protobuf":
            return self._protobuf(schema)
        if encoding == "cdr":
            return self._cdr(schema)
        if encoding == "ros1":
            return self._ros1(schema)
        if schema is None or not schema.data:
            return lambda data: Decoded("value", bytes(data))  # opaque: the bytes themselves
        raise UndecodableChannel(
            f"no decoder for {encoding!r} messages (schema encoding {schema.encoding!r})"
        )

    def _json(self, name: str) -> _Fn:
        if is_image_schema(name):

            def image(data: bytes) -> Decoded:
                msg = json.loads(data)
                return Decoded("image", pixels_of(name, msg), stamp_ns(msg))

            return image
        own = self.own
        return lambda data: Decoded("value", own.message(name, data))

    def _protobuf(self, schema: Any) -> _Fn:
        if schema is None or schema.encoding != "protobuf":
            raise UndecodableChannel("protobuf messages without a protobuf schema")
        own = self.own
        dec = own._factory.decoder_for("protobuf", schema)
        if dec is None:
            raise UndecodableChannel(f"no protobuf descriptor for {schema.name}")
        name = schema.name
        if name in _FLOWRT_IMAGES:

            def image(data: bytes) -> Decoded:
                msg = dec(data)
                ts = msg.timestamp
                stamp = ts.seconds * 1_000_000_000 + ts.nanos if msg.HasField("timestamp") else 0
                return Decoded("image", own.pixels(name, msg), stamp or None)

            return image
        if name == AUDIO_SCHEMA:
            return lambda data: Decoded("audio", data)  # the replay node makes the block
        return lambda data: Decoded("value", protobuf_to_plain(dec(data)))

    def _cdr(self, schema: Any) -> _Fn:
        if schema is None or not schema.data:
            raise UndecodableChannel("CDR messages without a schema (no type to read them)")
        if schema.encoding not in ("ros2msg", "ros2idl", "omgidl"):
            raise UndecodableChannel(f"CDR messages with a {schema.encoding!r} schema")
        store = self._store()
        typename = _register(store, schema)
        return _plain_or_image(schema.name, lambda data: store.deserialize_cdr(data, typename))

    def _ros1(self, schema: Any) -> _Fn:
        if schema is None or schema.encoding != "ros1msg":
            raise UndecodableChannel("ROS 1 messages without a ros1msg schema")
        from mcap_ros1.decoder import DecoderFactory

        dec = DecoderFactory().decoder_for("ros1", schema)
        if dec is None:
            raise UndecodableChannel(f"cannot read the ros1msg schema of {schema.name}")
        return _plain_or_image(schema.name, dec)

    def _store(self) -> Any:
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.EMPTY)
        return self._typestore


def undecodable(files: list[Any], topics: list[str]) -> dict[str, str]:
    """Of ``topics`` of a recording, those no decoder reads, each with why (one line)."""
    from .reader import channel_schemas

    channels = channel_schemas(files)
    decoder = MessageDecoder()
    out = {}
    for t in topics:
        if t in channels:
            why = decoder.why_not(*channels[t])
            if why is not None:
                out[t] = why
    return out


def _plain_or_image(name: str, read: Callable[[bytes], Any]) -> _Fn:
    if is_image_schema(name):

        def image(data: bytes) -> Decoded:
            msg = to_plain(read(data))
            return Decoded("image", pixels_of(name, msg), stamp_ns(msg))

        return image
    return lambda data: Decoded("value", to_plain(read(data)))


def _register(store: Any, schema: Any) -> str:
    """Add the types of a ``ros2msg``/``ros2idl`` schema to ``store``; the message's type name.

    A ``ros2msg`` schema is the message's definition followed by its dependencies, each after
    a line of ``=`` and ``MSG: pkg/msg/Name`` (what ``rosbag2`` and ``mcap`` write); an IDL
    schema the same with ``IDL:`` sections.
    """
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    text = bytes(schema.data).decode()
    name = _normal(schema.name)
    if schema.encoding == "ros2msg":
        types = get_types_from_msg(text, name)
    else:
        sep = "=" * 80 + "\n"
        types = {}
        for part in text.split(sep) if text.startswith(sep) else [text]:
            body = part.split("\n", 1)[1] if part.startswith("IDL: ") else part
            if body.strip():
                types.update(get_types_from_idl(body))
    if name not in types and name not in store.fielddefs:
        raise UndecodableChannel(f"the schema does not define {schema.name}")
    # A type already known with another definition (two files, two versions) is not
    # registered again: rosbags refuses a conflicting definition.
    new = {k: v for k, v in types.items() if k not in store.fielddefs}
    if new:
        store.register(new)
    try:
        store.get_msgdef(name)  # compiles the reader: a type it names but lacks fails here
    except KeyError as e:
        raise UndecodableChannel(f"the schema of {schema.name} lacks the type {e}") from None
    return name


def _normal(name: str) -> str:
    """``pkg/Name`` (ROS 1 style, some writers) -> ``pkg/msg/Name``."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name
