"""The sync node (issue 29): time-aligned sets as message_filters makes them, every value
left out counted with its reason; table-driven on virtual time."""

from __future__ import annotations

from typing import Any

import pytest
from flowrt.nodes.sync import Sync

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.testing import NodeHarness


def stamped(t: float) -> dict[str, float]:
    return {"timestamp": t}


@pytest.mark.parametrize(
    ("policy", "slop", "a", "b", "sets", "unmatched"),
    [
        ("approximate", "10ms", [0.0, 0.1, 0.2], [0.004, 0.104, 0.204], 3, {}),
        (
            "approximate",
            "1ms",
            [0.0, 0.1, 0.2],
            [0.004, 0.104, 0.204],
            0,
            {"no partner within slop": 5},
        ),
        ("exact", "0ms", [0.0, 0.1, 0.2], [0.0, 0.1, 0.25], 2, {"no partner within slop": 1}),
        ("approximate", "10ms", [0.0, 0.003, 0.1], [0.005, 0.105], 2, {"superseded": 1}),
    ],
    ids=["4ms-apart-slop-10ms", "4ms-apart-slop-1ms", "exact", "superseded"],
)
def test_sets_and_unmatched_reasons(
    policy: str, slop: str, a: list[float], b: list[float], sets: int, unmatched: dict[str, int]
) -> None:
    h = NodeHarness(Sync, {"policy": policy, "slop": slop}, name="pair")
    for ta in a:  # all of a first, then b: the queues hold them (queue 10)
        h.process(left=stamped(ta))
    for tb in b:
        h.process(right=stamped(tb))
    got = [v for port, v in h.ctx.published if port == "set"]
    assert len(got) == sets
    for s in got:
        assert s["spread_ms"] <= float(slop.removesuffix("ms")) + 1e-9
        assert set(s) == {"left", "right", "stamp", "spread_ms"}
    report = h.node.report()
    counts: dict[str, int] = {}
    for per in report["by_input"].values():
        for reason, n in per.items():
            if n:
                counts[reason] = counts.get(reason, 0) + n
    assert counts == unmatched


def test_a_full_queue_drops_its_oldest_as_overflow() -> None:
    h = NodeHarness(Sync, {"queue": 3}, name="pair")
    for k in range(5):
        h.process(left=stamped(k * 0.1))
    assert h.node.report()["by_input"]["left"]["queue overflow"] == 2


async def test_two_cameras_4ms_apart() -> None:
    """The issue's case: two 30 fps cameras 4 ms apart; slop 10 ms pairs >= 90 % of the
    frames, slop 1 ms none and counts every frame unmatched."""
    for slop, expect_sets in (("10ms", True), ("1ms", False)):
        g = GraphBuilder("cams")
        for name, phase in (("left", 0), ("right", 4)):
            g.add(
                name,
                "capture",
                params={"source": "synthetic:flash", "fps": 30, "size": [32, 24]},
                trigger={"timer": "33.333ms", "phase": f"{phase}ms"},
            )
        g.add(
            "pair",
            "sync",
            params={"slop": slop},
            inputs={"left": "left.frame", "right": "right.frame"},
        )
        clock = VirtualClock()
        async with Runtime(g.build(), clock=clock) as rt:
            sets = rt.subscribe("pair.set", size=1000)
            await clock.advance(3.0)
            got = sets.drain()
            report: dict[str, Any] = rt.stats().reports["pair"]
            frames = rt.stats().edge("left.frame->pair.left").published
        if expect_sets:
            assert len(got) >= 0.9 * frames
            assert all(s["spread_ms"] == pytest.approx(4, abs=0.5) for s in got)
        else:
            assert got == []
            assert report["unmatched"] >= 2 * frames - 2  # every frame but the queues' last
        assert isinstance(flowrt.AudioBlock, type)
