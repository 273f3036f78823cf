"""The haptic devices (issue 42): the simulated handle, evdev against a fake device object,
and the node's reactions to a device that fails, comes back, or has buttons."""

from __future__ import annotations

import math
import re
from collections import deque
from typing import Any

import evdev
import pytest
from evdev import ecodes
from flowrt.nodes.haptic import DeviceError, Haptic, SimDevice, make_device
from flowrt.nodes.haptic.evdev_device import EvdevDevice, EvdevParams
from flowrt.nodes.haptic.sim import SimParams

from flowrt import FatalError, GraphBuilder, GraphError
from flowrt.testing import HarnessContext, NodeHarness


def _run(dev: SimDevice, seconds: float, force: tuple[float, float, float] = (0, 0, 0)) -> Any:
    dev.open()
    state = dev.read_state(0.0)
    for i in range(1, int(seconds * 1000) + 1):
        dev.apply_force(force, (i - 1) / 1000)
        state = dev.read_state(i / 1000)
    return state


def test_the_hand_pulls_the_handle_to_its_target() -> None:
    state = _run(SimDevice(SimParams(hand={"target": (60, -20, 10)})), 3.0)
    assert state.position == pytest.approx((60, -20, 10), abs=0.5)


def test_a_force_holds_the_hand_back_like_a_spring_would() -> None:
    """At rest, the device force balances the hand: 40 N/m x (60 mm - x) = 1 N -> x = 35 mm."""
    state = _run(SimDevice(SimParams()), 4.0, force=(-1.0, 0.0, 0.0))
    assert state.position[0] == pytest.approx(35.0, abs=0.5)


def test_the_workspace_is_a_hard_stop() -> None:
    dev = SimDevice(SimParams(hand={"target": (500, 0, 0)}, workspace=[[-100, 100]] * 3))
    state = _run(dev, 2.0)
    assert state.position[0] == pytest.approx(100.0)


def test_a_scripted_hand_follows_its_points() -> None:
    dev = SimDevice(
        SimParams(hand={"mode": "script", "points": [[0, 0, 0, 0], [1, 80, 0, 0]], "loop": False})
    )
    assert dev.hand_target(0.5) == pytest.approx((40, 0, 0))
    assert _run(dev, 3.0).position[0] == pytest.approx(80, abs=1)


def test_the_device_limit_caps_what_the_motors_give() -> None:
    dev = SimDevice(SimParams(max_force=1.0))
    dev.open()
    dev.read_state(0.0)
    dev.apply_force((9.0, -9.0, 0.0), 0.0)
    assert dev.force == [1.0, -1.0, 0.0]


def test_a_dotted_path_device_that_does_not_import_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="no_such_module"):
        make_device("no_such_module:Arm", {})


def test_a_device_that_does_not_import_fails_setup_and_tears_down_quietly() -> None:
    """The runtime tears a node down after a failed setup: no AttributeError on top."""
    from flowrt.node import make_node

    node = make_node(Haptic, {"device": "json:NoSuchArm"}, HarnessContext("haptic"))
    with pytest.raises(FatalError, match="NoSuchArm"):
        node.setup()
    node.teardown()


@pytest.mark.parametrize(
    ("device", "said"),
    [
        ("no_such_module:Arm", "no module named 'no_such_module'"),
        ("no_such_pkg.arms:Arm", "no module named 'no_such_pkg'"),
        ("nope", "unknown device 'nope'"),
    ],
)
def test_a_device_module_that_is_not_there_is_a_graph_error(device: str, said: str) -> None:
    """``device: nosuchmod:Dev`` passed flowrt validate and failed the run."""
    g = GraphBuilder("h")
    g.add("h", "haptic", params={"device": device})
    with pytest.raises(GraphError, match=re.escape(said)):
        g.build()


def test_an_enable_button_the_device_lacks_is_refused_at_setup() -> None:
    """A misspelt deadman would hold the force at zero for ever, with no error."""
    sim = {"buttons": [[0.010, "stylus", True]]}
    with pytest.raises(FatalError, match=r"enable_button 'stylis' is not a button .*\(stylus\)"):
        NodeHarness(Haptic, {"sim": sim, "enable_button": "stylis"}, name="haptic")
    with pytest.raises(FatalError, match="it has none"):
        NodeHarness(Haptic, {"enable_button": "stylus"}, name="haptic")


