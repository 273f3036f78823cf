"""What a swap may change and how (issue 37 items 1 and 2): an allow-list of params per kind
over the control endpoint, path params confined to their folder, params merged into the
running ones, and a node owning a socket releasing it before its replacement binds."""

from __future__ import annotations

import asyncio
import json
import socket
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from conftest import recorded_counter
from flowrt.nodes.basic import Relay
from flowrt.nodes.recorder import Recorder
from flowrt.nodes.station.display import Display
from flowrt.nodes.tracker import Tracker
from pydantic import BaseModel, ConfigDict

from flowrt import GraphBuilder, Input, Node, NodeSwapped, Output, Runtime, SwapError, VirtualClock
from flowrt.cli.kinds import describe
from flowrt.control._swap_policy import SwapRefused, UnknownParams, check_params
from flowrt.control.server import ControlConfig, ControlServer

# --- the allow-list, alone -----------------------------------------------------------------


def folders(tmp_path: Path) -> Any:
    return lambda param: str(tmp_path / "recs")


@pytest.mark.parametrize(
    ("params", "reason"),
    [
        ({"path": "/tmp/elsewhere"}, "params path may not be changed"),
        ({"graph_file": "/etc/passwd", "name": "x"}, "params graph_file may not be changed"),
        ({"session": "/abs/dir/x"}, "must be relative, without '..'"),
        ({"session": "../../x"}, "must be relative, without '..'"),
        ({"session": "a/../../x"}, "must be relative, without '..'"),
        ({"session": "~/x"}, "must be relative"),
        ({"session": 5}, "must be a folder name"),
    ],
)
def test_what_a_swap_may_not_change_is_refused_with_the_reason(
    tmp_path: Path, params: dict[str, Any], reason: str
) -> None:
    with pytest.raises(SwapRefused, match=reason):
        check_params("recorder", Recorder, params, folders(tmp_path))


class Open(Node):
    """A kind whose params take any name: no name is unknown, one not in ``swappable`` is
    still refused."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="allow")
        gain: float = 1.0

    swappable = frozenset({"gain"})


@pytest.mark.parametrize(
    ("kind", "cls", "params", "refusal", "message"),
    [
        (
            "tracker", Tracker, {"objekt": "ball"}, UnknownParams,
            "tracker: unknown param 'objekt' (did you mean 'object'?); see flowrt kinds tracker",
        ),
        (
            "tracker", Tracker, {"object": "ball", "binz": 32, "colors": {}}, UnknownParams,
            "tracker: unknown params 'binz' (did you mean 'bins'?), "
            "'colors' (did you mean 'colours'?); see flowrt kinds tracker",
        ),
        (
            "recorder", Recorder, {"xyzzy": 1}, UnknownParams,
            "recorder: unknown param 'xyzzy'; see flowrt kinds recorder",
        ),
        # unknown before not swappable: the spelling is the first thing to fix
        (
            "recorder", Recorder, {"pth": "/", "path": "/"}, UnknownParams,
            "recorder: unknown param 'pth' (did you mean 'path'?)",
        ),
        ("relay", Relay, {"gain": 2}, UnknownParams, "relay: unknown param 'gain';"),
        # a real param that may not be changed stays a 403, with the graph file's advice
        (
            "recorder", Recorder, {"path": "/tmp"}, SwapRefused,
            "recorder: params path may not be changed over the control endpoint",
        ),
        ("open", Open, {"gian": 2}, SwapRefused, "params gian may not be changed"),
    ],
)  # fmt: skip
def test_a_param_the_kind_does_not_have_is_unknown_with_a_suggestion(
    tmp_path: Path,
    kind: str,
    cls: type[Node],
    params: dict[str, Any],
    refusal: type[SwapRefused],
    message: str,
) -> None:
    """Not "may not be changed ... edit the graph file instead" for a typo: the graph file
    has no such param either (the YAML validator's "did you mean", over the endpoint)."""
    with pytest.raises(SwapRefused) as refused:
        check_params(kind, cls, params, folders(tmp_path))
    assert type(refused.value) is refusal
    assert message in str(refused.value)


def test_a_session_is_resolved_inside_its_folder_links_included(tmp_path: Path) -> None:
    recs = tmp_path / "recs"
    recs.mkdir()
    (recs / "out").symlink_to(tmp_path)  # a link inside that leads out
    ok = check_params("recorder", Recorder, {"session": "day1/run", "name": "d"}, folders(tmp_path))
    assert ok == {"session": str(recs / "day1/run"), "name": "d"}
    with pytest.raises(SwapRefused, match="leads out of"):
        check_params("recorder", Recorder, {"session": "out/x"}, folders(tmp_path))


def test_flowrt_kinds_shows_the_allow_list() -> None:
    info = describe("recorder")
    assert "session" in info["swappable"]
    assert "path" not in info["swappable"]
    assert info["swap_folders"] == {"session": "path"}
    display = describe("display")["swappable"]
    assert not {"host", "port", "token", "allowed_hosts", "recordings"} & set(display)
    assert describe("relay")["swappable"] == []


# --- merging --------------------------------------------------------------------------------


class Scaled(Node):
    class Params(BaseModel):
        factor: float = 1.0
        offset: float = 0.0

    value = Input(int)
    out = Output(float)

    def process(self, value: int) -> float:
        return value * self.params.factor + self.params.offset


async def test_a_swap_merges_the_given_params_into_the_running_ones() -> None:
    g = GraphBuilder("merge")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.add("alg", Scaled, params={"factor": 2.0, "offset": 1.0}, inputs={"value": "src.value"})
    g.add(
        "drive",
        "arbiter",
        params={"sources": {"a": {}}, "zero": {"vx": 0.0}, "timeout": "300ms"},
        trigger={"timer": "50ms"},
    )
    graph = g.build()
    alg = graph.nodes["alg"]  # a value set after the file, as flowrt run --display-port does
    alg.params = alg.params.model_validate({**alg.params.model_dump(), "factor": 3.0})
    clock = VirtualClock()
    async with Runtime(graph, clock=clock) as rt:
        await clock.advance(0.2)
        kind = rt.graph.spec.nodes["alg"].kind
        await rt.swap("alg", kind, {"offset": 5.0})
        params = rt.runner("alg").rnode.params
        assert (params.factor, params.offset) == (3.0, 5.0)  # type: ignore[attr-defined]
        await rt.swap("drive", "arbiter", {"mode": "blend"})
        arb = rt.runner("drive").rnode.params
        # merged as written: "300ms" is not read again as 0.3 ms
        assert (arb.mode, arb.timeout, list(arb.sources)) == ("blend", 0.3, ["a"])  # type: ignore[attr-defined]
        await rt.swap("drive", "arbiter", {"timeout": "100ms"})
        arb = rt.runner("drive").rnode.params
        assert (arb.mode, arb.timeout) == ("blend", 0.1)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"name": "day\n1"}, "letters, digits, _ and -"),
        ({"name": "d" * 300}, "letters, digits, _ and -"),
        ({"session": "s" * 300}, "at most 255 bytes"),
        ({"session": "day1\nrun"}, "a control character"),
    ],
)
async def test_a_recorder_swapped_to_a_session_it_cannot_make_is_refused_at_the_swap(
    tmp_path: Path, params: dict[str, Any], message: str
) -> None:
    """Refused when swapped, as when loaded (it was refused only at the next start, the
    recorder then in an error state): the running recorder is untouched."""
    g = recorded_counter(tmp_path, "50ms", start=False)
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        before = rt.runner("rec").rnode
        with pytest.raises((SwapError, ValueError), match=message):
            await rt.swap("rec", "recorder", params)
        assert rt.runner("rec").rnode is before


