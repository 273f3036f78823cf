"""Where a monitor may hold the loop (flowrt/monitors/_quiet.py): the middle of the widest
gap between timer releases, over the timers' (bounded) hyperperiod."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowrt.monitors._quiet import delay_to_gap, quiet_gap

CASES = [
    # (timers as (period s, phase s), (offset s, cycle s))
    (((0.1, 0.0),), (0.05, 0.1)),
    (((0.1, 0.03),), (0.08, 0.1)),
    (((0.04, 0.0), (0.1, 0.0)), (0.18, 0.2)),  # releases 0 40 80 100 120 160: the last 40
    # a phase not below its period (a timer shortened under its phase before that was
    # refused): the releases are at phase mod period; it used to raise on an empty cycle
    (((0.04, 0.06),), (0.0, 0.04)),  # releases at 20 ms of each 40: the middle is 0
]


@pytest.mark.parametrize(("timers", "expected"), CASES)
def test_the_widest_gap(
    timers: tuple[tuple[float, float], ...], expected: tuple[float, float]
) -> None:
    offset, cycle = quiet_gap(timers)
    assert offset == pytest.approx(expected[0])
    assert cycle == pytest.approx(expected[1])


@given(
    st.lists(
        st.tuples(st.integers(1, 200), st.integers(0, 400)).map(
            lambda t: (t[0] / 1000, t[1] / 1000)
        ),
        min_size=1,
        max_size=4,
    ),
    st.floats(0, 10),
)
def test_a_delay_is_always_found_and_never_on_a_release(
    timers: list[tuple[float, float]], now: float
) -> None:
    """Whatever the timers (a phase above its period included): a finite delay within one
    cycle (the hyperperiod is a bounded window, so its gaps are not exact beyond it)."""
    delay = delay_to_gap(timers, now, 0.0, 0.0)
    _, cycle = quiet_gap(tuple(sorted(timers)))
    assert 0 <= delay <= cycle + 1e-9
