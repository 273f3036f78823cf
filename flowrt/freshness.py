"""How old a value is: the one rule every node that judges freshness uses.

A driving node (arbiter, teleop, health, the decision table) must decide whether a command is
recent enough to act on. Judging by the value's identity ("first seen") fails both ways: a
source that publishes the same object every tick (a constant, a dict mutated in place, the
interned ``True``) looks stale, and a value read again looks new. The runtime knows better:
every edge stamps each publication with the runtime clock, so a value's age is the time
since it was published on the edge the node reads (:meth:`flowrt.NodeContext.input_time`).

A value may also carry its own ``timestamp`` (an attribute or a mapping key): a relay that
forwards an old measurement keeps its age. That stamp is trusted only when it can be read in
this machine's clock: a stamp in the future (another machine's monotonic clock, imported over
Zenoh) is ignored, never taken as "brand new"; a stamp in the past makes the value older, never
younger. So the age used is the older of the two, and a foreign clock can only make a value
stale (the safe side), never keep it fresh.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

__all__ = ["FUTURE_TOLERANCE", "age_of", "own_timestamp"]

FUTURE_TOLERANCE = 0.001  # seconds: a stamp this far ahead of now is still this clock's


def own_timestamp(value: Any) -> float | None:
    """The value's own ``timestamp`` (attribute or mapping key), when finite; else None."""
    t = value.get("timestamp") if isinstance(value, Mapping) else getattr(value, "timestamp", None)
    if isinstance(t, bool) or not isinstance(t, int | float):
        return None
    t = float(t)
    return t if math.isfinite(t) else None


def age_of(now: float, published: float | None, value: Any = None) -> float | None:
    """Seconds since ``value`` was made, from its publication time and its own timestamp.

    ``published`` is the runtime-clock time of its publication on the edge (None: unknown).
    Returns None when neither is known (nothing was ever received). A stamp ahead of ``now``
    by more than :data:`FUTURE_TOLERANCE` comes from another clock and is ignored.
    """
    ages: list[float] = []
    if published is not None:
        ages.append(now - published)
    stamp = own_timestamp(value) if value is not None else None
    if stamp is not None and stamp <= now + FUTURE_TOLERANCE:
        ages.append(now - stamp)
    return max(ages) if ages else None
