"""Teleop's safety rules (issue 23) as properties on virtual time.

For arbitrary interleavings of joystick values (NaNs and wrong types among them), silences,
republished objects, button presses and deadman releases:

- outside ``run`` the command is exactly zero;
- on a tick whose input is stale, missing, invalid or whose deadman is released, the command
  is zero (and teleop is no longer in ``run``);
- ``run`` is entered only on a tick where every axis is centred;
- every command value is finite.
"""

from __future__ import annotations

import math
from typing import Any

from flowrt.nodes.joystick import JoyState
from flowrt.nodes.teleop import Teleop
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt.testing import NodeHarness

TIMEOUT = 0.1
BAND = 0.1
PARAMS = {
    "axes": {"vx": {"input": "y", "scale": 0.8}, "w": {"input": "x", "scale": 1.5}},
    "buttons": {"start": "a", "stop": "b", "deadman": "lb"},
    "timeout_ms": TIMEOUT * 1000,
    "centre_band": BAND,
}

# mostly centred sticks, so that runs reach ``run`` and then meet NaNs, silences, releases
axis = st.one_of(
    st.sampled_from([0.0, 0.0, 0.0, 0.05, 0.5, -0.7, math.nan, math.inf, "up"]),
    st.floats(min_value=-1, max_value=1),
)
# axes and buttons of a reading; made into a JoyState stamped at the tick it is published
pressed_mostly = st.sampled_from([True, True, True, False])
joy = st.tuples(axis, axis, st.booleans(), st.booleans(), pressed_mostly)
action = st.one_of(
    st.just(("hold", None)), st.tuples(st.just("new"), joy), st.just(("again", None))
)
tick = st.tuples(
    st.one_of(st.floats(min_value=0.005, max_value=0.04), st.floats(max_value=0.3, min_value=0.04)),
    action,
)


def valid(j: JoyState) -> bool:
    return all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        for v in j.axes.values()
    )


@settings(max_examples=150, deadline=None)
@given(st.lists(tick, min_size=1, max_size=60))
def test_teleop_safety_rules_hold_for_any_interleaving(ticks: list[Any]) -> None:
    h = NodeHarness(Teleop, PARAMS, name="teleop")
    now = 0.0
    held: JoyState | None = None
    published = -math.inf
    previous = "idle"
    for dt, (kind, value) in ticks:
        now += dt
        h.ctx.time = now
        if kind == "new":
            x, y, a, b, lb = value
            # stamped in this clock, as the joystick node does; stop pressed rarely
            held = JoyState({"x": x, "y": y}, {"a": a, "b": b and a, "lb": lb}, now)
        if kind == "new" or (kind == "again" and held is not None):
            assert held is not None
            published = now
            h.publish("joy", held)
        out = h.process(joy=held)
        cmd, mode = out["command"], out["mode"]
        assert all(math.isfinite(x) for x in cmd.values())
        if mode != "run":
            assert all(x == 0.0 for x in cmd.values())
        # the older of publication and the reading's own stamp (republished: old stamp)
        age = max(now - published, now - held.timestamp) if held is not None else math.inf
        fresh = held is not None and age <= TIMEOUT and valid(held)
        deadman = held is not None and bool(held.buttons.get("lb"))
        if not fresh or not deadman:
            assert all(x == 0.0 for x in cmd.values())
            assert mode != "run"
        if mode == "run" and previous != "run":
            assert held is not None
            assert all(abs(v) <= BAND for v in held.axes.values())
        previous = mode


def test_nan_axis_in_run_gives_zero_and_back_to_initialization_counted_once() -> None:
    h = NodeHarness(Teleop, PARAMS, name="teleop")
    h.ctx.time = 0.0
    h.process(joy=JoyState({"x": 0.0, "y": 0.0}, {"a": True, "lb": True}, 0.0))
    h.ctx.time = 0.02
    out = h.process(joy=JoyState({"x": 0.0, "y": 0.0}, {"lb": True}, 0.02))
    assert out["mode"] == "run"
    h.ctx.time = 0.04
    out = h.process(joy=JoyState({"x": 0.0, "y": 0.5}, {"lb": True}, 0.04))
    assert out["command"]["vx"] > 0
    bad = JoyState({"x": 0.0, "y": math.nan}, {"lb": True}, 0.06)
    for k in range(3):
        h.ctx.time = 0.06 + 0.01 * k
        out = h.process(joy=bad)
        assert out["command"] == {"vx": 0.0, "w": 0.0}
        assert out["mode"] == "initialization"
    assert h.node.report()["invalid"] == 1
    alerts = [e for e in h.ctx.events if getattr(e, "alert", "") == "teleop-invalid"]
    assert len(alerts) == 1


def test_a_foreign_clock_timestamp_in_the_future_does_not_keep_teleop_driving() -> None:
    """Issue 32 item 12: a value stamped by another machine's clock (ahead of ours) ages by
    this machine's publication time; it never stays fresh forever."""
    h = NodeHarness(Teleop, PARAMS, name="teleop")
    h.ctx.time = 0.0
    h.process(joy=JoyState({"x": 0.0, "y": 0.0}, {"a": True, "lb": True}, 1e6))
    h.ctx.time = 0.02
    foreign = JoyState({"x": 0.0, "y": 0.0}, {"lb": True}, 1e6 + 0.02)
    assert h.process(joy=foreign)["mode"] == "run"
    h.ctx.time = 0.04
    moving = JoyState({"x": 0.0, "y": 0.9}, {"lb": True}, 1e6 + 0.04)
    assert h.process(joy=moving)["command"]["vx"] > 0
    h.ctx.time = 0.04 + TIMEOUT + 0.01  # the joystick stopped publishing
    out = h.process(joy=moving)
    assert out["command"] == {"vx": 0.0, "w": 0.0}
