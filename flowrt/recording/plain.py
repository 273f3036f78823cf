"""Decoded foreign messages as plain values: what a ``replay`` node publishes on ``message``.

Each decoding library gives its own objects (``rosbags`` dataclasses with numpy arrays,
``mcap_ros2``/genpy classes with ``__slots__``, protobuf messages); a graph should not depend
on which one read the file, so every message becomes dicts, lists, numbers, strings and
``bytes`` (a ``uint8[]``/``bytes`` field, e.g. an image's pixels, stays ``bytes``, not a list
of a million ints).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["protobuf_to_plain", "to_plain"]

_SCALARS = (bool, int, float, str, bytes)


def to_plain(value: Any) -> Any:
    """A ROS 1/ROS 2 message object (any of the libraries') as dicts, lists and scalars."""
    if value is None or isinstance(value, _SCALARS):
        return value
    if isinstance(value, bytearray | memoryview):
        return bytes(value)
    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        if value and isinstance(value[0], _SCALARS):  # numbers, strings: nothing to convert
            return list(value)
        return [to_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {  # rosbags' classes carry their type name as a field: not message data
            f.name: to_plain(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if not f.name.startswith("__")
        }
    slots = _slots(type(value))
    if slots:
        return {name: to_plain(getattr(value, name, None)) for name in slots}
    if hasattr(value, "DESCRIPTOR") and hasattr(value, "ListFields"):
        return protobuf_to_plain(value)
    return repr(value)


def _slots(cls: type) -> list[str]:
    """Field names of a genpy / mcap_ros2 message class (their ``__slots__``)."""
    out: list[str] = []
    for c in reversed(cls.__mro__):
        s = c.__dict__.get("__slots__", ())
        out.extend([s] if isinstance(s, str) else [x for x in s if not x.startswith("_")])
    return out


def protobuf_to_plain(msg: Any) -> dict[str, Any]:
    """Every field of a protobuf message, defaults included (a plot needs its zeros too).

    ``json_format`` would turn bytes into base64 text and 64-bit integers into strings; here
    they stay ``bytes`` and ``int``.
    """
    out: dict[str, Any] = {}
    for f in msg.DESCRIPTOR.fields:
        v = getattr(msg, f.name)
        if f.message_type is not None and f.message_type.GetOptions().map_entry:
            out[f.name] = {
                k: protobuf_to_plain(x) if hasattr(x, "DESCRIPTOR") else x for k, x in v.items()
            }
        elif _repeated(f):
            out[f.name] = [protobuf_to_plain(x) if hasattr(x, "DESCRIPTOR") else x for x in v]
        elif f.message_type is not None:
            out[f.name] = protobuf_to_plain(v) if msg.HasField(f.name) else None
        else:
            out[f.name] = v
    return out


def _repeated(field: Any) -> bool:
    is_repeated = getattr(field, "is_repeated", None)  # protobuf >= 5.27
    if is_repeated is not None:
        return bool(is_repeated)
    return bool(field.label == field.LABEL_REPEATED)
