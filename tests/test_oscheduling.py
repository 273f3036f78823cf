"""OS scheduling of workers without SCHED_FIFO: nice by rank, CPU pinning, spin-waiting."""

from __future__ import annotations

import asyncio
import os
import resource
import time
from typing import Any

import psutil
import pytest

from flowrt.system._priorities import FairShare, lowest_nice
from flowrt.workers import PoolExecutor, ProcessExecutor
from flowrt.workers.child import Anticipation, Linger


class Pid:
    def process(self, **inputs: Any) -> int:
        return os.getpid()


@pytest.mark.parametrize(
    ("floor", "expected"),
    [
        # root: the loop at -20, the top priority 3 levels above it, then 3 per rank
        (-20, {45: -17, 40: -14, 35: -11, 25: -8, 20: -5, 15: -2}),
        # no privilege: everyone at or above the machine's nice 0, still ranked
        (0, {45: 0, 40: 3, 35: 6, 25: 9, 20: 12, 15: 15}),
        # a limit of -5 (RLIMIT_NICE 25): the top rank may not go above 0
        (-5, {45: -2, 40: 1, 35: 4, 25: 7, 20: 10, 15: 13}),
    ],
)
def test_fair_share_ranks_priorities_three_levels_apart(
    floor: int, expected: dict[int, int]
) -> None:
    fair = FairShare([45, 45, 40, 35, 25, 20, 15, 15], floor)
    assert {p: fair.nice(p) for p in expected} == expected


def test_fair_share_places_unknown_priorities_and_caps_at_19() -> None:
    fair = FairShare([50, 10], floor=10)
    assert fair.nice(60) == fair.nice(50) == 10  # above the top: the top's level
    assert fair.nice(30) == 13  # between: ranks below 50
    assert fair.nice(10) == 13
    assert fair.nice(1) == 16  # below both
    assert FairShare(range(1, 20), floor=0).nice(1) == 19


def test_lowest_nice_is_what_the_kernel_allows() -> None:
    low = lowest_nice()
    current = os.getpriority(os.PRIO_PROCESS, 0)
    assert -20 <= low <= current
    if os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_NICE)[0] == 0:
        assert low == current


async def test_worker_is_pinned_to_its_cpus_and_reports_it() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    pinned = ProcessExecutor("pinned", Pid, priority=30, realtime=False, cpus=(cpus[-1],))
    free = ProcessExecutor("free", Pid, priority=30, realtime=False)
    await asyncio.gather(pinned.start(), free.start())
    try:
        pid = await pinned.call({})
        assert os.sched_getaffinity(pid) == {cpus[-1]}
        assert pinned.granted.endswith(f"cpus {cpus[-1]}"), pinned.granted
        assert os.sched_getaffinity(await free.call({})) == set(cpus)
        assert "cpus" not in free.granted
    finally:
        await asyncio.gather(pinned.stop(), free.stop())


async def test_partly_available_cpus_pin_to_those_that_exist() -> None:
    ex = ProcessExecutor("part", Pid, priority=30, realtime=False, cpus=(0, 4095))
    await ex.start()
    try:
        assert os.sched_getaffinity(await ex.call({})) == {0}
        assert ex.granted.endswith("cpus 0 (asked 0,4095)"), ex.granted
    finally:
        await ex.stop()


async def test_unavailable_cpu_is_reported_not_fatal() -> None:
    ex = ProcessExecutor("far", Pid, priority=30, realtime=False, cpus=(4096,))
    await ex.start()
    try:
        assert "cpus 4096 not available" in ex.granted
        assert await ex.call({}) == ex.pid  # still runs, on the CPUs it had
    finally:
        await ex.stop()


async def test_nice_comes_from_the_runtime_ranking() -> None:
    fair = FairShare([45, 15], floor=os.getpriority(os.PRIO_PROCESS, 0))
    low = ProcessExecutor("low", Pid, priority=15, realtime=False, nice_of=fair.nice)
    await low.start()
    try:
        assert low.granted == f"nice {fair.nice(15)}"
        assert psutil.Process(low.pid).nice() == fair.nice(15)
    finally:
        await low.stop()


