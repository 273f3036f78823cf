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
  numbers a number, a union of other types a string (the value written as JSON text);
- a tuple (``prefixItems``) of numbers (or of strings, or of booleans) becomes a typed array
  (``minItems``/``maxItems`` kept); a tuple of mixed types becomes an object whose fields are
  named by position, ``_0``, ``_1`` ...; an array item that is itself an array (which the
  apps refuse: ``Unsupported array item type: "array"``) becomes such an object too;
- ``bytes`` (``"format": "binary"``) becomes a string with ``"contentEncoding": "base64"``,
  which the apps show as bytes;
- an object without ``properties`` (a free-form mapping) gets ``"properties": {}``, and
  keeps the schema of its values as ``additionalProperties`` (rewritten as a field's): its
  keys are names known only at run time (nodes, ports, reasons), so ``properties`` cannot
  list them, yet a validator can still check every value. The apps' parser reads
  ``properties`` only and passes over ``additionalProperties`` (its source, both apps), so
  the topic stays readable. A value schema without a type (``{"not": {"type": "null"}}``)
  is kept as it is, its values written unchanged, not as text;
- a field with no type (``Any``) becomes a string, the one type every value can be shown as.

Every message must then match its schema, for a validator (jsonschema, ajv) as for the apps:
:func:`conform` gives a value the shape of its schema, decided by the schema alone: a field
whose value is ``None`` (or a non-finite float) is left out rather than written ``null`` (no
field is ``required``), a tuple that became an object is written as that object, a value under
a ``string`` schema is written as text, a mapping's values as its ``additionalProperties``
says. The README ("The message shapes") says the same for readers.

The choice (docs/DESIGN-NOTES.md): JSON with such schemas rather than protobuf built from
the models: the recording keeps one encoder for every value type, the apps plot the fields,
and a plain reader (``json``) needs no generated code.
"""

from __future__ import annotations

from typing import Any

__all__ = ["app_schema", "conform", "schema_problems"]

PRIMITIVES = ("boolean", "string", "number", "integer")
# the keys from which _field tells a value's type (else it has none: Any)
TYPED = frozenset(
    [
        "type",
        "$ref",
        "anyOf",
        "oneOf",
        "allOf",
        "enum",
        "const",
        "properties",
        "items",
        "prefixItems",
    ]
)


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
    union = _union(s, defs, seen)
    if union is not None:
        return {**union, **keep}
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
        if t == "string" and (s.get("format") == "binary" or s.get("contentEncoding")):
            out["contentEncoding"] = "base64"  # bytes: the apps decode them
        return out
    if t == "array" or "prefixItems" in s or "items" in s:
        prefix = s.get("prefixItems")
        if isinstance(prefix, list) and prefix and not s.get("items"):
            return {**_tuple([_field(p, defs, seen) for p in prefix]), **keep}
        items = s.get("items")
        return {**_array(_field(items if isinstance(items, dict) else {}, defs, seen)), **keep}
    if t == "object" or "properties" in s:
        props = s.get("properties") or {}
        return {
            "type": "object",
            "properties": {str(k): _field(v, defs, seen) for k, v in props.items()},
            **_values(s, defs, seen),
            **keep,
        }
    return {"type": "string", **keep}  # Any: no type the apps could read


def _values(s: dict[str, Any], defs: dict[str, Any], seen: tuple[str, ...]) -> dict[str, Any]:
    """``additionalProperties`` for a mapping whose values have a schema, else nothing.

    ``true``/``{}`` (any value) would tell a validator nothing, and ``false`` (a closed model)
    only that no field beyond ``properties`` comes, so both stay out as before. A value schema
    with no type (``{"not": {"type": "null"}}``: any value but null) is kept as written: the
    apps need no type there, and made text as a field of no type is, every value would be
    rewritten as JSON text."""
    v = s.get("additionalProperties")
    if not isinstance(v, dict) or not v.keys() - {"title", "description"}:
        return {}
    if not v.keys() & TYPED:
        return {"additionalProperties": v}
    return {"additionalProperties": _field(v, defs, seen)}


def _union(s: dict[str, Any], defs: dict[str, Any], seen: tuple[str, ...]) -> dict[str, Any] | None:
    """The one shape of an ``anyOf``/``oneOf``/``allOf`` (None: ``s`` is not one): an enum of
    constants, the branch itself when it is the only one besides null, else the one type all
    branches can be written as (numbers, or text)."""
    for key in ("anyOf", "oneOf", "allOf"):
        branches = s.get(key)
        if isinstance(branches, list) and branches:
            if key == "oneOf" and all(isinstance(b, dict) and "const" in b for b in branches):
                return _enum(b["const"] for b in branches)
            real = [b for b in branches if not (isinstance(b, dict) and b.get("type") == "null")]
            shapes = [_field(b, defs, seen) for b in real] or [{"type": "string"}]
            types = {b.get("type") for b in shapes}
            if len(types) > 1 and types <= {"number", "integer"}:
                return {"type": "number"}
            if len(types) > 1:  # int | str ...: written as text, the one type all can be
                return {"type": "string"}
            return shapes[0]
    return None


def _tuple(items: list[dict[str, Any]]) -> dict[str, Any]:
    """A fixed-size tuple: a typed array when its items share a primitive type (numbers and
    integers together are numbers), else an object with one field per position."""
    types = {i.get("type") for i in items}
    if types <= {"number", "integer"} or (len(types) == 1 and types <= {"string", "boolean"}):
        t = "integer" if types == {"integer"} else types.pop() if len(types) == 1 else "number"
        if t == "string" and any("contentEncoding" in i for i in items):
            return _positional(items)
        n = len(items)
        return {"type": "array", "items": {"type": t}, "minItems": n, "maxItems": n}
    return _positional(items)


def _array(item: dict[str, Any]) -> dict[str, Any]:
    """An array of ``item``; an item that is an array itself (the apps read no array of
    arrays) becomes an object: positional for a fixed size, else ``{"values": [...]}``."""
    if item.get("type") == "array":
        n = item.get("maxItems")
        if isinstance(n, int) and item.get("minItems") == n:
            item = _positional([item["items"]] * n)
        else:
            item = {"type": "object", "properties": {"values": item}}
    return {"type": "array", "items": item}


def _positional(items: list[dict[str, Any]]) -> dict[str, Any]:
    """An object whose fields are a sequence's positions, ``_0``, ``_1`` ..."""
    return {"type": "object", "properties": {f"_{i}": item for i, item in enumerate(items)}}


def conform(value: Any, schema: Any, coerce: bool = True) -> Any:
    """``value`` (JSON-ready: :func:`flowrt.recording.encoding.to_jsonable`) in the shape of
    ``schema`` (an :func:`app_schema`): absent rather than ``null``, positional objects for
    the tuples that became objects, text where the schema says string. Decided by the
    schema alone, so the recorder, the live server and Zenoh write the same bytes.

    ``coerce=False`` (a schema guessed from a sample, not derived from a type): only a
    ``None`` where the schema has a typed field is left out; nothing else is changed."""
    if not isinstance(schema, dict):
        return value
    t = schema.get("type")
    if t == "object":
        props = schema.get("properties") or {}
        rest = schema.get("additionalProperties")  # a mapping's values (any name)
        if isinstance(value, list | tuple) and coerce:
            if props and all(k.startswith("_") for k in props):
                value = {f"_{i}": v for i, v in enumerate(value)}
            elif set(props) == {"values"}:
                value = {"values": value}
        if not isinstance(value, dict):
            return value
        return {
            k: conform(v, props.get(k, rest), coerce)
            for k, v in value.items()
            if not (_null(v) and (coerce or k in props))
        }
    if t == "array" and isinstance(value, list | tuple):
        items = schema.get("items")
        return [conform(v, items, coerce) for v in value]
    if not coerce:
        return value
    if t == "string" and value is not None and not isinstance(value, str):
        import json

        return json.dumps(value, separators=(",", ":"))
    if t == "integer" and isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def _null(v: Any) -> bool:
    return v is None or (isinstance(v, float) and v != v)


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
    """Where ``schema`` breaks the apps' rules (empty: the apps read every field).

    A port of ``parseJsonSchema`` (``@lichtblick/mcap-support``; ``@foxglove/mcap-support``
    the same, plus ``oneOf`` of numeric constants, which flowrt does not write): the root and
    every nested object ``"type": "object"`` with ``properties``; each field ``boolean``,
    ``string`` (no ``contentEncoding`` but ``base64``), ``number``/``integer``, ``object`` or
    ``array``; an array's ``items`` one of ``boolean``, ``string`` (no ``contentEncoding``),
    ``number``/``integer`` or ``object`` (no array of arrays). ``$ref``/``anyOf``/``oneOf``
    are refused too: the parser ignores them and so would lose the field's type.
    ``additionalProperties`` is not checked: the parser never reads it (a mapping's values are
    for validators).
    """
    if not isinstance(schema, dict):
        return [f"{path or '<root>'}: not a schema"]
    where = path or "<root>"
    if schema.get("type") != "object":
        return [f"{where}: expected type object, got {schema.get('type')!r}"]
    props = schema.get("properties")
    if not isinstance(props, dict):
        return [f"{where}: object without properties"]
    problems: list[str] = []
    for name, field in props.items():
        at = f"{path}.{name}" if path else str(name)
        if not isinstance(field, dict):
            problems.append(f"{at}: not a schema")
            continue
        problems += [f"{at}: {k}" for k in ("$ref", "anyOf", "oneOf", "allOf") if k in field]
        t = field.get("type")
        if t == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                problems.append(f"{at}: contentEncoding {field['contentEncoding']!r}")
        elif t == "object":
            problems += schema_problems(field, at)
        elif t == "array":
            items = field.get("items")
            it = items.get("type") if isinstance(items, dict) else None
            if it == "object":
                problems += schema_problems(items, f"{at}[]")
            elif it == "string" and items.get("contentEncoding") is not None:  # type: ignore[union-attr]
                problems.append(f"{at}[]: contentEncoding in an array item")
            elif it not in ("boolean", "string", "number", "integer"):
                problems.append(f"{at}: unsupported array item type {it!r}")
        elif t not in ("boolean", "number", "integer"):
            problems.append(f"{at}: unsupported type {t!r}")
    return problems
