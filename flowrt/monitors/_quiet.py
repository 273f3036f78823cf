"""Where a monitor may hold the loop: the widest gap between timer releases.

Monitors that hold the loop for a while (a terminal table, a summary line) wait for the
middle of that gap, so their work falls where no timer (and so no frame tick) is due.
"""

from __future__ import annotations

import math
from functools import lru_cache


@lru_cache(maxsize=8)
def quiet_gap(timers: tuple[tuple[float, float], ...]) -> tuple[float, float]:
    """(offset of the widest gap's middle, cycle) in seconds over the timers' hyperperiod.

    ``timers``: (period, phase) of each enabled timer, in seconds, sorted (the cache key).
    The hyperperiod is bounded (2 s, or ten of the longest period): a window, not forever.
    """
    # a phase is below its period (checked wherever one is set); were it not, the releases
    # are still at phase mod period, and no instant may be left out of the cycle
    us = [(pu, round(ph * 1e6) % pu) for p, ph in timers if (pu := max(1, round(p * 1e6)))]
    cycle = 1
    for p, _ in us:
        cycle = cycle * p // math.gcd(cycle, p)
    cycle = min(cycle, 10 * max(p for p, _ in us), 2_000_000)
    instants = sorted(
        {ph + k * p for p, ph in us for k in range(cycle // p + 1) if ph + k * p < cycle}
    )
    gaps = [(b - a, a) for a, b in zip(instants, [*instants[1:], instants[0] + cycle], strict=True)]
    width, start = max(gaps)
    return (((start + width / 2) % cycle) / 1e6, cycle / 1e6)


def delay_to_gap(
    timers: list[tuple[float | None, float]], now: float, origin: float, at_least: float
) -> float:
    """Seconds from ``now`` to the middle of the next widest gap, at least ``at_least``.

    ``timers``: (period or None, phase) of each node; a None or zero period is no timer.
    """
    running = tuple(sorted((p, ph) for p, ph in timers if p))
    if not running:
        return at_least
    offset, cycle = quiet_gap(running)
    base = origin + offset
    k = math.ceil((now + at_least - base) / cycle)
    return max(0.0, base + k * cycle - now)
