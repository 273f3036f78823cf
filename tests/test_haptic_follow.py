"""Device space to actuator space (issue 42): linear scaling, axis locks (param and input),
and the two follow modes for slow actuators."""

from __future__ import annotations

import math
from typing import Any

import pytest
from flowrt.nodes.haptic import Haptic
from flowrt.nodes.haptic.follow import Follower, scale
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt.testing import NodeHarness


def test_scaling_maps_the_device_range_onto_the_actuator_range() -> None:
    assert scale(-100, (-100, 100), (0.0, 0.2)) == 0.0
    assert scale(100, (-100, 100), (0.0, 0.2)) == pytest.approx(0.2)
    assert scale(0, (-100, 100), (0.5, -0.5)) == 0.0  # a reversed axis


def test_last_point_goes_straight_and_trajectory_travels_the_path() -> None:
    corner = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]  # the hand goes right, then up, quickly
    paths = {}
    for mode in ("trajectory", "last_point"):
        f = Follower(2, mode, max_speed=1.0, path_points=100)  # type: ignore[arg-type]
        f.update(corner[0], [False, False], 0.0)
        f.update(corner[1], [False, False], 0.01)
        f.update(corner[2], [False, False], 0.01)
        seen = [tuple(f.update(corner[2], [False, False], 0.1)) for _ in range(25)]
        paths[mode] = seen
    traj = paths["trajectory"]
    assert all(y == pytest.approx(0.0, abs=1e-9) for x, y in traj if x < 0.999)  # along x first
    assert traj[-1] == pytest.approx((1.0, 1.0))
    last = paths["last_point"]
    assert any(0.1 < x < 0.9 and 0.1 < y < 0.9 for x, y in last)  # the diagonal
    assert last[-1] == pytest.approx((1.0, 1.0))


def test_a_full_path_drops_its_oldest_point_and_counts_it() -> None:
    f = Follower(1, "trajectory", max_speed=0.001, path_points=3)
    f.update((0.0,), [False], 0.0)
    for x in (1.0, 2.0, 3.0, 4.0, 5.0):
        f.update((x,), [False], 0.001)
    assert f.dropped == 2
    assert [p[0] for p in f.path] == [3.0, 4.0, 5.0]


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
            st.tuples(st.booleans(), st.booleans()),
            st.floats(0, 0.1),
        ),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from(["trajectory", "last_point"]),
    st.sampled_from([None, 0.5, 5.0]),
)
def test_a_locked_axis_never_moves_and_speed_is_bounded(
    steps: list[Any], mode: Any, speed: float | None
) -> None:
    f = Follower(2, mode, speed, path_points=1000)
    prev: list[float] | None = None
    for point, locked, dt in steps:
        target = f.update(point, list(locked), dt)
        if prev is not None:
            for i in range(2):
                if locked[i]:
                    assert target[i] == prev[i]
            if speed is not None:
                assert math.dist(target, prev) <= speed * dt + 1e-9
        prev = target


def _harness(**params: Any) -> NodeHarness:
    base = {"sim": {"hand": {"target": [50, 50, 50]}}, "actuator": {"x": [0, 1]}}
    return NodeHarness(Haptic, base | params, name="haptic")


def test_the_node_locks_from_its_param_and_its_input() -> None:
    h = _harness(lock=["z"])
    h.ctx.time = 0.0
    first = h.process()["target"]
    assert first.locked == ("z",)
    for i in range(1, 200):  # the hand pulls to (50, 50, 50) mm
        h.ctx.time = i * 0.001
        out = h.process(lock=["y"] if i >= 100 else None)["target"]
    assert out.locked == ("y", "z")
    assert out.values[2] == first.values[2]  # z never moved
    assert out.values[0] > first.values[0]  # x did
    assert 0.0 <= out.values[0] <= 1.0  # scaled onto [0, 1]


def test_an_unreadable_lock_value_locks_every_axis_and_is_counted() -> None:
    h = _harness()
    h.ctx.time = 0.0
    out = h.process(lock=42)
    assert out["target"].locked == ("x", "y", "z")
    assert h.node.report()["invalid_locks"] == 1


def test_a_handle_past_its_range_does_not_take_the_actuators_past_theirs() -> None:
    h = _harness(sim={"hand": {"mode": "none"}})
    h.ctx.time = 0.0
    h.node.device.advance(0.0)
    h.node.device.pos[0] = 0.150  # 150 mm: beyond the reported -100..100
    out = h.process()
    assert out["position"].position[0] == pytest.approx(150.0)
    assert out["target"].values[0] == 1.0  # the top of x's actuator range [0, 1]
