"""Swapping a node's algorithm while running, reloading it from disk, and modes that set params.

Virtual time: the swap happens between two activations of the swapped node, and a critical
node at 20 Hz beside it keeps every activation with no miss.
"""

from __future__ import annotations

import asyncio
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from conftest import drained, wait_until
from pydantic import BaseModel

from flowrt import GraphBuilder, Input, Node, NodeSwapped, Output, Runtime, SwapError, VirtualClock


class Doubler(Node):
    class Params(BaseModel):
        factor: float = 2.0

    value = Input(int)
    out = Output(float)

    def setup(self) -> None:
        self.calls = 0

    def process(self, value: int) -> float:
        self.calls += 1
        return value * self.params.factor

    def get_state(self) -> Any:
        return self.calls

    def set_state(self, state: Any) -> None:
        self.calls = state


class Negator(Node):
    value = Input(int)
    out = Output(float)

    def setup(self) -> None:
        self.calls = 0

    def process(self, value: int) -> float:
        self.calls += 1
        return -float(value)

    def set_state(self, state: Any) -> None:
        self.calls = state


class BrokenSetup(Node):
    value = Input(int)
    out = Output(float)

    def setup(self) -> None:
        raise RuntimeError("no calibration file")

    def process(self, value: int) -> float:
        return 0.0


class Critical(Node):
    tick = Output(int)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> int:
        self.n += 1
        return self.n


def graph() -> Any:
    g = GraphBuilder("swap")
    g.add("src", "counter", trigger={"timer": "10ms"})
    g.add("alg", Doubler, inputs={"value": "src.value"})
    g.add("crit", Critical, trigger={"timer": "50ms"}, deadline="5ms", priority=90)
    return g.build()


async def test_swap_takes_over_between_activations_and_others_see_nothing() -> None:
    clock = VirtualClock()
    async with Runtime(graph(), clock=clock) as rt:
        out = rt.subscribe("alg.out", size=1024)
        await clock.advance(0.5)
        before = out.drain()
        crit_before = rt.stats().node("crit").activations
        await rt.swap("alg", Negator)
        await clock.advance(0.5)
        after = out.drain()
        stats = rt.stats()
        swapped = [e for e in rt.events if isinstance(e, NodeSwapped)]
        calls = rt.scheduler.runners["alg"].executor.node.calls  # type: ignore[attr-defined]
    assert before
    assert all(v >= 0 for v in before)
    assert after
    assert all(v <= 0 for v in after)
    assert calls == len(before) + len(after)  # the old instance's state was handed over
    crit = stats.node("crit")
    assert crit.deadline_misses == 0
    assert crit.skipped == 0
    assert crit.activations == crit_before + 10  # 20 Hz, continuous across the swap
    assert stats.node("alg").kind.endswith("Negator")
    assert stats.node("alg").errors == 0
    assert [(e.node, e.previous_kind) for e in swapped] == [("alg", swapped[0].previous_kind)]


@pytest.mark.parametrize(
    ("kind", "params", "reason"),
    [
        ("no_such_kind", None, "unknown node kind"),
        ("nonexistent_module_xyz:Thing", None, "cannot import"),
        (BrokenSetup, None, "no calibration file"),
        (Doubler, {"factor": "not a number"}, "params"),
        ("sink", None, "has no port"),  # its output `out` is connected
    ],
)
async def test_failing_swap_keeps_the_old_node(kind: Any, params: Any, reason: str) -> None:
    clock = VirtualClock()
    async with Runtime(graph(), clock=clock) as rt:
        out = rt.subscribe("alg.out", size=1024)
        await clock.advance(0.2)
        with pytest.raises(SwapError, match=reason):
            await rt.swap("alg", kind, params)
        await clock.advance(0.2)
        values = out.drain()
        alg = rt.stats().node("alg")
    assert len(values) >= 35
    assert all(v >= 0 for v in values)  # still the Doubler
    assert alg.errors == 0
    assert alg.state != "failed"


