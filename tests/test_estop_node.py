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
        "releases_refused": 0,
    }


def test_what_is_not_an_action_is_ignored(rtdb: RTDB) -> None:
    h = _harness(rtdb, {"initial": "released"})
    for bad in ({"action": "release"}, {"action": "fly", "id": "x"}, "stop", {"id": 3}):
        h.ctx.rtdb.write(WEB_ESTOP, bad)
        assert h.process()["active"] is False


@pytest.mark.parametrize(
    ("batch", "active", "presses", "refused"),
    [
        # another page's Release 5 ms after a Stop, both within one period: the Stop holds
        ([("stop", "s1"), ("release", "r1")], True, 1, 1),
        ([("release", "r1"), ("stop", "s1")], True, 1, 0),
        ([("stop", "s1"), ("stop", "s2")], True, 2, 0),
        ([("release", "r1")], False, 0, 0),
    ],
)
def test_every_action_of_a_period_is_applied_a_stop_first(
    rtdb: RTDB, batch: list[tuple[str, str]], active: bool, presses: int, refused: int
) -> None:
    """Only the newest action was read each period: a Stop followed by another page's
    Release within 50 ms was never applied nor counted (9 of 10 such presses lost)."""
    h = _harness(rtdb, {"initial": "released"})
    h.process()
    for what, aid in batch:
        h.ctx.rtdb.write(WEB_ESTOP, {"action": what, "id": aid})
    out = h.process()
    assert out["active"] is active
    report = h.node.report()
    assert (report["presses"], report["releases_refused"]) == (presses, refused)
    assert h.process()["active"] is active  # applied once: read again, nothing changes
    if refused:
        assert _act(h, "release", "r9")["active"] is False  # a Release sent after: applied


def test_a_fresh_instance_takes_the_page_s_state_not_its_past(rtdb: RTDB) -> None:
    for what, aid in [("stop", "s1"), ("release", "r1"), ("stop", "s2"), ("release", "r2")]:
        rtdb.write(WEB_ESTOP, {"action": what, "id": aid})
    h = _harness(rtdb, {"initial": "engaged"})
    assert h.process()["active"] is False
    assert h.node.report()["presses"] == 0
