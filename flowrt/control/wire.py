"""The control endpoint's wire format: the bodies it accepts and the JSON it answers.

Each request body is a strict pydantic model (unknown keys refused, bounded strings), so a
request is refused whole, with the reason, before anything is changed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator

from ..events import Event, NodeFailed
from ..graph.spec import TimingOverride
from ..kernel.timing import TimingChange


class TimingRequest(TimingOverride):
    """Body of ``POST /timing``: the node and the fields to change (ms for timer/deadline).

    The graph file's own model (:class:`flowrt.graph.spec.TimingOverride`), so a request obeys the
    same rules as a mode in a graph file, and is refused whole by the endpoint's server
    process before the runtime sees it. ``force`` passes admission control (never the
    ranges, which ``Runtime.apply_timing`` checks against the node).
    """

    node: str = Field(max_length=256)
    force: StrictBool = False  # past admission control: "yes" is no yes
    enabled: StrictBool | None = None

    @field_validator("priority", mode="before")
    @classmethod
    def _no_bool(cls, v: Any) -> Any:
        """``true`` is no priority (pydantic would read it as 1)."""
        if isinstance(v, bool):
            raise ValueError("priority must be a number, not true/false")
        return v

    def change(self) -> TimingChange:
        """The one value the runtime applies (``Runtime.apply_timing(node, change)``)."""
        return TimingChange.unchecked(self)


class ModeRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: str = Field(max_length=256)
    force: StrictBool = False  # past admission control: "yes" is no yes


class SwapRequest(BaseModel):
    """``POST /swap``: a node's algorithm replaced while running (``Runtime.swap``)."""

    model_config = ConfigDict(extra="forbid")
    node: str = Field(max_length=256)
    kind: str = Field(max_length=1024)
    params: dict[str, Any] | None = None


class ReloadRequest(BaseModel):
    """``POST /reload``: a node's module re-imported from disk (``Runtime.reload``)."""

    model_config = ConfigDict(extra="forbid")
    node: str = Field(max_length=256)


class RecordRequest(BaseModel):
    """``POST /record``: start or stop the graph's recorder nodes (or one of them)."""

    model_config = ConfigDict(extra="forbid")
    action: Literal["start", "stop"]
    node: str | None = None
    name: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_\-]{1,64}$",
        description="with start: the session's name, NAME_NNN (default: the recorder's)",
    )


def jsonable(value: Any) -> Any:
    """A JSON-friendly copy of event fields and RTDB values (repr for what is not data)."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    item = getattr(value, "item", None)  # numpy scalars
    if callable(item) and getattr(value, "shape", None) == ():
        return jsonable(item())
    return repr(value)


def event_json(event: Event) -> dict[str, Any]:
    out = {"kind": event.kind, **jsonable(event)}
    if isinstance(event, NodeFailed):
        out.pop("traceback", None)
    return out
