"""One shape per change: the control endpoint's one route table, ``TimingRequest.change()``
and ``Runtime.apply_timing``, the one door of run-time timing (issue 39, step 3).

The runtime's side of the endpoint is driven here without its server process (that is
tests/test_control.py): ``control_routes.answer`` is what the runtime runs for each request
the server process forwards.
"""

from __future__ import annotations

import json
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from conftest import recorded_counter
from pydantic import ValidationError

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.control.routes import BY_OP, ENDPOINTS, ROUTES, answer
from flowrt.control.wire import ModeRequest, TimingRequest
from flowrt.events import TimingChanged
from flowrt.kernel.timing import TimingChange
from flowrt.rtdb import RECORD_COMMAND


class Server:
    """What a handler asks of the control server: its runtime and the kinds a swap may name."""

    def __init__(self, rt: Runtime) -> None:
        self.rt = rt

    def allowed_kinds(self) -> set[str]:
        return {"burn", "counter"}


def graph() -> flowrt.Graph:
    g = GraphBuilder("routes")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.add("slow", "burn", params={"ms": 0.1}, trigger={"timer": "100ms"}, priority=20)
    g.mode("attack", slow={"timer": "50ms", "priority": 40})
    return g.build()


@pytest.fixture
async def server() -> AsyncIterator[Server]:
    async with Runtime(graph(), clock=VirtualClock()) as rt:
        yield Server(rt)


async def ask(server: Server, op: str, body: dict[str, Any] | None = None) -> tuple[int, Any]:
    status, data = await answer(server, op, json.dumps(body).encode() if body else b"")
    return status, json.loads(data)


def test_the_index_lists_the_endpoints_users_know() -> None:
    """Scripts read ``GET /``: the list is the one it always was, in its order."""
    assert ENDPOINTS == [
        "GET /stats",
        "GET /events?n=50",
        "GET /modes",
        "POST /mode",
        "POST /timing",
        "GET /qos",
        "GET /rtdb",
        "GET /rtdb/{name}?n=8",
        "POST /record",
        "POST /swap",
        "POST /reload",
    ]
    assert len(BY_OP) == len(ROUTES)  # one route per operation
    assert all((r.method == "POST") == (r.body is not None) for r in ROUTES)


def test_a_timing_request_is_one_timing_change() -> None:
    req = TimingRequest.model_validate({"node": "a", "timer": "80ms", "deadline": 5, "force": True})
    assert req.change() == TimingChange(timer_ms=80.0, deadline_ms=5.0)


@pytest.mark.parametrize(
    ("model", "body", "field"),
    [  # read as true or 1 before: "force": "yes" went past admission control
        (TimingRequest, {"node": "a", "timer": 50, "force": "yes"}, "force"),
        (TimingRequest, {"node": "a", "timer": 50, "force": 1}, "force"),
        (TimingRequest, {"node": "a", "priority": True}, "priority"),
        (TimingRequest, {"node": "a", "enabled": "yes"}, "enabled"),
        (ModeRequest, {"mode": "attack", "force": "yes"}, "force"),
    ],
)
def test_a_request_takes_its_types_as_written(
    model: type[Any], body: dict[str, Any], field: str
) -> None:
    with pytest.raises(ValidationError) as info:
        model.model_validate_json(json.dumps(body))
    assert [e["loc"][0] for e in info.value.errors()] == [field]


async def test_timing_is_answered_through_apply_timing(server: Server) -> None:
    status, reply = await ask(server, "timing", {"node": "slow", "timer": 200, "priority": 30})
    assert status == 200
    assert reply == {"node": "slow", "change": "timer_ms 100.0 -> 200.0, priority 20 -> 30"}
    changed = [e for e in server.rt.events if isinstance(e, TimingChanged)]
    assert [(e.node, e.origin) for e in changed] == [("slow", "control")]


@pytest.mark.parametrize(
    ("body", "status", "error"),
    [
        ({"node": "slwo", "priority": 30}, 404, "unknown node 'slwo'"),
        ({"node": "slow", "period": 2}, 400, "slow: period/phase in frames apply to frame"),
        # what the server process would have refused is still refused whole here
        ({"node": "slow", "priority": 30, "timer": float("nan")}, 400, "slow: timer must be"),
        ({"node": "slow", "priority": "high"}, 400, "slow: priority must be an integer"),
    ],
)
async def test_a_refused_timing_change_changes_nothing(
    server: Server, body: dict[str, Any], status: int, error: str
) -> None:
    got, reply = await ask(server, "timing", body)
    assert (got, reply["error"][: len(error)]) == (status, error)
    assert server.rt.scheduler.runners["slow"].timing.priority == 20


