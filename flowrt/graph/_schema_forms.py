"""The graph file's short forms in its published JSON Schema (``flowrt schema graph``).

The models accept a one-string form where an object is expected (``inputs: {frame:
cam.frame}``, an export's ``node.port``, an import's key, ``trigger: loop``) through "before"
validators, which a generated schema does not see: it refused the shipped graph files that
``flowrt validate`` accepts. These hooks put each short form beside its object.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pydantic import BaseModel, GetJsonSchemaHandler

__all__ = ["short_form_schema", "trigger_words"]


def short_form_schema(what: str) -> Callable[..., Any]:
    """A model's JSON Schema (``flowrt schema graph``) that also takes its one-string short
    form, as its ``_short_form`` validator does (``inputs: {frame: cam.frame}``): the
    schema refused the shipped graph files that ``flowrt validate`` accepts."""

    def schema(cls: type[BaseModel], core: Any, handler: GetJsonSchemaHandler) -> Any:
        full = handler.resolve_ref_schema(handler(core))
        return {"anyOf": [{"type": "string", "description": what}, full]}

    return schema


def trigger_words(schema: dict[str, Any]) -> None:
    """The trigger's one-word forms (``trigger: loop``, ``trigger: input``) in its schema."""
    schema["anyOf"] = [*schema.get("anyOf", []), {"enum": ["loop", "input"]}]
