"""The arbiter's safety rules (issue 23), as properties on virtual time and end to end.

Properties, for arbitrary interleavings of source values, lock values, silences, republished
objects and NaNs (hypothesis, through the node harness: publication times as an edge stamps
them):

(a) while any lock is engaged the output is exactly ``zero``;
(b) the output is ``zero`` or the command of a source fresh and valid at that tick (or the
    blend of those), never a stale or non-finite one;
(c) a command is published on every activation.

End to end (a Runtime on a virtual clock): an e-stop published once keeps the robot at zero
until ``False``; a silent heartbeat lock stops it within heartbeat + 3 ticks; a source that
publishes the same object every tick keeps its command passing; NaN falls back to the next
source.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
from flowrt.nodes.arbiter import Arbiter, valid_command
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock
from flowrt.testing import NodeHarness

KEYS = ["vx", "w"]
ZERO = {"vx": 0.0, "w": 0.0}
TIMEOUT = 0.1
HEARTBEAT = 0.3

finite = st.floats(min_value=-5, max_value=5, allow_nan=False)
bad = st.sampled_from([math.nan, math.inf, -math.inf, "fast", None, True, 10**400])
command = st.one_of(
    st.fixed_dictionaries({"vx": finite, "w": finite}),
    st.fixed_dictionaries({"vx": bad, "w": finite}),
    st.fixed_dictionaries({"vx": finite}),  # a missing key counts as 0
)
# per source, per tick: keep what the edge holds, publish a new value, or republish the same
source_action = st.one_of(
    st.just(("hold", None)), st.tuples(st.just("new"), command), st.just(("again", None))
)
lock_action = st.sampled_from(["hold", "hold", "hold", True, False, "again"])
tick = st.tuples(
    st.floats(min_value=0.005, max_value=0.15),  # time to the next activation
    source_action,
    source_action,
    lock_action,
)


class Model:
    """What the rules say, computed apart from the arbiter."""

    def __init__(self, heartbeat: float | None, initial: str) -> None:
        self.held: dict[str, Any] = {}
        self.published: dict[str, float] = {}
        self.heartbeat = heartbeat
        self.initial = initial
        self.start: float | None = None

    def fresh_command(self, name: str, now: float) -> dict[str, float] | None:
        if name not in self.held or now - self.published[name] > TIMEOUT:
            return None
        value = self.held[name]
        if not valid_command(value, KEYS):
            return None
        return {k: float(value.get(k, 0.0)) for k in KEYS}

    def locked(self, now: float) -> bool:
        if "estop" in self.held:
            value = self.held["estop"]
            engaged = bool(value)
        else:
            engaged = self.initial == "engaged"
        if self.heartbeat is not None and not engaged:
            assert self.start is not None
            last = self.published.get("estop", self.start)
            engaged = now - last > self.heartbeat
        return engaged


def run_ticks(mode: str, heartbeat: float | None, initial: str, ticks: list[Any]) -> None:
    lock: dict[str, Any] = {"initial": initial}
    if heartbeat is not None:
        lock["heartbeat"] = f"{heartbeat * 1000:g}ms"
    params = {
        "mode": mode,
        "timeout": f"{TIMEOUT * 1000:g}ms",
        "sources": {"a": {"priority": 10}, "b": {"priority": 5, "weight": 3.0}},
        "locks": {"estop": lock},
        "zero": ZERO,
    }
    h = NodeHarness(Arbiter, params, name="drive")
    model = Model(heartbeat, initial)
    now = 0.0
    for dt, act_a, act_b, act_lock in ticks:
        now += dt
        h.ctx.time = now
        if model.start is None:
            model.start = now
        for name, (kind, value) in (("a", act_a), ("b", act_b)):
            if kind == "new" or (kind == "again" and name in model.held):
                value = value if kind == "new" else model.held[name]
                model.held[name], model.published[name] = value, now
                h.publish(name, value)
        if act_lock in (True, False) or (act_lock == "again" and "estop" in model.held):
            value = act_lock if act_lock != "again" else model.held["estop"]
            model.held["estop"], model.published["estop"] = value, now
            h.publish("estop", value)
        out = h.process(**model.held)
        # (c) a command on every activation
        assert isinstance(out, dict)
        assert set(out["command"]) == set(KEYS)
        cmd = out["command"]
        assert all(math.isfinite(x) for x in cmd.values())
        fresh = {n: c for n in ("a", "b") if (c := model.fresh_command(n, now)) is not None}
        if model.locked(now):  # (a)
            assert cmd == ZERO
            assert out["selected"] is None
            continue
        # (b) zero, or a fresh source's command, or the blend of the fresh ones
        if not fresh:
            assert cmd == ZERO
            assert out["selected"] is None
        elif mode == "priority":
            want = "a" if "a" in fresh else "b"
            assert out["selected"] == want
            assert cmd == fresh[want]
        else:
            weights = {"a": 1.0, "b": 3.0}
            total = sum(weights[n] for n in fresh)
            for k in KEYS:
                expect = sum(weights[n] * fresh[n][k] for n in fresh) / total
                assert cmd[k] == pytest.approx(expect, abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(
    mode=st.sampled_from(["priority", "blend"]),
    heartbeat=st.sampled_from([None, HEARTBEAT]),
    initial=st.sampled_from(["engaged", "released"]),
    ticks=st.lists(tick, min_size=1, max_size=40),
)
def test_arbiter_safety_rules_hold_for_any_interleaving(
    mode: str, heartbeat: float | None, initial: str, ticks: list[Any]
) -> None:
    run_ticks(mode, heartbeat, initial, ticks)


def test_invalid_commands_are_counted_once_per_publication_and_alerted_once_per_burst() -> None:
    h = NodeHarness(
        Arbiter,
        {"sources": {"a": {"priority": 10}, "b": {}}, "locks": [], "zero": ZERO},
        name="drive",
    )
    bad_cmd = {"vx": math.nan, "w": 0.0}
    good = {"vx": 0.5, "w": 0.0}
    for k in range(5):  # the same NaN held for 5 ticks: one publication
        h.ctx.time = 0.02 * k
        out = h.process(a=bad_cmd, b=good)
        assert out["selected"] == "b"
        assert out["command"] == good
    h.ctx.time = 0.12
    h.publish("a", {"vx": math.inf, "w": 0.0})
    h.process(a={"vx": math.inf, "w": 0.0}, b=good)
    report = h.node.report()
    assert report["sources"]["a"]["invalid"] == 2
    assert report["invalid"] == 2
    alerts = [e for e in h.ctx.events if getattr(e, "alert", "") == "arbiter-invalid"]
    assert len(alerts) == 1  # one burst
    h.ctx.time = 0.14
    assert h.process(a={"vx": 1.0, "w": 0.0}, b=good)["selected"] == "a"  # burst over
    h.ctx.time = 0.16
    h.process(a={"vx": "fast", "w": 0.0}, b=good)
    alerts = [e for e in h.ctx.events if getattr(e, "alert", "") == "arbiter-invalid"]
    assert len(alerts) == 2


def test_commands_are_clamped_to_their_limits_and_counted() -> None:
    """Issue 37 item 10: ``vx: 1e300`` was forwarded to the actuator as it came."""
    h = NodeHarness(
        Arbiter,
        {"sources": {"a": {}}, "zero": ZERO, "limits": {"vx": [-0.5, 1.5]}},
        name="drive",
    )
    for k, vx in enumerate([1e300, 1e300, -7.0, 1.0]):
        h.ctx.time = 0.02 * k
        h.publish("a", {"vx": vx, "w": 1e6})
        out = h.process(a={"vx": vx, "w": 1e6})
        assert out["command"]["w"] == 100.0  # the default limit of a key not named
        assert out["command"]["vx"] == min(1.5, max(-0.5, vx))
    report = h.node.report()
    assert report["clamped"] == 4  # every publication held a key past its limit
    alerts = [e for e in h.ctx.events if getattr(e, "alert", "") == "arbiter-clamped"]
    assert len(alerts) == 1  # one burst
    with pytest.raises(ValueError, match="min <= max"):
        Arbiter.Params.model_validate(
            {"sources": {"a": {}}, "zero": ZERO, "limits": {"vx": [2, 1]}}
        )
    with pytest.raises(ValueError, match="zero command outside"):
        Arbiter.Params.model_validate(
            {"sources": {"a": {}}, "zero": ZERO, "limits": {"vx": [0.1, 1]}}
        )
    assert Arbiter.Params.model_validate(
        {"sources": {"a": {}}, "zero": ZERO, "limits": {"vx": 2}}
    ).bounds("vx") == (-2, 2)


@pytest.mark.parametrize(
    "locks",
    [
        ["estop"],
        {"estop": None},
        {"estop": {"heartbeat": "300ms"}},
        {"estop": {"heartbeat": 300, "initial": "released"}},
    ],
)
def test_both_forms_of_locks_are_accepted(locks: Any) -> None:
    p = Arbiter.Params.model_validate({"sources": {"a": {}}, "locks": locks, "zero": ZERO})
    assert list(p.locks) == ["estop"]


@pytest.mark.parametrize(
    "bad_value", [None, [1, 2], {"a": 1}, 10**400, "fast", True, math.nan, "0ms"]
)
@pytest.mark.parametrize("field", ["timeout", "low_pass", "heartbeat"])
def test_duration_params_refuse_every_bad_value_as_a_validation_error(
    field: str, bad_value: Any
) -> None:
    from pydantic import ValidationError

    base: dict[str, Any] = {"sources": {"a": {}}, "zero": ZERO}
    if field == "timeout":
        base["timeout"] = bad_value
    elif field == "low_pass":
        base["sources"] = {"a": {"low_pass": bad_value}}
        if bad_value is None:
            return  # null is "no filter" here
    else:
        base["locks"] = {"estop": {"heartbeat": bad_value}}
        if bad_value is None:
            return  # null is "no heartbeat"
    with pytest.raises(ValidationError):
        Arbiter.Params.model_validate(base)


# --- end to end, on a virtual clock ------------------------------------------------------


class Source(Node):
    """A node the test publishes through (never activated by itself)."""

    out = Output(object)


def drive_graph(locks: Any) -> GraphBuilder:
    g = GraphBuilder("drive")
    for name in ("joy", "plan", "estop"):
        g.add(name, Source, trigger={"timer": 3_600_000}, enabled=False)
    g.add(
        "drive",
        "arbiter",
        trigger={"timer": 20},
        params={
            "timeout": "200ms",
            "sources": {"joy": {"priority": 100}, "plan": {"priority": 10}},
            "locks": locks,
            "zero": ZERO,
        },
        inputs={"joy": "joy.out", "plan": "plan.out", "estop": "estop.out"},
    )
    return g


async def steer(rt: Runtime, clock: VirtualClock, sub: Any, joy: Any, n: int) -> list[Any]:
    """``joy`` published on every one of ``n`` ticks of 20 ms: the commands that came out."""
    for _ in range(n):
        rt.publish("joy.out", joy)  # the same object every tick: stays fresh
        await clock.advance(0.02)
    return [v for v in sub.drain()]


async def test_an_estop_published_once_keeps_zero_until_false() -> None:
    clock = VirtualClock()
    async with Runtime(drive_graph(["estop"]).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.2}
        rt.publish("estop.out", False)
        moving = await steer(rt, clock, sub, joy, 10)
        assert moving[-1] == joy
        rt.publish("estop.out", True)  # once, as a button publishing on change does
        stopped = await steer(rt, clock, sub, joy, 75)  # 1.5 s, far past the 200 ms timeout
        assert len(stopped) >= 70
        assert all(c == ZERO for c in stopped)
        rt.publish("estop.out", False)
        assert (await steer(rt, clock, sub, joy, 5))[-1] == joy


async def test_a_disabled_arbiter_publishes_the_zero_command_once() -> None:
    """A mode or a program disabling the arbiter left the actuator's driver on the last
    command it had (a CAN transmitter resends it): the zero command is published at once;
    enabled again, it steers from zero."""
    clock = VirtualClock()
    async with Runtime(drive_graph(["estop"]).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.2}
        rt.publish("estop.out", False)
        assert (await steer(rt, clock, sub, joy, 10))[-1] == joy
        rt.set_timing("drive", enabled=False)
        assert sub.drain() == [ZERO]  # at once, before any tick
        assert await steer(rt, clock, sub, joy, 20) == []  # disabled: nothing more
        rt.set_timing("drive", enabled=True)
        assert (await steer(rt, clock, sub, joy, 5))[-1] == joy


@pytest.mark.parametrize(
    ("value", "moves"),
    [
        (False, True),
        (0, True),
        ({"active": False, "release": 3}, True),
        ({"pressed": False}, True),
        # truthiness released these: only a false value does; each is counted
        ({}, False),
        ([], False),
        ("", False),
        (0.0, False),
        ({"active": None}, False),
        ({"release": "x"}, False),
        ("false", False),
        (float("nan"), False),
    ],
)
async def test_only_a_false_value_releases_a_lock(value: Any, moves: bool) -> None:
    clock = VirtualClock()
    async with Runtime(drive_graph(["estop"]).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.2}
        rt.publish("estop.out", value)
        assert ((await steer(rt, clock, sub, joy, 5))[-1] == joy) is moves, value
        invalid = rt.stats().reports["drive"]["locks_invalid"]
        assert invalid == ({} if moves else {"estop": 1}), invalid


async def test_a_silent_heartbeat_lock_stops_within_heartbeat_plus_three_ticks() -> None:
    clock = VirtualClock()
    graph = drive_graph({"estop": {"heartbeat": "300ms"}}).build()
    async with Runtime(graph, clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.0}
        for _ in range(10):
            rt.publish("estop.out", False)
            rt.publish("joy.out", joy)
            await clock.advance(0.02)
        assert sub.drain()[-1] == joy
        silent_from = clock.now()
        first_zero: float | None = None
        for _ in range(40):  # the e-stop node died: nothing more from it
            rt.publish("joy.out", joy)
            await clock.advance(0.02)
            if first_zero is None and any(c == ZERO for c in sub.drain()):
                first_zero = clock.now()
        assert first_zero is not None
        assert first_zero - silent_from <= 0.300 + 3 * 0.020 + 1e-9


async def test_a_nan_command_is_never_passed_on_and_the_next_source_is_used() -> None:
    clock = VirtualClock()
    async with Runtime(drive_graph({"estop": {"initial": "released"}}).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        sel = rt.subscribe("drive.selected", size=1000)
        plan = {"vx": 0.3, "w": 0.0}
        for _ in range(20):
            rt.publish("joy.out", {"vx": math.nan, "w": 0.0})
            rt.publish("plan.out", plan)
            await clock.advance(0.02)
        commands = sub.drain()
        assert commands
        assert all(c == plan for c in commands)
        assert set(sel.drain()) == {"plan"}
        report = rt.stats().reports["drive"]
        assert report["sources"]["joy"]["invalid"] == 20


async def _beat(rt: Runtime, clock: VirtualClock, estop: Any, joy: Any, n: int) -> None:
    for _ in range(n):
        if estop is not None:
            rt.publish("estop.out", estop)
        rt.publish("joy.out", joy)
        await clock.advance(0.02)


@pytest.mark.parametrize("kind", ["release-id", "boolean"])
async def test_after_silence_hold_needs_a_new_release(kind: str) -> None:
    """Issue 40: a link cut engages the lock; the station coming back still saying
    "released" does not free it: only a new release does (a new id, or true then false)."""
    clock = VirtualClock()
    locks = {"estop": {"heartbeat": "300ms", "after_silence": "hold"}}
    async with Runtime(drive_graph(locks).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.0}
        engaged = {"active": True, "release": None} if kind == "release-id" else True
        released = {"active": False, "release": "r1"} if kind == "release-id" else False
        await _beat(rt, clock, engaged, joy, 5)  # the station engaged when first heard
        await _beat(rt, clock, released, joy, 10)  # then the operator's release
        assert sub.drain()[-1] == joy
        await _beat(rt, clock, None, joy, 25)  # the link is cut for 0.5 s
        assert sub.drain()[-1] == ZERO
        await _beat(rt, clock, released, joy, 50)  # back, still "released": held at zero
        held = sub.drain()
        assert len(held) >= 45
        assert all(c == ZERO for c in held)
        assert rt.stats().reports["drive"]["held"] == ["estop"]
        if kind == "release-id":  # the operator releases again: a release of its own
            await _beat(rt, clock, {"active": False, "release": "r2"}, joy, 5)
        else:
            await _beat(rt, clock, True, joy, 2)
            assert sub.drain()[-1] == ZERO
            await _beat(rt, clock, False, joy, 5)
        assert sub.drain()[-1] == joy
        assert rt.stats().reports["drive"]["held"] == []


async def test_after_silence_hold_a_release_from_before_the_start_does_not_count() -> None:
    """A restarted robot hears a station released long ago: it stays at zero until the
    operator releases again (a new id)."""
    clock = VirtualClock()
    locks = {"estop": {"heartbeat": "300ms", "after_silence": "hold"}}
    async with Runtime(drive_graph(locks).build(), clock=clock) as rt:
        sub = rt.subscribe("drive.command", size=1000)
        joy = {"vx": 1.0, "w": 0.0}
        await _beat(rt, clock, {"active": False, "release": "old"}, joy, 20)
        assert all(c == ZERO for c in sub.drain())
        await _beat(rt, clock, {"active": False, "release": "new"}, joy, 5)
        assert sub.drain()[-1] == joy
