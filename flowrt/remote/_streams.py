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
object (``SimpleNamespace``, its schema name in ``_type``), a plain value unwrapped from
``{"value": ...}``, a positional object always back as a tuple. When the importer knows the
type (its module is imported here, or is flowrt's own) each field is restored by its type
hint: nested typed values as attribute objects, tuples, bytes from base64, a field left out
as ``None``; why hints and not the schema: the schema says "array" for a tuple and a list
alike, and loses which object was a nested dataclass. The ``timestamp`` is set by the
import from the header's capture time (:mod:`flowrt.remote._importer`). Never pickle, never
import a module a peer names (but flowrt's own).
"""

from __future__ import annotations

import base64
import dataclasses
import functools
import importlib
import json
import math
import sys
import types
import typing
from typing import Any

import msgspec

from ..audio import AudioBlock
from ..recording.encoding import FLOAT_TYPES, plain_value

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
    the value is read as that exporter wrote it.

    A flat mapping (``builtins.dict``, no nested object or array) is returned as parsed:
    what the general restoring would give, without its per-field calls (this runs cold on
    Zenoh's thread, for every message, where those cost ~80 us)."""
    # the C parser alone unless a marked mapping may be in the text (escapes included)
    marked = b"__type__" in payload or b"\\u" in payload
    obj = json.loads(payload, object_hook=_marked) if marked else _loads(payload)
    if not schema_name or not isinstance(obj, dict):
        return obj
    ts = obj.get("timestamp")
    if isinstance(ts, int) and not isinstance(ts, bool):  # epoch ns, as recorded: seconds
        obj["timestamp"] = ts / 1e9  # (the import puts its capture time on its clock here)
    if schema_name == "builtins.dict" and _flat(obj):
        return obj
    cls = _resolve(schema_name)
    module = schema_name.rpartition(".")[0]
    if cls is not None:
        return _typed(obj, cls)
    if module and module.split(".")[0] not in _PLAIN_MODULES:  # a type not known here
        ns = types.SimpleNamespace(**{k: _restore(v, None) for k, v in obj.items()})
        ns.__dict__["_type"] = schema_name
        return ns
    if set(obj) == {"value"} and schema_name != "builtins.dict":
        return _restore(plain_value(schema_name, obj["value"]), None)
    if not obj and schema_name in FLOAT_TYPES:  # a non-finite float, left out (JSON has none)
        return math.nan
    return _restore(obj, None)


def _typed(obj: dict[str, Any], cls: type) -> types.SimpleNamespace:
    """A typed value as an attribute object: every field of ``cls`` (absent: ``None``),
    each restored by its type hint (nested typed values, tuples, bytes)."""
    hints = _hints(cls)
    fields: dict[str, Any] = {k: math.nan if h is float else None for k, h in hints.items()}
    fields.update({k: _restore(v, hints.get(k)) for k, v in obj.items()})
    ns = types.SimpleNamespace(**fields)
    ns.__dict__["_type"] = f"{cls.__module__}.{cls.__qualname__}"
    return ns


def _restore(v: Any, hint: Any) -> Any:
    """``v`` as JSON gave it, back in the shape of ``hint`` (a field's type; None: unknown):
    a tuple from an array or a positional object (``_0``, ``_1`` ..., always a tuple), a
    typed value from an object, bytes from base64 text."""
    if hint is None and not isinstance(v, dict | list):  # nothing to restore (cold: cheap)
        return v
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        branches = [a for a in typing.get_args(hint) if a is not type(None)]
        hint = next((a for a in branches if _fits(v, a)), None)
        origin = typing.get_origin(hint)
    if v is None:
        return None
    if isinstance(v, dict) and v and all(k == f"_{i}" for i, k in enumerate(v)):
        v = list(v.values())
        if origin is not tuple:
            hint, origin = None, tuple
    if isinstance(hint, type) and isinstance(v, dict) and _is_typed(hint):
        return _typed(v, hint)
    if hint is bytes and isinstance(v, str):
        try:
            return base64.b64decode(v, validate=True)
        except ValueError:
            return v
    args = typing.get_args(hint)
    if isinstance(v, dict):
        sub = args[1] if origin is dict and len(args) == 2 else None
        return {k: _restore(x, sub) for k, x in v.items()}
    if isinstance(v, list):
        if origin is tuple:
            if len(args) == 2 and args[1] is Ellipsis:
                args = (args[0],) * len(v)
            subs = args if len(args) == len(v) else (None,) * len(v)
            return tuple(_restore(x, a) for x, a in zip(v, subs, strict=True))
        sub = args[0] if origin in (list, set, frozenset) and args else None
        return [_restore(x, sub) for x in v]
    return v


def _fits(v: Any, hint: Any) -> bool:
    """Whether the JSON value ``v`` can be a value of ``hint`` (a union's branch)."""
    t = typing.get_origin(hint) or hint
    if isinstance(v, dict):
        return t is dict or (isinstance(t, type) and _is_typed(t)) or t is tuple
    if isinstance(v, list):
        return t in (tuple, list, set, frozenset)
    if isinstance(v, str):
        return t in (str, bytes)
    return isinstance(t, type) and isinstance(v, t)


def _is_typed(t: type) -> bool:
    return dataclasses.is_dataclass(t) or hasattr(t, "model_json_schema")


@functools.lru_cache(maxsize=256)
def _hints(cls: type) -> dict[str, Any]:
    """The fields of a dataclass or pydantic model and their types (``Any`` when a hint does
    not resolve)."""
    if dataclasses.is_dataclass(cls):
        names = [f.name for f in dataclasses.fields(cls)]
    else:
        names = list(getattr(cls, "model_fields", {}))
    try:
        hints = typing.get_type_hints(cls)
    except Exception:
        hints = {}
    return {n: hints.get(n) for n in names}


def decode_audio(payload: bytes, seq: int, epoch_offset: float) -> AudioBlock:
    """A ``foxglove.RawAudio`` payload as an :class:`~flowrt.AudioBlock` (float32 samples),
    decoded as replay decodes a recorded one, its first sample's Unix time moved onto this
    runtime's clock (``epoch_offset``: Unix time minus this runtime's clock)."""
    block: AudioBlock = _audio_decoder()(payload, seq, epoch_offset)
    return block


@functools.cache
def _audio_decoder() -> Any:
    from mcap.records import Schema

    from ..recording.encoding import Decoder, audio_schema

    s = audio_schema()
    schema = Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    dec = Decoder()
    return lambda data, seq, off: dec.audio(schema, data, seq, off)


_DECODE: Any = msgspec.json.Decoder().decode


def _loads(payload: bytes) -> Any:
    """``json.loads(payload)``, by msgspec's decoder where it reads the text: this runs cold
    on Zenoh's thread for every message, where ``json.loads`` cost ~18 us and msgspec ~4 us
    (cache-evicted calls, median), with the same values (integers of any size included).
    What msgspec refuses and ``json`` reads (``NaN``, ``1e400``, a BOM, lone surrogates,
    UTF-16) goes to ``json.loads``."""
    try:
        return _DECODE(payload)
    except msgspec.DecodeError:
        return json.loads(payload)


def _flat(obj: dict[str, Any]) -> bool:
    """No nested object or array, and not a positional object (``_0`` first: a tuple).
    A loop, not ``all()`` of a generator: a frame resumed per field, cold on this path."""
    for k, v in obj.items():  # noqa: SIM110
        if k == "_0" or type(v) is dict or type(v) is list:
            return False
    return True


def _marked(d: dict[str, Any]) -> Any:
    if "__type__" not in d:
        return d
    t = d.pop("__type__")
    ns = types.SimpleNamespace(**d)
    ns.__dict__["_type"] = t
    return ns


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
    if isinstance(cls, type) and _is_typed(cls):
        return cls
    return None
