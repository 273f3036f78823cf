"""``flowrt kinds``: the node kinds a graph file may name, and what each one takes.

``flowrt kinds`` lists every kind (built-in ones and those third-party packages register
under the ``flowrt.nodes`` entry points) with one line each; ``flowrt kinds KIND`` shows its
inputs and outputs (types, the edge policy a graph gets when it names none) and its params
(type, default, range, description), read from the node class and its pydantic model, as
``ros2 interface show`` does for messages. ``--json`` prints the same as one JSON document.
"""

from __future__ import annotations

import argparse
import inspect
import json
import re
import textwrap
from typing import Any

from rich.console import Console
from rich.table import Table

from .common import EXIT_BAD_GRAPH, EXIT_OK, stdout_console
from .json_output import emit


def _type_name(t: Any) -> str:
    if t is object:
        return "any"
    return str(getattr(t, "__name__", t))


#: A pointer to elsewhere at the end of a docstring's first line: it is read here alone.
_POINTER = re.compile(
    r"\s*(?:\(\s*see [^()]*\)|[;,]\s*see (?:the module\b[^.;]*|above|below))\s*\.?\s*$",
    re.IGNORECASE,
)


def _summary(cls: Any) -> str:
    """The docstring's first sentence as ``flowrt kinds`` lists it: without a "(see the
    module docstring)" or "see above" that points nowhere from a list, nor reST quotes."""
    doc = (cls.__doc__ or "").strip().splitlines()
    if not doc:
        return ""
    line = _POINTER.sub("", doc[0].strip()).replace("``", "")
    return line if not line or line.endswith((".", "!", "?", ":")) else line + "."


def _default_policy(port: Any) -> str:
    from ..frames import Frame

    if port.policy:
        return str(port.policy)
    is_frame = isinstance(port.type, type) and issubclass(port.type, Frame)
    return "latest" if is_frame else "queue (latest for frames)"


def _range(field: Any) -> str:
    bounds = []
    for m in getattr(field, "metadata", ()):
        for attr, sign in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            v = getattr(m, attr, None)
            if v is not None:
                bounds.append(f"{sign} {v}")
        for attr, word in (("min_length", "min length"), ("max_length", "max length")):
            v = getattr(m, attr, None)
            if v is not None:
                bounds.append(f"{word} {v}")
    return ", ".join(dict.fromkeys(bounds))  # a bound both a type and a Field give: once


def describe(kind: str) -> dict[str, Any]:
    """What ``flowrt kinds KIND --json`` prints (KindError when the kind does not resolve)."""
    from pydantic_core import PydanticUndefined

    from ..graph._registry import resolve_kind

    cls = resolve_kind(kind)
    inputs = [
        {
            "name": name,
            "type": _type_name(p.type),
            "required": p.required,
            "policy": _default_policy(p),
            "doc": p.doc,
        }
        for name, p in cls.inputs.items()
    ]
    if cls.any_inputs is not None:
        p = cls.any_inputs
        inputs.append(
            {
                "name": "*",
                "type": _type_name(p.type),
                "required": p.required,
                "policy": _default_policy(p),
                "doc": p.doc or "inputs of any name",
            }
        )
    outputs = [
        {"name": name, "type": _type_name(p.type), "doc": p.doc} for name, p in cls.outputs.items()
    ]
    params = []
    for name, f in getattr(cls.Params, "model_fields", {}).items():
        default: Any
        if f.default is not PydanticUndefined:
            default = f.default
        elif f.default_factory is not None:
            default = f.default_factory()
        else:
            default = None
        params.append(
            {
                "name": name,
                "type": _annotation(f.annotation),
                "required": f.is_required(),
                "default": _jsonable(default),
                "range": _range(f),
                "description": f.description or "",
            }
        )
    return {
        "kind": kind,
        "class": f"{cls.__module__}:{cls.__qualname__}",
        "summary": _summary(cls),
        "inputs": inputs,
        "outputs": outputs,
        "params": params,
        # what POST /swap (flowrt ctl swap) may change; path params confined to a folder
        "swappable": sorted(getattr(cls, "swappable", ())),
        "swap_folders": dict(getattr(cls, "swap_folders", {})),
        "timing": _timing_note(cls),
    }


def _timing_note(cls: Any) -> str:
    """A kind released by a timer of its own (its default trigger) may ask for precise
    release: said where a user looks for what a kind can do ("" for the others)."""
    returns = str(inspect.signature(cls.default_trigger).return_annotation)
    if "TimerTrigger" not in returns:
        return ""
    return "precise release: timing: precise (costs a thread; CPU while spinning)"


