"""``flowrt run --control``: the endpoint's process starts beside the run, not before it.

On a machine the graph keeps busy the endpoint's process (the lowest priority) took 15 s to
import: ``--duration 5`` ran 13.6 s and a Ctrl-C in that window waited 14 s. Here the
server is a stand-in whose start takes as long as the test says; the runtime is real.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from flowrt import GraphBuilder, Runtime
from flowrt.cli.run import _serve_run


class SlowServer:
    """A control server whose process serves after ``after`` seconds (None: never), or
    fails then (``fails``)."""

    url = "http://127.0.0.1:1"

    def __init__(self, after: float | None, fails: bool = False) -> None:
        self.after = after
        self.fails = fails
        self.spawned = False
        self.stopped = False

    async def spawn(self) -> None:
        self.spawned = True

    async def wait_ready(self) -> None:
        await asyncio.sleep(3600 if self.after is None else self.after)
        if self.fails:
            raise RuntimeError("the control endpoint's process did not start: TimeoutError()")

    async def stop(self) -> None:
        self.stopped = True


def graph() -> Any:
    g = GraphBuilder("startup")
    g.add("src", "counter", trigger={"timer": "10ms"})
    return g.build()


@pytest.mark.parametrize(
    ("server", "ends_within", "failed"),
    [
        (SlowServer(after=None), 0.9, None),  # never serves: the run still lasts 0.3 s
        (SlowServer(after=0.05), 0.9, None),  # serves during the run
        (SlowServer(after=0.1, fails=True), 0.9, "did not start"),  # fails: the run stops
    ],
)
async def test_the_duration_counts_from_the_runs_start_not_the_endpoints(
    server: SlowServer, ends_within: float, failed: str | None
) -> None:
    g = graph()
    loop = asyncio.get_running_loop()
    async with Runtime(g) as rt:
        t0 = loop.time()
        why = await _serve_run(rt, server, g, 0.3 if failed is None else 30.0)
        elapsed = loop.time() - t0
    assert server.spawned
    assert server.stopped
    assert elapsed < ends_within
    if failed is None:
        assert why is None
        assert elapsed >= 0.3
    else:
        assert why is not None
        assert failed in why


async def test_a_stop_asked_while_the_endpoint_starts_is_not_held_by_it() -> None:
    g = graph()
    server = SlowServer(after=None)
    loop = asyncio.get_running_loop()
    async with Runtime(g) as rt:
        loop.call_later(0.1, rt.request_stop)  # what a signal does during the run
        t0 = loop.time()
        assert await _serve_run(rt, server, g, None) is None
        assert loop.time() - t0 < 0.6
    assert server.stopped
