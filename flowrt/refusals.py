"""Values a driving node refuses (NaN, inf, a string where a speed belongs), counted once.

The arbiter, teleop and the joystick each refuse such values with the same rule: a refused
value is counted once per publication (a latest edge hands the same value to every
activation until a new one comes), and one ``HealthAlert`` is raised per burst of refusals,
not per tick; a valid value ends the burst.
"""

from __future__ import annotations

import math
from typing import Any

from .events import HealthAlert

__all__ = ["Refusals", "finite_number"]


def finite_number(v: Any) -> bool:
    """A finite int or float (not a bool): what an axis or a speed may be."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an int beyond a float's range
        return False


class Refusals:
    """The refusals of one input: ``count`` (once per publication) and the burst's alert."""

    def __init__(self, alert: str, detail: str) -> None:
        self.alert, self.detail = alert, detail
        self.count = 0
        self._counted: float | None = None  # publication time of the last one counted
        self._in_burst = False  # an alert was raised and no valid value came since

    def refuse(self, ctx: Any, published: float | None) -> None:
        """Count a refused value published at ``published`` (None: unknown, always counted);
        raise the alert when a burst begins."""
        if published is None or published != self._counted:
            self.count += 1
            self._counted = published
        if not self._in_burst:
            self._in_burst = True
            ctx.emit(HealthAlert(ctx.elapsed(), ctx.name, self.alert, self.detail, "warning"))

    def accept(self) -> None:
        """A valid value: the burst, if any, is over."""
        self._in_burst = False
