"""What the CLI says when there is nothing to say, and what ``--duration`` counts."""

from __future__ import annotations

import asyncio
import sys
import time

import pytest

from flowrt import GraphBuilder, Node, Output, Runtime, VirtualClock
from flowrt.control.server import ControlConfig, ControlServer

pytestmark = pytest.mark.timeout(60)


async def ctl(url: str, *args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "flowrt.cli", "ctl", "--url", url, *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["events"], "none (no event"),
        (["rtdb"], "none (no RTDB record"),
    ],
)
async def test_ctl_says_none_when_empty(args: list[str], said: str) -> None:
    g = GraphBuilder("quiet")
    g.add("src", "counter", trigger={"timer": "50ms"})
    config = ControlConfig("127.0.0.1", 0)
    async with (
        Runtime(g.build(), clock=VirtualClock()) as rt,
        ControlServer(rt, config) as control,
    ):
        code, out, err = await ctl(control.url, *args)
    assert code == 0, err
    assert out.strip().startswith(said), out


class SlowSetup(Node):
    """Takes a second to set up, as a camera or a model may."""

    tick = Output(int)

    def setup(self) -> None:
        time.sleep(1.0)

    def process(self) -> int:
        return 1


async def test_duration_counts_from_when_every_node_is_set_up() -> None:
    g = GraphBuilder("slow-start")
    g.add("slow", SlowSetup, trigger={"timer": "1s"})
    g.add("tick", "counter", trigger={"timer": "10ms"})
    async with Runtime(g.build()) as rt:
        await rt.run(0.5)
        ticks = rt.stats().node("tick").activations
    # 0.5 s of running at 100 Hz (were the 1 s set-up counted, the run would be over at once)
    assert ticks >= 25, ticks