async def test_set_params_inline_between_activations() -> None:
    clock = VirtualClock()
    async with Runtime(graph(), clock=clock) as rt:
        out = rt.subscribe("alg.out", size=1024)
        await clock.advance(0.1)
        rt.set_params("alg", {"factor": 10.0})
        await clock.advance(0.1)
        values = out.drain()
        with pytest.raises(ValueError, match="factor"):
            rt.set_params("alg", {"factor": "x"})
    assert values[1] == pytest.approx(2.0)  # counter value 1, factor 2
    assert values[-1] == pytest.approx((len(values) - 1) * 10.0)  # the new factor


MODES_GRAPH = """
name: modes-params
nodes:
  src: {kind: counter, trigger: {timer: 10ms}}
  drive:
    kind: arbiter
    trigger: {timer: 20ms}
    params:
      mode: blend
      timeout: 1s
      sources: {a: {weight: 1.0}, b: {weight: 1.0, priority: 7}}
      zero: {v: 0.0}
    inputs: {a: fa.output, b: fb.output}
  fa: {kind: "tests.test_swap:Const", params: {v: 1.0}, trigger: {timer: 20ms}}
  fb: {kind: "tests.test_swap:Const", params: {v: 0.0}, trigger: {timer: 20ms}}
modes:
  favour_b: {nodes: {drive: {params: {sources: {b: {weight: 3.0}}}}}}
  nominal: {}
"""


class Const(Node):
    class Params(BaseModel):
        v: float = 0.0

    output = Output(dict)

    def process(self) -> dict[str, float]:
        return {"v": self.params.v}


async def test_mode_sets_arbiter_weights_and_switching_back_restores_them(
    tmp_path: Path,
) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(MODES_GRAPH)
    clock = VirtualClock()
    async with Runtime.from_file(path, clock=clock) as rt:
        cmd = rt.subscribe("drive.command", policy="latest")
        await clock.advance(0.2)
        blended = cmd.drain()[-1]["v"]
        rt.set_mode("favour_b")
        await clock.advance(0.2)
        favoured = cmd.drain()[-1]["v"]
        params = rt.scheduler.runners["drive"].rnode.params
        rt.set_mode("nominal")
        await clock.advance(0.2)
        restored = cmd.drain()[-1]["v"]
    assert blended == pytest.approx(0.5)
    assert favoured == pytest.approx(0.25)  # weights 1 and 3
    assert params.sources["b"].priority == 7  # merged: the rest of the source kept
    assert restored == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("mode", "message"),
    [
        ("{nodes: {drive: {params: {mode: fastest}}}}", "modes.m.nodes.drive.params"),
        ("{nodes: {drive: {params: {sources: {a: {weight: -1}}}}}}", "greater than or equal"),
    ],
)
def test_bad_mode_params_are_located(tmp_path: Path, mode: str, message: str) -> None:
    from flowrt import Graph, GraphError

    path = tmp_path / "g.yaml"
    path.write_text(MODES_GRAPH.replace("  nominal: {}", f"  m: {mode}"))
    with pytest.raises(GraphError) as e:
        Graph.from_file(path)
    text = str(e.value)
    assert message in text or message in "\n".join(str(d) for d in e.value.diagnostics)
    assert f"{path}:" in "\n".join(str(d) for d in e.value.diagnostics)


