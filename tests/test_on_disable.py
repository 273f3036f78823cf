"""A node disabled while it runs leaves what it drives safe (``Node.on_disable``,
flowrt/kernel/disabling.py): the hook runs once per disabling, between calls and never beside
one, not at all when the node is enabled again before its running call ended; the haptic
node's device force is zero from the disabling on (it kept its last force before)."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from pydantic import BaseModel, ConfigDict

from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock


class Driver(Node):
    """Commands a device each tick; its hook says when it ran and whether a call was on."""

    out = Output(int)

    def setup(self) -> None:
        self.calls = 0
        self.in_call = False
        self.hooks: list[tuple[int, bool]] = []  # (calls so far, a call was running)

    def process(self) -> int:
        self.calls += 1
        return self.calls

    def on_disable(self) -> None:
        self.hooks.append((self.calls, self.in_call))


class SlowDriver(Driver):
    """A coroutine node whose call ends when the test opens its gate."""

    def setup(self) -> None:
        super().setup()
        self.gate = asyncio.Event()

    async def process(self) -> int:  # type: ignore[override]
        self.in_call = True
        await self.gate.wait()
        self.gate.clear()
        self.calls += 1
        self.in_call = False
        return self.calls


def _node(rt: Runtime, name: str) -> Any:
    return rt.scheduler.runners[name].executor.node  # type: ignore[attr-defined]


async def _runtime_with(cls: type[Node]) -> tuple[Runtime, VirtualClock]:
    g = GraphBuilder()
    g.add("d", cls, trigger={"timer": "10ms"})
    clock = VirtualClock()
    return Runtime(g.build(), clock=clock), clock


# (the steps, each "off"/"on" or a virtual wait in ms; the hooks expected)
CASES = [
    (["off"], 1),
    (["off", "off"], 1),  # disabled once: one hook
    (["off", 50, "on", 50, "off"], 2),
    (["on"], 0),  # enabling an enabled node is no disabling
]


@pytest.mark.parametrize(("steps", "hooks"), CASES, ids=[str(c[0]) for c in CASES])
async def test_the_hook_runs_once_per_disabling(steps: list[Any], hooks: int) -> None:
    rt, clock = await _runtime_with(Driver)
    async with rt:
        await clock.advance(0.1)
        for step in steps:
            if isinstance(step, int):
                await clock.advance(step / 1000)
            else:
                rt.set_timing("d", enabled=step == "on")
        await clock.advance(0.1)
        node = _node(rt, "d")
        assert len(node.hooks) == hooks
        if hooks and steps[-1] == "off":
            calls_at_hook = node.hooks[-1][0]
            assert node.calls == calls_at_hook  # no call after the last disabling's hook


class Publisher(Driver):
    """Its hook returns what to publish, as ``process`` does (a zero command)."""

    def on_disable(self) -> int:  # type: ignore[override]
        super().on_disable()
        return -1


class Wrong(Driver):
    def on_disable(self) -> str:  # type: ignore[override]
        return "not an int"


class Raising(Driver):
    def on_disable(self) -> None:
        raise RuntimeError("motor brake failed")


# (the node's class, what its disabling published, its state after, its reason)
HOOKS = [
    (Publisher, [-1], "idle", ""),  # published as process's result is
    (Wrong, [], "failed", "on_disable() failed: OutputError"),  # refused: the node fails
    (Raising, [], "failed", "motor brake failed"),
]


@pytest.mark.parametrize(("cls", "published", "state", "why"), HOOKS, ids=lambda c: str(c))
async def test_what_the_hook_returns_is_published_and_a_failure_fails_the_node(
    cls: type[Node], published: list[int], state: str, why: str
) -> None:
    """A failed safe-state hook was logged only, the run exiting 0 with the device perhaps
    left pushing: the node is given up (torn down), its reason said, the run's failure."""
    rt, clock = await _runtime_with(cls)
    async with rt:
        await clock.advance(0.1)
        sub = rt.subscribe("d.out", size=100)
        rt.set_timing("d", enabled=False)
        await clock.advance(0.05)
        assert sub.drain() == published
        rt.set_timing("d", enabled=True)  # (while disabled, the table says "disabled")
        await clock.advance(0.1)
        node = rt.stats().node("d")
        assert (node.state, why in node.reason) == (state, True)
        if state == "failed":
            assert sub.drain() == []  # failed for good: enabling it runs nothing
            assert node.errors == 1
            assert [f.name for f in rt.failures()] == ["d"]


async def test_a_running_call_ends_before_the_hook() -> None:
    rt, clock = await _runtime_with(SlowDriver)
    async with rt:
        await clock.advance(0.015)  # the first call (released at 10 ms) runs until its gate
        node = _node(rt, "d")
        assert node.in_call
        rt.set_timing("d", enabled=False)
        await clock.advance(0.05)
        assert node.hooks == []  # not beside the running call
        node.gate.set()
        await clock.advance(0.01)
        assert node.hooks == [(1, False)]
        assert node.calls == 1


async def test_enabled_again_before_the_call_ended_no_hook() -> None:
    rt, clock = await _runtime_with(SlowDriver)
    async with rt:
        await clock.advance(0.015)
        rt.set_timing("d", enabled=False)
        rt.set_timing("d", enabled=True)
        node = _node(rt, "d")
        node.gate.set()
        await clock.advance(0.1)
        assert node.calls >= 1
        assert node.hooks == []


