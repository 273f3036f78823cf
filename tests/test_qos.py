"""QoS manager: the paper's mode change, mode semantics, overload shedding and restoring."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import flowrt
from flowrt import Frame, GraphBuilder, Input, Node, Output, Runtime, TimerTrigger, VirtualClock
from flowrt.graph._resolve import Graph, resolve
from flowrt.graph.spec import Placement, QosSpec
from flowrt.runtime._qos import LoadSample

REPO = Path(__file__).resolve().parents[1]


def cambada_inline() -> Graph:
    """graphs/cambada.yaml, every node on the loop (virtual time, no worker options), no display."""
    spec = Graph.from_file(REPO / "graphs" / "cambada.yaml").spec
    nodes = {
        name: ns.model_copy(update={"placement": Placement.inline, "cpus": None, "spin": None})
        for name, ns in spec.nodes.items()
        if ns.kind != "display"
    }
    return resolve(spec.model_copy(update={"nodes": nodes}))


async def test_paper_mode_change_on_cambada() -> None:
    """Remove Ball_Om, Ball_Fr every 2 frames, Line every frame at priority 40 (the paper).

    The critical trackers keep running on every frame across the change, the changed ones
    follow their new timing from the very next tick of their camera, nothing else moves.
    """
    clock = VirtualClock()
    graph = cambada_inline()
    trackers = {n: rn.trigger for n, rn in graph.nodes.items() if rn.spec.kind == "tracker"}
    async with Runtime(graph, clock=clock) as rt:
        subs = {n: rt.subscribe(f"{n}.detection", size=256) for n in trackers}
        await clock.advance(0.8)
        # the first tick of each camera after the change: its frames are numbered from 0
        first = {cam: rt.stats().node(cam).completions for cam in ("front_cam", "omni_cam")}
        rt.set_mode("paper_mode_change")
        await clock.advance(0.8)
        stats = rt.stats()
        changes = [e for e in rt.events if isinstance(e, flowrt.TimingChanged)]
        modes = [e for e in rt.events if isinstance(e, flowrt.ModeChanged)]
        rec = rt.rtdb.read("flowrt.mode")
        ran = {n: [d.seq for d in sub.drain()] for n, sub in subs.items()}

    def ticks(name: str, after: bool) -> list[int]:
        k0 = first[trackers[name].frame]  # type: ignore[union-attr]
        return [k for k in ran[name] if (k >= k0) == after]

    assert min(first.values()) >= 15
    for name, trig in trackers.items():  # before: the graph's own timing (Table 2)
        k0 = first[trig.frame]  # type: ignore[union-attr]
        period, phase = trig.period, trig.phase  # type: ignore[union-attr]
        assert ticks(name, False) == [k for k in range(k0) if k % period == phase], name
    after = {n: ticks(n, True) for n in trackers}
    k_fr, k_om = first["front_cam"], first["omni_cam"]
    n_fr, n_om = stats.node("front_cam").completions, stats.node("omni_cam").completions
    assert after["avoid_fr"] == list(range(k_fr, n_fr))  # every frame, as before
    assert after["avoid_om"] == list(range(k_om, n_om))
    assert after["ball_om"] == []  # removed
    assert after["ball_fr"] == [k for k in range(k_fr, n_fr) if k % 2 == 0]  # from the next tick
    assert after["line"] == list(range(k_om, n_om))  # every frame from the next tick
    assert after["bgoal"] == [k for k in range(k_om, n_om) if k % 4 == 1]  # undisturbed
    assert after["ypost"] == [k for k in range(k_om, n_om) if k % 16 == 4]
    # the critical trackers kept one frame between activations, and never skipped
    for name in ("avoid_fr", "avoid_om"):
        s = stats.node(name)
        assert s.interval.min == pytest.approx(50.0)
        assert s.interval.max == pytest.approx(50.0)
        assert s.skipped == 0
        assert s.deadline_misses == 0
        assert s.period == "each"
    assert stats.node("line").priority == 40
    assert stats.node("line").period == "each"
    assert stats.node("ball_fr").period == "1/2"
    assert not stats.node("ball_om").enabled
    assert stats.node("ball_om").state == "disabled"
    assert {e.node for e in changes} == {"ball_om", "ball_fr", "line"}
    assert all(e.origin == "mode paper_mode_change" for e in changes)
    assert modes[-1].mode == "paper_mode_change"
    assert modes[-1].previous is None
    assert rec is not None
    assert rec.value == "paper_mode_change"


class Camera(Node):
    frame = Output(Frame)


class Reader(Node):
    """A cheap frame consumer: the critical work."""

    frame = Input(Frame)
    out = Output(int)

    def process(self, frame: Frame) -> int:
        return frame.seq


class Source(Node):
    """A frame source on a timer (20 ms by default)."""

    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=20.0)

    def setup(self) -> None:
        self.seq = 0

    def process(self) -> Frame:
        self.seq += 1
        return Frame(np.zeros((4, 4, 3), np.uint8), source=self.ctx.name, seq=self.seq)


def modes_graph() -> Graph:
    g = GraphBuilder("modes")
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add(
        "a",
        Reader,
        trigger={"frame": "cam", "period": 4, "phase": 3},
        inputs={"frame": "cam.frame"},
    )
    g.add("b", Reader, trigger={"frame": "cam"}, inputs={"frame": "cam.frame"}, priority=20)
    g.add("t", "counter", trigger={"timer": "50ms"})
    g.mode("attack", a={"period": 2, "phase": 1}, b={"priority": 30})
    g.mode("defend", b={"enabled": False}, t={"timer": "100ms"})
    g.mode("nominal")
    return g.build()


@pytest.mark.parametrize(
    ("node", "change", "error"),
    [  # the node's phase kept by a mode that changes its period / timer alone, and does not fit
        ("a", {"period": 2}, r"modes.broken.nodes.a.phase: phase 3 must be in 0..1"),
        ("t", {"timer": "40ms"}, r"nodes.t.timer: phase 60 ms must be less than the timer 40 ms"),
        ("t", {"timer_phase": 120}, r"t.timer_phase: phase 120 ms must be less than the timer 100"),
    ],
)
def test_a_mode_that_cannot_apply_is_refused_at_load(
    node: str, change: dict[str, Any], error: str
) -> None:
    g = GraphBuilder("modes")
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add(
        "a",
        Reader,
        trigger={"frame": "cam", "period": 4, "phase": 3},
        inputs={"frame": "cam.frame"},
    )
    g.add("t", "counter", trigger={"timer": "100ms", "phase": "60ms"})
    g.mode("broken", **{node: change})
    with pytest.raises(flowrt.GraphError, match=error):
        g.build()


async def test_mode_switch_returns_what_the_previous_mode_changed() -> None:
    clock = VirtualClock()
    async with Runtime(modes_graph(), clock=clock) as rt:
        rt.set_mode("attack")
        s = rt.stats()
        assert (s.node("a").period, s.node("b").priority) == ("1/2 +1", 30)
        rt.set_timing("b", deadline=5.0)  # an operator's change: no mode touches deadlines
        rt.set_mode("defend")
        s = rt.stats()
        assert (s.node("a").period, s.node("b").priority) == ("1/4 +3", 20)  # back to the graph
        assert not s.node("b").enabled
        assert s.node("t").period == "100ms"
        assert s.node("b").deadline_ms == 5.0
        with pytest.raises(ValueError, match="phase"):  # an invalid change is refused whole
            rt.set_timing("a", period=2, phase=3)
        assert rt.stats().node("a").period == "1/4 +3"
        assert rt.mode == "defend"
        with pytest.raises(KeyError, match="did you mean"):
            rt.set_mode("atack")
        rt.set_mode("nominal")
        s = rt.stats()
        assert s.node("b").enabled
        assert s.node("t").period == "50ms"
        assert s.node("a").period == "1/4 +3"
        assert [e.mode for e in rt.events if isinstance(e, flowrt.ModeChanged)] == [
            "attack",
            "defend",
            "nominal",
        ]


class Decider(Node):
    """Switches mode from what it reads in the RTDB (the decision-table idea)."""

    def process(self) -> None:
        rec = self.ctx.rtdb.read("ball_distance")
        if rec is not None and not rec.stale:
            self.ctx.set_mode("defend" if rec.value < 1.0 else "attack")


async def test_a_node_switches_modes_from_rtdb_state() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add("b", Reader, trigger={"frame": "cam"}, inputs={"frame": "cam.frame"})
    g.add("decide", Decider, trigger={"timer": "100ms"})
    g.mode("attack", b={"priority": 30})
    g.mode("defend", b={"enabled": False})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.15)
        assert rt.mode is None
        rt.rtdb.write("ball_distance", 0.5, validity_ms=500)
        await clock.advance(0.1)
        assert rt.mode == "defend"
        assert not rt.stats().node("b").enabled
        rt.rtdb.write("ball_distance", 3.0, validity_ms=500)
        await clock.advance(0.1)
        assert rt.mode == "attack"
        assert rt.stats().node("b").enabled
        modes = [e for e in rt.events if isinstance(e, flowrt.ModeChanged)]
        assert modes[-1].origin == "node decide"


def with_qos(g: GraphBuilder, **overload: Any) -> Graph:
    """The builder's graph with a ``qos: {overload: ...}`` section, as a graph file has it."""
    qos = QosSpec.model_validate({"overload": overload})
    return resolve(g.spec().model_copy(update={"qos": qos}), kinds=g.kinds)


