"""Worker watchdogs: a hung worker is killed, a worker starved of CPU is not (issue 19, item 4)."""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
import time
from typing import Any

import pytest

from flowrt import GraphBuilder, HealthAlert, Input, Node, NodeFailed, Output, Runtime
from flowrt.workers import channel, watchdog


class Work(Node):
    """Tracker-like work: ``ms`` of CPU time per call (so a starved call takes longer)."""

    value = Input(object)
    out = Output(object)

    def process(self, value: Any) -> Any:
        end = time.thread_time() + 0.004
        while time.thread_time() < end:
            pass
        return value


class Forever(Node):
    """Hangs on its third call: spinning on the CPU, or asleep."""

    value = Input(object)
    out = Output(object)
    spin = True

    def setup(self) -> None:
        self.calls = 0

    def process(self, value: Any) -> Any:
        self.calls += 1
        if self.calls == 3:
            while True:
                if not self.spin:
                    time.sleep(0.01)
        return value


class Sleeper(Forever):
    spin = False


# ------------------------------------------------------------------ the decision, from /proc


class _Loop:
    def __init__(self) -> None:
        self.t = 0.0

    def time(self) -> float:
        return self.t


@pytest.mark.parametrize(
    ("cpu", "wait", "state", "starved"),
    [
        (0.010, 0.450, "R", True),  # waited on the run queue nearly all the window
        (0.010, 0.450, "S", True),  # ... and has just gone to sleep: starved all the same
        (0.000, 0.000, "R", True),  # still queued: schedstat counts the wait when it ends
        (0.490, 0.005, "R", False),  # had the CPU and spun: hung
        (0.000, 0.000, "S", False),  # asleep, not waiting for a CPU: hung (blocked)
        (0.200, 0.250, "R", True),  # half-starved: waited more than half the window
        (0.300, 0.150, "R", False),  # waited less than half: hung
        (0.010, None, "R", True),  # no schedstat: runnable and little CPU
        (0.010, None, "S", False),  # no schedstat: asleep
        (0.400, None, "R", False),  # no schedstat: ran most of the window
    ],
)
def test_watchdog_tells_starved_from_hung(
    monkeypatch: pytest.MonkeyPatch, cpu: float, wait: float | None, state: str, starved: bool
) -> None:
    check_starved(monkeypatch, cpu, wait, state, starved)


def test_a_call_that_had_a_whole_watchdog_of_cpu_is_hung(monkeypatch: pytest.MonkeyPatch) -> None:
    """Spinning on a loaded machine: a share of the CPU in each window, never half; the CPU
    time since the call began is what ends it (watchdog 0.5 s)."""
    check_starved(monkeypatch, 0.2, 0.3, "R", True, call_cpu=0.8)  # 0.4 s of CPU in all
    check_starved(monkeypatch, 0.2, 0.3, "R", False, call_cpu=0.7)  # 0.5 s: the watchdog


def check_starved(
    monkeypatch: pytest.MonkeyPatch,
    cpu: float,
    wait: float | None,
    state: str,
    starved: bool,
    call_cpu: float = 1.0,
) -> None:
    """The verdict on a 0.5 s window in which the worker ran ``cpu`` s and waited ``wait``."""
    w = channel.Worker("w")
    loop = _Loop()
    w._loop = loop  # type: ignore[assignment]
    w.pid = 12345
    w._progress = (0.0, 1.0, None if wait is None else 2.0)
    w._call_cpu = call_cpu
    loop.t = 0.5
    progress = (0.5, 1.0 + cpu, None if wait is None else 2.0 + wait)
    monkeypatch.setattr(channel, "progress_of", lambda pid, now: progress)
    monkeypatch.setattr(channel, "state_of", lambda pid: state)
    detail = w._starved(0.5)
    assert bool(detail) is starved
    if starved:
        assert "starved of CPU" in detail


def test_progress_is_read_from_proc() -> None:
    got = watchdog.progress_of(os.getpid(), 1.0)
    assert got is not None
    t, cpu, _ = got
    assert t == 1.0
    assert cpu > 0
    assert watchdog.state_of(os.getpid()) == "R"  # this process, reading its own stat


def graph(node: type[Node], n: int = 1, watchdog: str = "300ms") -> Any:
    g = GraphBuilder("watchdog")
    g.add("src", "counter", trigger={"timer": "50ms"})
    for i in range(n):
        g.add(
            f"w{i}",
            node,
            inputs={"value": "src.value"},
            placement="process",
            watchdog=watchdog,
            restart={"backoff": "20ms"},
        )
    return g.build()


