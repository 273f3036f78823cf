"""The ``estop`` node: the page's STOP/Release latched and published as a heartbeat (issue 40)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from flowrt.nodes.estop import WEB_ESTOP, Estop

from flowrt.rtdb import RTDB
from flowrt.testing import NodeHarness


@pytest.fixture
def rtdb() -> Iterator[RTDB]:
    with RTDB() as db:
        yield db


def _harness(rtdb: RTDB, params: dict[str, Any]) -> NodeHarness:
    h = NodeHarness(Estop, params, name="estop")
    h.ctx._rtdb = rtdb  # the display writes the page's actions there
    return h


def _act(h: NodeHarness, action: str, aid: str) -> dict[str, Any]:
    h.ctx.rtdb.write(WEB_ESTOP, {"action": action, "id": aid})
    out: dict[str, Any] = h.process()
    return out


def test_starts_engaged_and_latches_each_action_once(rtdb: RTDB) -> None:
    h = _harness(rtdb, {"rate_hz": 20})
    first = h.process()
    assert first["active"] is True
    assert first["release"] is None
    released = _act(h, "release", "r1")
    assert released["active"] is False
    assert released["release"] == "r1"
    assert h.process()["active"] is False  # latched: the record read again changes nothing
    assert _act(h, "stop", "s1")["active"] is True
    assert h.process()["active"] is True
    again = _act(h, "release", "r2")  # every release its own id: the robot tells them apart
    assert again == {"active": False, "release": "r2", "since": again["since"]}
    assert h.node.report() == {
        "estop": "released",
        "since": again["since"],
        "presses": 1,
        "releases": 2,
    }


def test_what_is_not_an_action_is_ignored(rtdb: RTDB) -> None:
    h = _harness(rtdb, {"initial": "released"})
    for bad in ({"action": "release"}, {"action": "fly", "id": "x"}, "stop", {"id": 3}):
        h.ctx.rtdb.write(WEB_ESTOP, bad)
        assert h.process()["active"] is False
