"""The haptic node's safety rules (issue 42) as properties on virtual time.

For arbitrary interleavings of forces (vectors, mappings, vision walls), NaN/inf/wrong-type
values, silences, republished objects, lock values and device faults (hypothesis, through
the node harness with the simulated device; publication times as an edge stamps them):

(a) the applied force is zero whenever the force input is stale, invalid or absent, or the
    device reports an error;
(b) its magnitude never exceeds ``max_force``;
(c) its change per tick never exceeds ``max_rate`` x dt (a cut to zero aside: zero at once);
(d) locked axes of ``target`` never move while locked;
(e) what the device was given is what ``applied`` says.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
from flowrt.nodes.haptic import Fixture, Force, Haptic
from flowrt.nodes.haptic.safety import parse_force
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt.testing import NodeHarness

AXES = ("x", "y", "z")
MAX_FORCE = 3.0
MAX_RATE = 200.0  # N/s
TIMEOUT = 0.05
RATE_HZ = 1000.0

newtons = st.floats(min_value=-20, max_value=20, allow_nan=False)
bad_number = st.sampled_from([math.nan, math.inf, -math.inf, "hard", None, True, 10**400])
good_force = st.one_of(
    st.tuples(newtons, newtons, newtons),
    st.lists(newtons, min_size=3, max_size=3),
    st.fixed_dictionaries({"x": newtons}, optional={"y": newtons, "z": newtons}),
    st.builds(lambda v: Force(AXES, v, 0.0), st.tuples(newtons, newtons, newtons)),
    st.builds(
        lambda a, k: Fixture("wall", ("x", "y"), a, (-1.0, 0.0), k, 0.0, True, 0.0),
        st.tuples(st.floats(-100, 100), st.floats(-100, 100)),
        st.floats(0, 5000),
    ),
)
bad_force = st.one_of(
    st.tuples(bad_number, newtons, newtons),
    st.lists(newtons, min_size=2, max_size=2),  # wrong length
    st.fixed_dictionaries({"x": bad_number}),
    st.sampled_from(["push", 3.0, object()]),
    st.builds(
        lambda a: Fixture("wall", ("x", "y"), (a, 0.0), (-1.0, 0.0), 300.0, 0.0, True, 0.0),
        st.sampled_from([math.nan, math.inf]),
    ),
    st.just(Fixture("wall", ("q",), (0.0,), (1.0,), 300.0, 0.0, True, 0.0)),  # no such axis
)
force_action = st.one_of(
    st.just(("hold", None)),
    st.tuples(st.just("new"), good_force),
    st.tuples(st.just("new"), bad_force),
    st.just(("again", None)),
)
lock_action = st.one_of(
    st.just(("hold", None)),
    st.tuples(st.just("new"), st.lists(st.sampled_from(AXES), max_size=3, unique=True)),
    st.tuples(st.just("new"), st.sampled_from([True, False, {"x": True}, "zz", 7])),
)
gap = st.one_of(st.floats(min_value=0.0002, max_value=0.003), st.floats(0.003, 0.2))
tick = st.tuples(gap, force_action, lock_action)


def _locked_by(value: Any) -> set[str]:
    """What the rules say a lock value locks (an unreadable one: every axis)."""
    if value is None:
        return set()
    if isinstance(value, bool):
        return set(AXES) if value else set()
    if isinstance(value, dict):
        return {k for k, v in value.items() if v}
    if isinstance(value, list):
        return set(value)
    return set(AXES)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(tick, min_size=1, max_size=60),
    st.tuples(st.floats(0, 0.3), st.floats(0, 0.2)),
    st.lists(st.sampled_from(AXES), max_size=2, unique=True),
)
def test_the_force_is_safe_whatever_arrives(
    ticks: list[Any], fault: tuple[float, float], param_locks: list[str]
) -> None:
    start, length = fault
    params = {
        "device": "sim",
        "sim": {"faults": [[start, start + length]], "max_force": 10.0},
        "max_force": MAX_FORCE,
        "max_rate": MAX_RATE,
        "timeout": f"{TIMEOUT * 1000:g}ms",
        "rate_hz": RATE_HZ,
        "lock": param_locks,
        "actuator": {"x": [0, 1], "y": [0, 1], "z": [0, 1]},
    }
    h = NodeHarness(Haptic, params, name="haptic")
    held: dict[str, Any] = {}
    published: dict[str, float] = {}
    now = 0.0
    prev_applied = (0.0, 0.0, 0.0)
    prev_target: tuple[float, ...] | None = None
    prev_locked: set[str] = set()
    for dt, (f_kind, f_value), (l_kind, l_value) in ticks:
        now += dt
        h.ctx.time = now
        for port, kind, value in (("force", f_kind, f_value), ("lock", l_kind, l_value)):
            if kind == "new" or (kind == "again" and port in held):
                held[port] = value if kind == "new" else held[port]
                published[port] = now
                h.publish(port, held[port])
        out = h.process(**held)
        applied = out["applied"].values
        device_t = now - h.node.device.t0
        faulty = start <= device_t < start + length
        force = held.get("force")
        stale = force is None or now - published["force"] > TIMEOUT
        invalid = False
        if not stale and not isinstance(force, Fixture):
            invalid = parse_force(force, AXES) is None
        elif not stale:
            bad_fixture = not all(math.isfinite(a) for a in force.anchor) or force.axes == ("q",)
            invalid = bad_fixture
        # (a)
        if stale or invalid or faulty:
            assert applied == (0.0, 0.0, 0.0), (stale, invalid, faulty, out["applied"])
        # (b)
        assert math.sqrt(sum(f * f for f in applied)) <= MAX_FORCE
        # (c)
        if any(applied):  # the first tick comes one period after a zero force
            since = dt if prev_target is not None else 1.0 / RATE_HZ
            step = MAX_RATE * min(since, 2.0 / RATE_HZ)
            change = math.sqrt(
                sum((a - b) ** 2 for a, b in zip(applied, prev_applied, strict=False))
            )
            assert change <= step + 1e-9, (change, step)
        # (d)
        locked = set(param_locks) | _locked_by(held.get("lock"))
        assert set(out["target"].locked) == locked
        target = out["target"].values
        if prev_target is not None:
            for i, axis in enumerate(AXES):
                if axis in locked and axis in prev_locked:
                    assert target[i] == prev_target[i]
        # (e)
        assert tuple(h.node.device.force) == applied
        prev_applied, prev_target, prev_locked = applied, target, locked
    h.teardown()
    assert h.node.device.force == [0.0, 0.0, 0.0]  # zero at stop


def test_a_stale_force_is_zero_and_counted() -> None:
    h = NodeHarness(Haptic, {"timeout": "50ms", "max_rate": 1e5}, name="haptic")
    h.ctx.time = 1.0
    out = h.process(force=(1.0, 0.0, 0.0))
    assert out["applied"].values == (1.0, 0.0, 0.0)
    h.ctx.time = 1.06  # nothing new for 60 ms
    out = h.process(force=(1.0, 0.0, 0.0))  # the same object: its publication time is kept
    assert out["applied"].values == (0.0, 0.0, 0.0)
    assert out["applied"].reason == "stale"
    assert h.node.report()["stale"] == 1


def test_an_old_camera_frame_makes_a_fresh_publication_stale() -> None:
    """A wall republished now from a frame taken 200 ms ago is judged on the frame's time."""
    h = NodeHarness(Haptic, {"timeout": "100ms"}, name="haptic")
    h.ctx.time = 5.0
    wall = Fixture("wall", ("x", "y"), (-50.0, 0.0), (-1.0, 0.0), 300.0, 0.0, True, 4.8)
    out = h.process(force=wall)
    assert out["applied"].reason == "stale"


