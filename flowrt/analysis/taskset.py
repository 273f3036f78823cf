"""Task-set files: a system that is not (yet) a graph, analysed like pyCPA's task lists.

::

    tasks:            # highest priority first, unless a `priority:` (higher = more important)
      - {name: sensor, wcet: 51us, period: 1ms, deadline: 1ms, blocking: 0us, jitter: 0us}
    preemptive: true  # false: non-preemptive fixed priority (an event loop, a CAN bus)

Durations use the graph files' syntax (``51us``, ``10ms``, ``2s``, a bare number is ms).
Errors are located diagnostics (file:line:column, key), like a graph file's.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..graph._loading import parse_yaml, pydantic_diagnostics
from ..graph.diagnostics import Diagnostic, GraphError, Severity
from ..graph.spec import DurationMs
from .rta import Task


class TaskSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    wcet: DurationMs
    period: DurationMs
    deadline: DurationMs | None = None
    blocking: DurationMs = 0.0
    jitter: DurationMs = 0.0
    priority: float | None = Field(default=None, description="higher = more important")

    @field_validator("wcet", "blocking", "jitter")
    @classmethod
    def _non_negative(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"must be a finite duration >= 0, got {v:g} ms")
        return v

    @field_validator("period", "deadline")
    @classmethod
    def _positive(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"must be a finite positive duration, got {v:g} ms")
        return v


class TaskSetSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    tasks: list[TaskSpec] = Field(min_length=1)
    preemptive: bool = True

    @model_validator(mode="after")
    def _unique(self) -> TaskSetSpec:
        names = [t.name for t in self.tasks]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"task names must be unique: {', '.join(dup)}")
        return self


def is_task_set(data: Any) -> bool:
    """A mapping with ``tasks:`` and no ``nodes:`` is a task-set file."""
    return isinstance(data, dict) and "tasks" in data and "nodes" not in data


def parse_task_set(text: str, file: str = "<tasks>") -> tuple[list[Task], bool]:
    """The tasks of a task-set file (with priorities) and whether it is preemptive.

    Raises GraphError with located diagnostics.
    """
    data, locs, errors = parse_yaml(text, file)
    if errors:
        raise GraphError(errors)
    try:
        spec = TaskSetSpec.model_validate(data)
    except ValidationError as e:
        raise GraphError(pydantic_diagnostics(e, locs, model=TaskSetSpec)) from None
    given = [t.priority is not None for t in spec.tasks]
    if any(given) and not all(given):
        raise GraphError(
            [Diagnostic(Severity.error, "give priority: to every task or to none", "tasks", file)]
        )
    n = len(spec.tasks)
    tasks = [
        Task(
            t.name,
            t.wcet,
            t.period,
            t.deadline,
            t.jitter,
            t.blocking,
            t.priority if t.priority is not None else float(n - k),
        )
        for k, t in enumerate(spec.tasks)
    ]
    return tasks, spec.preemptive
