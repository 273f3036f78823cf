"""Teleoperation: input shaping, locks, the safe-start state machine, the joystick sources and
the arbiter, through the node harness (virtual time: ``h.ctx.time``)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from flowrt.nodes.arbiter import Arbiter
from flowrt.nodes.joystick import JoyState, Joystick, load_script
from flowrt.nodes.teleop import AxisShaping, Teleop, shape
from pydantic import ValidationError

from flowrt import GraphBuilder, GraphError
from flowrt.testing import NodeHarness

# --- shaping ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("x", "params", "expected"),
    [
        (0.0, {}, 0.0),
        (0.05, {"dead_band": 0.1}, 0.0),  # inside the band
        (-0.1, {"dead_band": 0.1}, 0.0),  # on its edge
        (1.0, {"dead_band": 0.1}, 1.0),  # full scale still reachable
        (-1.0, {"dead_band": 0.1}, -1.0),
        (0.55, {"dead_band": 0.1}, 0.5),  # re-scaled: (0.55 - 0.1) / 0.9
        (0.5, {"dead_band": 0.0, "scale": 2.0}, 1.0),
        (0.5, {"dead_band": 0.0, "invert": True}, -0.5),
        (0.5, {"dead_band": 0.0, "curve": "expo", "expo": 1.0}, 0.125),
        (0.5, {"dead_band": 0.0, "curve": "expo", "expo": 0.5}, 0.3125),
        (3.0, {"dead_band": 0.0}, 1.0),  # clamped
        (math.nan, {}, 0.0),
    ],
)
def test_shape(x: float, params: dict[str, object], expected: float) -> None:
    assert shape(x, AxisShaping(input="x", **params)) == pytest.approx(expected)


def test_dead_band_is_continuous() -> None:
    a = AxisShaping(input="x", dead_band=0.2)
    just_out = shape(0.2 + 1e-9, a)
    assert 0 < just_out < 1e-6
    xs = [i / 1000 for i in range(1001)]
    ys = [shape(x, a) for x in xs]
    assert all(abs(b - c) < 0.002 for b, c in itertools.pairwise(ys))


# --- the state machine --------------------------------------------------------------------

AXES = {"vx": {"input": "y", "dead_band": 0.0}, "w": {"input": "x", "dead_band": 0.0}}


def joy(t: float, x: float = 0.0, y: float = 0.0, **buttons: bool) -> JoyState:
    return JoyState({"x": x, "y": y}, dict(buttons), t)


def teleop(**params: object) -> NodeHarness:
    h = NodeHarness(Teleop, {"axes": AXES, **params}, name="tele")
    h.ctx.timer_period = 0.02
    return h


def step(h: NodeHarness, t: float, value: JoyState | None) -> dict[str, object]:
    h.ctx.time = t
    return h.process(joy=value)


def start(h: NodeHarness, t: float = 0.0) -> float:
    """Click start with centred sticks: idle -> initialization -> run."""
    step(h, t, joy(t))
    step(h, t + 0.02, joy(t + 0.02, start=True))
    out = step(h, t + 0.04, joy(t + 0.04))
    assert out["mode"] == "run"
    return t + 0.04


def test_idle_gives_zero_until_started() -> None:
    h = teleop()
    out = step(h, 0.0, joy(0.0, y=0.8))
    assert out == {"command": {"vx": 0.0, "w": 0.0}, "mode": "idle"}


def test_initialization_holds_zero_until_every_axis_is_centred() -> None:
    h = teleop()
    step(h, 0.0, joy(0.0, y=0.8))
    out = step(h, 0.02, joy(0.02, y=0.8, start=True))
    assert out["mode"] == "initialization"
    assert out["command"] == {"vx": 0.0, "w": 0.0}
    out = step(h, 0.04, joy(0.04, y=0.8))  # still deflected
    assert out["mode"] == "initialization"
    out = step(h, 0.06, joy(0.06, y=0.0))  # centred
    assert out["mode"] == "run"
    out = step(h, 0.08, joy(0.08, y=0.5))
    assert out["command"]["vx"] == pytest.approx(0.5)


def test_stale_input_gives_zero_on_every_tick_and_falls_back() -> None:
    h = teleop()
    t = start(h)
    last = joy(t + 0.02, y=0.7)
    assert step(h, t + 0.02, last)["command"]["vx"] == pytest.approx(0.7)
    # The joystick stops publishing: the same (old) value is read again on each tick.
    outs = [step(h, t + 0.02 + k * 0.02, last) for k in range(1, 10)]
    late = [o for o in outs if o["mode"] != "run"]
    assert late, "the timeout (3 periods = 60 ms) must end run"
    for o in late:
        assert o["command"] == {"vx": 0.0, "w": 0.0}
        assert o["mode"] == "initialization"
    assert len(late) >= 6  # zero on every tick, not once


def test_no_input_at_all_is_zero() -> None:
    h = teleop()
    start(h)
    for k in range(5):
        out = step(h, 1.0 + k * 0.02, None)
        assert out["command"] == {"vx": 0.0, "w": 0.0}


def test_deadman_must_be_held_in_run() -> None:
    h = teleop(buttons={"start": "a", "stop": "b", "deadman": "lb"})
    step(h, 0.0, joy(0.0))
    step(h, 0.02, joy(0.02, a=True))
    out = step(h, 0.04, joy(0.04))  # centred but deadman not held
    assert out["mode"] == "initialization"
    out = step(h, 0.06, joy(0.06, lb=True))
    assert out["mode"] == "run"
    assert step(h, 0.08, joy(0.08, y=0.4, lb=True))["command"]["vx"] == pytest.approx(0.4)
    for k in range(3):  # released: zero on every tick
        out = step(h, 0.10 + 0.02 * k, joy(0.10 + 0.02 * k, y=0.4))
        assert out["command"] == {"vx": 0.0, "w": 0.0}
        assert out["mode"] == "initialization"


def test_stop_click_returns_to_idle_from_run() -> None:
    h = teleop()
    t = start(h)
    out = step(h, t + 0.02, joy(t + 0.02, y=0.5, stop=True))
    assert out["mode"] == "idle"
    assert out["command"] == {"vx": 0.0, "w": 0.0}


def test_held_start_button_is_one_click() -> None:
    h = teleop(calibration=True)
    step(h, 0.0, joy(0.0))
    assert step(h, 0.02, joy(0.02, start=True))["mode"] == "calibration"
    assert step(h, 0.04, joy(0.04, start=True))["mode"] == "calibration"  # still held
    step(h, 0.06, joy(0.06))
    assert step(h, 0.08, joy(0.08, start=True))["mode"] in ("initialization", "run")


def test_calibration_records_centre_and_range() -> None:
    h = teleop(calibration=True)
    step(h, 0.0, joy(0.0, y=0.1))
    step(h, 0.02, joy(0.02, y=0.1, start=True))  # centre: 0.1
    for k, y in enumerate((0.6, -0.4, 0.1)):  # range: +0.5 / -0.5 around the centre
        step(h, 0.04 + 0.02 * k, joy(0.04 + 0.02 * k, y=y))
    step(h, 0.12, joy(0.12, y=0.1, start=True))
    out = step(h, 0.14, joy(0.14, y=0.1))
    assert out["mode"] == "run"
    assert out["command"]["vx"] == pytest.approx(0.0)
    assert step(h, 0.16, joy(0.16, y=0.6))["command"]["vx"] == pytest.approx(1.0)
    assert step(h, 0.18, joy(0.18, y=0.35))["command"]["vx"] == pytest.approx(0.5)


def test_every_transition_is_an_event() -> None:
    h = teleop()
    t = start(h)
    step(h, t + 0.02, joy(t + 0.02, stop=True))
    kinds = [(e.alert, e.detail.split(":")[0]) for e in h.ctx.events]
    assert kinds == [
        ("teleop-state", "idle -> initialization"),
        ("teleop-state", "initialization -> run"),
        ("teleop-state", "run -> idle"),
    ]


def test_rate_limit() -> None:
    axes = {"vx": {"input": "y", "dead_band": 0.0, "max_rate": 1.0}}
    h = NodeHarness(Teleop, {"axes": axes}, name="tele")
    h.ctx.timer_period = 0.1
    t = 0.0
    for b in (False, True, False):
        h.ctx.time = t
        h.process(joy=JoyState({"y": 0.0}, {"start": b}, t))
        t += 0.1
    outs = []
    for _ in range(4):
        h.ctx.time = t
        outs.append(h.process(joy=JoyState({"y": 1.0}, {}, t))["command"]["vx"])
        t += 0.1
    assert outs == pytest.approx([0.1, 0.2, 0.3, 0.4])


def test_locked_axis_discards_input_and_holds_its_value() -> None:
    axes = {
        "vx": {"input": "y", "dead_band": 0.0},
        "w": {"input": "x", "dead_band": 0.0, "lock": {"value": 0.25, "button": "u"}},
    }
    h = NodeHarness(Teleop, {"axes": axes}, name="tele")
    t = start(h)
    out = step(h, t + 0.02, joy(t + 0.02, x=0.9, y=0.3))
    assert out["command"] == pytest.approx({"vx": 0.3, "w": 0.25})
    step(h, t + 0.04, joy(t + 0.04, x=0.9, y=0.3, u=True))  # unlock
    out = step(h, t + 0.06, joy(t + 0.06, x=0.9, y=0.3))
    assert out["command"]["w"] == pytest.approx(0.9)


def test_locked_axis_with_measured_state_is_a_p_controller() -> None:
    axes = {
        "w": {
            "input": "x",
            "dead_band": 0.0,
            "scale": 1.0,
            "lock": {"value": 1.0, "field": "heading", "gain": 0.5},
        }
    }
    h = NodeHarness(Teleop, {"axes": axes}, name="tele")
    h.ctx.time = 0.0
    h.process(joy=joy(0.0))
    h.ctx.time = 0.02
    h.process(joy=joy(0.02, start=True))
    h.ctx.time = 0.04
    out = h.process(joy=joy(0.04, x=-1.0), state={"heading": 0.2})
    assert out["command"]["w"] == pytest.approx(0.4)  # 0.5 * (1.0 - 0.2)
    h.ctx.time = 0.06
    out = h.process(joy=joy(0.06), state={"heading": -5.0})
    assert out["command"]["w"] == pytest.approx(1.0)  # clamped to scale


@pytest.mark.parametrize(
    "params",
    [
        {"axes": {}},
        {"axes": {"vx": {"input": "y", "dead_band": 1.0}}},
        {"axes": {"vx": {"input": "y", "scale": math.inf}}},
        {"axes": {"vx": {"input": "y"}}, "buttons": {"start": "a", "stop": "a"}},
        {"axes": {"vx": {"input": "y"}}, "timeout_ms": math.nan},
    ],
)
def test_teleop_params_refused(params: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        Teleop.Params.model_validate(params)


# --- joystick sources ---------------------------------------------------------------------


def test_script_joystick(tmp_path: Path) -> None:
    script = tmp_path / "drive.csv"
    script.write_text("time,x,axis:y,button:a\n0,0,0,0\n0.1,0.5,-0.5,1\n0.3,2,0,0\n")
    assert load_script(script)[2][1] == {"x": 1.0, "y": 0.0}  # clamped to [-1, 1]
    h = NodeHarness(Joystick, {"source": f"script:{script}", "end": "silent"})
    seen = []
    for k in range(6):
        h.ctx.time = 10.0 + k * 0.1
        seen.append(h.process())
    assert seen[0] == JoyState({"x": 0.0, "y": 0.0}, {"a": False}, 10.0)
    assert seen[1].axes == {"x": 0.5, "y": -0.5}
    assert seen[1].buttons == {"a": True}
    assert seen[3].axes == {"x": 1.0, "y": 0.0}
    assert seen[4] is None
    assert seen[5] is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x,y\n0,1\n", "first column must be 'time'"),
        ("time,x\n0,abc\n", "not a number"),
        ("time,x\n0,1,2\n", "expected 2 finite numbers"),
        ("time,x\n0,nan\n", "expected 2 finite numbers"),
    ],
)
def test_bad_script(tmp_path: Path, text: str, message: str) -> None:
    script = tmp_path / "bad.csv"
    script.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_script(script)
    # and at validate, located (it passed flowrt validate and failed the run)
    g = GraphBuilder("j")
    g.add("j", "joystick", params={"source": f"script:{script}"})
    with pytest.raises(GraphError, match=message):
        g.build()


def test_missing_evdev_device_is_an_error_state_and_reopened() -> None:
    h = NodeHarness(Joystick, {"source": "evdev:/dev/input/event-missing", "reopen_ms": 100})
    h.ctx.time = 0.0
    assert h.process() is None
    assert h.ctx.error is not None
    assert "event-missing" in h.ctx.error
    assert h.node.attempts == 1
    h.ctx.time = 0.05
    h.process()
    assert h.node.attempts == 1  # backoff
    h.ctx.time = 0.2
    h.process()
    assert h.node.attempts == 2


# --- arbiter ------------------------------------------------------------------------------

ZERO = {"vx": 0.0, "w": 0.0}


def arbiter(**params: object) -> NodeHarness:
    base: dict[str, object] = {
        "timeout": "100ms",
        "sources": {"joy": {"priority": 100}, "plan": {"priority": 10}},
        "locks": ["estop"],
        "zero": ZERO,
    }
    base.update(params)
    return NodeHarness(Arbiter, base, name="drive")


def arb(h: NodeHarness, t: float, **inputs: object) -> dict[str, object]:
    """One activation at ``t``; the lock ``estop`` released unless given (it latches)."""
    h.ctx.time = t
    if "estop" in h.node.params.locks:
        inputs.setdefault("estop", RELEASED)
    return h.process(**inputs)


RELEASED = False


def test_priority_highest_fresh_source_wins() -> None:
    h = arbiter()
    j, p = {"vx": 1.0, "w": 0.1}, {"vx": 0.2, "w": 0.0}
    assert arb(h, 0.0, joy=j, plan=p) == {"command": j, "selected": "joy"}
    # joy goes stale (same object read again), plan keeps publishing new values
    out = arb(h, 0.15, joy=j, plan={"vx": 0.3, "w": 0.0})
    assert out == {"command": {"vx": 0.3, "w": 0.0}, "selected": "plan"}
    assert h.node.switches == 2


def test_no_fresh_source_gives_zero_every_time() -> None:
    h = arbiter()
    j = {"vx": 1.0, "w": 0.1}
    arb(h, 0.0, joy=j)
    for k in range(1, 6):
        out = arb(h, 0.1 + k * 0.05, joy=j)  # never a stale command
        assert out == {"command": ZERO, "selected": None}


def test_lock_forces_zero() -> None:
    h = arbiter()
    j = {"vx": 1.0, "w": 0.1}
    assert arb(h, 0.0, joy=j, estop={"active": True})["command"] == ZERO
    assert arb(h, 0.01, joy={"vx": 1.0, "w": 0.1}, estop=False)["command"] == j


def test_a_lock_latches_until_a_false_value() -> None:
    h = arbiter()
    stop = {"active": True}
    assert arb(h, 0.0, joy={"vx": 1.0, "w": 0.0}, estop=stop)["selected"] is None
    assert arb(h, 5.0, joy={"vx": 1.0, "w": 0.0}, estop=stop)["selected"] is None
    assert arb(h, 5.1, joy={"vx": 1.0, "w": 0.0}, estop={"active": False})["selected"] == "joy"


def test_blend_renormalises_over_fresh_sources() -> None:
    h = arbiter(mode="blend", sources={"a": {"weight": 1.0}, "b": {"weight": 3.0}}, locks=[])
    out = arb(h, 0.0, a={"vx": 1.0, "w": 0.0}, b={"vx": 0.0, "w": 1.0})
    assert out["selected"] == "blend"
    assert out["command"] == pytest.approx({"vx": 0.25, "w": 0.75})
    b = {"vx": 0.0, "w": 1.0}
    arb(h, 0.05, a={"vx": 1.0, "w": 0.0}, b=b)
    out = arb(h, 0.2, a={"vx": 1.0, "w": 0.0}, b=b)  # b stale: a alone, weight 1 of 1
    assert out["command"] == pytest.approx({"vx": 1.0, "w": 0.0})


def test_blend_filters() -> None:
    h = arbiter(mode="blend", sources={"a": {"max_rate": 1.0}}, locks=[], timeout="1s")
    outs = [arb(h, 0.1 * k, a={"vx": 1.0, "w": 0.0})["command"]["vx"] for k in range(4)]
    assert outs == pytest.approx([0.0, 0.1, 0.2, 0.3])
    h = arbiter(mode="blend", sources={"a": {"low_pass": "100ms"}}, locks=[], timeout="1s")
    outs = [arb(h, 0.1 * k, a={"vx": 1.0, "w": 0.0})["command"]["vx"] for k in range(3)]
    assert outs == pytest.approx([0.0, 0.5, 0.75])


def test_timestamp_of_the_value_decides_freshness() -> None:
    h = arbiter()
    old = JoyState(timestamp=0.0)
    assert arb(h, 0.5, joy={"vx": 1.0, "w": 0.0, "timestamp": 0.0})["selected"] is None
    assert old.timestamp == 0.0


@pytest.mark.parametrize(
    "params",
    [
        {"timeout": "0ms"},
        {"timeout": "nan"},
        {"zero": {}},
        {"zero": {"vx": math.inf}},
        {"locks": ["joy"]},
        {"sources": {}},
    ],
)
def test_arbiter_params_refused(params: dict[str, object]) -> None:
    base: dict[str, object] = {"sources": {"joy": {}}, "zero": ZERO}
    base.update(params)
    with pytest.raises(ValidationError):
        Arbiter.Params.model_validate(base)


async def test_a_web_joystick_without_a_page_is_waiting_not_an_error() -> None:
    """Issue 43 item 6: a headless station ended with ``node joy in error: no live view page
    is sending``, exit 1. Waiting for an operator is a state, shown as such."""
    from flowrt import GraphBuilder, Runtime, VirtualClock

    g = GraphBuilder("station")
    g.add("joy", "joystick", params={"source": "web", "web_timeout_ms": 100})
    g.add("sink", "sink", inputs={"input": "joy.output"})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.5)
        node = rt.stats().node("joy")
        assert (node.state, rt.failures()) == ("waiting", [])
        assert "waiting for an operator" in node.reason
        rt.rtdb.write("joystick.web", {"axes": {"x": 0.2}, "buttons": {}}, validity_ms=500)
        await clock.advance(0.05)
        assert rt.stats().node("joy").state in ("idle", "running")
        await clock.advance(0.5)  # the page went silent
        node = rt.stats().node("joy")
        assert (node.state, rt.failures()) == ("waiting", [])
        assert "stopped sending" in node.reason
    assert node.errors == 0


@pytest.mark.parametrize(
    ("end", "expected"),
    [
        # the last row (the deadman let go) held as long as the gap before it, then row 0
        ("loop", [0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0]),
        ("hold", [0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
        ("silent", [0.0, 0.0, 0.5, 0.5, 0.0, None, None, None, None, None, None]),
    ],
)
def test_a_script_s_last_row_is_published_whatever_its_end(
    tmp_path: Path, end: str, expected: list[float | None]
) -> None:
    """A looping script's last row was held 1 ms: never published, the row before it
    (driving, deadman held) went on for the rest of the run."""
    script = tmp_path / "drive.csv"
    script.write_text("time,y,button:tl\n0,0,0\n0.2,0.5,1\n0.4,0,0\n")
    h = NodeHarness(Joystick, {"source": f"script:{script}", "end": end})
    seen = []
    for k in range(11):
        h.ctx.time = 10.0 + k * 0.1 + 0.01
        out = h.process()
        seen.append(None if out is None else out.axes["y"])
    assert seen == expected