def overload_graph(**overload: Any) -> Graph:
    frames = {"frame": "cam.frame"}
    g = GraphBuilder("overload")
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False, priority=50)
    g.add("crit", Reader, trigger={"frame": "cam"}, inputs=frames, priority=45, deadline=15)
    g.add("low_a", Reader, trigger={"frame": "cam"}, inputs=frames, priority=10)
    g.add("low_b", "counter", trigger={"timer": "40ms"}, priority=15)
    g.add(
        "mid", Reader, trigger={"frame": "cam", "period": 2, "phase": 1}, inputs=frames, priority=30
    )
    defaults = {"interval": 100, "loop_lag_ms": 5, "miss_rate": None, "restore_after": 300}
    return with_qos(g, **{**defaults, **overload})


class Model:
    """A load model for the controller: base load plus what the shed-able nodes cost.

    Costs are fractions of the frame time; the controller sees ``lag = 5 ms * load``, so its
    5 ms threshold means 'overloaded above 100 %' and calm means 'below 50 %'.
    """

    cost = {"low_a": 0.15, "low_b": 0.15, "mid": 0.1}

    def __init__(self, rt: Runtime) -> None:
        self.rt = rt
        self.base = 1.0

    def load(self) -> float:
        total = self.base
        for name, cost in self.cost.items():
            r = self.rt.scheduler.runners[name]
            if not r.timing.enabled:
                continue
            nominal = 1 if r.timing.timer is None else 0.04
            now = r.timing.period if r.timing.timer is None else r.timing.timer
            total += cost * nominal / now * (2 if name == "mid" else 1)  # mid: period 2 nominal
        return total

    def __call__(self) -> LoadSample:
        return LoadSample(loop_lag_ms=5.0 * self.load())


