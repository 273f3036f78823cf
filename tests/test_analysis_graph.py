"""Graph-level analyses: timing view, response times per resource, per-tick load, phases."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

TESTS = Path(__file__).parent
if str(TESTS) not in sys.path:  # the typed test kinds, `graphkinds:FrameSource` etc.
    sys.path.insert(0, str(TESTS))

from flowrt import Graph  # noqa: E402
from flowrt.analysis.load import load_tables  # noqa: E402
from flowrt.analysis.phases import advise, snippet  # noqa: E402
from flowrt.analysis.rta import Task, global_response_time  # noqa: E402
from flowrt.analysis.schedulability import analyse  # noqa: E402
from flowrt.analysis.timing import Budget, NodeTiming, apply_changes, graph_timing  # noqa: E402
from flowrt.kernel.timing import TimingChange  # noqa: E402

pytestmark = pytest.mark.timeout(30)


def _graph(readers: str, cam: str = "wcet: 1ms") -> Graph:
    return Graph.from_text(
        "nodes:\n"
        "  cam: {kind: 'graphkinds:FrameSource', params: {period_ms: 10}, priority: 50, "
        f"{cam}}}\n" + readers
    )


def _reader(name: str, extra: str) -> str:
    return (
        f"  {name}: {{kind: 'graphkinds:FrameReader', inputs: {{frame: cam.frame}}, "
        f"placement: process, {extra}}}\n"
    )


TWO_ON_CPU0 = _reader(
    "hi", "trigger: {frame: cam}, priority: 30, wcet: 2ms, deadline: 5ms, cpus: [0]"
) + _reader("lo", "trigger: {frame: cam}, priority: 20, wcet: 3ms, deadline: 5ms, cpus: [0]")


def test_pinned_workers_by_hand() -> None:
    v = analyse(graph_timing(_graph(TWO_ON_CPU0)))
    cam, hi, lo = v.node("cam"), v.node("hi"), v.node("lo")
    # cam: alone on the loop, 1 ms.
    assert (cam.resource, cam.response_ms, cam.schedulable) == ("loop", pytest.approx(1), True)
    # hi on CPU 0: released when cam publishes (jitter 1 ms), preempted by the loop's 1 ms.
    assert hi.jitter_ms == pytest.approx(1)
    assert hi.response_ms == pytest.approx(3)
    # lo: w = 3 + ceil(w/10)*1 + ceil((w+1)/10)*2 = 6 > its 5 ms deadline.
    assert lo.response_ms == pytest.approx(6)
    assert (hi.schedulable, lo.schedulable, v.schedulable) == (True, False, False)
    assert v.utilisation == pytest.approx(0.6)


def test_separate_cpus_do_not_interfere() -> None:
    g = _graph(TWO_ON_CPU0.rsplit("cpus: [0]", 1)[0] + "cpus: [1]}\n")
    v = analyse(graph_timing(g))
    assert v.node("lo").resource == "cpu 1"
    assert v.node("lo").response_ms == pytest.approx(4)  # only the loop's 1 ms
    assert v.schedulable


def test_unpinned_worker_gets_the_global_bound() -> None:
    g = _graph(TWO_ON_CPU0.rsplit(", cpus: [0]", 1)[0] + "}\n")
    v = analyse(graph_timing(g), cpus=2)
    lo = v.node("lo")
    assert lo.resource == "any cpu"
    # R = 3 + floor(((ceil(R/10)+1)*1 + (ceil((R+1)/10)+1)*2) / 2) = 3 + 3 = 6
    assert lo.response_ms == pytest.approx(6)
    one = global_response_time(Task("x", 3, 10), [Task("h", 1, 10)], 2)
    assert one.response == pytest.approx(4)  # 3 + floor(2 / 2)


def test_inline_nodes_block_each_other_non_preemptively() -> None:
    g = _graph(
        "  fast: {kind: counter, trigger: {timer: 10ms}, priority: 40, wcet: 1ms}\n"
        "  slow: {kind: counter, trigger: {timer: 100ms}, priority: 5, wcet: 4ms}\n"
    )
    v = analyse(graph_timing(g))
    # fast waits for slow already running (4 ms, less 1 ns) and for cam (higher priority).
    assert v.node("fast").blocking_ms == pytest.approx(4)
    assert v.node("fast").response_ms == pytest.approx(6, abs=1e-5)
    assert v.node("slow").response_ms == pytest.approx(6)  # cam 1 + fast 1 + own 4


def test_missing_budget_and_disabled_nodes() -> None:
    g = _graph(_reader("r", "trigger: {frame: cam}, priority: 30"))
    v = analyse(graph_timing(g))
    assert v.node("r").schedulable is None
    assert "no budget" in v.node("r").note
    assert not v.schedulable
    off = apply_changes(graph_timing(g), {"r": TimingChange(enabled=False)})
    assert [n.name for n in analyse(off).nodes] == ["cam"]
    assert analyse(off).schedulable


def test_overloaded_node_does_not_poison_the_rest() -> None:
    g = _graph(
        _reader("hog", "trigger: {frame: cam}, priority: 30, wcet: 12ms, cpus: [0]")
        + _reader("ok", "trigger: {frame: cam}, priority: 20, wcet: 1ms, cpus: [1]")
    )
    v = analyse(graph_timing(g))
    assert v.node("hog").schedulable is False
    assert v.node("ok").response_ms == pytest.approx(2)


def test_changes_apply_to_the_analysis() -> None:
    t = graph_timing(_graph(TWO_ON_CPU0))
    slower = apply_changes(t, {"lo": TimingChange(deadline_ms=8.0), "hi": TimingChange(period=2)})
    v = analyse(slower)
    assert v.node("hi").period_ms == pytest.approx(20)
    assert v.node("lo").schedulable


# --- per-tick load and phases ------------------------------------------------------------------

PAPER = (
    _reader("a", "trigger: {frame: cam, period: 1}, priority: 45, wcet: 2ms")
    + _reader("b", "trigger: {frame: cam, period: 4, phase: 1}, priority: 25, wcet: 3ms")
    + _reader("c", "trigger: {frame: cam, period: 4, phase: 3}, priority: 25, wcet: 3ms")
    + _reader("d", "trigger: {frame: cam, period: 8, phase: 0}, priority: 20, wcet: 3ms")
)


def test_load_table_sums_budgets_per_tick() -> None:
    (tab,) = load_tables(graph_timing(_graph(PAPER)))
    assert (tab.source, tab.frame_ms, len(tab.ticks)) == ("cam", 10, 8)
    assert [k.total_ms for k in tab.ticks] == [5, 5, 2, 5, 2, 5, 2, 5]
    assert tab.ticks[0].nodes == ["a", "d"]
    assert tab.ticks[0].per_cpu_ms == {"any cpu": 5}
    assert tab.heaviest == 0


def test_phase_advice_spreads_all_zero_phases() -> None:
    zero = PAPER.replace("phase: 1", "phase: 0").replace("phase: 3", "phase: 0")
    t = graph_timing(_graph(zero))
    (tab,) = load_tables(t)
    assert tab.peak_ms == 11  # a + b + c + d on tick 0
    (adv,) = [a for a in advise(t) if a.clock == "cam"]
    assert (adv.peak_before, adv.peak_after) == (11, 5)
    assert adv.after["a"] == 0
    text = snippet([adv], t)
    assert "# cam: heaviest tick 11ms -> 5ms" in text
    assert "trigger: {frame: cam, period: 4, phase:" in text
    # The advice keeps every period and really reaches the peak it announces.
    plan = {n: TimingChange(phase=int(p)) for n, p in adv.changed.items()}
    (after,) = load_tables(apply_changes(t, plan))
    assert after.peak_ms == 5


def test_phase_advice_keeps_phases_that_are_already_best() -> None:
    t = graph_timing(_graph(PAPER))
    (adv,) = [a for a in advise(t) if a.clock == "cam"]
    assert adv.changed == {}
    assert snippet([adv], t) == ""


def test_phase_advice_counts_nodes_without_budgets() -> None:
    zero = PAPER.replace(", wcet: 3ms", "").replace("phase: 1", "phase: 0")
    (adv,) = [a for a in advise(graph_timing(_graph(zero))) if a.clock == "cam"]
    assert adv.measure == "nodes"
    assert adv.peak_after == 2


def test_timer_phases_are_advised_apart() -> None:
    g = Graph.from_text(
        "nodes:\n"
        "  c1: {kind: counter, trigger: {timer: 50ms}, wcet: 5ms}\n"
        "  c2: {kind: counter, trigger: {timer: 50ms}, wcet: 5ms}\n"
    )
    t = graph_timing(g)
    (adv,) = advise(t)
    assert (adv.clock, adv.peak_before, adv.peak_after) == ("timers", 10, 5)
    assert sorted(adv.after.values()) == [0, 25]
    assert "{timer: 50ms, phase: 25ms}" in snippet([adv], t)


@settings(max_examples=80, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from([1, 2, 3, 4, 6]), st.integers(1, 9), st.integers(0, 5)),
        min_size=1,
        max_size=5,
    )
)
def test_phase_search_finds_the_least_heaviest_tick(items: list[tuple[int, int, int]]) -> None:
    from itertools import product
    from math import lcm

    from flowrt.analysis.phases import _Item, _loads, search

    its = [_Item(f"n{i}", p, ph % p, float(w)) for i, (p, w, ph) in enumerate(items)]
    h = lcm(*(it.period for it in its))
    got = max(_loads(its, search(its, h), h))
    best = min(max(_loads(its, list(c), h)) for c in product(*(range(it.period) for it in its)))
    assert got == best
    assert got <= max(_loads(its, [it.phase for it in its], h))  # never worse than now


def test_wcet_must_be_finite_and_positive() -> None:
    from flowrt.graph.diagnostics import GraphError

    for bad in ("0ms", "-1ms", ".inf"):
        with pytest.raises(GraphError, match="wcet"):
            Graph.from_text(
                f"nodes:\n  c: {{kind: counter, trigger: {{timer: 5ms}}, wcet: {bad}}}\n"
            )


@st.composite
def _timings(draw: st.DrawFn) -> dict[str, NodeTiming]:
    """Random graphs' timing tables: timers, frame readers, input chains, any placement."""
    n = draw(st.integers(1, 7))
    out: dict[str, NodeTiming] = {}
    for i in range(n):
        name = f"n{i}"
        earlier = list(out)
        kind = draw(st.sampled_from(["timer", "frame", "input"] if earlier else ["timer"]))
        budget = draw(st.one_of(st.none(), st.floats(0.01, 30)))
        t = NodeTiming(
            name=name,
            trigger=kind,
            priority=draw(st.integers(1, 99)),
            placement=draw(st.sampled_from(["inline", "process", "pool"])),
            order=i,
            enabled=draw(st.booleans()) or i == 0,
            deadline_ms=draw(st.one_of(st.none(), st.floats(0.5, 100))),
            budget=None if budget is None else Budget(budget, "test"),
        )
        if t.placement == "process":
            t = replace(t, cpus=draw(st.one_of(st.none(), st.sampled_from([(0,), (1,), (0, 1)]))))
        if kind == "timer":
            t = replace(t, timer_ms=draw(st.sampled_from([5.0, 10.0, 20.0, 50.0])))
        elif kind == "frame":
            period = draw(st.integers(1, 4))
            t = replace(
                t,
                source=draw(st.sampled_from(earlier)),
                period=period,
                phase=draw(st.integers(0, period - 1)),
            )
        else:
            picks = draw(st.lists(st.sampled_from(earlier), min_size=1, max_size=3, unique=True))
            t = replace(t, producers=tuple(picks))
        out[name] = t
    return out


@settings(max_examples=120, deadline=None)
@given(_timings(), st.integers(1, 4))
def test_any_graph_is_analysed_without_error(timing: dict[str, NodeTiming], cpus: int) -> None:
    """Admission control runs this on every run-time change: it must never raise, and every
    bound it gives is at least the node's own budget and no more than infinity."""
    v = analyse(timing, cpus)
    assert [x.name for x in v.nodes] == sorted(
        (t.name for t in timing.values() if t.enabled),
        key=lambda n: (-timing[n].priority, timing[n].order),
    )
    for x in v.nodes:
        if x.response_ms is not None and x.budget is not None:
            assert x.response_ms >= x.budget.ms - 1e-6
        if x.schedulable is None:
            assert x.note
    load_tables(timing)
    advise(timing)