async def test_the_runtime_side_does_not_validate_the_body_again(
    server: Server, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server process accepted the body with the request model: the change is checked
    once more only against its node (``Runtime.apply_timing``), not by a second model pass."""

    def second_pass(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("TimingRequest validated twice")

    monkeypatch.setattr(TimingRequest, "model_validate", second_pass)
    status, reply = await ask(server, "timing", {"node": "slow", "deadline": 20.0})
    assert (status, reply["change"]) == (200, "deadline_ms None -> 20.0")


async def test_every_origin_goes_through_apply_timing(
    server: Server, monkeypatch: pytest.MonkeyPatch
) -> None:
    rt = server.rt
    seen: list[tuple[str, str]] = []
    door = Runtime.apply_timing

    def spy(self: Runtime, node: str, change: TimingChange, **kw: Any) -> str:
        seen.append((node, kw["origin"]))
        return door(self, node, change, **kw)

    monkeypatch.setattr(Runtime, "apply_timing", spy)
    rt.set_timing("slow", priority=25)  # the API's keywords
    await ask(server, "timing", {"node": "slow", "priority": 26})  # the control endpoint
    assert seen == [("slow", "api"), ("slow", "control")]


async def test_routes_answer_reads_and_unknown_operations(server: Server) -> None:
    status, index = await ask(server, "index")
    assert (status, index) == (200, {"graph": "routes", "endpoints": ENDPOINTS})
    assert (await ask(server, "modes"))[1] == {"modes": ["attack"], "current": None}
    assert (await ask(server, "mode", {"mode": "attack"}))[1] == {"mode": "attack"}
    status, reply = await ask(server, "rtdb_record", {"name": "nothing", "n": 1})
    assert (status, reply) == (404, {"error": "no record 'nothing'"})
    status, reply = await ask(server, "record", {"action": "start"})
    assert status == 404
    assert "no recorder node" in reply["error"]
    assert (await ask(server, "nope"))[0] == 404


async def test_a_swap_of_a_param_the_kind_does_not_have_is_422(server: Server) -> None:
    """A typo is the request's fault (422, "did you mean"), not a refused param (403)."""
    body = {"node": "slow", "kind": "burn", "params": {"mss": 2}}
    status, data = await ask(server, "swap", body)
    assert (status, data) == (
        422,
        {"error": "burn: unknown param 'mss' (did you mean 'ms'?); see flowrt kinds burn"},
    )
    status, data = await ask(server, "swap", {**body, "kind": "relay", "params": {}})
    assert status == 403, data  # a kind the graph does not allow: still a rule
    assert server.rt.runner("slow").rnode.params.ms == 0.1  # type: ignore[attr-defined]


def test_one_module_owns_the_recorders_command_key() -> None:
    """``flowrt.record.NODE`` is spelled once, in flowrt.rtdb; the control endpoint, the
    recorder node and the operator's page take it from there."""
    from flowrt.nodes import recorder
    from flowrt.nodes.station import record as operator_record

    assert recorder.COMMAND_RECORD is RECORD_COMMAND is operator_record.COMMAND
    root = Path(flowrt.__file__).parent
    spelled = [
        str(p.relative_to(root.parent))
        for folder in (root, root.parent / "nodes")
        for p in folder.rglob("*.py")
        if '"flowrt.record."' in p.read_text()
    ]
    assert spelled == ["flowrt/rtdb.py"]


async def test_post_record_answers_once_the_recorders_obeyed(tmp_path: Path) -> None:
    """POST /record answered 200 before the recorder had done anything: two starts at once
    were both 200 with one session made, a start while recording "done". Now it is
    answered once the recorder obeyed, one start or stop at a time (with the operator
    page's): one of two concurrent starts records, the other is 409."""
    import asyncio

    g = recorded_counter(tmp_path, start=False, writer="thread")
    async with Runtime(g.build()) as rt:
        server = Server(rt)
        await asyncio.sleep(0.2)  # the recorder says it is stopped
        one, two = await asyncio.gather(
            ask(server, "record", {"action": "start", "name": "one"}),
            ask(server, "record", {"action": "start", "name": "two"}),
        )
        assert sorted([one[0], two[0]]) == [200, 409], (one, two)
        won, lost = (one, two) if one[0] == 200 else (two, one)
        session = won[1]["sessions"]["rec"]
        assert session.endswith(("one_001", "two_001"))
        assert "already recording: rec into" in lost[1]["error"]
        assert os.listdir(tmp_path) == [session.rsplit("/", 1)[-1]]
        status, stopped = await ask(server, "record", {"action": "stop"})
        assert (status, stopped["sessions"]) == (200, {"rec": session})
        status, again = await ask(server, "record", {"action": "stop"})
        assert (status, again["error"]) == (409, "not recording")
        status, unnamed = await ask(server, "record", {"action": "start"})
        assert status == 200, unnamed
        assert unnamed["nodes"] == ["rec"]
        await ask(server, "record", {"action": "stop"})


@pytest.mark.parametrize(
    "change",
    [{"enabled": False}, {"timer": 3600000}, {"phase": 10}, {"priority": 5}],
)
async def test_the_timing_of_what_keeps_a_robot_safe_is_the_graph_file_s(
    change: dict[str, Any],
) -> None:
    """A local caller disabled the arbiter (or set its timer to an hour) over the endpoint:
    the robot kept its last command, the page's Stop no longer reaching it. Refused (403),
    as the arbiter's safety params are; the embedding API (the program's own) may."""
    g = GraphBuilder("safe")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.add("stop", "estop")
    g.add(
        "drive",
        "arbiter",
        params={"sources": {"a": {}}, "zero": {"vx": 0.0}, "timeout": "300ms"},
        trigger={"timer": "50ms"},
    )
    # a haptic device, disabled, kept its last force (the force input stale for 0.9 s)
    g.add("hand", "haptic", params={"device": "sim"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        for node, kind in (("drive", "an arbiter"), ("stop", "an estop"), ("hand", "a haptic")):
            status, reply = await ask(Server(rt), "timing", {"node": node, **change})
            assert status == 403, reply
            assert f"{node}: {kind} keeps the robot safe" in reply["error"]
            assert rt.stats().node(node).enabled
        status, _ = await ask(Server(rt), "timing", {"node": "src", "priority": 7})
        assert status == 200
        rt.set_timing("drive", priority=30)  # the program's own API: its choice
