"""A stream's values over Zenoh: the recorder's description of the stream, on the wire.

An exported message is encoded by the stream's :class:`~flowrt.recording.streams.StreamBook`
description, the one the recorder and the live server use: its Zenoh payload is the bytes of
the recording's MCAP message (JSON in the shape of its schema: a ``None`` field left out, a
tuple as a typed array or a positional object ``_0``, ``_1`` ..., a ``timestamp`` as epoch
nanoseconds; audio as ``foxglove.RawAudio`` protobuf), and its Zenoh encoding names the
schema (``application/json;SCHEMA``, ``application/protobuf;foxglove.RawAudio``), the name
of the recording's channel schema. A plain program reading JSON gets what a recording holds,
and validates it against the same schema.

Back in a flowrt import (:func:`decode_json`) the value is what the exporter published, as
far as a network peer can say: a typed value (a dataclass, a pydantic model) as an attribute
object (``SimpleNamespace``, its schema name in ``_type``), a fixed-size array or positional
object back as a tuple, a field left out back as ``None`` (when the importer knows the type:
its module is imported here, or is flowrt's own), a plain value unwrapped from
``{"value": ...}``. The ``timestamp`` is set by the import from the header's capture time
(:mod:`flowrt.remote_import`). Never pickle, never import a module a peer names (but
flowrt's own).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import json
import sys
import types
from typing import Any

from .audio import AudioBlock

__all__ = ["AUDIO_SCHEMA", "decode_audio", "decode_json", "encoding_of", "schema_of_sample"]

AUDIO_SCHEMA = "foxglove.RawAudio"
_PLAIN_MODULES = ("builtins", "numpy")  # values of these types are not typed objects


def encoding_of(message_encoding: str, schema_name: str) -> Any:
    """The Zenoh encoding of a stream's payloads: the MIME type and its schema's name."""
    import zenoh

    base = (
        zenoh.Encoding.APPLICATION_JSON
        if message_encoding == "json"
        else zenoh.Encoding.APPLICATION_PROTOBUF
    )
    return base.with_schema(schema_name)


def schema_of_sample(sample: Any) -> str:
    """The schema name in a sample's Zenoh encoding (``""`` when it names none)."""
    enc = getattr(sample, "encoding", None)
    if enc is None:
        return ""
    _, _, schema = str(enc).partition(";")
    return schema


def decode_json(payload: bytes, schema_name: str) -> Any:
    """A JSON payload of a flowrt export back as its value (see the module docstring).

    Without a schema name (an exporter of an older flowrt: marked mappings, ``__type__``)
    the value is read as that exporter wrote it."""
    obj = json.loads(payload, object_hook=_marked)
    if not schema_name or not isinstance(obj, dict):
        return obj
    ts = obj.get("timestamp")
    if isinstance(ts, int) and not isinstance(ts, bool):  # epoch ns, as recorded: seconds
        obj["timestamp"] = ts / 1e9  # (the import puts its capture time on its clock here)
    cls = _resolve(schema_name)
    module = schema_name.rpartition(".")[0]
    typed = cls is not None or (module and module.split(".")[0] not in _PLAIN_MODULES)
    if not typed:
        if set(obj) == {"value"} and schema_name != "builtins.dict":
            return _tuples(obj["value"], None)
        return {k: _tuples(v, None) for k, v in obj.items()}
    schema = _type_schema(cls) if cls is not None else None
    props = schema.get("properties", {}) if schema else {}
    fields: dict[str, Any] = {k: None for k in props}  # left out on the wire: None
    fields.update({k: _tuples(v, props.get(k)) for k, v in obj.items()})
    ns = types.SimpleNamespace(**fields)
    ns.__dict__["_type"] = schema_name
    return ns


def decode_audio(payload: bytes, seq: int, epoch_offset: float) -> AudioBlock:
    """A ``foxglove.RawAudio`` payload as an :class:`~flowrt.AudioBlock` (float32 samples),
    decoded as replay decodes a recorded one, its first sample's Unix time moved onto this
    runtime's clock (``epoch_offset``: Unix time minus this runtime's clock)."""
    block: AudioBlock = _audio_decoder()(payload, seq, epoch_offset)
    return block


@functools.cache
def _audio_decoder() -> Any:
    from mcap.records import Schema

    from .recording.encoding import Decoder, audio_schema

    s = audio_schema()
    schema = Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    dec = Decoder()
    return lambda data, seq, off: dec.audio(schema, data, seq, off)


def _marked(d: dict[str, Any]) -> Any:
    if "__type__" not in d:
        return d
    t = d.pop("__type__")
    ns = types.SimpleNamespace(**d)
    ns.__dict__["_type"] = t
    return ns


def _tuples(v: Any, schema: Any) -> Any:
    """Tuples back: a positional object (``_0``, ``_1`` ...) always, a fixed-size array when
    the schema says so (``minItems == maxItems``); nested objects by their own schema."""
    s = schema if isinstance(schema, dict) else {}
    if isinstance(v, dict):
        if v and all(k == f"_{i}" for i, k in enumerate(v)):
            props = s.get("properties") or {}
            return tuple(_tuples(x, props.get(k)) for k, x in v.items())
        props = s.get("properties") or {}
        return {k: _tuples(x, props.get(k)) for k, x in v.items()}
    if isinstance(v, list):
        items = s.get("items")
        out = [_tuples(x, items) for x in v]
        n = s.get("maxItems")
        return tuple(out) if isinstance(n, int) and s.get("minItems") == n else out
    return v


def _resolve(name: str) -> type | None:
    """The dataclass or pydantic model named ``name``: from a module already imported here,
    or from flowrt's own package (installed code); a peer never makes this import anything
    else."""
    module, _, qual = name.rpartition(".")
    if not module or module.split(".")[0] in _PLAIN_MODULES:
        return None
    mod = sys.modules.get(module)
    if mod is None and module.split(".")[0] == "flowrt":
        try:
            mod = importlib.import_module(module)
        except Exception:
            return None
    cls = getattr(mod, qual, None) if mod is not None else None
    if isinstance(cls, type) and (
        dataclasses.is_dataclass(cls) or hasattr(cls, "model_json_schema")
    ):
        return cls
    return None


@functools.lru_cache(maxsize=256)
def _type_schema(cls: type) -> dict[str, Any] | None:
    """The app schema of ``cls`` (what the recorder's schema is made from), for its fields."""
    from pydantic import TypeAdapter

    from .recording.jsonschema import app_schema

    try:
        return app_schema(TypeAdapter(cls).json_schema())
    except Exception:
        return None
