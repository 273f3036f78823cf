"""Time-aligned sets from several inputs, as ROS 2's message_filters do.

::

    pair:
      kind: sync
      params: {policy: approximate, slop: 10ms, queue: 10}
      inputs: {left: cam_l.frame, right: cam_r.frame, audio: mic.audio}

Each input (any names) keeps a queue of its newest ``queue`` values. A value's time is its own
``timestamp`` (frames, audio blocks, mappings with a ``timestamp`` key), else its publication
time (:meth:`flowrt.NodeContext.input_time`).

- ``exact``: a set is made of one value per input with the same timestamp.
- ``approximate`` (the ApproximateTime policy): as soon as every queue holds a value, the set
  whose timestamps spread least is formed from the queues' heads: the input with the oldest
  head pivots; the set is emitted when its spread (newest minus oldest) is within ``slop``;
  else the oldest head is dropped (it can never find partners closer than those now waiting).

Output ``set``: a mapping ``{input: value, ..., "stamp": the newest timestamp of the set,
"spread_ms": newest minus oldest}``. Every value that never makes it into a set is counted
as ``unmatched`` with its reason, in :meth:`Sync.report` (so in the statistics): ``no partner
within slop``, ``queue overflow`` (its queue was full), ``superseded`` (a newer value of the
same input made a set first).
"""

from __future__ import annotations

from collections import deque
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from flowrt import Frame, Input, InputTrigger, Node, Output, parse_duration_ms
from flowrt.freshness import own_timestamp

__all__ = ["Sync", "SyncParams"]

REASONS = ("no partner within slop", "queue overflow", "superseded")


class SyncParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    policy: Literal["exact", "approximate"] = "approximate"
    slop: float = Field(default=0.01, description="largest spread of a set (duration, 10ms)")
    queue: int = Field(default=10, ge=1, le=10_000, description="values kept per input")

    @field_validator("slop", mode="before")
    @classmethod
    def _slop(cls, v: Any) -> float:
        ms = parse_duration_ms(v)
        if ms < 0 or ms > 3_600_000:
            raise ValueError("must be a duration between 0 and 1 h, e.g. 10ms")
        return ms / 1000


def _own(value: Any) -> Any:
    """A frame kept past its activation is copied out of the shared pool: a set is a mapping,
    and the edges' link counting holds frames, not mappings of them."""
    if isinstance(value, Frame):
        return Frame(
            value.data.copy(),
            source=value.source,
            seq=value.seq,
            timestamp=value.timestamp,
            pixel_format=value.pixel_format,
        )
    return value


def value_time(value: Any, published: float | None) -> float | None:
    """The value's own timestamp (flowrt.freshness's reading of it), else its publication."""
    own = own_timestamp(value)
    return own if own is not None else published


class Sync(Node):
    """Joins its inputs into time-aligned sets (see the module docstring)."""

    swappable = frozenset({"policy", "slop", "queue"})  # over the control endpoint: flowrt kinds

    Params = SyncParams
    any_inputs = Input(object, required=False, policy="queue", doc="streams to align")
    set = Output(dict, doc="{input: value, ..., stamp, spread_ms}")

    @classmethod
    def default_trigger(cls, params: Any) -> InputTrigger:
        return InputTrigger()

    def setup(self) -> None:
        self.queues: dict[str, deque[tuple[float, Any]]] = {}
        self.unmatched: dict[str, dict[str, int]] = {}
        self.sets = 0

    def _drop(self, name: str, value: Any, reason: str) -> None:
        per = self.unmatched.setdefault(name, dict.fromkeys(REASONS, 0))
        per[reason] += 1

    def process(self, **inputs: Any) -> None:
        for name, value in inputs.items():
            if value is None:
                continue
            t = value_time(value, self.ctx.input_time(name))
            if t is None:
                continue
            q = self.queues.setdefault(name, deque())
            q.append((t, _own(value)))
            if len(q) > self.params.queue:
                _, old = q.popleft()
                self._drop(name, old, "queue overflow")
        names = sorted(self.queues)
        while len(names) >= 2 and all(self.queues[n] for n in names):
            self._match(names)

    def _match(self, names: list[str]) -> None:
        """One step: a set from the queues' heads, or the oldest head dropped."""
        heads = {n: self.queues[n][0] for n in names}
        times = [t for t, _ in heads.values()]
        spread = max(times) - min(times)
        exact = self.params.policy == "exact"
        ok = spread == 0 if exact else spread <= self.params.slop + 1e-12
        if ok:
            out: dict[str, Any] = {n: self.queues[n].popleft()[1] for n in names}
            out["stamp"] = max(times)
            out["spread_ms"] = spread * 1000
            self.sets += 1
            self.ctx.publish("set", out)
            return
        oldest = min(names, key=lambda n: heads[n][0])
        q = self.queues[oldest]
        _, value = q.popleft()
        others = max(heads[n][0] for n in names if n != oldest)
        # a newer value of the same input that fits the others better takes its place
        later = bool(q) and q[0][0] <= others + self.params.slop
        self._drop(oldest, value, "superseded" if later else "no partner within slop")

    def report(self) -> dict[str, Any]:
        """Sets made and values left out, per input and reason (``reports``)."""
        total = sum(sum(r.values()) for r in self.unmatched.values())
        return {"sets": self.sets, "unmatched": total, "by_input": self.unmatched}