async def test_pool_switches_cpus_per_node() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    pool = PoolExecutor("p", size=1, realtime=False)
    a = pool.executor_for("a", Pid, priority=30, cpus=(cpus[0],))
    b = pool.executor_for("b", Pid, priority=30)
    await a.start()
    await b.start()
    try:
        pid = await a.call({})
        assert os.sched_getaffinity(pid) == {cpus[0]}
        assert await b.call({}) == pid
        assert os.sched_getaffinity(pid) == set(cpus)
    finally:
        await pool.stop()


def test_anticipation_predicts_the_next_periodic_call() -> None:
    a = Anticipation()
    a.configure(1, 0.0003)
    assert a.window(0.0) is None  # nothing known yet
    for k in range(5):
        a.called(1, 10.0 + 0.05 * k)
    start, end = a.window(10.21) or (0.0, 0.0)
    assert start == pytest.approx(10.25 - 0.0003)
    assert end == pytest.approx(10.25 + 0.0003)
    # the expected call did not come: look at the one after
    start, _ = a.window(10.26) or (0.0, 0.0)
    assert start == pytest.approx(10.30 - 0.0003)
    start, _ = a.window(11.001) or (0.0, 0.0)  # many skipped: the next one still ahead
    assert start == pytest.approx(11.05 - 0.0003)
    a.configure(1, 0.0)
    assert a.window(10.26) is None


def test_anticipation_ignores_calls_too_close_to_spin_between() -> None:
    a = Anticipation()
    a.configure(1, 0.0003)
    for k in range(6):
        a.called(1, 1.0 + 0.001 * k)  # 1 ms apart: spinning 0.6 ms of each would be waste
    assert a.window(1.01) is None
    b = Anticipation()
    b.configure(1, 0.0003)
    for _ in range(6):
        b.called(1, 2.0)  # all at once: no period at all
    assert b.window(2.0) is None


def test_anticipation_ignores_irregular_calls() -> None:
    a = Anticipation()
    a.configure(1, 0.0003)
    for t in (0.0, 0.05, 0.06, 0.2, 0.21):
        a.called(1, t)
    assert a.window(0.22) is None


def test_linger_only_for_calls_back_to_back() -> None:
    """Three requests running within the span of their reply: poll before sleeping; the
    first that comes later ends it; a periodic node never lingers."""
    ln = Linger(span=0.0002)
    t = 1.0
    for _ in range(2):
        ln.replied_at(t)
        t += 0.00005
        ln.arrived(t)
    assert ln.window(t) is None  # two are not a stream yet
    ln.replied_at(t)
    ln.arrived(t + 0.00005)
    assert ln.window(2.0) == (2.0, 2.0 + 0.0002)
    ln.alone = False  # calls pipelined behind it: the loop, not the worker, is waited for
    assert ln.window(2.0) is None
    ln.alone = True
    ln.replied_at(3.0)
    ln.arrived(3.0 + 0.001)  # the stream slowed: sleep in recv again
    assert ln.window(3.1) is None
    periodic = Linger(span=0.0002)
    for k in range(10):
        periodic.replied_at(k * 0.033)
        periodic.arrived(k * 0.033 + 0.0329)
    assert periodic.window(1.0) is None


async def test_spinning_worker_serves_periodic_and_late_calls() -> None:
    ex = ProcessExecutor("spin", Pid, priority=30, realtime=False, spin=0.002)
    await ex.start()
    try:
        for _ in range(6):
            assert await ex.call({}) == ex.pid
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.1)  # far past the expected call: the worker blocks again
        t0 = time.monotonic()
        assert await ex.call({}) == ex.pid
        assert time.monotonic() - t0 < 1.0
        cpu = psutil.Process(ex.pid).cpu_times()
        assert cpu.user + cpu.system < 1.0  # it spun around calls, not all the time
    finally:
        await ex.stop()