def test_buttons_are_click_events() -> None:
    sim = {"buttons": [[0.010, "a", True], [0.020, "a", False]], "hand": {"mode": "none"}}
    h = NodeHarness(Haptic, {"sim": sim}, name="haptic")
    events = []
    for i in range(30):
        h.ctx.time = 0.001 * i
        out = h.process()
        if "buttons" in out:
            events.append((round(h.ctx.time, 3), out["buttons"].pressed, out["buttons"].released))
    assert events == [(0.01, ("a",), ()), (0.02, (), ("a",))]


class Flaky:
    """A device that fails on demand: unplugged, then back."""

    def __init__(self) -> None:
        self.inner = SimDevice(SimParams(hand={"mode": "none"}))
        self.broken = False
        self.opens = 0
        self.forces: list[tuple[float, ...]] = []

    def open(self) -> Any:
        if self.broken:
            raise OSError(19, "No such device")
        self.opens += 1
        return self.inner.open()

    def read_state(self, now: float) -> Any:
        if self.broken:
            raise DeviceError("unplugged")
        return self.inner.read_state(now)

    def apply_force(self, force: Any, now: float) -> None:
        self.forces.append(tuple(force))
        self.inner.apply_force(force, now)

    def close(self) -> None:
        self.inner.close()


def test_a_lost_device_is_an_error_state_then_reopened_with_backoff() -> None:
    h = NodeHarness(Haptic, {"reopen": "50ms", "max_rate": 1e5}, name="haptic")
    flaky = Flaky()
    h.node.device = flaky
    h.node._open(0.0)
    push = (1.0, 0.0, 0.0)
    reasons = []
    for i in range(200):
        h.ctx.time = 0.001 * i
        flaky.broken = 50 <= i < 100
        h.publish("force", push)
        out = h.process(force=push)
        reasons.append(out["applied"].reason if out else None)
        if i == 60:
            assert h.ctx.error is not None
            assert "unplugged" in h.ctx.error
    assert reasons[49] == ""
    assert reasons[50] == "device-error"
    assert set(reasons[51:100]) == {None}  # closed: nothing is read, nothing is published
    assert reasons[199] == ""
    assert h.ctx.error is None
    assert flaky.opens == 2
    assert h.node.report()["reopens"] >= 1


# --- evdev, against a fake device object -------------------------------------------------


