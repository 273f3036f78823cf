"""The loop keeps off the CPUs of pinned workers while others remain (system/_loop_cpus)."""

from __future__ import annotations

import os
import threading
from typing import Any

import pytest

from flowrt.graph._loading import load_text
from flowrt.graph._resolve import resolve
from flowrt.system._loop_cpus import LoopCpus

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
    reason="needs CPU affinity and two CPUs",
)

GRAPH = """
name: pinned
nodes:
  cam: {kind: capture, params: {source: "synthetic:soccer"}}
  ball:
    kind: tracker
    params: {object: ball}
    trigger: {frame: cam}
    inputs: {frame: cam.frame}
    placement: PLACEMENT
    CPUS
"""


def _in_a_thread(text: str) -> tuple[str, set[int], set[int]]:
    """apply() and restore() on a thread of their own (the test process keeps its CPUs):
    what apply said, the thread's CPUs after apply and after restore."""
    graph = resolve(*load_text(text))
    out: dict[str, Any] = {}

    def run() -> None:
        cpus = LoopCpus()
        cpus.apply(graph)
        out["said"] = cpus.granted
        out["during"] = os.sched_getaffinity(0)
        cpus.restore()
        out["after"] = os.sched_getaffinity(0)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return out["said"], out["during"], out["after"]


@pytest.mark.parametrize(
    ("placement", "cpus", "kept_off"),
    [
        ("process", "cpus: [FIRST]", True),  # a pinned worker: its CPU is its own
        ("process", "", False),  # not pinned: the loop keeps every CPU
        ("pool", "", False),  # workers, none pinned
        ("process", "cpus: [ALL]", False),  # no CPU would be left: unchanged
    ],
)
def test_the_loop_keeps_off_pinned_workers_cpus(placement: str, cpus: str, kept_off: bool) -> None:
    mine = os.sched_getaffinity(0)
    first = min(mine)
    cpus = cpus.replace("FIRST", str(first)).replace("ALL", ", ".join(map(str, sorted(mine))))
    said, during, after = _in_a_thread(GRAPH.replace("PLACEMENT", placement).replace("CPUS", cpus))
    assert after == mine
    if kept_off:
        assert during == mine - {first}
        assert said.startswith("cpus ")
        assert f"not {first}" in said
    else:
        assert during == mine
        assert said == ""


def test_a_run_with_a_pinned_worker_moves_the_loop_and_gives_its_cpus_back() -> None:
    """End to end: a tracker in a worker pinned to the first CPU; the loop thread runs on the
    others during the run (its scheduling says so) and has every CPU again after it."""
    import flowrt

    mine = os.sched_getaffinity(0)
    first = min(mine)
    text = GRAPH.replace("PLACEMENT", "process").replace("CPUS", f"cpus: [{first}]")
    out: dict[str, Any] = {}

    async def run() -> None:
        async with flowrt.Runtime(resolve(*load_text(text))) as rt:
            await rt.run(0.5)
            out["during"] = os.sched_getaffinity(0)
            out["said"] = rt.stats().loop_scheduling
            out["ball"] = next(n for n in rt.stats().nodes if n.name == "ball").completions

    def thread() -> None:
        flowrt.run(run())
        out["after"] = os.sched_getaffinity(0)

    t = threading.Thread(target=thread)
    t.start()
    t.join(60)
    assert out["during"] == mine - {first}
    assert f"cpus {','.join(map(str, sorted(mine - {first})))} (not {first})" in out["said"]
    assert out["after"] == mine
    assert out["ball"] > 0  # the pinned worker ran
