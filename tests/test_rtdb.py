"""The RTDB: latest value, validity and stale reads, history, sharing with worker processes."""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import dataclass
from typing import Any

import pytest

from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock
from flowrt.frames import SHM_DIR
from flowrt.rtdb import RTDB, RtdbHandle


@dataclass(frozen=True)
class Ball:
    """Tracker object info, as CAMBADA's trackers put it in the RTDB."""

    x: float
    y: float
    seen: bool


class FakeTime:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_latest_value_history_and_names() -> None:
    clock = FakeTime()
    with RTDB(clock=clock, history=4) as db:
        assert db.read("ball") is None
        assert db.history("ball") == []
        assert "ball" not in db
        for i in range(6):
            clock.t += 0.01
            assert db.write("ball", Ball(i, -i, True)) == i + 1
        db.write("robot.pose", (1.0, 2.0, 0.5))
        rec = db.read("ball")
        assert rec is not None
        assert rec.value == Ball(5, -5, True)
        assert rec.seq == 6
        assert rec.timestamp == pytest.approx(0.06)
        assert rec.age == 0.0
        assert not rec.stale
        assert rec.validity is None
        assert [r.value.x for r in db.history("ball")] == [2, 3, 4, 5]  # ring of 4, oldest first
        assert [r.seq for r in db.history("ball", 2)] == [5, 6]
        assert db.names() == ["ball", "robot.pose"]
        assert db.value("missing", "default") == "default"
        with pytest.raises(ValueError, match="max_value"):
            db.write("big", b"x" * 10_000)
        with pytest.raises(ValueError, match="record name"):
            db.write("", 1)


def test_stale_read_after_the_validity_window() -> None:
    clock = FakeTime()
    with RTDB(clock=clock) as db:
        db.write("ball", Ball(1, 2, True), validity_ms=100)
        clock.t += 0.099
        rec = db.read("ball")
        assert rec is not None
        assert not rec.stale
        assert rec.validity == pytest.approx(0.1)
        clock.t += 0.002
        rec = db.read("ball")
        assert rec is not None
        assert rec.stale
        assert rec.age == pytest.approx(0.101)
        assert db.value("ball", fresh=True) is None  # a stale value is not handed out as fresh
        assert db.value("ball") == Ball(1, 2, True)
        # a declared validity applies to writes that give none; a new write is fresh again
        db.declare("ball", validity_ms=50)
        db.write("ball", Ball(3, 4, True))
        clock.t += 0.049
        assert not db.read("ball").stale  # type: ignore[union-attr]
        clock.t += 0.002
        assert db.read("ball").stale  # type: ignore[union-attr]
        # timestamped at capture time: already old when written
        db.write("ball", Ball(5, 6, True), timestamp=clock.t - 0.2, validity_ms=100)
        assert db.read("ball").stale  # type: ignore[union-attr]


def test_segment_is_named_for_reclaim_and_removed_on_close() -> None:
    db = RTDB()
    name = os.path.basename(db.path)
    assert name.startswith(f"flowrt_{os.getpid()}_rtdb")
    db.write("x", 1)
    other = RTDB.attach(db.handle)
    assert other.read("x").value == 1  # type: ignore[union-attr]
    other.close()
    assert os.path.exists(db.path)  # an attached copy never unlinks
    db.close()
    assert not os.path.exists(db.path)
    db.close()  # idempotent


def _writer(handle: RtdbHandle, n: int) -> None:
    db = RTDB.attach(handle)
    for i in range(n):
        db.write("pair", (i, -i, str(i) * (i % 50)))  # sizes vary: torn reads would show
    db.write("done", True)
    db.close()


def test_reads_are_consistent_while_another_process_writes() -> None:
    with RTDB() as db:
        proc = multiprocessing.get_context("spawn").Process(
            target=_writer, args=(db.handle, 20_000)
        )
        proc.start()
        reads = 0
        last = -1
        deadline = time.monotonic() + 30
        while db.read("done") is None and time.monotonic() < deadline:
            rec = db.read("pair")
            if rec is None:
                continue
            i, j, s = rec.value
            assert j == -i
            assert s == str(i) * (i % 50)
            assert i >= last  # never an older value after a newer one
            last = i
            reads += 1
            history = db.history("pair", 4)
            assert [r.value[0] for r in history] == sorted(r.value[0] for r in history)
        proc.join(10)
        assert proc.exitcode == 0
        assert reads > 10
        assert db.read("pair").value[0] == 19_999  # type: ignore[union-attr]


class Tracker(Node):
    """Writes what it 'sees' into the RTDB, valid for 100 ms, and reads another record."""

    out = Output(object)

    def process(self) -> Any:
        self.ctx.rtdb.write("ball", Ball(1.0, 2.0, True), validity_ms=100)
        rec = self.ctx.rtdb.read("command")
        return None if rec is None else (rec.value, rec.stale)


async def test_nodes_write_and_read_records_on_runtime_time() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("ball_fr", Tracker, trigger={"timer": "1000ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        out = rt.subscribe("ball_fr.out")
        await clock.advance(0.01)
        rec = rt.rtdb.read("ball")
        assert rec is not None
        assert rec.value == Ball(1.0, 2.0, True)
        assert rec.timestamp == pytest.approx(0.0)
        await clock.advance(0.05)
        assert not rt.rtdb.read("ball").stale  # type: ignore[union-attr]
        await clock.advance(0.06)
        assert rt.rtdb.read("ball").stale  # type: ignore[union-attr]  # tracker quiet 110 ms
        rt.rtdb.write("command", "attack", validity_ms=500)
        await clock.advance(1.0)  # next activation at t=1 s: the command is 0.89 s old
        assert out.get_nowait() == ("attack", True)
        path = rt.rtdb.path
    left = [n for n in os.listdir(SHM_DIR) if n.startswith(f"flowrt_{os.getpid()}_rtdb")]
    assert os.path.basename(path) not in left  # no segment outlives the runtime
    assert not left


class WorkerTracker(Node):
    """Runs in a worker process: reads the main process's record, writes its own."""

    out = Output(object)

    def process(self) -> Any:
        cmd = self.ctx.rtdb.value("command")
        self.ctx.rtdb.write("from_worker", (os.getpid(), cmd))
        return cmd


async def test_worker_processes_share_the_records() -> None:
    g = GraphBuilder()
    g.add("tracker", WorkerTracker, trigger={"timer": "20ms"}, placement="process")
    async with Runtime(g.build()) as rt:
        rt.rtdb.write("command", "defend")
        rec = None
        for _ in range(200):
            await rt.run(0.025)
            rec = rt.rtdb.read("from_worker")
            if rec is not None and rec.value[1] == "defend":
                break
        assert rec is not None
        pid, cmd = rec.value
        assert cmd == "defend"
        assert pid != os.getpid()
        assert rt.stats().node("tracker").errors == 0


async def test_runtime_without_rtdb_use_creates_no_segment() -> None:
    mine = f"flowrt_{os.getpid()}_rtdb"  # other processes on the machine have their own

    def segments() -> set[str]:
        return {n for n in os.listdir(SHM_DIR) if n.startswith(mine)}

    before = segments()
    g = GraphBuilder()
    g.add("a", "counter", trigger={"timer": "10ms"})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock):
        await clock.advance(0.05)
        assert segments() == before
