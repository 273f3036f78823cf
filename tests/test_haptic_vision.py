"""Forces from vision (issue 42): a tracked object becomes a wall or spring, rendered by the
haptic loop against the handle; end to end on a virtual clock."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from flowrt.nodes.haptic import Fixture, VisionForce
from flowrt.nodes.haptic.fixtures import fixture_force

from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock
from flowrt.testing import NodeHarness

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Seen:
    """What a tracker publishes, as far as vision_force reads it."""

    found: bool
    centroid: tuple[float, float] | None
    size: tuple[int, int] = (320, 240)
    timestamp: float = 0.0


def _wall(x: float, k: float = 300.0, b: float = 0.0) -> Fixture:
    return Fixture("wall", ("x", "y"), (x, 0.0), (-1.0, 0.0), k, b, True, 0.0)


def test_a_wall_pushes_only_from_behind_it() -> None:
    wall = _wall(10.0)
    assert fixture_force(wall, AXES, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)
    fx, fy, fz = fixture_force(wall, AXES, (20.0, 5.0, 0.0), (0.0, 0.0, 0.0)) or ()
    assert fx == pytest.approx(-3.0)  # 300 N/m x 10 mm, along the normal
    assert (fy, fz) == (0.0, 0.0)


def test_wall_damping_resists_only_motion_into_the_wall() -> None:
    wall = _wall(10.0, b=10.0)
    into = fixture_force(wall, AXES, (20.0, 0.0, 0.0), (100.0, 0.0, 0.0))
    out = fixture_force(wall, AXES, (20.0, 0.0, 0.0), (-100.0, 0.0, 0.0))
    assert into is not None
    assert out is not None
    assert into[0] == pytest.approx(-3.0 - 1.0)
    assert out[0] == pytest.approx(-3.0)


def test_a_spring_pulls_towards_the_object() -> None:
    spring = Fixture("spring", ("x", "y"), (10.0, -10.0), (1.0, 0.0), 100.0, 0.0, True, 0.0)
    assert fixture_force(spring, AXES, (0.0, 0.0, 7.0), (0.0, 0.0, 0.0)) == pytest.approx(
        (1.0, -1.0, 0.0)
    )


def test_the_image_position_maps_onto_the_workspace() -> None:
    h = NodeHarness(VisionForce, {"u_range": [-100, 100], "v_range": [100, -100]})
    h.ctx.time = 1.0
    fix = h.process(detection=Seen(True, (240.0, 60.0), timestamp=0.97))
    assert fix.anchor == pytest.approx((50.0, 50.0))
    assert fix.timestamp == 0.97  # the camera frame's time: the age is vision-to-motor
    gone = h.process(detection=Seen(False, None, timestamp=0.99))
    assert not gone.found
    assert fixture_force(gone, AXES, (90.0, 0.0, 0.0), (0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)


class Camera(Node):
    out = Output(object)  # published by the test


async def test_the_wall_the_camera_sees_holds_the_hand_back() -> None:
    """The hand pulls to x = +60 mm (40 N/m); a wall seen at the image centre (x = 0 mm, 300
    N/m) holds it near 40 x (60 - d) = 300 x d, d = 7 mm, at 1 kHz on a virtual clock; the
    tracker then stalls: the wall goes stale and the hand reaches its target."""
    g = GraphBuilder("haptic-vision")
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add("wall", "vision_force", params={"stiffness": 300}, inputs={"detection": "cam.out"})
    g.add(
        "haptic",
        "haptic",
        params={"max_force": 3.0, "max_rate": 500.0, "timeout": "100ms"},
        inputs={"force": "wall.force"},
    )
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        positions = rt.subscribe("haptic.position", size=10_000)
        applied = rt.subscribe("haptic.applied", size=10_000)
        for _ in range(60):  # 2 s of a 30 fps camera
            rt.publish("cam.out", Seen(True, (160.0, 120.0), timestamp=clock.now()))
            await clock.advance(1 / 30)
        held = positions.drain()[-1].position[0]
        forces = applied.drain()
        assert held == pytest.approx(7.0, abs=1.0)
        assert max(abs(f.values[0]) for f in forces) <= 3.0
        assert forces[-1].reason in ("", "rate-limited")
        await clock.advance(1.5)  # no more frames
        assert applied.drain()[-1].reason == "stale"
        assert positions.drain()[-1].position[0] == pytest.approx(60.0, abs=1.0)
        assert len(forces) >= 1900  # the loop ran at 1 kHz while vision gave 30 walls/s


def test_the_wall_at_the_readme_stiffness_gives_no_energy_back() -> None:
    """The simulated handle (nobody holding it) thrown at 0.2 m/s against a 300 N/m wall
    rendered at 1 kHz leaves it with less energy than it came with (virtual time)."""
    from flowrt.nodes.haptic import Haptic

    sim = {"hand": {"mode": "none"}, "start": [-5, 0, 0], "velocity": [200, 0, 0]}
    params = {"sim": sim, "max_force": 3.0, "max_rate": 200.0, "timeout": "10s"}
    h = NodeHarness(Haptic, params, name="haptic")
    wall = _wall(0.0, k=300.0)
    dev = h.node.device

    def energy() -> float:
        return dev.kinetic_energy() + 0.5 * 300.0 * max(0.0, dev.pos[0]) ** 2

    entered = left = None
    for i in range(1000):
        h.ctx.time = i / 1000
        h.publish("force", wall)
        h.process(force=wall)
        if dev.pos[0] > 0 and entered is None:
            entered = energy()
        if entered is not None and dev.pos[0] <= 0:
            left = energy()
            break
    assert entered is not None, "the handle never reached the wall"
    assert left is not None, "the handle never came back out"
    assert 0 < left < entered


@pytest.mark.parametrize(
    "params",
    [
        {"u_range": [5, 5]},  # the wall at one place whatever the camera sees
        {"v_range": [float("nan"), 1]},  # NaN reached the haptic loop
        {"image_size": [0, 240]},
    ],
)
def test_a_degenerate_image_mapping_is_refused(params: dict[str, object]) -> None:
    from flowrt.nodes.haptic.vision import VisionForceParams
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=next(iter(params))):
        VisionForceParams.model_validate(params)


@pytest.mark.parametrize(
    "params",
    [
        {"actuator": [[0.0, 0.0], [0.0, 0.2]]},  # was a ZeroDivisionError every frame
        {"workspace": [[-100, 100], [float("inf"), 100]]},
    ],
)
def test_a_view_range_of_zero_width_is_refused(params: dict[str, object]) -> None:
    from flowrt.nodes.haptic.view import HapticViewParams
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="with lo != hi"):
        HapticViewParams.model_validate(params)