async def test_overload_sheds_lowest_priority_first_then_restores_in_reverse() -> None:
    clock = VirtualClock()
    graph = overload_graph(max_slowdown=4)
    async with Runtime(graph, clock=clock) as rt:
        assert rt.qos is not None
        model = Model(rt)
        rt.qos.measure = model
        await clock.advance(1.05)  # 10 evaluations: 9 steps make it, the 10th finds no load
        shed = [(e.node, e.change) for e in rt.events if isinstance(e, flowrt.TimingChanged)]
        assert shed == [
            ("low_a", "period 1 -> 2"),  # lowest priority, slowed first ...
            ("low_a", "period 2 -> 4"),  # ... up to max_slowdown
            ("low_b", "timer_ms 40.0 -> 80.0"),  # timer nodes too
            ("low_b", "timer_ms 80.0 -> 160.0"),
            ("mid", "period 2 -> 4"),
            ("mid", "period 4 -> 8"),
            ("low_a", "enabled True -> False"),  # nothing left to slow: disable, lowest first
            ("low_b", "enabled True -> False"),
            ("mid", "enabled True -> False"),
        ]
        status = rt.qos_status()
        assert [s.describe() for s in status.shed] == ["low_a off", "low_b off", "mid off"]
        assert "shed: low_a off" in status.describe()
        recorded = rt.rtdb.read("flowrt.runtime._qos")  # the QoS state is in the RTDB too
        assert recorded is not None
        assert recorded.value.shed == status.shed
        s = rt.stats()
        assert s.node("crit").period == "each"
        assert s.node("crit").enabled
        # still overloaded (base 100 %): nothing more to shed, nothing undone
        await clock.advance(0.5)
        assert len([e for e in rt.events if isinstance(e, flowrt.TimingChanged)]) == 9
        # load falls: after restore_after (300 ms) calm, one step back per evaluation
        model.base = 0.0
        await clock.advance(0.25)
        assert len(rt.qos_status().shed) == 3
        await clock.advance(1.2)
        restored = [(e.node, e.change) for e in rt.events if isinstance(e, flowrt.TimingChanged)][
            9:
        ]
        assert restored == [
            ("mid", "enabled False -> True"),
            ("low_b", "enabled False -> True"),
            ("low_a", "enabled False -> True"),
            ("mid", "period 8 -> 4"),
            ("mid", "period 4 -> 2"),
            ("low_b", "timer_ms 160.0 -> 80.0"),
            ("low_b", "timer_ms 80.0 -> 40.0"),
            ("low_a", "period 4 -> 2"),
            ("low_a", "period 2 -> 1"),
        ]
        assert rt.qos_status().shed == ()
        assert not rt.qos_status().overloaded
        assert all(
            e.origin == "qos" and e.t > 0 for e in rt.events if isinstance(e, flowrt.TimingChanged)
        )


