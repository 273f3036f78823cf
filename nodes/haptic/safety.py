"""What force may reach the device: the haptic node's safety rules, as pure functions.

The rules (proven by property tests on virtual time, tests/test_haptic_safety.py):

- **Valid**: a force is a sequence of one finite number per device axis, a mapping of axis
  name -> finite number (absent axes are 0), or an object with such ``values`` (a
  :class:`~flowrt.nodes.haptic.messages.Force`). NaN, inf, a string, a bool, a wrong length:
  refused, counted, and the force is cut to zero.
- **Clamped**: the force vector's magnitude never exceeds ``max_force`` (the direction is
  kept: clamping each axis alone would turn a push along a wall into a push through it).
- **Rate-limited**: the vector changes by at most ``max_rate`` x dt per tick (dt capped at
  ``max_dt``, so a stalled loop does not earn a large step). Rising and falling alike.
- **Cut**: stale, invalid, a device error, the stop: the force goes to zero *at once*; zero is
  the safe state, and a rate limit on the way down would keep pushing on a fault. That is the
  one exception to the rate limit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from flowrt.refusals import finite_number

__all__ = ["ForceLimiter", "parse_force"]


def _number(v: Any) -> float | None:
    if isinstance(v, np.floating | np.integer) and not isinstance(v, np.bool_):
        v = v.item()
    return float(v) if finite_number(v) else None


_META = frozenset({"timestamp", "_type", "why"})
"""Keys of a force mapping that are not axes (a recorded or remote ``Force``)."""


def parse_force(value: Any, axes: Sequence[str]) -> tuple[float, ...] | None:
    """The force ``value`` asks for, one float per axis, or None when it is refused."""
    values = getattr(value, "values", None)
    if isinstance(value, Mapping):
        values = value.get("values")
        if values is None:
            if set(value) - set(axes) - _META:  # {"z": 1} on x, y was a zero force, uncounted
                return None
            out = [0.0] * len(axes)
            for i, name in enumerate(axes):
                if name in value:
                    x = _number(value[name])
                    if x is None:
                        return None
                    out[i] = x
            return tuple(out)
    elif values is None or callable(values):
        values = value
    if isinstance(values, str | bytes) or not isinstance(values, Sequence | np.ndarray):
        return None
    if len(values) != len(axes):
        return None
    parsed = [_number(x) for x in values]
    if any(x is None for x in parsed):
        return None
    return tuple(x for x in parsed if x is not None)


class ForceLimiter:
    """Clamps and rate-limits the force vector tick by tick; cuts to zero on a fault."""

    def __init__(self, n: int, max_force: float, max_rate: float, max_dt: float) -> None:
        self.max_force, self.max_rate, self.max_dt = max_force, max_rate, max_dt
        self.applied: tuple[float, ...] = (0.0,) * n
        self.clamped = 0  # ticks where the wanted force was above max_force
        self.limited = 0  # ticks where the rate limit held the change back

    def cut(self) -> tuple[float, ...]:
        """Zero force now (stale, invalid, device error, stop)."""
        self.applied = (0.0,) * len(self.applied)
        return self.applied

    def step(self, wanted: Sequence[float], dt: float) -> tuple[float, ...]:
        """The force to apply this tick, ``dt`` seconds after the last one."""
        norm = math.hypot(*wanted)  # (sqrt of the squares overflowed: 1e200 N became 0)
        if norm > self.max_force:
            self.clamped += 1
            s = self.max_force / norm
            wanted = [f * s for f in wanted]
        step = self.max_rate * min(max(dt, 0.0), self.max_dt)
        delta = [w - a for w, a in zip(wanted, self.applied, strict=True)]
        dn = math.hypot(*delta)
        if dn > step:
            # Inside the max_force ball both ends are, so every point between them is too.
            self.limited += 1
            s = step / dn
            wanted = [a + d * s for a, d in zip(self.applied, delta, strict=True)]
        norm = math.sqrt(sum(f * f for f in wanted))
        if norm > self.max_force:  # rounding: never above, not even by one ulp
            s = self.max_force / norm * (1 - 1e-12)
            wanted = [f * s for f in wanted]
        self.applied = tuple(wanted)
        return self.applied
