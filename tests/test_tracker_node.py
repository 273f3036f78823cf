"""The tracker node in runtimes: accuracy against the synthetic truth, frame identity of its
detections, bad input, worker placement, and the CAMBADA demo graph (paper Table 2)."""

from __future__ import annotations

import asyncio
import os
import pickle
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import wait_until
from flowrt.nodes.colour import OBJECTS, Detection
from flowrt.nodes.tracker import FrameDetection, Tracker, TrackerParams
from pydantic import ValidationError

import flowrt
from flowrt import HealthAlert, NodeFailed

REPO = Path(__file__).resolve().parents[1]
CAMBADA = REPO / "graphs" / "cambada.yaml"
SCORED = ["ball", "blue_goal", "yellow_goal", "blue_post", "yellow_post"]

# Table 2 of the CAMBADA paper: node -> (camera, period, phase, priority).
TABLE2 = {
    "avoid_fr": ("front_cam", 1, 0, 45),
    "avoid_om": ("omni_cam", 1, 0, 45),
    "ball_om": ("omni_cam", 1, 0, 40),
    "ball_fr": ("front_cam", 1, 0, 35),
    "bgoal": ("omni_cam", 4, 1, 25),
    "ygoal": ("omni_cam", 4, 3, 25),
    "line": ("omni_cam", 8, 0, 20),
    "bpost": ("omni_cam", 16, 2, 15),
    "ypost": ("omni_cam", 16, 4, 15),
}


async def run_trackers(
    objects: list[str],
    *,
    frames: int,
    capture: dict[str, Any] | None = None,
    tracker: dict[str, Any] | None = None,
    placement: str = "inline",
    max_seconds: float = 20.0,
) -> tuple[dict[str, list[Any]], dict[int, Any], list[Any], Any]:
    """Synthetic capture (fast) with one tracker per object; returns detections, truths, events."""
    g = flowrt.GraphBuilder("trackers")
    g.add("cam", "capture", params={"pacing": "fast", "seed": 0, "clutter": 0.3, **(capture or {})})
    for name in objects:
        g.add(
            name,
            "tracker",
            params={"object": name, **(tracker or {})},
            trigger={"frame": "cam"},
            inputs={"frame": "cam.frame"},
            placement=placement,
        )
    rt = flowrt.Runtime(g.build())
    events: list[Any] = []
    rt.on_event(events.append)
    async with rt:
        truth_sub = rt.subscribe("cam.truth", size=100_000)
        subs = {n: rt.subscribe(f"{n}.detection", size=100_000) for n in objects}
        loop = asyncio.get_running_loop()
        end = loop.time() + max_seconds
        while loop.time() < end:
            await asyncio.sleep(0.05)
            if min(rt.stats().node(n).completions for n in objects) >= frames:
                break
        stats = rt.stats()
        dets = {n: s.drain() for n, s in subs.items()}
        truths = {t.index: t for t in truth_sub.drain()}
    return dets, truths, events, stats


# ---------------------------------------------------------------- params


def test_params() -> None:
    assert TrackerParams().object == "ball"
    assert TrackerParams(object="obstacle").object_spec() == OBJECTS["obstacle"]
    # A partial spec overrides the named object's.
    p = TrackerParams.model_validate(
        {"object": "ball", "spec": {"min_area": 5, "roi": [0, 0.5, 1, 1]}}
    )
    assert p.object_spec().min_area == 5
    assert p.object_spec().colour == "orange"
    assert p.object_spec().surround == OBJECTS["ball"].surround
    # A complete custom spec with a custom colour.
    p = TrackerParams.model_validate(
        {
            "object": "cone",
            "spec": {"colour": "pink"},
            "colours": {"pink": [[300, 340], [80, 255], [80, 255]]},
        }
    )
    assert p.table().names[0] == "pink"
    with pytest.raises(ValidationError, match="did you mean 'ball'"):
        TrackerParams(object="bal")
    with pytest.raises(ValidationError, match="unknown in space hsv"):
        TrackerParams.model_validate({"object": "x", "spec": {"colour": "purple"}})
    with pytest.raises(ValidationError, match="matches no colour at all"):
        TrackerParams.model_validate({"colours": {"void": [[0, 360], [0, 255], [300, 400]]}})
    with pytest.raises(ValidationError):
        TrackerParams.model_validate({"space": "lab"})
    with pytest.raises(ValidationError):
        TrackerParams.model_validate({"object": "ball", "spec": {"min_area": 50, "max_area": 10}})


