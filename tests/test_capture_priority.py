"""An offline decoder below the worker readers it feeds (issue 44 item 5).

With ``pacing: fast``, every period-1 frame reader in a worker and a ``--realtime`` loop, the
capture's reader thread takes SCHED_FIFO 1 before it opens its device (so FFmpeg's threads,
created by the open, inherit it); with a reader on the loop, or under the fair scheduler, it
keeps the loop's priority.
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest
from flowrt.nodes.capture.node import Capture
from flowrt.nodes.capture.reader import EOF, Reader, lower_priority

import flowrt


class _Empty:
    """A device with nothing in it: the reader reports the end of stream at once."""

    rewindable = False
    dims = None
    position = 0

    def read(self, into: Any = None) -> None:
        return None

    def release(self) -> None:
        pass


async def _nice_seen_by_the_open(background: bool) -> tuple[int, str]:
    """The nice level of the thread while it opens its device, and what the reader reports."""
    seen: list[int] = []

    def opener(alert: Callable[[str, str], None], start: int) -> _Empty:
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))  # Linux: the calling thread's
        return _Empty()

    r = Reader("cam", opener, asyncio.get_running_loop(), latest=False, background=background)
    item = await r.get(5.0)
    assert item is not None
    assert item[0] == EOF
    r.thread.join(5.0)
    return seen[0], r.priority


@pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling calls")
async def test_under_the_fair_scheduler_a_background_reader_keeps_the_loops_nice() -> None:
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        pytest.skip("the test process runs a real-time policy")
    base = os.getpriority(os.PRIO_PROCESS, 0)
    assert await _nice_seen_by_the_open(background=True) == (base, "inherited")
    assert await _nice_seen_by_the_open(background=False) == (base, "inherited")


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling calls")
async def test_under_sched_fifo_a_background_reader_opens_its_device_at_fifo_1() -> None:
    """The open (where FFmpeg creates its decoding threads) already runs at SCHED_FIFO 1; the
    loop's thread keeps its own policy; a reader that is not background keeps the loop's."""
    seen: list[tuple[int, int]] = []

    def opener(alert: Callable[[str, str], None], start: int) -> _Empty:
        seen.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))
        return _Empty()

    loop = asyncio.get_running_loop()
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))  # the loop's thread
    except OSError:
        pytest.skip("SCHED_FIFO not permitted here")
    try:
        readers = [Reader("cam", opener, loop, latest=False, background=b) for b in (True, False)]
    finally:
        os.sched_setscheduler(0, before[0], before[1])
    for r in readers:
        item = await r.get(5.0)
        assert item is not None
        assert item[0] == EOF
        r.thread.join(5.0)
    assert sorted(seen) == [(os.SCHED_FIFO, 1), (os.SCHED_FIFO, 50)]  # threads race to open
    assert [r.priority for r in readers] == ["SCHED_FIFO 1", "inherited"]


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling calls")
def test_under_sched_fifo_the_reader_takes_the_lowest_real_time_priority() -> None:
    got: list[Any] = []

    def thread() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        except OSError:
            got.append(None)
            return
        got.append((lower_priority(), os.sched_getscheduler(0), os.sched_getparam(0)))

    t = threading.Thread(target=thread)
    t.start()
    t.join(5.0)
    if got == [None]:
        pytest.skip("SCHED_FIFO not permitted here")
    ((granted, policy, param),) = got
    assert (granted, policy, param.sched_priority) == ("SCHED_FIFO 1", os.SCHED_FIFO, 1)


def _graph(*readers: tuple[str, str, int]) -> Any:
    """cam plus trackers (name, placement, period) on its frames."""
    g = flowrt.GraphBuilder("offline")
    g.add("cam", "capture", params={"pacing": "fast"})
    for name, placement, period in readers:
        g.add(
            name,
            "tracker",
            params={"object": "ball"},
            trigger={"frame": "cam", "period": period},
            placement=placement,
            inputs={"frame": "cam.frame"},
        )
    return g.build()


@pytest.mark.parametrize(
    ("readers", "below"),
    [
        ([("t", "process", 1)], True),
        ([("t", "pool", 1), ("u", "process", 1)], True),
        ([("t", "process", 1), ("u", "inline", 1)], False),  # the loop's helpers would starve it
        ([("t", "process", 1), ("u", "inline", 4)], True),  # samples by design: not waited for
        ([], False),
    ],
)
def test_the_decoder_goes_below_only_when_every_paced_reader_is_in_a_worker(
    readers: list[tuple[str, str, int]], below: bool
) -> None:
    node = SimpleNamespace(ctx=SimpleNamespace(name="cam", graph=_graph(*readers)))
    assert Capture._readers_in_workers(node) is below  # type: ignore[arg-type]


def test_outside_a_runtime_the_decoder_keeps_its_priority() -> None:
    class NoGraph:
        name = "cam"

        @property
        def graph(self) -> Any:
            raise RuntimeError("graph is only available to inline nodes on the event loop")

    assert Capture._readers_in_workers(SimpleNamespace(ctx=NoGraph())) is False  # type: ignore[arg-type]
