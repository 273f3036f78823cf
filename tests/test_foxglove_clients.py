"""The live Foxglove server with the clients users have (issue 26): both WebSocket
subprotocols, and @foxglove/ws-protocol's FoxgloveClient receiving frames at the source rate."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest

import flowrt
from flowrt import Node, Output
from flowrt.recording.live import FoxgloveLive

REPO = Path(__file__).resolve().parents[1]


def ticker() -> flowrt.Graph:
    g = flowrt.GraphBuilder("fox")
    g.add("tick", "counter", trigger={"timer": 50})
    return g.build()


def ws_client() -> Callable[[int, str, str], Awaitable[dict[str, Any]]]:
    """tests/js/ws_client.mjs (@foxglove/ws-protocol, ajv), as a coroutine giving its JSON
    line for (port, topic, seconds); the test is skipped without Node.js and
    FLOWRT_NODE_MODULES."""
    modules = os.environ.get("FLOWRT_NODE_MODULES")
    node = shutil.which("node")
    if not modules or node is None:
        pytest.skip("needs Node.js and FLOWRT_NODE_MODULES with @foxglove/ws-protocol and ajv")
    script = Path(modules).parent / "ws_client.mjs"  # ES modules resolve beside node_modules
    shutil.copyfile(REPO / "tests" / "js" / "ws_client.mjs", script)

    async def run(port: int, topic: str, seconds: str) -> dict[str, Any]:
        proc = await asyncio.create_subprocess_exec(
            node, str(script), f"ws://127.0.0.1:{port}", topic, seconds,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 0, err.decode()
        got: dict[str, Any] = json.loads(out)
        return got

    return run


@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
async def test_both_subprotocols_are_served(subprotocol: str) -> None:
    """foxglove.websocket.v1 (Lichtblick, Studio 1.x, ws-protocol) got HTTP 400."""
    live = FoxgloveLive(port=0)
    async with flowrt.Runtime(ticker(), monitors=[live]), aiohttp.ClientSession() as s:
        url = f"ws://127.0.0.1:{live.port}/"
        async with s.ws_connect(url, protocols=[subprotocol]) as ws:
            assert ws.protocol == subprotocol
            info = json.loads((await ws.receive(timeout=5)).data)
            assert info["op"] == "serverInfo"


@pytest.mark.slow
@pytest.mark.node
async def test_foxglove_ws_protocol_client_receives_frames_at_the_source_rate(
    tmp_path: Path,
) -> None:
    client = ws_client()
    live = FoxgloveLive(port=0)
    async with flowrt.Runtime.from_file(REPO / "graphs" / "cambada.yaml", monitors=[live]):
        got = await client(live.port, "front_cam.frame", "3")
    assert got["subprotocol"] == "foxglove.websocket.v1"  # the client's default
    assert "front_cam.frame" in got["channels"]
    assert got["messages"] >= 0.75 * 20 * got["seconds"]  # the camera's 20 fps


@pytest.mark.slow
@pytest.mark.node
async def test_ws_protocol_client_gets_can_messages_that_ajv_validates(tmp_path: Path) -> None:
    """Issue 38: a can node's per-message outputs were never advertised live, and messages did
    not match their schemas; @foxglove/ws-protocol + ajv read every JSON channel."""
    client = ws_client()
    live = FoxgloveLive(port=0)
    async with flowrt.Runtime.from_file(REPO / "graphs" / "can.yaml", monitors=[live]):
        got = await client(live.port, "json", "3")
    assert {"chassis.WheelSpeeds", "chassis.status", "/flowrt/stats"} <= set(got["json"])
    assert got["invalid"] == {}


class Mixed(Node):
    """An ``Output(object)`` whose values change type: ints, and every third one text."""

    out = Output(object)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> object:
        self.n += 1
        return self.n if self.n % 3 else f"text {self.n}"


@pytest.mark.slow
@pytest.mark.node
async def test_a_stream_changing_type_is_served_on_a_channel_per_type(tmp_path: Path) -> None:
    """Its text values were sent on the channel of its first value's schema (integer),
    which ajv refused; served as recorded now: one channel per type on the topic."""
    client = ws_client()
    g = flowrt.GraphBuilder("mixed")
    g.add("src", Mixed, trigger={"timer": "20ms"})
    live = FoxgloveLive(port=0)
    async with flowrt.Runtime(g.build(), monitors=[live]):
        await asyncio.sleep(0.3)  # both types sent once: both channels advertised
        got = await client(live.port, "json", "2")
    assert got["channels"].count("src.out") == 2
    assert got["json"]["src.out"] > 0
    assert got["invalid"] == {}
