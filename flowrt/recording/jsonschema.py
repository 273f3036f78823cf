"""JSON schemas the Foxglove and Lichtblick apps accept, made from pydantic's.

The apps read a JSON channel's schema with ``parseJsonSchema`` (``@foxglove/mcap-support``,
``@lichtblick/mcap-support``) to learn its fields for plots and the message path syntax. That
parser walks ``properties`` and needs, for every field, a ``type`` (``boolean``, ``string``,
``number``, ``integer``, ``object`` with ``properties``, ``array`` with ``items``); a field
with ``anyOf`` (pydantic's ``X | None``), ``$ref`` (a nested model), ``prefixItems`` (a
tuple) or no type at all makes it drop the whole topic, so no detection, statistic or CAN
signal could be plotted. :func:`app_schema` rewrites a schema into that subset:

- ``$ref`` inlined from ``$defs`` (a recursive model is cut to an empty object);
- ``anyOf``/``oneOf`` with ``null`` (an optional) becomes the other branch; a union of
  several types becomes its first type (JSON carries the value whatever the schema says);
- a tuple (``prefixItems``) becomes an array of its first item's schema;
- an object without ``properties`` (a free-form mapping) gets ``"properties": {}``;
- a field with no type (``Any``) becomes a string, the one type every value can be shown as.

The choice (docs/DESIGN-NOTES.md): JSON with such schemas rather than protobuf built from
the models: the recording keeps one encoder for every value type, the apps plot the fields,
and a plain reader (``json``) needs no generated code.
"""

from __future__ import annotations

from typing import Any

__all__ = ["app_schema", "schema_problems"]

PRIMITIVES = ("boolean", "string", "number", "integer")


def app_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` rewritten for the apps' parser (see the module docstring); the root is an
    object with ``properties``."""
    defs = dict(schema.get("$defs", {}))
    out = _field(schema, defs, ())
    if out.get("type") != "object":  # a plain value is recorded as {"value": ...}
        out = {"type": "object", "properties": {"value": out}}
    for key in ("title", "description"):
        if key in schema:
            out[key] = schema[key]
    return out


def _field(s: Any, defs: dict[str, Any], seen: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(s, dict):
        return {"type": "string"}
    keep = {k: s[k] for k in ("description", "title") if k in s}
    if "$ref" in s:
        name = str(s["$ref"]).rsplit("/", 1)[-1]
        if name in seen or name not in defs:  # recursive, or unknown: an empty object
            return {"type": "object", "properties": {}, **keep}
        return {**_field(defs[name], defs, (*seen, name)), **keep}
    for key in ("anyOf", "oneOf", "allOf"):
        branches = s.get(key)
        if isinstance(branches, list) and branches:
            if key == "oneOf" and all(isinstance(b, dict) and "const" in b for b in branches):
                return {**_enum(b["const"] for b in branches), **keep}
            real = [b for b in branches if not (isinstance(b, dict) and b.get("type") == "null")]
            return {**_field(real[0] if real else {}, defs, seen), **keep}
    t = s.get("type")
    if isinstance(t, list):  # ["number", "null"]
        t = next((x for x in t if x != "null"), None)
    if "enum" in s and t is None:
        return {**_enum(s["enum"]), **keep}
    if "const" in s and t is None:
        return {**_enum([s["const"]]), **keep}
    if t in PRIMITIVES:
        out: dict[str, Any] = {"type": t, **keep}
        if "enum" in s:
            out["enum"] = s["enum"]
        return out
    if t == "array" or "prefixItems" in s or "items" in s:
        items = s.get("items")
        if not isinstance(items, dict) or not items:
            prefix = s.get("prefixItems") or [{}]
            items = prefix[0] if isinstance(prefix, list) and prefix else {}
        return {"type": "array", "items": _field(items, defs, seen), **keep}
    if t == "object" or "properties" in s:
        props = s.get("properties") or {}
        return {
            "type": "object",
            "properties": {str(k): _field(v, defs, seen) for k, v in props.items()},
            **keep,
        }
    return {"type": "string", **keep}  # Any: no type the apps could read


def _enum(values: Any) -> dict[str, Any]:
    values = list(values)
    if all(isinstance(v, bool) for v in values):
        return {"type": "boolean"}
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return {"type": "integer", "enum": values}
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return {"type": "number", "enum": values}
    return {"type": "string", "enum": [str(v) for v in values]}


def schema_problems(schema: Any, path: str = "") -> list[str]:
    """Where ``schema`` breaks the apps' rules (empty: every field can be read); the same
    walk as ``parseJsonSchema``: every field typed, arrays with items, objects with
    properties, no ``$ref``/``anyOf``."""
    problems: list[str] = []
    if not isinstance(schema, dict):
        return [f"{path or '<root>'}: not a schema"]
    where = path or "<root>"
    for key in ("$ref", "anyOf", "oneOf", "allOf", "prefixItems"):
        if key in schema:
            problems.append(f"{where}: {key}")
    t = schema.get("type")
    if t == "object":
        props = schema.get("properties")
        if not isinstance(props, dict):
            problems.append(f"{where}: object without properties")
        else:
            for k, v in props.items():
                problems += schema_problems(v, f"{path}.{k}" if path else str(k))
    elif t == "array":
        items = schema.get("items")
        if not isinstance(items, dict):
            problems.append(f"{where}: array without items")
        else:
            problems += schema_problems(items, f"{where}[]")
    elif t not in PRIMITIVES:
        problems.append(f"{where}: type {t!r}")
    return problems
