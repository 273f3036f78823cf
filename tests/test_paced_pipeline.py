"""A ``pacing: fast`` source overlaps with a frame reader in a worker (issue 12, item 7).

The source publishes a frame only when its period-1 frame readers can take it
(``NodeContext.wait_readers``). A reader in a worker of its own is pipelined: the next frame
goes to the worker while it computes the current one, so the source runs ahead by at most the
reader's window (``pipeline``, 2 by default), and still no frame is skipped, even through a
``latest`` input. Inline readers keep the lock-step. ``paced_lead_max`` in the node's stats
is the most frames the source had published that the reader had not finished.
"""

from __future__ import annotations

import asyncio
import time

import pytest
from pydantic import BaseModel

from flowrt import Frame, GraphBuilder, Input, LoopTrigger, Node, Output, Runtime


class Paced(Node):
    """A source paced by its readers (as ``capture`` with ``pacing: fast``): ``count`` frames,
    then a stop request (the end of a file with ``on_eof: exit``)."""

    class Params(BaseModel):
        count: int = 24
        paced: bool = True

    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: object) -> LoopTrigger:
        return LoopTrigger()

    def setup(self) -> None:
        self.n = 0

    async def process(self) -> Frame | None:
        if self.n >= self.params.count:
            if self.n == self.params.count:
                self.ctx.request_stop()
                self.n += 1
            await asyncio.sleep(0.01)
            return None
        f = self.ctx.new_frame((32, 48, 3))
        f.data[...] = self.n % 256
        f.seq = self.n
        self.n += 1
        if self.params.paced:
            await self.ctx.wait_readers()
        else:
            await asyncio.sleep(0)  # a live source: its own rate, readers or not
        return f


class Track(Node):
    """Slower than the source (so that the source can run ahead); returns the frame's seq."""

    frame = Input(Frame)
    seq = Output(int)

    def process(self, frame: Frame) -> int:
        assert int(frame.data[0, 0, 0]) == frame.seq % 256  # the pixels of that very frame
        time.sleep(0.004)
        return frame.seq


class Collect(Node):
    """Keeps every value in arrival order (inline, input-triggered, lossless)."""

    value = Input(int)
    seen: list[int] = []

    def process(self, value: int) -> None:
        Collect.seen.append(value)


def graph(
    placement: str, policy: str, pipeline: int | None, paced: bool = True, count: int = 24
) -> GraphBuilder:
    g = GraphBuilder("paced")
    g.add("src", Paced, params={"paced": paced, "count": count})
    extra = {} if pipeline is None else {"pipeline": pipeline}
    g.add(
        "track",
        Track,
        trigger={"frame": "src"},
        inputs={"frame": {"from": "src.frame", "policy": policy}},
        placement=placement,
        priority=40,
        **extra,
    )
    g.add("sink", Collect, inputs={"value": {"from": "track.seq", "policy": "lossless"}})
    return g


async def run(g: GraphBuilder) -> Runtime:
    Collect.seen = []
    rt = Runtime(g.build())
    async with rt:
        await asyncio.wait_for(rt.run(), 40)
    return rt


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("placement", "policy", "pipeline", "lead"),
    [
        ("inline", "latest", None, 1),  # lock-step: the source waits for the reader
        ("process", "latest", None, 2),  # default window: one computing, one on its way
        ("process", "latest", 3, 3),
        ("process", "queue", None, 2),
        ("process", "lossless", None, 2),
        ("process", "latest", 1, 2),  # no pipelining: one running, the next one deferred
        ("pool", "latest", None, 2),  # a shared worker: one call, the next one deferred
    ],
)
async def test_paced_source_runs_ahead_by_the_window_and_loses_nothing(
    placement: str, policy: str, pipeline: int | None, lead: int
) -> None:
    rt = await run(graph(placement, policy, pipeline))
    stats = rt.stats()
    track = stats.node("track")
    count = Paced.Params().count
    assert Collect.seen == list(range(count))  # every frame, in order, whatever the placement
    assert track.completions == count
    assert track.skipped == 0
    assert track.dropped == 0
    assert track.paced_lead_max == lead  # it did run ahead, and by no more than the bound
    for edge in stats.edges:
        assert edge.dropped == 0, edge


@pytest.mark.timeout(60)
async def test_a_live_source_keeps_latest_freshness() -> None:
    """A source that does not pace itself: the worker reader is not pipelined (one call at a
    time, always the newest frame), frames it had no time for are skipped, not queued."""
    rt = await run(graph("process", "latest", None, paced=False))
    track = rt.stats().node("track")
    assert track.paced_lead_max == 0
    assert track.skipped > 0  # frames in microseconds, 4 ms calls: a latest reader samples
    assert Collect.seen == sorted(Collect.seen)
    assert len(Collect.seen) < Paced.Params().count


@pytest.mark.timeout(60)
@pytest.mark.parametrize("placement", ["inline", "process", "pool"])
async def test_a_stop_mid_stream_finishes_the_frames_in_flight(placement: str) -> None:
    """Stopped before the end: what the source published is tracked (drained), nothing lost."""
    Collect.seen = []
    g = graph(placement, "latest", None, count=100_000)
    rt = Runtime(g.build())
    async with rt:
        await asyncio.wait_for(rt.run(0.3), 40)
    stats = rt.stats()
    track = stats.node("track")
    published = stats.edge("track.frame").published
    assert 0 < published < 100_000
    assert Collect.seen == list(range(published))
    assert track.completions == published
    assert track.skipped == 0
    assert track.dropped == 0