class FakeInputDevice:
    """What EvdevDevice uses of ``evdev.InputDevice``, recorded for the assertions."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.name = "Fake Force Wheel"
        self.events: deque[Any] = deque()
        self.uploaded: list[Any] = []
        self.written: list[tuple[int, int, int]] = []
        self.erased: list[int] = []
        self.closed = False
        self.gone = False

    def capabilities(self, absinfo: bool = True) -> dict[int, list[Any]]:
        info = evdev.AbsInfo(value=0, min=-32768, max=32767, fuzz=0, flat=0, resolution=0)
        return {
            ecodes.EV_ABS: [(ecodes.ABS_X, info), (ecodes.ABS_Y, info)],
            ecodes.EV_KEY: [ecodes.BTN_TRIGGER],
            ecodes.EV_FF: [ecodes.FF_CONSTANT, ecodes.FF_SPRING],
        }

    def read_one(self) -> Any:
        if self.gone:
            raise OSError(19, "No such device")
        return self.events.popleft() if self.events else None

    def upload_effect(self, effect: Any) -> int:
        self.uploaded.append(effect)
        return 3 if effect.id == -1 else int(effect.id)

    def write(self, etype: int, code: int, value: int) -> None:
        self.written.append((etype, code, value))

    def erase_effect(self, eid: int) -> None:
        self.erased.append(eid)

    def close(self) -> None:
        self.closed = True


def _event(etype: int, code: int, value: int) -> Any:
    return evdev.InputEvent(0, 0, etype, code, value)


def _evdev(**params: Any) -> tuple[EvdevDevice, FakeInputDevice]:
    fakes: list[FakeInputDevice] = []

    def opener(path: str) -> FakeInputDevice:
        fakes.append(FakeInputDevice(path))
        return fakes[-1]

    dev = EvdevDevice("/dev/input/event7", EvdevParams(**params), opener)
    info = dev.open()
    assert info.axes == ("x", "y")
    assert info.max_force == params.get("max_force", 2.0)
    return dev, fakes[0]


def test_evdev_axes_are_millimetres_and_keys_are_buttons() -> None:
    dev, fake = _evdev(travel=200.0)
    fake.events.extend(
        [
            _event(ecodes.EV_ABS, ecodes.ABS_X, 32767),
            _event(ecodes.EV_ABS, ecodes.ABS_Y, -32768),
            _event(ecodes.EV_KEY, ecodes.BTN_TRIGGER, 1),
        ]
    )
    state = dev.read_state(1.0)
    assert state.position == pytest.approx((100.0, -100.0), abs=0.01)
    assert state.buttons == {"trigger": True}


def test_evdev_constant_force_direction_and_level() -> None:
    dev, fake = _evdev(max_force=2.0)
    dev.apply_force((2.0, 0.0), 0.0)  # full force to the right: Linux direction 0xC000
    effect = fake.uploaded[-1]
    assert effect.type == ecodes.FF_CONSTANT
    assert effect.direction == 0xC000
    assert effect.u.ff_constant_effect.level == 0x7FFF
    assert fake.written == [(ecodes.EV_FF, 3, 1)]  # played once, then updated in place
    dev.apply_force((0.0, 1.0), 0.001)  # half force down: 0x0000
    assert fake.uploaded[-1].id == 3
    assert fake.uploaded[-1].direction == 0
    assert fake.uploaded[-1].u.ff_constant_effect.level == 0x4000
    n = len(fake.uploaded)
    dev.apply_force((0.0, 1.0), 0.002)  # unchanged: no ioctl in the 1 kHz loop
    assert len(fake.uploaded) == n
    dev.close()
    assert (ecodes.EV_FF, 3, 0) in fake.written
    assert fake.erased == [3]
    assert fake.closed


def test_evdev_spring_is_centred_where_the_force_would_vanish() -> None:
    dev, fake = _evdev(effect="spring", stiffness=100.0, travel=100.0)
    dev.read_state(0.0)  # the handle at the centre
    dev.apply_force((1.0, 0.0), 0.0)  # 1 N at 100 N/m: centre 10 mm to the right
    cond = fake.uploaded[-1].u.ff_condition_effect
    assert fake.uploaded[-1].type == ecodes.FF_SPRING
    assert cond[0].center == round(10 / 50 * 0x7FFF)
    assert cond[1].right_coeff == 0  # no force on y: no spring there


def test_evdev_unplugged_is_a_device_error() -> None:
    dev, fake = _evdev()
    fake.gone = True
    with pytest.raises(DeviceError, match="No such device"):
        dev.read_state(0.0)


def test_evdev_without_force_feedback_is_an_input_only_device() -> None:
    class NoFF(FakeInputDevice):
        def capabilities(self, absinfo: bool = True) -> dict[int, list[Any]]:
            caps = super().capabilities(absinfo)
            del caps[ecodes.EV_FF]
            return caps

    dev = EvdevDevice("/dev/input/event7", EvdevParams(), NoFF)
    assert dev.open().max_force is None
    assert math.isfinite(dev.read_state(0.0).position[0])


def test_an_enable_button_is_a_deadman() -> None:
    sim = {"buttons": [[0.010, "stylus", True], [0.020, "stylus", False]], "hand": {"mode": "none"}}
    params = {"sim": sim, "enable_button": "stylus", "max_rate": 1e5}
    h = NodeHarness(Haptic, params, name="haptic")
    reasons = []
    for i in range(30):
        h.ctx.time = 0.001 * i
        h.publish("force", (1.0, 0.0, 0.0))
        reasons.append(h.process(force=(1.0, 0.0, 0.0))["applied"].reason)
    assert set(reasons[:10]) == {"disabled"}
    assert set(reasons[10:20]) == {""}
    assert set(reasons[20:]) == {"disabled"}