@pytest.mark.subprocess  # a worker (or writer) process, from its graph
@pytest.mark.timeout(30)
@pytest.mark.parametrize("node", [Forever, Sleeper])
async def test_a_hung_worker_is_still_killed(node: type[Node]) -> None:
    failures: list[NodeFailed] = []
    async with Runtime(graph(node)) as rt:
        rt.on_event(lambda e: failures.append(e) if isinstance(e, NodeFailed) else None)
        for _ in range(100):
            await asyncio.sleep(0.05)
            if failures:
                break
    assert failures
    assert "hung" in failures[0].error
    # (on a loaded machine a spinning worker may first be spared as starved, then killed)


# ------------------------------------------------------------------ the reproduction

BUSY = "import time\nt = time.monotonic()\nwhile time.monotonic() - t < {s}:\n    pass\n"


def _chrt_refusal() -> str:
    """Why two SCHED_FIFO busy loops cannot be run here ('' if they can)."""
    if shutil.which("chrt") is None:
        return "chrt is not installed"
    try:
        with open("/proc/sys/kernel/sched_rt_runtime_us") as f:
            if int(f.read()) < 0:
                return "RT throttling is off: SCHED_FIFO busy loops would freeze the machine"
    except OSError:
        return "cannot read /proc/sys/kernel/sched_rt_runtime_us"
    r = subprocess.run(["chrt", "-f", "50", "true"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"chrt -f 50 is not permitted: {r.stderr.strip()}"
    return ""


@pytest.mark.timeout(60)
async def test_cpu_starvation_kills_no_worker() -> None:
    """Two SCHED_FIFO busy loops take both CPUs for 3 s (the kernel's RT throttling leaves
    5 % to everything else) while three workers with 300 ms watchdogs run: none is killed."""
    why = _chrt_refusal()
    if why:
        pytest.skip(why)
    failures: list[NodeFailed] = []
    alerts: list[HealthAlert] = []

    def seen(e: Any) -> None:
        if isinstance(e, NodeFailed):
            failures.append(e)
        elif isinstance(e, HealthAlert) and e.alert == "cpu-starvation":
            alerts.append(e)

    async with Runtime(graph(Work, n=3)) as rt:
        rt.on_event(seen)
        await asyncio.sleep(0.5)
        pids = {n: rt.scheduler.runners[n].executor.pid for n in ("w0", "w1", "w2")}  # type: ignore[attr-defined]
        busy = [
            await asyncio.create_subprocess_exec(
                "chrt", "-f", "50", sys.executable, "-c", BUSY.format(s=3.0)
            )
            for _ in range(2)
        ]
        for p in busy:
            await asyncio.wait_for(p.wait(), 30)
        await asyncio.sleep(1.0)  # calls in flight at the end of the starvation complete
        stats = rt.stats()
        after = {n: rt.scheduler.runners[n].executor.pid for n in pids}  # type: ignore[attr-defined]
    assert [p.returncode for p in busy] == [0, 0]
    assert not failures, [f.error for f in failures]
    assert after == pids
    for n in pids:
        node = stats.node(n)
        assert (node.errors, node.restarts) == (0, 0)
        assert node.completions > 10
    # Each detection is counted; the alert says it once per episode.
    assert len(alerts) <= 1
    assert stats.loop.starvation_events >= len(alerts)


@pytest.mark.subprocess  # a worker process
@pytest.mark.timeout(30)
async def test_a_call_between_a_workers_eof_and_its_exit_fails_with_its_death() -> None:
    """A worker killed from outside closes its socket a moment before its exit is reaped; a
    call in that moment (seen on a loaded machine) failed with a bare "not running" instead
    of who killed it, and its node's failure said nothing of the SIGKILL."""
    from flowrt.workers.errors import WorkerError
    from flowrt.workers.wire import OP_EXIT

    w = channel.Worker("w")
    await w.spawn()
    try:
        os.kill(w.pid, 9)
        assert w._transport is not None
        w._transport.abort()  # the EOF seen, the sentinel not yet
        assert not w.usable
        with pytest.raises(WorkerError) as e:
            await asyncio.wait_for(w.request((OP_EXIT,), "n", 0, None), 5)
        assert e.value.kind == "killed"
        assert "SIGKILL" in str(e.value)
    finally:
        await w.wait_exit()