class Source(Node):
    out = Output(object)  # published by the test


async def test_a_disabled_haptic_node_pushes_no_more() -> None:
    """1.5 N asked for ever (a fresh force every 10 ms): disabled, the device's force is zero
    from then on (it was 1.5 N for as long as the node stayed disabled); enabled again, the
    force ramps back from zero at the rate limit."""
    g = GraphBuilder()
    g.add("f", Source, trigger={"timer": 3_600_000}, enabled=False)
    sim = {"hand": {"mode": "none"}}
    params = {"sim": sim, "max_force": 3.0, "max_rate": 100.0, "timeout": "1s"}
    g.add("haptic", "haptic", params=params, inputs={"force": "f.out"})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        for _ in range(50):
            rt.publish("f.out", [1.5, 0.0, 0.0])
            await clock.advance(0.01)
        device = _node(rt, "haptic").device
        assert device.force[0] == pytest.approx(1.5)
        applied = rt.subscribe("haptic.applied", size=100)
        rt.set_timing("haptic", enabled=False)
        assert device.force == [0.0, 0.0, 0.0]
        said = applied.drain()  # what reads `applied` saw 1.5 N last, the device had 0
        assert [(f.values, f.reason) for f in said] == [((0.0, 0.0, 0.0), "disabled")]
        for _ in range(20):
            rt.publish("f.out", [1.5, 0.0, 0.0])
            await clock.advance(0.01)
        assert device.force == [0.0, 0.0, 0.0]
        rt.set_timing("haptic", enabled=True)
        rt.publish("f.out", [1.5, 0.0, 0.0])
        await clock.advance(0.0015)  # one or two 1 ms ticks: 100 N/s x 2 ms at most
        assert 0.0 < device.force[0] <= 0.2 + 1e-9


class Racer(Node):
    """A precise node whose hook checks that no call of it runs meanwhile (thread side)."""

    out = Output(int)

    def setup(self) -> None:
        self.lock = threading.Lock()
        self.running = False
        self.calls = 0
        self.overlaps = 0
        self.hooks: list[int] = []

    def process(self) -> int:
        with self.lock:
            self.running = True
        time.sleep(0.0002)
        self.calls += 1
        with self.lock:
            self.running = False
        return self.calls

    def on_disable(self) -> None:
        with self.lock:
            self.overlaps += self.running
        self.hooks.append(self.calls)


@pytest.mark.slow
async def test_a_precise_thread_never_runs_beside_the_hook() -> None:
    """Real time: disabled 20 times from the loop while its thread calls it every 1 ms."""
    g = GraphBuilder()
    g.add("r", Racer, trigger={"timer": "1ms"}, timing="precise")
    async with Runtime(g.build()) as rt:
        task = asyncio.ensure_future(rt.run(5.0))
        await asyncio.sleep(0.2)
        node = _node(rt, "r")
        for _ in range(20):
            rt.set_timing("r", enabled=False)
            await asyncio.sleep(0.02)
            calls = node.calls
            await asyncio.sleep(0.01)
            assert node.calls == calls  # disabled: no call after the hook
            rt.set_timing("r", enabled=True)
            await asyncio.sleep(0.02)
        await rt.stop()
        await task
    assert len(node.hooks) == 20
    assert node.overlaps == 0


class FileDriver(Node):
    """In a worker: each hook appends the calls made so far to ``<dir>/hooks``."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str

    out = Output(int)

    def setup(self) -> None:
        self.calls = 0

    def process(self) -> int:
        self.calls += 1
        return self.calls

    def on_disable(self) -> None:
        with Path(self.params.dir, "hooks").open("a") as f:
            f.write(f"{self.calls}\n")


def _hooks(path: Path) -> list[int]:
    return [int(x) for x in path.read_text().split()] if path.exists() else []


@pytest.mark.subprocess  # a worker process
@pytest.mark.timeout(60)
@pytest.mark.parametrize("placement", ["process", "pool"])
async def test_a_worker_node_runs_its_hook_in_its_worker(placement: str, tmp_path: Path) -> None:
    g = GraphBuilder()
    params = {"dir": str(tmp_path)}
    g.add("w", FileDriver, params=params, trigger={"timer": "20ms"}, placement=placement)
    hooks = tmp_path / "hooks"
    async with Runtime(g.build()) as rt:
        task = asyncio.ensure_future(rt.run(30.0))
        assert await wait_until(lambda: rt.stats().node("w").completions >= 3, within=20)
        rt.set_timing("w", enabled=False)
        assert await wait_until(lambda: len(_hooks(hooks)) == 1, within=10)
        done = rt.stats().node("w").completions
        assert _hooks(hooks)[0] == done  # every call sent before it ran before it
        await asyncio.sleep(0.1)
        assert rt.stats().node("w").completions == done  # none after
        rt.set_timing("w", enabled=True)
        assert await wait_until(lambda: rt.stats().node("w").completions > done, within=10)
        rt.set_timing("w", enabled=False)
        assert await wait_until(lambda: len(_hooks(hooks)) == 2, within=10)
        await rt.stop()
        await task
