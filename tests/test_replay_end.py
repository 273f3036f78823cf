"""Replay nodes of one run: the run ends after the longest stream, timed from the first
activation.

Found by a tester: every replay node with ``on_end: stop`` stopped the run at its own end,
so ``flowrt replay REC`` (one node per recorded source) ended with the shortest stream
(4 detections in 3 s) and cut the cameras short; and messages were due from the runtime's
start, before the worker processes were up, so the first frames came out in a burst that
their trackers skipped frames of.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import flowrt.nodes.replay as replay_mod
import pytest
from flowrt.nodes.replay import LEAD, Replay

import flowrt
from flowrt.cli import main
from flowrt.testing import NodeHarness

T0 = 1_700_000_000_000_000_000
PERIOD = 50_000_000  # ns: 20 Hz
STREAMS = {"short": 3, "long": 10}  # messages of each, from the same first time


def write(path: Path) -> Path:
    """A recording whose streams end at different times (short: 0.1 s, long: 0.45 s)."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        schema = json.dumps({"type": "object", "properties": {"i": {"type": "number"}}})
        sid = w.register_schema("Value", "jsonschema", schema.encode())
        ids = {n: w.register_channel(f"{n}.value", "json", sid) for n in STREAMS}
        for i in range(max(STREAMS.values())):
            for name, count in STREAMS.items():
                if i < count:
                    t = T0 + i * PERIOD
                    w.add_message(ids[name], t, json.dumps({"i": i}).encode(), t, i)
        w.finish()
    return path


async def replay_all(path: Path) -> tuple[dict[str, list[Any]], float]:
    """The recording replayed as ``flowrt replay`` does without ``--graph``: one replay node
    per recorded source, each with the default ``on_end: stop``."""
    g = flowrt.GraphBuilder("replay")
    for name in STREAMS:
        g.add(name, "replay", params={"path": str(path), "topics": [f"{name}.value"]})
    async with flowrt.Runtime(g.build()) as rt:
        subs = {n: rt.subscribe(f"{n}.message", size=64) for n in STREAMS}
        await asyncio.wait_for(rt.run(), timeout=10)  # the replay stops the run at its end
        took = rt.now()
        return {n: sub.drain() for n, sub in subs.items()}, took


def test_the_run_ends_after_the_longest_stream_with_every_message(tmp_path: Path) -> None:
    path = write(tmp_path / "two.mcap")
    got, took = asyncio.run(replay_all(path))
    assert {n: [m["i"] for m in v] for n, v in got.items()} == {
        n: list(range(c)) for n, c in STREAMS.items()
    }
    assert took >= (STREAMS["long"] - 1) * PERIOD / 1e9  # not at the short one's end (0.1 s)


def test_the_command_replays_the_whole_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path / "two.mcap")
    stats = tmp_path / "stats.json"
    code = main(["replay", str(path), "--no-ui", "--no-display", "--stats-json", str(stats)])
    capsys.readouterr()
    assert code == 0
    assert json.loads(stats.read_text())["uptime"] >= (STREAMS["long"] - 1) * PERIOD / 1e9


class _Sleeps:
    """``asyncio`` for the replay module, its sleeps noted (and not slept)."""

    def __init__(self) -> None:
        self.waits: list[float] = []

    async def sleep(self, seconds: float) -> None:
        self.waits.append(seconds)

    def __getattr__(self, name: str) -> Any:
        return getattr(asyncio, name)


def test_messages_are_due_from_the_first_activation_not_the_runtime_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = write(tmp_path / "two.mcap")
    sleeps = _Sleeps()
    monkeypatch.setattr(replay_mod, "asyncio", sleeps)
    h = NodeHarness(Replay, {"path": str(path), "topics": ["long.value"]}, name="long")
    h.ctx.time = 5.0  # the graph took 5 s to set up (workers starting) before this

    async def two() -> list[Any]:  # one loop: the next message is read ahead on it
        node: Any = h.node
        out = [await node.process(), await node.process()]
        await node.teardown()
        return out

    assert asyncio.run(two()) == [{"message": {"i": 0}}, {"message": {"i": 1}}]
    # due LEAD after the first activation, then one period later: no burst to catch up
    assert sleeps.waits == pytest.approx([LEAD, LEAD + PERIOD / 1e9])


def test_a_graph_run_again_starts_a_new_replay(tmp_path: Path) -> None:
    """The state the replay nodes share goes with the run: a second run of the same graph
    has its own time origin and its own ended nodes."""
    path = write(tmp_path / "two.mcap")
    g = flowrt.GraphBuilder("again")
    for name in STREAMS:
        g.add(name, "replay", params={"path": str(path), "topics": [f"{name}.value"]})
    graph = g.build()

    async def once() -> dict[str, int]:
        async with flowrt.Runtime(graph) as rt:
            subs = {n: rt.subscribe(f"{n}.message", size=64) for n in STREAMS}
            t = time.monotonic()
            await asyncio.wait_for(rt.run(), timeout=10)
            assert time.monotonic() - t >= (STREAMS["long"] - 1) * PERIOD / 1e9
            return {n: len(sub.drain()) for n, sub in subs.items()}

    assert asyncio.run(once()) == STREAMS
    assert not replay_mod._RUNS  # let go at the run's end
    assert asyncio.run(once()) == STREAMS
