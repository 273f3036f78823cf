"""Precise nodes in the analysis: judged on the thread that runs them, at load and at run time.

A ``timing: precise`` node called in its own release thread is not queued behind the loop's
callbacks; the analysis used to put it on the loop, so a 1 ms precise counter beside a
5 ms inline tracker was shown missing its deadline: ``flowrt check`` failed, ``flowrt run
--check`` refused to start, and admission control refused to enable the node again after
``--disable`` (the user's report: "worst-case response 5.14 ms > deadline 1 ms", response
p99 0.10 ms). Re-enabling the timing a graph started with must never be refused.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

import flowrt
from flowrt import Frame, GraphBuilder, Input, Node, Output, Runtime, VirtualClock
from flowrt.analysis.admission import AdmissionRefused, admit, current_timing
from flowrt.analysis.schedulability import analyse
from flowrt.analysis.timing import graph_timing
from flowrt.cli import main
from flowrt.kernel.timing import TimingChange

pytestmark = pytest.mark.timeout(60)

SLOW_MS = 5.0  # the inline "tracker" every precise case sits beside
TICK_MS = 0.05


class Count(Node):
    value = Output(int)

    def process(self) -> int:
        return 1


class AsyncCount(Node):
    value = Output(int)

    async def process(self) -> int:
        return 1


class Paint(Node):
    frame = Output(Frame)

    def process(self) -> None:
        return None


class Look(Node):
    frame = Input(Frame)
    value = Output(int)

    def process(self, frame: Frame | None = None) -> int:
        return 1


class Keep(Node):
    input = Input(int)

    def process(self, input: int) -> None:
        return None


def graph(
    kind: type[Node] = Count,
    inputs: dict[str, Any] | None = None,
    tick_enabled: bool = True,
    **tick: Any,
) -> flowrt.Graph:
    """``tick`` (1 ms, deadline 1 ms) beside ``slow``, 5 ms on the loop every 10 ms; ``mid``
    (1 ms on the loop, above ``tick``) is there disabled, for what the graph never ran."""
    g = GraphBuilder("px")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20}, priority=50)
    g.add(
        "tick",
        kind,
        trigger={"timer": "1ms"},
        inputs=inputs,
        priority=80,
        deadline="1ms",
        wcet=f"{TICK_MS}ms",
        enabled=tick_enabled,
        **tick,
    )
    g.add("slow", "counter", trigger={"timer": "10ms"}, priority=20, wcet=f"{SLOW_MS}ms")
    g.add("mid", "counter", trigger={"timer": "10ms"}, priority=90, wcet="1ms", enabled=False)
    g.add("keep", Keep, inputs={"input": "slow.value"}, priority=10)
    return g.build()


WHERE = [
    # case, tick's kind and spec, where it runs, shown schedulable
    ("sync precise: its thread", Count, {"timing": "precise"}, "precise thread", True),
    ("coroutine: handed to the loop", AsyncCount, {"timing": "precise"}, "loop", False),
    (
        "lossless input: served from the loop",
        Keep,
        {"timing": "precise", "inputs": {"input": {"from": "slow.value", "policy": "lossless"}}},
        "loop",
        False,
    ),
    (
        "frame input: on the loop",
        Look,
        {"timing": "precise", "inputs": {"frame": "cam.frame"}},
        "loop",
        False,
    ),
    ("publishes frames: on the loop", Paint, {"timing": "precise"}, "loop", False),
    ("worker: its worker runs it", Count, {"timing": "precise", "placement": "process"},
     "any cpu", False),
    ("normal timing: the loop's timer", Count, {}, "loop", False),
]  # fmt: skip


@pytest.mark.parametrize(
    ("kind", "spec", "where", "ok"), [w[1:] for w in WHERE], ids=[w[0] for w in WHERE]
)
def test_a_precise_node_is_analysed_where_it_runs(
    kind: type[Node], spec: dict[str, Any], where: str, ok: bool
) -> None:
    spec = dict(spec)
    v = analyse(graph_timing(graph(kind, spec.pop("inputs", None), **spec)), cpus=1)
    tick = v.node("tick")
    assert (tick.resource, tick.schedulable) == (where, ok)
    if where == "precise thread":  # no loop callback ahead of it, none blocking it
        assert (tick.response_ms, tick.blocking_ms, tick.jitter_ms) == (TICK_MS, 0.0, 0.0)


def test_the_loop_counts_a_precise_threads_calls_to_the_end_of_its_own() -> None:
    """slow's callback takes GIL turns with tick: every tick call released until it ends
    counts (7 = the 6 ms window's releases and one carried in), not only those before."""
    v = analyse(graph_timing(graph(Count, timing="precise")), cpus=1)
    assert v.node("slow").response_ms == pytest.approx(SLOW_MS + 7 * TICK_MS)
    assert v.node("slow").resource == "loop"


def test_precise_threads_take_turns_with_each_other() -> None:
    g = GraphBuilder("two")
    for name, prio in (("hi", 90), ("lo", 10)):  # the GIL ignores priorities
        g.add(name, Count, trigger={"timer": "1ms"}, timing="precise", priority=prio,
              deadline="1ms", wcet="0.3ms")  # fmt: skip
    v = analyse(graph_timing(g.build()), cpus=4)
    for name in ("hi", "lo"):  # its own call and the other's two (one carried in)
        assert v.node(name).response_ms == pytest.approx(0.9)
        assert v.node(name).resource == "precise thread"


def runner(timing: Any, precise: Any = None) -> SimpleNamespace:
    ex = SimpleNamespace(count=0, summary=lambda: SimpleNamespace(p99=0.0))
    return SimpleNamespace(timing=timing, counts=SimpleNamespace(execution=ex), precise=precise)


@pytest.mark.parametrize(
    ("release", "where"),
    [
        (SimpleNamespace(thread_mode=True), "precise thread"),
        (SimpleNamespace(thread_mode=False), "loop"),  # left its thread (long calls)
        (None, "precise thread"),  # virtual time: no thread; as the graph says
    ],
    ids=["in its thread", "left its thread", "no release thread"],
)
def test_admission_takes_where_a_precise_node_runs_now(release: Any, where: str) -> None:
    built = graph(Count, timing="precise")
    runners = {}
    for name, r in built.nodes.items():
        trig = r.trigger
        tm = SimpleNamespace(
            period=1,
            phase=0,
            timer=getattr(trig, "timer", 0) / 1000 or None,
            deadline=None,
            priority=r.spec.priority,
            enabled=r.spec.enabled,
        )
        runners[name] = runner(tm, release if name == "tick" else None)
    now = current_timing(built, runners)
    assert analyse(now, 1).node("tick").resource == where


async def _disable_then_enable(rt: Runtime) -> None:
    rt.set_timing("tick", enabled=False)
    rt.set_timing("tick", enabled=True)
    assert rt.stats().node("tick").enabled


REENABLE = [
    # case, tick's kind and spec: each started so, each must be enabled back
    ("sync precise: its own thread, schedulable", Count, {"timing": "precise"}),
    ("coroutine precise on the loop: unschedulable from the start", AsyncCount,
     {"timing": "precise"}),
    ("normal timing on the loop: unschedulable from the start", Count, {}),
]  # fmt: skip


@pytest.mark.parametrize(("kind", "spec"), [r[1:] for r in REENABLE], ids=[r[0] for r in REENABLE])
async def test_enabling_a_node_back_to_its_started_timing_is_admitted(
    kind: type[Node], spec: dict[str, Any]
) -> None:
    async with Runtime(graph(kind, **spec), clock=VirtualClock()) as rt:
        await _disable_then_enable(rt)


async def test_enabling_back_into_a_worse_loop_than_it_started_with_is_refused() -> None:
    """The started timing excuses no more than it had: ``mid`` (never run) above tick."""
    async with Runtime(graph(AsyncCount, timing="precise"), clock=VirtualClock()) as rt:
        rt.set_timing("tick", enabled=False)
        rt.set_timing("mid", enabled=True)  # tick is not running: nothing to judge
        with pytest.raises(AdmissionRefused, match=r"tick unschedulable"):
            rt.set_timing("tick", enabled=True)
        assert not rt.stats().node("tick").enabled
        rt.set_timing("mid", enabled=False)
        rt.set_timing("tick", enabled=True)


def test_admit_without_a_started_timing_keeps_the_plain_rule() -> None:
    built = graph(AsyncCount, timing="precise", tick_enabled=False)
    t = graph_timing(built)
    res = admit(t, {"tick": TimingChange(enabled=True)}, cpus=1)
    assert (res.admitted, res.refused_nodes) == (False, ["tick"])
    # the graph started with tick disabled: enabling it is not going back to anything
    res = admit(t, {"tick": TimingChange(enabled=True)}, cpus=1, started=t)
    assert (res.admitted, res.refused_nodes) == (False, ["tick"])


PRECISE_YAML = """\
name: precise
nodes:
  tick: {kind: counter, trigger: {timer: 1ms}, timing: precise, deadline: 1ms, priority: 80,
         wcet: 0.05ms}
  tsink:
    kind: sink
    deadline: 50ms
    wcet: 0.05ms
    inputs: {input: {from: tick.value, policy: queue, size: 64}}
  cam:
    kind: capture
    params: {source: "synthetic:soccer", fps: 20, size: [320, 240], seed: 1}
    priority: 50
    wcet: 8ms
  ball: {kind: tracker, params: {object: ball}, trigger: {frame: cam}, priority: 40,
         inputs: {frame: cam.frame}, wcet: 5ms}
"""


def test_flowrt_check_and_run_admit_the_users_graph(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "precise.yaml"
    path.write_text(PRECISE_YAML)
    assert main(["check", str(path), "--json", "--cpus", "2"]) == 0
    doc = json.loads(capsys.readouterr().out)
    where = {a["name"]: a["resource"] for a in doc["analysis"]}
    assert where == {"tick": "precise thread", "tsink": "loop", "cam": "loop", "ball": "loop"}
    tick = next(t for t in doc["tasks"] if t["name"] == "tick")
    assert (tick["response_ms"], tick["schedulable"]) == (0.05, True)
    assert main(["run", str(path), "--check", "--duration", "0.3", "--no-ui", "--no-display"]) == 0
    assert "timing may not hold" not in capsys.readouterr().err
