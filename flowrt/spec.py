"""Graph models: the one description of a graph, whether it came from YAML or from Python.

Everything the runtime needs is here and validated by pydantic, so that a graph that loads
is a graph that can run. Structural checks that need the node classes (ports, cycles, frame
sources) live in :mod:`flowrt.validation`.
"""

from __future__ import annotations

import re
from enum import Enum
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    field_validator,
    model_validator,
)
from pydantic.functional_validators import BeforeValidator

_DURATION = re.compile(r"^\s*(?P<num>[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(?P<unit>us|ms|s)?\s*$")
_UNIT_MS = {"us": 0.001, "ms": 1.0, "s": 1000.0, None: 1.0}


def parse_duration_ms(value: Any) -> float:
    """Read ``10ms``, ``1.5s``, ``200us`` or a bare number (milliseconds) as milliseconds."""
    if isinstance(value, bool):
        raise ValueError("expected a duration such as 10ms, 1.5s or 200us")
    if isinstance(value, int | float):
        return float(value)
    if isinstance(value, str):
        m = _DURATION.match(value)
        if m:
            return float(m.group("num")) * _UNIT_MS[m.group("unit")]
    raise ValueError(f"expected a duration such as 10ms, 1.5s or 200us, got {value!r}")


DurationMs = Annotated[float, BeforeValidator(parse_duration_ms)]
"""A duration in milliseconds; YAML may write it with a unit (us, ms, s)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FrameTrigger(_Strict):
    """Activate on the ticks of a frame source: every ``period`` frames, offset by ``phase``.

    The CAMBADA process-manager semantics: on tick ``k`` of the source, the node runs when
    ``k % period == phase``.
    """

    frame: str = Field(description="frame source: a node name, or node.port for a node with several")
    period: int = 1
    phase: int = 0


class TimerTrigger(_Strict):
    """Activate every ``timer`` milliseconds, ``phase`` ms after the runtime's time origin."""

    timer: DurationMs
    phase: DurationMs = 0.0


class InputTrigger(_Strict):
    """Activate when data arrives on the named inputs (``any`` = any input); never re-entrant."""

    input: str | list[str] = "any"


class LoopTrigger(_Strict):
    """Free-running: activate again as soon as the previous activation ends.

    For sources paced by their device (a camera's ``grab`` blocks until the next frame).
    """

    loop: Literal[True] = True


def _trigger_tag(v: Any) -> str | None:
    if isinstance(v, BaseModel):
        return {FrameTrigger: "frame", TimerTrigger: "timer", InputTrigger: "input"}.get(
            type(v), "loop"
        )
    if isinstance(v, dict):
        for key in ("frame", "timer", "input", "loop"):
            if key in v:
                return key
    return None


Trigger = Annotated[
    Annotated[FrameTrigger, Tag("frame")]
    | Annotated[TimerTrigger, Tag("timer")]
    | Annotated[InputTrigger, Tag("input")]
    | Annotated[LoopTrigger, Tag("loop")],
    Discriminator(
        _trigger_tag,
        custom_error_type="trigger",
        custom_error_message="a trigger needs one of the keys frame, timer, input or loop",
    ),
]


class Placement(str, Enum):
    inline = "inline"
    process = "process"
    pool = "pool"


class MissPolicy(str, Enum):
    """What happens to the result of an activation that missed its deadline."""

    continue_ = "continue"  # soft deadline: the late result is still delivered
    discard = "discard"  # firm deadline: the late result is dropped (and counted)


class EdgePolicy(str, Enum):
    latest = "latest"
    queue = "queue"
    lossless = "lossless"


class InputSpec(_Strict):
    """Where an input reads from and how its buffer behaves."""

    source: str = Field(alias="from", description="node.port that feeds this input")
    policy: EdgePolicy | None = None  # None: latest for frames, queue for messages
    size: int = Field(default=8, ge=1, description="capacity of queue/lossless buffers")

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    @model_validator(mode="before")
    @classmethod
    def _short_form(cls, data: Any) -> Any:
        if isinstance(data, str):
            return {"from": data}
        return data

    @field_validator("source")
    @classmethod
    def _node_dot_port(cls, v: str) -> str:
        if v.count(".") != 1 or not all(v.split(".")):
            raise ValueError(f"expected node.port, got {v!r}")
        return v

    @property
    def node(self) -> str:
        return self.source.split(".")[0]

    @property
    def port(self) -> str:
        return self.source.split(".")[1]


class RestartPolicy(_Strict):
    """When a node that raised is started again, and how long to wait (doubling each time)."""

    policy: Literal["always", "on-failure", "never"] = "on-failure"
    backoff: DurationMs = 100.0
    max_backoff: DurationMs = 5000.0
    max_restarts: int | None = None


class NodeSpec(_Strict):
    """One node of the graph: what it is, when it runs, where, and what it reads."""

    kind: str
    params: dict[str, Any] = Field(default_factory=dict)
    trigger: Trigger | None = None
    deadline: DurationMs | None = None
    miss_policy: MissPolicy = MissPolicy.continue_
    priority: int = Field(default=10, ge=1, le=99)
    placement: Placement = Placement.inline
    enabled: bool = True
    watchdog: DurationMs | None = None
    restart: RestartPolicy = RestartPolicy()
    inputs: dict[str, InputSpec] = Field(default_factory=dict)

    @field_validator("trigger", mode="before")
    @classmethod
    def _trigger_shorthand(cls, v: Any) -> Any:
        if v == "loop":
            return {"loop": True}
        if v == "input":
            return {"input": "any"}
        return v

    @field_validator("deadline", "watchdog")
    @classmethod
    def _positive(cls, v: float | None) -> float | None:
        if v is not None and v <= 0:
            raise ValueError("must be positive")
        return v


class ModeSpec(_Strict):
    """A named set of timing overrides (e.g. attacker / defender), applied as one change."""

    nodes: dict[str, TimingOverride] = Field(default_factory=dict)


class TimingOverride(_Strict):
    """The run-time adjustable part of a node's timing; unset fields keep their value."""

    period: int | None = None
    phase: int | None = None
    timer: DurationMs | None = None
    deadline: DurationMs | None = None
    priority: int | None = Field(default=None, ge=1, le=99)
    enabled: bool | None = None


ModeSpec.model_rebuild()


class GraphSpec(_Strict):
    """A whole graph. ``nodes`` keeps file order, which is also the tie-break for priority."""

    name: str = "graph"
    description: str = ""
    nodes: dict[str, NodeSpec]
    modes: dict[str, ModeSpec] = Field(default_factory=dict)
    initial_mode: str | None = None

    @field_validator("nodes")
    @classmethod
    def _names(cls, v: dict[str, NodeSpec]) -> dict[str, NodeSpec]:
        for name in v:
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_\-]*", name):
                raise ValueError(f"node name {name!r}: use letters, digits, _ and -")
        return v
