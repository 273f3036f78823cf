"""Direct hops between workers (flowrt.kernel.hops, flowrt.workers.hops).

A chain of ``placement: process`` nodes whose frames go straight from worker to worker, the
loop deciding each reader's release ahead: the same results, counters and statistics as the
usual way; the usual way whenever a hop cannot happen (an unstamped frame, a writer that
raises, a worker killed, a node disabled); none where the rules say so (a deadline, a pool).
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from typing import Any

import numpy as np
import pytest
from conftest import drained, wait_until
from pydantic import BaseModel

from flowrt import Frame, GraphBuilder, Input, Node, Output, Runtime
from flowrt.ipc import BlockingConn, pack
from flowrt.workers import hops as worker_hops
from flowrt.workers.wire import OP_SKIP

pytestmark = pytest.mark.timeout(90)

SHAPE = (24, 32, 3)


class Cam(Node):
    frame = Output(Frame)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> Frame:
        f = self.ctx.new_frame(SHAPE)
        f.data[...] = self.n % 251
        f.seq = self.n
        self.n += 1
        return f


class _Knobs(BaseModel):
    raise_every: int = 0  # the Nth, 2Nth... call raises
    die_at: int = 0  # the worker kills itself at this call
    stamped: bool = True  # False: returns Frame(array), the loop stamps it


class Add(Node):
    """A new frame: its input + 1 (uint8), the same sequence and time stamp."""

    Params = _Knobs
    input = Input(Frame)
    output = Output(Frame)

    def setup(self) -> None:
        self.calls = 0

    def process(self, input: Frame) -> Frame:
        self.calls += 1
        p = self.params
        if p.raise_every and self.calls % p.raise_every == 0:
            raise RuntimeError(f"call {self.calls}")
        if p.die_at and self.calls == p.die_at:
            os.kill(os.getpid(), signal.SIGKILL)
        if not p.stamped:
            return Frame(input.data + np.uint8(1))
        out = self.ctx.new_frame(input.shape)
        np.add(input.data, 1, out=out.data)
        out.seq, out.timestamp = input.seq, input.timestamp
        return out


class Check(Node):
    frame = Input(Frame)
    result = Output(object)

    def process(self, frame: Frame) -> tuple[int, int]:
        return frame.seq, int(frame.data[-1, -1, -1])


def _chain(adds: list[dict[str, Any]], **spec: Any) -> Any:
    g = GraphBuilder("hops")
    g.add("cam", Cam, trigger={"timer": "10ms"})
    prev = "cam.frame"
    for i, params in enumerate(adds):
        params = dict(params)
        where = params.pop("placement", "process")
        extra = {k: params.pop(k) for k in ("deadline",) if k in params}
        g.add(f"a{i}", Add, placement=where, params=params, inputs={"input": prev}, **extra)
        prev = f"a{i}.output"
    g.add("sink", Check, inputs={"frame": prev}, **spec)
    return g.build()


async def _run(
    graph: Any, want: int = 25, seconds: float = 1.0, then_stop: bool = False
) -> tuple[list[Any], Any]:
    async with Runtime(graph) as rt:
        sub = rt.subscribe("sink.result")
        await rt.run(seconds, then_stop=then_stop)
        got = sub.drain()
        await wait_until(lambda: len(drained(sub, got)) >= want, within=20)
        stats = rt.stats()
    return got, {n.name: n for n in stats.nodes}


def _pixels_right(got: list[tuple[int, int]], adds: int) -> None:
    """Each frame the camera's own after ``adds`` additions, none twice, in order."""
    assert got
    seqs = [seq for seq, _ in got]
    assert seqs == sorted(set(seqs)), seqs
    for seq, pixel in got:
        assert pixel == (seq % 251 + adds) % 256, (seq, pixel)


def _balanced(n: Any) -> None:
    """Every activation ended one way: completed, skipped, failed (error) or aborted."""
    assert n.activations >= n.completions + n.skipped
    assert n.activations - n.completions - n.skipped <= n.errors + n.aborted + 1


@pytest.mark.parametrize(
    ("adds", "hopped"),
    [
        ([{}, {}, {}], ["a1", "a2"]),  # a0 is fed by the loop's camera: no hop into it
        ([{}, {"stamped": False}, {}], ["a1"]),  # a1's frames have no time stamp: a2 the usual way
        ([{"deadline": 500}, {}, {}], ["a2"]),  # a writer with a deadline feeds the usual way
        ([{}, {"placement": "pool"}, {}], []),  # a pool's worker is shared: never waits
    ],
    ids=["chain", "unstamped", "deadline", "pool"],
)
@pytest.mark.parametrize("then_stop", [False, True], ids=["", "duration"])
async def test_hops_where_the_rules_allow_with_the_same_results(
    adds: list[dict[str, Any]], hopped: list[str], then_stop: bool
) -> None:
    """``then_stop``: a run whose stop is due from the start (``flowrt run --duration``)."""
    got, nodes = await _run(_chain(adds), then_stop=then_stop)
    _pixels_right(got, len(adds))
    for i in range(len(adds)):
        n = nodes[f"a{i}"]
        assert (n.errors, n.aborted, n.skipped) == (0, 0, 0), n
        _balanced(n)
        if n.name in hopped:
            assert n.direct_hops >= n.completions - 2 > 0, n  # all but a start-up's
        else:
            assert n.direct_hops == 0, n


