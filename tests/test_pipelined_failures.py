"""A failure with pipelined calls in flight: one failure per node instance, whatever failed.

A node at ``placement: process`` fed by a queue has up to ``pipeline`` (default 4) calls in
flight. When one fails, the instance is gone: the calls sent behind it are lost with it
(counted as ``aborted``), the back-off starts once, and a node given up stays given up.
A call that raises always did so; a result whose output check fails on the loop (a
misspelt key: an ``OutputError``) used to fail each call in flight in turn, each counted as
a new failure with a restart (or a give-up) of its own: 10 failures within a second instead
of a back-off, "given up" said again and again, and the node restarted after being given up.

Each row is the same graph with the failing node placed, pipelined and failing differently;
the window-1 rows (``pipeline: 1``, inline) are the reference the pipelined rows must match.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest

import flowrt
from flowrt import GraphBuilder, Input, Node, Output, Runtime

pytestmark = [pytest.mark.timeout(60), pytest.mark.subprocess]

BURST = 8  # values per tick of the source: more than a window, all queued at once


class Bursts(Node):
    """``BURST`` values per activation: the whole window is sent to the worker at once."""

    value = Output(float)

    def process(self) -> None:
        for i in range(BURST):
            self.ctx.publish("value", float(i))


class MisspeltOutput(Node):
    """Outputs ``score`` and ``level``; returns ``scor`` (the new user's typo)."""

    x = Input(float)
    score = Output(float)
    level = Output(float)

    def process(self, x: float) -> dict[str, float]:
        return {"scor": x, "level": 2.0}


class Raises(Node):
    """The same node, raising instead (the path that always backed off)."""

    x = Input(float)
    score = Output(float)
    level = Output(float)

    def process(self, x: float) -> dict[str, float]:
        raise ValueError("boom")


# id: (failing node, placement, pipeline, the window it gets)
ROWS: dict[str, tuple[type[Node], str, int | None, int]] = {
    "process-outputerror": (MisspeltOutput, "process", None, 4),
    "process-raise": (Raises, "process", None, 4),
    "process-pipeline1-outputerror": (MisspeltOutput, "process", 1, 1),
    "inline-outputerror": (MisspeltOutput, "inline", None, 1),
}


def _graph(row: str, restart: dict[str, Any]) -> flowrt.Graph:
    cls, placement, pipeline, _ = ROWS[row]
    extra: dict[str, Any] = {} if pipeline is None else {"pipeline": pipeline}
    g = GraphBuilder("pipelined_failures")
    g.add("src", Bursts, trigger={"timer": "50ms"})
    g.add(
        "n",
        cls,
        trigger={"input": "x"},
        inputs={"x": {"from": "src.value", "policy": "queue", "size": 2 * BURST}},
        placement=placement,
        restart=restart,
        **extra,
    )
    return g.build()


def _events(rt: Runtime, kind: type[flowrt.Event]) -> list[flowrt.Event]:
    return [e for e in rt.events if isinstance(e, kind) and e.node == "n"]


async def _until(rt: Runtime, done: Callable[[], bool], what: str, within: float = 10.0) -> None:
    """Run until ``done()`` (a worker's start-up, a call's round trip take a while on a
    loaded machine: bounded, not a fixed wait)."""
    end = time.monotonic() + within
    while not done():
        assert time.monotonic() < end, f"not {what} within {within} s"
        await rt.run(0.005)


def _settled(rt: Runtime, failures: int, window: int) -> Callable[[], bool]:
    """``failures`` failures, and the calls in flight of each failed instance back (aborted):
    or a failure more, which is what the test is to see."""

    def done() -> bool:
        n = rt.stats().node("n")
        return n.errors > failures or (
            n.errors == failures and n.aborted >= failures * (window - 1)
        )

    return done


@pytest.mark.parametrize("row", list(ROWS))
async def test_one_failure_per_instance_then_backoff(row: str) -> None:
    """The first failure moves the node to back-off; the calls in flight behind it are
    counted as aborted, not as failures of their own; the restarted instance fails once."""
    window = ROWS[row][3]
    restart = {"backoff": "500ms", "max_backoff": "500ms", "max_failures": None}
    async with Runtime(_graph(row, restart)) as rt:
        assert rt.scheduler.runners["n"].window == window  # the row tests what it says
        await _until(rt, _settled(rt, 1, window), "failed once")
        first = rt.stats().node("n")
        failed_first = len(_events(rt, flowrt.NodeFailed))
        await _until(rt, _settled(rt, 2, window), "failed twice")
        second = rt.stats().node("n")
        failed_second = len(_events(rt, flowrt.NodeFailed))
        restarted = len(_events(rt, flowrt.NodeRestarted))
    # Before the first restart: one failure, the node in back-off.
    assert (failed_first, first.errors, first.restarts) == (1, 1, 0)
    assert first.state == "backoff"
    assert first.completions == 0
    # The calls sent behind the failing one were lost with its instance (none: window 1).
    assert first.aborted == window - 1
    # The restarted instance failed once too (its window again lost with it).
    assert (failed_second, second.errors, second.restarts, restarted) == (2, 2, 1, 1)
    assert second.state == "backoff"
    assert second.aborted == 2 * (window - 1)


@pytest.mark.parametrize("row", list(ROWS))
async def test_given_up_stays_given_up(row: str) -> None:
    """``max_failures: 3``: three instances, each failing once, then given up, said once;
    the calls in flight of the last one change nothing (no error, restart or give-up)."""
    restart = {"max_failures": 3, "backoff": "30ms", "max_backoff": "30ms"}
    async with Runtime(_graph(row, restart), stop_on_failure=False) as rt:
        await _until(rt, lambda: bool(_events(rt, flowrt.NodeGaveUp)), "given up")
        at_give_up = rt.stats().node("n")
        await rt.run(0.3)  # six more bursts of the source, and the back-off of any restart
        after = rt.stats().node("n")
        failed = len(_events(rt, flowrt.NodeFailed))
        gave_up = len(_events(rt, flowrt.NodeGaveUp))
        restarted = len(_events(rt, flowrt.NodeRestarted))
    assert (failed, gave_up, restarted) == (3, 1, 2)
    assert (at_give_up.errors, at_give_up.restarts) == (3, 2)
    assert (after.errors, after.restarts) == (3, 2)  # not counting after the give-up
    assert after.state == "failed"
    assert "3 consecutive failures" in after.reason
    assert after.completions == 0