def test_a_nan_is_refused_counted_once_and_alerted_once() -> None:
    h = NodeHarness(Haptic, {}, name="haptic")
    bad = (math.nan, 0.0, 0.0)
    for i in range(5):
        h.ctx.time = 0.001 * i
        out = h.process(force=bad)
        assert out["applied"].values == (0.0, 0.0, 0.0)
        assert out["applied"].reason == "invalid"
    assert h.node.report()["invalid"] == 1  # one publication, held by the latest edge
    assert [e.alert for e in h.ctx.events] == ["haptic-invalid"]


def test_a_device_fault_zeroes_the_force_and_is_an_error_state() -> None:
    h = NodeHarness(Haptic, {"sim": {"faults": [[0.01, 0.02]]}, "max_rate": 1e5}, name="haptic")
    push = (1.0, 0.0, 0.0)
    seen = []
    for i in range(30):
        h.ctx.time = 0.001 * i
        h.publish("force", push)
        out = h.process(force=push)
        seen.append((out["applied"].reason, h.ctx.error))
    assert seen[5] == ("", None)
    assert seen[15][0] == "device-error"
    assert "motor fault" in (seen[15][1] or "")
    assert seen[25] == ("", None)  # the fault is over: the force and the node are back
    assert h.node.report()["device_errors"] == 1


def test_a_device_reading_nan_is_a_device_error_not_a_nan_force() -> None:
    """A diverged simulation (or a device bug) reads NaN: a wall evaluated there would ask
    for a NaN force; the node treats the reading as a device error and gives zero."""
    h = NodeHarness(Haptic, {"sim": {"hand": {"mode": "none"}}}, name="haptic")
    wall = Fixture("wall", ("x", "y"), (-50.0, 0.0), (-1.0, 0.0), 300.0, 0.0, True, 0.0)
    h.ctx.time = 0.001
    h.node.device.advance(0.0)
    h.node.device.pos[0] = math.nan
    out = h.process(force=wall)
    assert out["applied"].values == (0.0, 0.0, 0.0)
    assert out["applied"].reason == "device-error"
    assert "non-finite" in (h.ctx.error or "")
    assert h.node.device.force == [0.0, 0.0, 0.0]
    assert "target" not in out  # the actuators are not sent to NaN


@pytest.mark.parametrize(
    ("force", "parsed"),
    [
        ({"x": 1.0}, (1.0, 0.0, 0.0)),
        ({"x": 1.0, "timestamp": 3.0}, (1.0, 0.0, 0.0)),
        ({"q": 1.0}, None),  # an axis the device has not: it was a zero force, uncounted
        ({"X": 1.0}, None),
        ({"x": 1.0, "q": 5.0}, None),  # q ignored, x applied
        ({"force": [1, 0, 0]}, None),
    ],
)
def test_a_force_naming_an_axis_the_device_has_not_is_refused(
    force: dict[str, Any], parsed: tuple[float, ...] | None
) -> None:
    assert parse_force(force, AXES) == parsed


def test_a_huge_force_keeps_its_direction_at_max_force() -> None:
    """(the norm's squares overflowed to inf: 1e200 N along x became no force at all)"""
    from flowrt.nodes.haptic.safety import ForceLimiter

    limiter = ForceLimiter(2, max_force=2.0, max_rate=1e9, max_dt=1.0)
    assert limiter.step([1e200, 0.0], 1.0) == pytest.approx((2.0, 0.0))
