"""The system clock's periodic timers, with and without spinning before each release."""

from __future__ import annotations

import asyncio
import itertools
import time
from typing import Any

import pytest

from flowrt.clock import SystemClock


@pytest.mark.parametrize("spin", [0.0, 0.002])
async def test_periodic_ticks_never_fire_before_their_release(spin: float) -> None:
    clock = SystemClock(spin=spin)
    clock.origin = time.monotonic()
    seen: list[tuple[float, float, int]] = []
    done = asyncio.Event()

    def tick(release: float, missed: int) -> None:
        seen.append((release, time.monotonic(), missed))
        if len(seen) == 10:
            done.set()

    timer = clock.periodic(0.01, 0.003, tick)
    try:
        await asyncio.wait_for(done.wait(), 5)
    finally:
        timer.cancel()
    assert all(now >= r for r, now, _ in seen)  # spinning ends at the release, not before
    for (r0, _, _), (r1, _, missed) in itertools.pairwise(seen):
        assert r1 - r0 == pytest.approx(0.01 * (1 + missed), abs=1e-9)
    k = (seen[0][0] - clock.origin - 0.003) / 0.01  # on the grid origin + phase + k * period
    assert k == pytest.approx(round(k), abs=1e-6)


def test_spin_out_of_range_is_refused() -> None:
    with pytest.raises(ValueError, match="spin"):
        SystemClock(spin=0.5)


async def test_timers_due_together_fire_in_creation_order_after_one_wake_up() -> None:
    """Issue 31: a 10 ms timer created first (the scheduler creates them by priority) fires
    before the eight 100 ms timers that fall due with it every tenth tick, whichever period
    reached the instant; all of them on one timerfd."""
    clock = SystemClock()
    clock.origin = time.monotonic()
    order: list[tuple[float, str]] = []
    done = asyncio.Event()

    def tick(name: str) -> Any:
        def fire(release: float, missed: int) -> None:
            order.append((release, name))
            if len(order) > 60:
                done.set()

        return fire

    timers = [clock.periodic(0.01, 0.0, tick("fast"))]
    timers += [clock.periodic(0.1, 0.0, tick(f"slow{i}")) for i in range(8)]
    loop = asyncio.get_running_loop()
    try:
        assert len(clock._wheels) == 1  # one timerfd for all nine
        await asyncio.wait_for(done.wait(), 5)
    finally:
        for t in timers:
            t.cancel()
    assert not clock._wheels  # the last cancel closed it
    shared = [r for r, name in order if name == "slow0"]
    assert shared
    slows = [f"slow{i}" for i in range(8)]
    together = 0
    for r in shared:
        names = [name for r2, name in order if abs(r2 - r) < 1e-6]
        # a loaded machine may wake past an instant: the fast timer then fires once for the
        # releases it missed (a later release, ``missed`` > 0), not at this one
        assert names in (["fast", *slows], slows), names
        together += names[0] == "fast"
    assert together >= 1
    assert loop.is_running()
