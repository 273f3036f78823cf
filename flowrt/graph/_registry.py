"""Node kinds: names from the ``flowrt.nodes`` entry-point group, or ``package.module:Class``.

Built-in nodes are registered through the same entry points as third-party ones, so the
runtime never imports ``flowrt.nodes`` by name.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from functools import cache
from importlib.metadata import entry_points

from ..node import Node
from .diagnostics import did_you_mean

GROUP = "flowrt.nodes"


class KindError(LookupError):
    """A kind that does not resolve; the message is meant for the user."""


class NotImported(KindError):
    """A dotted-path kind left unimported on purpose (``flowrt validate --no-import``)."""


@cache
def _entry_points() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group=GROUP)}


def available_kinds() -> list[str]:
    return sorted(_entry_points())


def resolve_kind(
    kind: str | type[Node],
    extra: Mapping[str, type[Node]] | None = None,
    *,
    allow_import: bool = True,
) -> type[Node]:
    """The node class for ``kind``; raises KindError with a 'did you mean' hint.

    A dotted path (``package.module:Class``) imports that module, which runs its code: a
    graph file is code, like a Python script. ``allow_import=False`` raises NotImported for
    such a kind instead (installed entry-point kinds still resolve).
    """
    if isinstance(kind, type):
        if not issubclass(kind, Node):
            raise KindError(f"{kind.__qualname__} is not a flowrt.Node subclass")
        return kind
    if extra and kind in extra:
        return extra[kind]
    target = _entry_points().get(kind)
    if target is None and ":" not in kind:
        names = [*_entry_points(), *(extra or {})]
        raise KindError(f"unknown node kind {kind!r}" + did_you_mean(kind, names))
    module_name, _, attr = (target or kind).partition(":")
    if target is None and not allow_import:
        raise NotImported(f"node kind {kind!r} not imported (--no-import)")
    try:
        module = importlib.import_module(module_name)
    except (ImportError, ValueError, TypeError) as e:
        raise KindError(f"node kind {kind!r}: cannot import {module_name!r} ({e})") from None
    obj = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            names = [n for n in dir(module) if not n.startswith("_")]
            raise KindError(
                f"node kind {kind!r}: {module_name} has no {part!r}" + did_you_mean(part, names)
            ) from None
    if not (isinstance(obj, type) and issubclass(obj, Node)):
        raise KindError(f"node kind {kind!r} is not a flowrt.Node subclass")
    return obj