async def test_an_operators_change_to_a_shed_node_wins() -> None:
    clock = VirtualClock()
    graph = overload_graph(max_slowdown=2, disable=False)
    async with Runtime(graph, clock=clock) as rt:
        assert rt.qos is not None
        model = Model(rt)
        rt.qos.measure = model
        await clock.advance(0.35)  # low_a x2, low_b x2, mid x2 (no disabling)
        assert {s.node for s in rt.qos_status().shed} == {"low_a", "low_b", "mid"}
        rt.set_timing("low_a", period=3)  # the operator decides low_a's period now
        rt.set_timing("mid", priority=35)  # not a period change: mid stays shed
        assert {s.node for s in rt.qos_status().shed} == {"low_b", "mid"}
        model.base = 0.0
        await clock.advance(1.0)
        s = rt.stats()
        assert s.node("low_a").period == "1/3"  # left alone
        assert s.node("mid").period == "1/2 +1"
        assert s.node("low_b").period == "40ms"


class Late(Node):
    """Misses its 5 ms deadline: its result comes 10 ms (virtual) after release."""

    clock: VirtualClock

    async def process(self) -> None:
        fut = asyncio.get_running_loop().create_future()
        Late.clock.call_at(Late.clock.now() + 0.010, lambda: fut.set_result(None))
        await fut


async def test_deadline_miss_rate_triggers_shedding() -> None:
    clock = VirtualClock()
    Late.clock = clock
    g = GraphBuilder("misses")
    g.add("crit", "counter", trigger={"timer": "20ms"}, priority=45, deadline=15)
    g.add("late", Late, trigger={"timer": "20ms"}, priority=10, deadline=5)
    graph = with_qos(g, interval=100, loop_lag_ms=None, miss_rate=0.1, max_slowdown=2)
    async with Runtime(graph, clock=clock) as rt:
        await clock.advance(0.21)
        changes = [e for e in rt.events if isinstance(e, flowrt.TimingChanged)]
        assert changes
        assert changes[0].node == "late"
        assert changes[0].change == "timer_ms 20.0 -> 40.0"
        assert rt.qos_status().last is not None
        assert rt.qos_status().last.miss_rate > 0.1  # type: ignore[union-attr]
        assert "miss rate" in rt.qos_status().reason
        assert rt.stats().node("crit").deadline_misses == 0


async def test_real_overload_keeps_critical_nodes_on_time() -> None:
    """Burn nodes on the loop: a protected hog overloads it, low-priority burners are shed.

    Real time, generous thresholds: only outcomes are asserted (the critical nodes never
    miss and stay at period 1, the burners are slowed then disabled, and all is restored
    once the hog stops), not how long any step took.
    """
    g = GraphBuilder("burn")
    g.add("src", Source, priority=50)
    for name in ("crit1", "crit2"):
        g.add(
            name,
            Reader,
            trigger={"frame": "src"},
            inputs={"frame": "src.frame"},
            priority=45,
            deadline=20,
        )
    g.add("hog", "burn", params={"ms": 60}, trigger={"frame": "src"}, priority=30)
    g.add("low1", "burn", params={"ms": 2}, trigger={"frame": "src"}, priority=10)
    g.add("low2", "burn", params={"ms": 2}, trigger={"frame": "src"}, priority=15)
    graph = with_qos(
        g,
        interval=100,
        loop_lag_ms=15,  # the hog makes it ~30 ms; an idle loop on a busy machine, a few ms
        miss_rate=None,
        restore_after=300,
        max_slowdown=2,
        protect=["hog"],
    )

    async def until(cond: Any, within: float) -> bool:
        end = time.monotonic() + within
        while time.monotonic() < end:
            if cond():
                return True
            await rt.run(0.05)
        return bool(cond())

    async with Runtime(graph) as rt:

        def shed() -> set[str]:
            return {s.describe() for s in rt.qos_status().shed}

        assert await until(lambda: shed() == {"low1 off", "low2 off"}, 10.0), shed()
        qos_changes = [(e.node, e.change) for e in rt.events if isinstance(e, flowrt.TimingChanged)]
        assert qos_changes[:4] == [
            ("low1", "period 1 -> 2"),
            ("low2", "period 1 -> 2"),
            ("low1", "enabled True -> False"),
            ("low2", "enabled True -> False"),
        ]
        rt.set_timing("hog", enabled=False)  # the load falls
        assert await until(lambda: not shed(), 10.0), shed()
        s = rt.stats()
    misses = [e for e in rt.events if isinstance(e, flowrt.DeadlineMissed)]
    for name in ("crit1", "crit2"):
        assert s.node(name).deadline_misses == 0, misses
        assert s.node(name).period == "each"
        assert s.node(name).enabled
        assert s.node(name).completions >= s.node("src").completions - 2
    assert s.node("low1").period == "each"
    assert s.node("low1").enabled
    assert s.node("low2").period == "each"
    assert s.node("low2").enabled
    assert s.node("hog").completions > 5