async def test_reload_runs_the_edited_code(tmp_path: Path, monkeypatch: Any) -> None:
    module = tmp_path / "my_algo.py"
    code = textwrap.dedent(
        """
        from flowrt import Input, Node, Output

        class Algo(Node):
            value = Input(int)
            out = Output(float)

            def process(self, value):
                return {factor} * value
        """
    )
    module.write_text(code.format(factor=1))
    monkeypatch.syspath_prepend(str(tmp_path))
    g = GraphBuilder("reload")
    g.add("src", "counter", trigger={"timer": "10ms"}, params={"start": 1})
    g.add("alg", "my_algo:Algo", inputs={"value": "src.value"})
    clock = VirtualClock()
    try:
        async with Runtime(g.build(), clock=clock) as rt:
            out = rt.subscribe("alg.out", size=1024)
            await clock.advance(0.1)
            before = out.drain()
            module.write_text(code.format(factor=-1))
            await rt.reload("alg")
            await clock.advance(0.1)
            after = out.drain()
            kind = rt.stats().node("alg").kind
    finally:
        sys.modules.pop("my_algo", None)
    assert all(v > 0 for v in before)
    assert after
    assert all(v < 0 for v in after)
    assert kind == "my_algo:Algo"


async def test_swap_of_a_process_node() -> None:
    g = GraphBuilder("swap-process")
    g.add("src", "counter", trigger={"timer": "20ms"}, params={"start": 1})
    g.add("alg", "relay", inputs={"input": "src.value"}, placement="process")
    async with Runtime(g.build()) as rt:
        out = rt.subscribe("alg.output", size=1024)
        await asyncio.sleep(0.3)
        before = out.drain()
        # a loaded machine's worker answers later: waited for (bounded), before and after
        await wait_until(lambda: bool(drained(out, before)))
        await rt.swap("alg", "burn", {"ms": 0.1})
        await asyncio.sleep(0.3)
        after = out.drain()
        await wait_until(lambda: bool(drained(out, after)))
        alg = rt.stats().node("alg")
    assert before
    assert after
    assert alg.kind == "burn"
    assert alg.errors == 0
    assert alg.placement == "process"


class Spinner(Node):
    """A free-running (loop-triggered) node: released again as soon as it returns."""

    class Params(BaseModel):
        sign: int = 1

    out = Output(int)

    async def process(self) -> int:
        await asyncio.sleep(0.002)
        return self.params.sign


async def test_swap_of_a_loop_triggered_node() -> None:
    g = GraphBuilder("swap-loop")
    g.add("spin", Spinner, trigger="loop")
    async with Runtime(g.build()) as rt:
        out = rt.subscribe("spin.out", size=100_000)
        await asyncio.sleep(0.1)
        await rt.swap("spin", Spinner, {"sign": -1})
        await asyncio.sleep(0.1)
        values = out.drain()
        errors = rt.stats().node("spin").errors
    assert 1 in values
    assert -1 in values
    assert values.index(-1) > values.index(1)
    assert set(values[values.index(-1) :]) == {-1}  # no old instance after the swap
    assert errors == 0


async def test_bad_params_are_one_line_without_pydantic_links() -> None:
    """Issue 43: ``ctl swap --params '{"object": 5}'`` printed pydantic's documentation URL."""
    clock = VirtualClock()
    async with Runtime(graph(), clock=clock) as rt:
        with pytest.raises(SwapError) as info:
            await rt.swap("alg", Doubler, {"factor": "not a number"})
    text = str(info.value)
    assert "factor: " in text
    assert "'not a number'" in text
    assert "pydantic.dev" not in text
    assert "\n" not in text


CAN_GRAPH = Path(__file__).resolve().parent.parent / "graphs" / "can.yaml"


@pytest.mark.realtime
async def test_a_node_whose_ports_come_from_its_params_swaps_and_reloads() -> None:
    """A ``can`` node's ports are its DBC's messages: every swap or reload of one was refused
    ("kind 'can' has no port(s) MotorSetpoints, MotorSetpoints, ...")."""
    async with Runtime.from_file(CAN_GRAPH) as rt:
        await rt.run(0.3)
        await rt.swap("chassis", "can", {"max_bad": 3})
        await rt.reload("chassis")
        await rt.run(0.3)
        chassis = rt.stats().node("chassis")
        assert (chassis.state, chassis.errors) == ("idle", 0), chassis