def _annotation(t: Any) -> str:
    """A type as a user reads it: ``float | None``, ``one of 'a', 'b'``, ``list[str]``."""
    import types
    import typing

    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is typing.Annotated:
        return _annotation(args[0])
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join("None" if a is type(None) else _annotation(a) for a in args)
    if origin is not None:
        name = getattr(origin, "__name__", str(origin))
        return f"{name}[{', '.join(_annotation(a) for a in args)}]" if args else name
    if t is type(None):
        return "None"
    return str(getattr(t, "__name__", t)).replace("typing.", "")


def _jsonable(v: Any) -> Any:
    from pydantic import BaseModel

    if isinstance(v, BaseModel):  # a nested params model (haptic's sim): its fields, not a repr
        return v.model_dump(mode="json")
    try:
        json.dumps(v, allow_nan=False)
        return v
    except (TypeError, ValueError):
        return repr(v)


def cmd_kinds(args: argparse.Namespace) -> int:
    from ..graph._registry import KindError, available_kinds, resolve_kind

    err = Console(stderr=True, highlight=False, soft_wrap=True)
    if args.kind:
        try:
            info = describe(args.kind)
        except KindError as e:
            err.print(f"flowrt kinds: {e}", markup=False)
            return EXIT_BAD_GRAPH
        if args.json:
            emit(info)
        else:
            _show(stdout_console(), info)
        return EXIT_OK
    rows = []
    for kind in available_kinds():
        try:
            rows.append({"kind": kind, "summary": _summary(resolve_kind(kind))})
        except Exception as e:  # a third-party kind that does not import: say so, go on
            rows.append({"kind": kind, "summary": f"(cannot import: {e})"})
    if args.json:
        emit(rows)
        return EXIT_OK
    console = stdout_console()
    table = Table(box=None, show_header=True, header_style="bold")
    table.add_column("kind", no_wrap=True)
    table.add_column("what it is", overflow="fold")
    for r in rows:
        table.add_row(r["kind"], r["summary"])
    console.print(table)
    console.print("flowrt kinds KIND shows a kind's ports and params", style="dim")
    return EXIT_OK


def _show(console: Console, info: dict[str, Any]) -> None:
    """One port or param per line, its description indented below: readable at 80 columns."""
    from rich.text import Text

    def line(text: str, style: str = "", indent: int = 0) -> None:
        # wrapped here, continuation lines indented under their first: rich's own wrap
        # starts them at column 0, where they read as the next port or param
        pad = " " * indent
        for part in textwrap.wrap(
            text, console.width, initial_indent=pad, subsequent_indent=pad + "  " * bool(indent)
        ) or [""]:
            console.print(Text(part, style=style), soft_wrap=True)

    line(f"{info['kind']}  ({info['class']})", "bold")
    if info["summary"]:
        line(info["summary"])
    if info.get("timing"):
        line(info["timing"], "dim")
    for title, rows in (("inputs", info["inputs"]), ("outputs", info["outputs"])):
        line("")
        line(f"{title}" + ("" if rows else ": none"), "bold")
        for r in rows:
            policy = f", {r['policy']}" if "policy" in r else ""
            optional = "" if r.get("required", True) else ", optional"
            line(f"{r['name']}: {r['type']}{policy}{optional}", indent=2)
            if r["doc"]:
                line(r["doc"], "dim", indent=6)
    line("")
    line("params" + ("" if info["params"] else ": none"), "bold")
    for p in info["params"]:
        head = f"{p['name']}: {p['type']}"
        head += " (required)" if p["required"] else f" = {json.dumps(p['default'])}"
        if p["range"]:
            head += f"  [{p['range']}]"
        line(head, indent=2)
        if p["description"]:
            line(p["description"], "dim", indent=6)
    line("")
    swappable = info.get("swappable") or []
    line("a swap over the control endpoint may change: " + (", ".join(swappable) or "none"), "bold")
    for param, folder in (info.get("swap_folders") or {}).items():
        line(f"{param}: a relative path, resolved inside {folder}", "dim", indent=6)


def add_parsers(sub: Any) -> None:
    p = sub.add_parser("kinds", help="list the node kinds, or show one's ports and params")
    p.add_argument("kind", nargs="?", help="a kind (name or module:Class) to describe")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_kinds)