async def test_a_writer_that_raises_lets_its_reader_go() -> None:
    """Every third call of a1 raises: a2 armed by it is let go (its worker told), runs on
    what a1 publishes, never on what it did not."""
    got, nodes = await _run(_chain([{}, {"raise_every": 3}, {}]), want=15)
    _pixels_right(got, 3)
    a1, a2 = nodes["a1"], nodes["a2"]
    assert a1.errors >= 3
    assert (a2.errors, a2.aborted) == (0, 0), a2
    assert a2.completions <= a1.completions
    _balanced(a2)


@pytest.mark.parametrize("who", ["a1", "a2"])
async def test_a_worker_killed_mid_chain(who: str) -> None:
    """The writer's (or the reader's) worker dies while hops are armed: no hang, the node is
    restarted, the chain goes on with the right pixels."""
    adds: list[dict[str, Any]] = [{}, {}, {}]
    adds[int(who[1])] = {"die_at": 10}
    got, nodes = await _run(_chain(adds), want=30, seconds=2.0)
    _pixels_right(got, 3)
    assert nodes[who].restarts >= 1
    for n in nodes.values():
        _balanced(n)


async def test_a_reader_disabled_runs_at_most_the_call_decided_ahead() -> None:
    async with Runtime(_chain([{}, {}, {}])) as rt:
        sub = rt.subscribe("sink.result")
        await rt.run(0.6)
        assert rt.stats().node("a2").direct_hops > 0
        rt.set_timing("a2", enabled=False)
        before = rt.stats().node("a2").completions
        await rt.run(0.5)
        after = rt.stats().node("a2")
        assert after.completions <= before + 1, after  # an activation already decided
        got = sub.drain()
    _pixels_right(got, 3)


def _send_as(uid: int | None, addr: str, msg: bytes) -> None:
    """Connect to ``addr`` from a child process (running as ``uid``) and send ``msg``."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            if uid is not None:
                os.setuid(uid)
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(addr)
            s.sendall(msg)
            time.sleep(0.3)
        finally:
            os._exit(0)
    os.waitpid(pid, 0)


@pytest.mark.subprocess
@pytest.mark.parametrize(
    ("uid", "heard"),
    [(None, True), (65534, False)],
    ids=["same-user", "other-user"],
)
def test_a_hop_is_heard_from_our_own_user_only(uid: int | None, heard: bool) -> None:
    """An abstract address has no file permissions: a process of another user that sends a
    hop (a pickle: code) is not heard; the call waits for the loop's OP_SKIP instead."""
    if uid is not None and os.getuid() != 0:
        pytest.skip("needs root to run a sender as another user")
    runtime = 4_000_000 + (uid or 0)  # a runtime pid of the test's own: an address per case
    hops = worker_hops.Hops(runtime)
    addr = worker_hops.address(runtime, os.getpid())
    assert addr is not None
    assert hops.listener is not None
    main, child = socket.socketpair()
    try:
        threading.Thread(target=_send_as, args=(uid, addr, pack((7, "value"))), daemon=True).start()
        skip = threading.Timer(1.0, main.sendall, [pack((OP_SKIP, 7))])
        skip.start()
        got = hops.wait(7, BlockingConn(child))
    finally:
        skip.cancel()
        skip.join()
        main.close()
        child.close()
        hops.listener.close()
    assert got == ("value" if heard else worker_hops.SKIPPED)


async def test_a_host_publish_into_a_writer_output_is_not_taken_for_its_hop() -> None:
    """``Runtime.publish`` on a hop writer's output while its reader is armed: the reader's
    activation waits for the writer's own publication; the host's value is a value like any
    other (taken by a later activation, or overwritten and counted)."""
    host = Frame(np.full(SHAPE, 200, np.uint8), seq=10**6, timestamp=1.0)
    async with Runtime(_chain([{}, {}, {}])) as rt:
        sub = rt.subscribe("sink.result")
        await rt.run(0.4)
        for _ in range(20):
            rt.publish("a0.output", host)
            await rt.run(0.013)
        await rt.run(0.3)
        got = sub.drain()
        a1 = rt.stats().node("a1")
    from_host = [g for g in got if g[0] == 10**6]
    from_cam = [seq for seq, _ in got if seq != 10**6]
    assert from_cam == sorted(set(from_cam)), "a camera frame processed twice"
    _pixels_right([g for g in got if g[0] != 10**6], 3)
    assert all(pixel == 202 for _, pixel in from_host)
    assert a1.errors == 0
    _balanced(a1)
