"""World state and the decisions taken on it: the RTDB writer and the decision table.

``rtdb`` (:class:`Store`) writes every value it receives into an RTDB record named after
the input (or as ``records`` maps it), timestamped with the value's own ``timestamp`` when it
has one (a tracker's detection carries its frame's capture time), so a reader sees how old
the object information really is. This is how tracker output lands in the RTDB, as in
CAMBADA::

    world:
      kind: rtdb
      params: {validity_ms: 200}
      inputs: {ball: ball_fr.detection, obstacle: avoid_fr.detection}

``decision`` (:class:`Decision`) is the decision table of the agent-based control system:
on its timer it reads RTDB records, finds the first rule whose conditions hold and switches
the runtime to that rule's mode (only when it differs from the current one)::

    decide:
      kind: decision
      trigger: {timer: 100ms}
      params:
        rules:
          - {record: ball, field: found, eq: false, mode: search}
          - {record: ball, field: area, gt: 400, mode: defend}
        default: attack

A rule matches only a fresh record (not past its validity), unless it says ``stale: true``
(match only a stale one) or ``missing: true`` (match when the record was never written).
"""

from __future__ import annotations

import operator
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from flowrt import Input, Node, Output, TimerMs, TimerTrigger

__all__ = ["Decision", "Rule", "Store"]


class StoreParams(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    validity_ms: float | None = Field(
        default=None, gt=0, le=3_600_000, description="None: valid forever"
    )
    records: dict[str, str] = Field(default_factory=dict, description="input name -> record")


class Store(Node):
    """Writes each value that arrives into the RTDB (see the module docstring)."""

    swappable = frozenset({"validity_ms"})  # over the control endpoint: flowrt kinds

    Params = StoreParams
    any_inputs = Input(object, required=False, doc="values to record (any input name)")

    def process(self, **values: Any) -> None:
        db = self.ctx.rtdb
        for port, value in values.items():
            if value is None:
                continue
            # when the value was true: its publication time, or its own timestamp when that
            # is older and in this clock (flowrt.freshness: a foreign stamp never keeps a
            # record valid)
            age = self.ctx.input_age(port, value)
            db.write(
                self.params.records.get(port, port),
                value,
                validity_ms=self.params.validity_ms,
                timestamp=None if age is None else self.ctx.now() - age,
            )


_OPS = {
    "eq": operator.eq,
    "ne": operator.ne,
    "lt": operator.lt,
    "le": operator.le,
    "gt": operator.gt,
    "ge": operator.ge,
}


class Rule(BaseModel):
    """One row of the decision table: conditions on one record, and the mode they select."""

    model_config = ConfigDict(extra="forbid")
    record: str
    field: str | None = Field(default=None, description="attribute or key, dotted: a.b")
    eq: Any = None
    ne: Any = None
    lt: Any = None
    le: Any = None
    gt: Any = None
    ge: Any = None
    stale: bool = False
    missing: bool = False
    mode: str

    def matches(self, rec: Any) -> bool:
        if self.missing:
            return rec is None
        if rec is None or rec.stale != self.stale:
            return False
        value = _get(rec.value, self.field)
        try:
            return all(
                fn(value, getattr(self, name))
                for name, fn in _OPS.items()
                if name in self.model_fields_set
            )
        except TypeError:  # e.g. comparing None with a number: not a match
            return False


def _get(value: Any, path: str | None) -> Any:
    for part in path.split(".") if path else ():
        value = value.get(part) if isinstance(value, Mapping) else getattr(value, part, None)
    return value


class DecisionParams(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    rules: list[Rule] = Field(min_length=1, description="first match wins")
    default: str | None = Field(default=None, description="mode when no rule matches")
    interval_ms: TimerMs = Field(default=100.0, description="default timer trigger")


class Decision(Node):
    """Switches modes by a decision table over RTDB records (see the module docstring)."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset({"rules", "default", "interval_ms"})

    Params = DecisionParams
    mode = Output(str, doc="the mode chosen, published when it changes", rate_hz=None)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=params.interval_ms)

    def setup(self) -> None:
        self._failed: set[str] = set()

    def process(self) -> str | None:
        db = self.ctx.rtdb
        chosen = self.params.default
        for rule in self.params.rules:
            if rule.matches(db.read(rule.record)):
                chosen = rule.mode
                break
        if chosen is None or chosen == db.value("flowrt.mode") or chosen in self._failed:
            return None
        try:
            self.ctx.set_mode(chosen)
        except (KeyError, ValueError) as e:  # an unknown or invalid mode: say so once
            self._failed.add(chosen)
            self.ctx.log.error("%s: cannot switch to mode %r: %s", self.ctx.name, chosen, e)
            return None
        return str(chosen)