def test_bad_tracker_params_are_located_load_errors() -> None:
    text = """\
nodes:
  cam: {kind: capture}
  ball:
    kind: tracker
    params: {object: bal}
    inputs: {frame: cam.frame}
  odd:
    kind: tracker
    params:
      object: thing
      spec: {colour: nothing}
      colours: {nothing: [[0, 360], [0, 255], [300, 400]]}
    inputs: {frame: cam.frame}
"""
    with pytest.raises(flowrt.GraphError) as info:
        flowrt.Graph.from_text(text, "t.yaml")
    msg = str(info.value)
    assert "t.yaml:5:14: error: nodes.ball.params.object: unknown object 'bal'" in msg
    assert "nodes.odd.params.colours: colour class 'nothing' matches no colour at all" in msg


# ---------------------------------------------------------------- accuracy and identity


@pytest.mark.slow  # over 1 s of CPU
async def test_accuracy_on_the_synthetic_scene() -> None:
    """>= 99% of the frames where the object is visible detected, median error <= 2 px."""
    objects = [*SCORED, "obstacle", "line"]
    dets, truths, events, stats = await run_trackers(objects, frames=400)
    assert not [e for e in events if isinstance(e, NodeFailed)]
    report = {}
    for name in SCORED:
        assert stats.node(name).skipped == 0  # fast pacing waits for inline trackers
        pairs = [(d, truths[d.seq][name]) for d in dets[name] if d.seq in truths]
        assert len(pairs) >= 400
        visible = [(d, t) for d, t in pairs if t.visible]
        found = [(d, t) for d, t in visible if d.found]
        errors = [
            np.hypot(d.centroid[0] - t.centroid[0], d.centroid[1] - t.centroid[1]) for d, t in found
        ]
        report[name] = (len(visible), len(found) / len(visible), float(np.median(errors)))
        assert len(visible) > 100, report
        assert len(found) >= 0.99 * len(visible), report
        assert np.median(errors) <= 2.0, report
    # Obstacles: found on a robot in the lower region; lines: their pixels counted.
    obstacle_pairs = [(d, truths[d.seq]) for d in dets["obstacle"] if d.seq in truths]
    hits = considered = 0
    for d, t in obstacle_pairs:
        robots = [t[f"obstacle_{k}"] for k in range(3)]
        if not any(r.visible and r.bbox[1] + r.bbox[3] > 70 for r in robots):
            continue
        considered += 1
        hits += d.found and any(
            r.bbox and r.bbox[0] - 2 <= d.centroid[0] <= r.bbox[0] + r.bbox[2] + 2 for r in robots
        )
    assert considered > 100
    assert hits >= 0.95 * considered
    assert all(d.found for d in dets["line"])


async def test_detections_carry_their_frame() -> None:
    dets, _truths, _, _ = await run_trackers(["ball"], frames=20, capture={"size": [160, 120]})
    ball = dets["ball"]
    assert [d.seq for d in ball] == list(range(len(ball)))
    d = ball[-1]
    assert isinstance(d, FrameDetection)
    assert isinstance(d, Detection)
    assert d.source == "cam"
    assert d.object == "ball"
    assert d.size == (160, 120)
    assert d.timestamp > 0
    assert pickle.loads(pickle.dumps(d)) == d  # crosses process boundaries
    # Cost: the windowed search is much cheaper than classifying whole frames.
    tracked = [x for x in ball[1:] if x.found]
    assert tracked
    assert np.median([x.cost for x in tracked]) < 160 * 120 / 2