class Distance(Node):
    """Publishes a distance the test sets: stands in for a tracker's object info."""

    value = 5.0
    out = Output(float)

    def process(self) -> float:
        return Distance.value


async def test_decision_table_node_switches_modes_from_recorded_tracker_output() -> None:
    clock = VirtualClock()
    Distance.value = 5.0
    g = GraphBuilder()
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add("b", Reader, trigger={"frame": "cam"}, inputs={"frame": "cam.frame"})
    g.add("ball", Distance, trigger={"timer": "50ms"})
    g.add("world", "rtdb", params={"validity_ms": 120}, inputs={"ball_distance": "ball.out"})
    rules = [
        {"record": "ball_distance", "missing": True, "mode": "search"},
        {"record": "ball_distance", "stale": True, "mode": "search"},
        {"record": "ball_distance", "lt": 1.0, "mode": "defend"},
    ]
    g.add("decide", "decision", params={"rules": rules, "default": "attack", "interval_ms": 100})
    g.mode("attack", b={"priority": 30})
    g.mode("defend", b={"enabled": False})
    g.mode("search", b={"priority": 5})
    async with Runtime(g.build(), clock=clock) as rt:
        chosen = rt.subscribe("decide.mode")
        await clock.advance(0.25)
        assert rt.mode == "attack"  # the record exists, fresh, not close: the default
        Distance.value = 0.5
        await clock.advance(0.1)
        assert rt.mode == "defend"
        assert not rt.stats().node("b").enabled
        rt.set_timing("ball", enabled=False)  # the tracker goes quiet: its record goes stale
        await clock.advance(0.3)
        assert rt.mode == "search"
        rec = rt.rtdb.read("ball_distance")
        assert rec is not None
        assert rec.stale
        modes = [e for e in rt.events if isinstance(e, flowrt.ModeChanged)]
        assert [m.mode for m in modes] == ["attack", "defend", "search"]
        assert {m.origin for m in modes} == {"node decide"}
        assert chosen.drain() == ["attack", "defend", "search"]


async def test_a_timers_phase_changes_at_run_time() -> None:
    """Issue 24: a timer's phase is changeable at run time (API, ctl --timer-phase, modes),
    checked like the rest: below its timer, timer-triggered nodes only."""
    from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock

    class Stamp(Node):
        out = Output(float)

        def process(self) -> float:
            return self.ctx.now()

    g = GraphBuilder("phase")
    g.add("t", Stamp, trigger={"timer": 100})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        sub = rt.subscribe("t.out", size=100)
        await clock.advance(0.35)
        before = [round(x * 1000) % 100 for x in sub.drain()]
        text = rt.set_timing("t", timer_phase=30)
        assert "timer_phase_ms 0.0 -> 30.0" in text
        await clock.advance(0.5)
        after = [round(x * 1000) % 100 for x in sub.drain()]
        with pytest.raises(ValueError, match=r"timer_phase must be in 0\.\.100"):
            rt.set_timing("t", timer_phase=150)
        # the timer alone, below the phase it keeps: refused (it was taken, and the control
        # endpoint and the status lines stopped answering), with both at once: fine
        with pytest.raises(ValueError, match=r"timer 20 ms must be above its phase 30 ms"):
            rt.set_timing("t", timer=20)
        assert "timer_ms 100.0 -> 20.0" in rt.set_timing("t", timer=20, timer_phase=10)
    assert set(before) == {0}
    assert set(after[1:]) == {30}
