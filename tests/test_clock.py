"""The system clock's periodic timers, with and without spinning before each release."""

from __future__ import annotations

import asyncio
import itertools
import time

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