async def test_rgb_frames_give_the_same_detections() -> None:
    bgr, _, _, _ = await run_trackers(["ball"], frames=30)
    rgb, _, _, _ = await run_trackers(["ball"], frames=30, capture={"pixel_format": "RGB"})
    key = [(d.seq, d.found, d.centroid) for d in bgr["ball"][:30]]
    assert key == [(d.seq, d.found, d.centroid) for d in rgb["ball"][:30]]


async def test_grey_frames_are_bad_input_not_a_crash() -> None:
    dets, _, events, stats = await run_trackers(
        ["ball"], frames=10, capture={"pixel_format": "GRAY"}
    )
    assert not [e for e in events if isinstance(e, NodeFailed)]
    assert stats.node("ball").errors == 0
    assert dets["ball"]
    assert not any(d.found for d in dets["ball"])
    bad = [e for e in events if isinstance(e, HealthAlert) and e.alert == "bad-input"]
    assert len(bad) == 1
    assert "needs colour frames" in bad[0].detail


async def test_custom_colour_class_that_matches_nothing_in_the_scene() -> None:
    # A valid class, but no pixel of the scene has it: never found, never an error.
    tracker = {"spec": {"colour": "cyan"}, "colours": {"cyan": [[170, 190], [150, 255], [80, 255]]}}
    dets, _, events, _ = await run_trackers(["ball"], frames=10, tracker=tracker)
    assert len(dets["ball"]) >= 10
    assert not any(d.found for d in dets["ball"])
    assert not [e for e in events if isinstance(e, NodeFailed)]


async def test_tracker_in_a_worker_process() -> None:
    dets, truths, events, stats = await run_trackers(
        ["ball"], frames=40, placement="process", capture={"pacing": "realtime", "fps": 50}
    )
    assert not [e for e in events if isinstance(e, NodeFailed)]
    assert stats.node("ball").errors == 0
    ball = [d for d in dets["ball"] if d.seq in truths]
    assert len(ball) >= 30
    visible = [d for d in ball if truths[d.seq]["ball"].visible]
    assert sum(d.found for d in visible) >= 0.95 * len(visible)


def test_tracker_is_built_from_class_and_params() -> None:
    """What a worker does: unpickle the class and params, build, set up, process."""
    cls, params = pickle.loads(pickle.dumps((Tracker, TrackerParams(object="blue_goal"))))
    node = cls()
    node.params = params
    node.ctx = flowrt.NodeContext("bgoal")
    node.setup()
    from flowrt.nodes.scene import SoccerScene

    img, truth = SoccerScene(seed=0, clutter=0.3).render(0)
    d = node.process(frame=flowrt.Frame(img, source="omni_cam", seq=7))
    assert d.found
    assert d.seq == 7
    assert d.source == "omni_cam"
    assert (
        np.hypot(
            d.centroid[0] - truth["blue_goal"].centroid[0],
            d.centroid[1] - truth["blue_goal"].centroid[1],
        )
        < 2
    )


# ---------------------------------------------------------------- the CAMBADA graph


def test_cambada_graph_is_table2() -> None:
    graph = flowrt.Graph.from_file(CAMBADA)
    assert not graph.warnings
    for name, (cam, period, phase, prio) in TABLE2.items():
        node = graph.nodes[name]
        assert node.spec.kind == "tracker"
        assert node.trigger == flowrt.FrameTrigger(frame=cam, period=period, phase=phase)
        assert node.spec.priority == prio
        assert node.spec.placement.value == "process"
        assert node.spec.deadline is not None
        assert node.spec.deadline <= 50 * period
        assert node.spec.inputs["frame"].source == f"{cam}.frame"
    for cam in ("front_cam", "omni_cam"):
        p = graph.nodes[cam].params
        assert (p.fps, p.size, p.source) == (20, (320, 240), "synthetic:soccer")
    assert graph.nodes["avoid_fr"].spec.deadline <= 20
    assert graph.nodes["ball_om"].spec.deadline <= 20
    assert graph.nodes["display"].spec.kind == "display"


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "200"}
    cmd = [sys.executable, "-c", "from flowrt.cli import main; main()", *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env, timeout=60)


