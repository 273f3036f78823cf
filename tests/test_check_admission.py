"""Admission control: run-time timing changes and mode switches that would break a deadline."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace

import pytest

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.analysis.admission import AdmissionRefused, admit, current_timing
from flowrt.cli import main
from flowrt.control.server import ControlConfig, ControlServer
from flowrt.kernel.timing import TimingChange

pytestmark = pytest.mark.timeout(60)


def graph() -> flowrt.Graph:
    """crit (deadline 5 ms) waits on the loop for at most one 2.5 ms run of `other`: 4.5 ms.
    `other` every 2 ms at a higher priority would take the whole loop: crit never runs."""
    g = GraphBuilder("adm")
    g.add("crit", "counter", trigger={"timer": "10ms"}, priority=30, wcet="2ms", deadline="5ms")
    g.add("other", "counter", trigger={"timer": "10ms"}, priority=20, wcet="2.5ms")
    g.mode("rush", other={"timer": "2ms", "priority": 40})
    g.mode("calm", other={"timer": "20ms"})
    return g.build()


URLS: dict[int, str] = {}  # runtime -> its control endpoint


@pytest.fixture
async def rt() -> AsyncIterator[Runtime]:
    async with (
        Runtime(graph(), clock=VirtualClock()) as r,
        ControlServer(r, ControlConfig("127.0.0.1", 0)) as control,
    ):
        URLS[id(r)] = control.url
        yield r
        del URLS[id(r)]


async def test_a_change_that_breaks_a_deadline_is_refused(rt: Runtime) -> None:
    with pytest.raises(AdmissionRefused, match=r"crit unschedulable .* > deadline 5 ms"):
        rt.set_timing("other", timer=2.0, priority=40)
    st = rt.stats().node("other")
    assert (st.priority, st.period) == (20, "10ms")  # nothing applied
    # a harmless change goes through; a forced one too
    assert "timer_ms 10.0 -> 20.0" in rt.set_timing("other", timer=20.0)
    rt.set_timing("other", timer=2.0, priority=40, force=True)
    assert rt.stats().node("other").priority == 40


async def test_a_mode_switch_is_checked_as_one_change(rt: Runtime) -> None:
    with pytest.raises(ValueError, match="refused by admission control"):
        rt.set_mode("rush")
    assert rt.mode is None
    assert rt.stats().node("other").priority == 20
    rt.set_mode("calm")
    assert rt.mode == "calm"
    rt.set_mode("rush", force=True)
    assert rt.mode == "rush"
    # already unschedulable: a change that makes nothing worse is still admitted
    rt.set_timing("other", timer=3.0)


async def test_the_overload_controller_is_not_checked(rt: Runtime) -> None:
    rt.set_timing("other", timer=2.0, priority=40, origin="qos")
    assert rt.stats().node("other").priority == 40


async def test_flowrt_ctl_refuses_then_forces(
    rt: Runtime, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["ctl", "--url", URLS[id(rt)]]

    def ctl(*args: str) -> int:
        return main([*base, *args])

    code = await asyncio.to_thread(ctl, "timing", "other", "--timer", "2", "--priority", "40")
    assert code == 1
    assert "refused by admission control" in capsys.readouterr().err
    assert rt.stats().node("other").priority == 20
    code = await asyncio.to_thread(
        ctl, "timing", "other", "--timer", "2", "--priority", "40", "--force"
    )
    assert code == 0
    assert rt.stats().node("other").priority == 40
    code = await asyncio.to_thread(ctl, "mode", "calm", "--force")
    assert code == 0
    # a malformed value is a bad argument (exit 2); a refused change (above) is exit 1
    capsys.readouterr()
    code = await asyncio.to_thread(ctl, "timing", "other", "--deadline", "0")
    assert code == 2, capsys.readouterr().err


def test_budgets_are_declared_wcet_else_measured_p99() -> None:
    g = GraphBuilder("m")
    g.add("a", "counter", trigger={"timer": "10ms"}, priority=30, deadline="3ms")
    g.add("b", "counter", trigger={"timer": "10ms"}, priority=20, wcet="1ms")
    built = g.build()

    def runner(timer: float, prio: int, count: int, p99: float) -> SimpleNamespace:
        timing = SimpleNamespace(
            period=1, phase=0, timer=timer, deadline=None, priority=prio, enabled=True
        )
        ex = SimpleNamespace(count=count, summary=lambda: SimpleNamespace(p99=p99))
        return SimpleNamespace(timing=timing, counts=SimpleNamespace(execution=ex))

    runners = {"a": runner(0.010, 35, 10, 1.5), "b": runner(0.020, 20, 10, 99.0)}
    t = current_timing(built, runners)
    assert t["a"].budget is not None
    assert (t["a"].budget.ms, t["a"].budget.source) == (1.5, "measured p99")
    assert t["b"].budget is not None
    assert (t["b"].budget.ms, t["b"].budget.source) == (1, "wcet")  # declared wins
    # the runners' current timing (an operator's changes) replaces the graph's
    assert (t["a"].priority, t["b"].timer_ms) == (35, 20)
    # not yet run: not judged, so not refused
    quiet = {"a": runner(0.010, 30, 0, 0.0), "b": runner(0.010, 50, 10, 1.0)}
    res = admit(current_timing(built, quiet), {"b": TimingChange(timer_ms=0.5)})
    assert res.admitted


def test_run_check_refuses_an_unschedulable_graph(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(
        "nodes:\n"
        "  crit: {kind: counter, trigger: {timer: 10ms}, priority: 30, wcet: 2ms, deadline: 3ms}\n"
        "  other: {kind: counter, trigger: {timer: 10ms}, priority: 20, wcet: 2.5ms}\n"
    )
    assert main(["run", str(path), "--check", "--duration", "0.2", "--no-ui"]) == 1
    err = capsys.readouterr().err
    assert "refusing to start" in err
    assert "crit: worst-case response 4.5 ms > deadline 3 ms" in err
    # without --check: a warning, and the run goes ahead
    assert main(["run", str(path), "--duration", "0.2", "--no-ui"]) == 0
    assert "warning: the timing may not hold" in capsys.readouterr().err