# --- over the endpoint ----------------------------------------------------------------------


@pytest.mark.subprocess
async def test_the_endpoint_never_points_a_recorder_outside_its_folder(tmp_path: Path) -> None:
    recs = tmp_path / "recs"
    g = GraphBuilder("rec")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.add(
        "recorder",
        "recorder",
        params={"path": str(recs), "writer": "thread", "log_report": False},
        inputs={"src.value": {"from": "src.value", "policy": "lossless"}},
    )
    async with (
        Runtime(g.build()) as rt,
        ControlServer(rt, ControlConfig("127.0.0.1", 0)) as server,
        aiohttp.ClientSession() as http,
    ):

        async def swap(params: dict[str, Any]) -> tuple[int, dict[str, Any]]:
            body = {"node": "recorder", "kind": "recorder", "params": params}
            async with http.post(server.url + "/swap", json=body) as r:
                return r.status, json.loads(await r.text())

        for bad in ({"session": str(tmp_path / "abs")}, {"session": "../../x"}, {"path": "/"}):
            status, body = await swap(bad)
            assert status == 403, body
            assert "control endpoint" in body["error"]
        status, body = await swap({"session": "day1", "name": "drive"})
        assert status == 200, body
        await asyncio.sleep(0.5)
        assert rt.rtdb.value("flowrt.recording.recorder") == str(recs / "day1")
    assert written(tmp_path) == ["recs", "recs/day1/day1.mcap", "recs/rec_001/rec_001.mcap"]


def written(folder: Path) -> list[str]:
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.suffix == ".mcap" or p.parent == folder
    )


# --- a node owning a socket -----------------------------------------------------------------


class BrokenView(Display):
    async def setup(self) -> None:
        raise RuntimeError("no certificate")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.subprocess
async def test_a_display_swapped_keeps_its_port_and_serves_on(tmp_path: Path) -> None:
    """The display swapped with one param: merged (same port), the old server released before
    the new one binds; a swap that cannot start leaves a display as before, serving."""
    port = free_port()
    g = GraphBuilder("view")
    g.add("view", "display", params={"port": port, "jpeg_quality": 70})
    async with Runtime(g.build()) as rt, aiohttp.ClientSession() as http:

        async def served() -> int:
            async with http.get(f"http://127.0.0.1:{port}/stats.json") as r:
                return r.status

        assert await served() == 200
        await rt.swap("view", "display", {"max_fps": 5})
        params = rt.runner("view").rnode.params
        assert (params.port, params.max_fps, params.jpeg_quality) == (port, 5, 70)  # type: ignore[attr-defined]
        assert await served() == 200
        node = rt.stats().node("view")
        assert (node.state, node.reason) in (("idle", ""), ("running", ""))
        with pytest.raises(SwapError):
            await rt.swap("view", "display", {"jpeg_quality": 0})  # refused by its model
        with pytest.raises(SwapError):
            await rt.swap("view", "relay")  # a kind that cannot take the node's place
        assert await served() == 200
        with pytest.raises(SwapError, match="no certificate"):
            await rt.swap("view", BrokenView)  # torn down first; a display as before again
        assert await served() == 200
        assert rt.runner("view").rnode.cls is Display
        swapped = [e for e in rt.events if isinstance(e, NodeSwapped) and e.node == "view"]
        assert len(swapped) == 1  # the good swap; the refused ones leave no NodeSwapped