def test_cambada_cli_validate_and_graph() -> None:
    ok = _cli("validate", "graphs/cambada.yaml")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "ok" in ok.stdout
    shown = _cli("graph", "graphs/cambada.yaml")
    assert shown.returncode == 0, shown.stderr
    # The activation table of the omni camera shows Table 2's pattern over 16 ticks.
    rows = {}
    for line in shown.stdout.splitlines():
        cells = line.split()  # node, prio, then one cell per tick
        if len(cells) == 18 and cells[0] in TABLE2:
            rows[cells[0]] = "".join("X" if c == "X" else "." for c in cells[2:])
    assert rows["bgoal"] == ".X...X...X...X.."
    assert rows["ygoal"] == "...X...X...X...X"
    assert rows["line"] == "X.......X......."
    assert rows["bpost"] == "..X............."
    assert rows["ypost"] == "....X..........."
    assert rows["avoid_om"] == "X" * 16


def _cambada_spec(placement: str, display: bool) -> flowrt.GraphSpec:
    data = yaml.safe_load(CAMBADA.read_text())
    for name in TABLE2:
        data["nodes"][name]["placement"] = placement
        if placement == "inline":  # worker options have no meaning on the loop
            data["nodes"][name].pop("cpus", None)
            data["nodes"][name].pop("spin", None)
    if display:
        data["nodes"]["display"]["params"]["port"] = 0  # any free port
    else:
        del data["nodes"]["display"]
    return flowrt.GraphSpec.model_validate(data)


async def _run_cambada(
    spec: flowrt.GraphSpec, seconds: float, counted: str
) -> tuple[Any, list[Any], dict[str, list[Any]]]:
    """``seconds`` of the graph, and more (bounded) until ``counted`` has completed 20 times
    and every tracker once: a loaded machine makes fewer in the time than the tests assert."""
    rt = flowrt.Runtime(spec)
    events: list[Any] = []
    rt.on_event(events.append)
    async with rt:
        subs = {n: rt.subscribe(f"{n}.detection", size=1000) for n in TABLE2}
        await rt.run(seconds)

        def made() -> bool:
            st = rt.stats()
            return st.node(counted).completions >= 20 and all(
                st.node(n).completions >= 1 for n in TABLE2
            )

        await wait_until(made)
        stats = rt.stats()
        dets = {n: s.drain() for n, s in subs.items()}
    return stats, events, dets


async def test_cambada_runs_inline() -> None:
    stats, events, dets = await _run_cambada(
        _cambada_spec("inline", display=False), 1.6, "omni_cam"
    )
    assert not [e for e in events if isinstance(e, NodeFailed)]
    ticks = stats.node("omni_cam").completions
    assert ticks >= 20
    for name, (cam, period, phase, _) in TABLE2.items():
        s = stats.node(name)
        assert s.errors == 0
        assert abs(s.activations - ticks / period) <= 2, (name, s.activations, ticks)
        # Each activation ran on a tick of its phase: the frame's seq says which.
        assert dets[name]
        assert {d.seq % period for d in dets[name]} == {phase}
        assert {d.source for d in dets[name]} == {cam}


async def test_cambada_runs_as_shipped() -> None:
    """Worker processes and the display, as `flowrt run graphs/cambada.yaml` runs it."""
    stats, events, dets = await _run_cambada(
        _cambada_spec("process", display=True), 2.5, "avoid_om"
    )
    assert not [e for e in events if isinstance(e, NodeFailed)]
    for name in TABLE2:
        assert stats.node(name).errors == 0
        assert stats.node(name).completions >= 1, name
        assert dets[name]
    assert stats.node("avoid_om").completions >= 20
    assert sum(d.found for d in dets["ball_om"]) >= 1
