"""The agent example (graphs/agent.yaml) on virtual time: the decision table switches the
situation, the modes change the arbiter's weights, the robot moves without colliding, and
disabling a behaviour mid-run leaves the others' activations untouched."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from flowrt.nodes.agent import ARENA, OBSTACLES, RobotSim, cast
from test_stream_rates import _counters, _Written  # what a report reads of a writer

from flowrt import Graph, GraphBuilder, ModeChanged, Runtime, VirtualClock
from flowrt.graph._resolve import resolve
from flowrt.recording import build_report, nominal_rates

REPO = Path(__file__).resolve().parents[1]


def agent_graph() -> Graph:
    spec = Graph.from_file(REPO / "graphs" / "agent.yaml").spec
    nodes = {k: v for k, v in spec.nodes.items() if v.kind != "display"}
    return resolve(spec.model_copy(update={"nodes": nodes}))


@pytest.mark.parametrize(
    ("x", "y", "angle", "expected"),
    [
        (1.0, 0.5, -math.pi / 2, 0.5),  # down to the floor wall
        (5.0, 2.0, 0.0, 1.0),  # right wall
        (1.0, 1.4, 0.0, 1.0 - OBSTACLES[0][2]),  # the first obstacle, centre (2.0, 1.4)
        (0.5, 3.9, math.pi / 2, 0.1),  # top wall
    ],
)
def test_cast(x: float, y: float, angle: float, expected: float) -> None:
    assert cast(x, y, angle, 10.0) == pytest.approx(expected, abs=1e-9)
    assert cast(x, y, angle, expected / 2) == pytest.approx(expected / 2)


async def test_agent_runs_switches_situations_and_stays_clear() -> None:
    clock = VirtualClock()
    async with Runtime(agent_graph(), clock=clock) as rt:
        pose = rt.subscribe("robot.pose", policy="latest")
        await clock.advance(40.0)
        final = pose.drain()[-1]
        stats = rt.stats()
        modes = {e.mode for e in rt.events if isinstance(e, ModeChanged)}
        weights = rt.scheduler.runners["drive"].rnode.params.sources
    assert final["collisions"] == 0
    assert 0 < final["x"] < ARENA[0]
    assert 0 < final["y"] < ARENA[1]
    moved = math.hypot(final["x"] - 0.6, final["y"] - 0.6)
    assert moved > 0.3
    assert "wall_following" in modes
    assert len(modes) >= 2, modes  # the decision table switched at least once
    assert {n.name for n in stats.nodes if n.errors} == set()
    mode = rt.mode
    assert mode is not None
    expected = {"tracking": 4.0, "avoidance": 0.2, "wall_following": 0.0}[mode]
    assert weights["track"].weight == expected


async def test_disabling_a_behaviour_leaves_the_others_untouched() -> None:
    clock = VirtualClock()
    async with Runtime(agent_graph(), clock=clock) as rt:
        await clock.advance(2.0)
        before = {n.name: n.activations for n in rt.stats().nodes}
        rt.set_timing("wall", enabled=False)
        await clock.advance(2.0)
        rt.set_timing("wall", enabled=True)
        await clock.advance(2.0)
        stats = {n.name: n for n in rt.stats().nodes}
    for name, period in (("robot", 0.02), ("avoid", 0.02), ("drive", 0.02), ("track", 0.04)):
        assert stats[name].activations - before[name] == pytest.approx(4.0 / period, abs=1)
        assert stats[name].deadline_misses == 0
        assert stats[name].skipped == 0
    assert stats["wall"].activations - before["wall"] == pytest.approx(20, abs=1)  # 2 s of 4


def test_robot_sim_declares_the_arenas_rate_from_its_params() -> None:
    """The arena is drawn every ``render_every`` steps; pose and sense every step."""
    rates = RobotSim.output_rates(RobotSim.Params(rate_hz=50, render_every=5))
    assert rates["arena"] == 10.0
    assert "pose" not in rates  # once per activation, as sense
    assert "sense" not in rates
    assert RobotSim.output_rates(RobotSim.Params(rate_hz=40, render_every=2))["arena"] == 20.0


async def test_the_recording_report_expects_the_arena_at_its_render_rate() -> None:
    """``flowrt record graphs/agent.yaml`` reported ``robot.arena expected 250 received 50
    missing 200``: the arena was expected at the robot's 50 Hz step rate."""
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("robot", "robot_sim", params={"rate_hz": 50, "render_every": 5})
    async with Runtime(g.build(), clock=clock) as rt:
        arena = rt.subscribe("robot.arena", size=256)
        pose = rt.subscribe("robot.pose", size=256)
        await clock.advance(2.0)
        frames = arena.drain()
        poses = len(pose.drain())
        stats = rt.stats()
    rates = nominal_rates(stats)
    assert rates["robot"] == pytest.approx(50.0)
    assert rates["robot.arena"] == pytest.approx(10.0)
    step = 1.0 / 50
    writer = _Written(
        {
            "pose": _counters("robot.pose", poses, 0.0, (poses - 1) * step),
            "arena": _counters(
                "robot.arena", len(frames), frames[0].timestamp, frames[-1].timestamp
            ),
        }
    )
    report = build_report(writer, "rec_001", "2026-01-01T00:00:00", 2.0, rates)
    by = {s.source: s for s in report.streams}
    assert by["robot.arena"].received == len(frames) > 0
    assert by["robot.arena"].expected == len(frames)
    assert by["robot.arena"].missing == 0
    assert by["robot.pose"].missing == 0


async def test_the_arbiters_selected_has_no_rate_while_nothing_is_valid() -> None:
    """``drive.selected expected 250 received 249 missing 1`` in a clean recording of the
    agent graph: the arbiter publishes nothing on ``selected`` while no source is valid (its
    first tick), so that output has no per-activation rate to expect."""
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("src", "counter", trigger={"timer": "20ms"})
    g.add(
        "drive",
        "arbiter",
        trigger={"timer": "20ms"},
        params={"mode": "priority", "sources": {"a": {"priority": 1}}, "zero": {"vx": 0.0}},
        inputs={"a": "src.value"},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.5)
        stats = rt.stats()
    rates = nominal_rates(stats)
    assert rates["drive"] == pytest.approx(50.0)
    assert rates["drive.selected"] is None  # no rate: the report expects no count of it
    assert "drive.command" not in rates  # every activation: the node's own 50 Hz
