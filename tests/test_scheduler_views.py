"""The scheduler's read API (``flowrt.kernel.views``): what modules outside the kernel read of
a node, as snapshots that cannot change the node or change under their reader."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

import flowrt
from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock
from flowrt.kernel import NodeView


class Reporting(Node):
    """A node with a ``report()``: what ``RuntimeStats.reports`` carries."""

    out = Output(int)

    def process(self, inputs: dict[str, Any]) -> dict[str, Any]:
        return {"out": 1}

    def report(self) -> dict[str, int]:
        return {"seen": 1}


def graph() -> Any:
    g = GraphBuilder("views")
    g.add("fast", "counter", trigger={"timer": "50ms"}, deadline="40ms", priority=30)
    g.add("slow", Reporting, trigger={"timer": "100ms"}, priority=20)
    return g.build()


async def test_timing_of_is_a_copy() -> None:
    async with Runtime(graph(), clock=VirtualClock()) as rt:
        tm = rt.scheduler.timing_of("slow")
        tm.priority = 99  # the reader's copy: the node keeps its priority
        assert rt.scheduler.timing_of("slow").priority == 20
        rt.set_timing("slow", priority=25)
        assert (tm.priority, rt.scheduler.timing_of("slow").priority) == (99, 25)
        with pytest.raises(KeyError):
            rt.scheduler.timing_of("nobody")


async def test_views_are_snapshots_in_the_graphs_order() -> None:
    clock = VirtualClock()
    async with Runtime(graph(), clock=clock) as rt:
        before = rt.scheduler.node_views()
        await clock.advance(0.5)
        after = {v.name: v for v in rt.scheduler.node_views()}
        assert rt.scheduler.node_view("fast") == after["fast"]
        assert rt.stats().reports == {"slow": {"seen": 1}}
    assert [v.name for v in before] == ["fast", "slow"]
    assert all(isinstance(v, NodeView) for v in before)
    assert before[0].activations == 0  # taken before the run: it did not move
    assert after["fast"].activations == rt.stats().node("fast").activations >= 9
    assert after["fast"].timing.deadline == pytest.approx(0.04)
    assert after["slow"].node.spec.priority == 20
    with pytest.raises(AttributeError):
        after["fast"].activations = 0  # type: ignore[misc]


@pytest.mark.parametrize("module", ["runtime/_qos.py", "runtime/_stats.py", "runtime/_modes.py"])
def test_readers_outside_the_kernel_use_the_read_api(module: str) -> None:
    """The overload controller, the statistics and the timing check read nodes through views
    and ``timing_of``, not through runners (issue 39: qos alone read 21 runner fields)."""
    source = (Path(flowrt.__file__).parent / module).read_text()
    allowed = {"runtime/_modes.py": 1}  # admission control's RunnerView, not yet a view
    found = re.findall(r"\.runners\b|\.rnode\b|\.counts\.|NodeRunner", source)
    assert len(found) == allowed.get(module, 0), found
