"""The live view's server under hostile and careless clients (issue 37 items 5 and 8).

The server (:class:`flowrt.nodes.station.server.ViewServer`) runs here in the test's own
event loop on a real socket on 127.0.0.1; the display node's side of its channel is played
by :class:`FakeNode`, which answers statistics and the record panel's calls, and frames are
put in the server's cache directly (JPEG bytes): no runtime, no process.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest
from flowrt.nodes.station.server import ViewServer, _joystick

from flowrt.control.serving import pack, unpack


class FakeNode:
    """The display node's end of the channel: statistics, the record panel's answers."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.joy: list[Any] = []
        self.joy_refused = 0  # told to the node: its joystick-invalid alert
        self.calls: list[dict[str, Any]] = []

    async def run(self) -> None:
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                header, _ = await unpack(self.reader)
                op = header.get("op")
                if op == "stats":
                    self.writer.write(pack({"op": "stats", "display": {}}, b"null"))
                elif op == "joy":
                    self.joy.append(header["value"])
                elif op == "joy-refused":
                    self.joy_refused += 1
                elif op == "record":
                    self.calls.append(header)
                    result = {"status": 409, "error": "not recording"}
                    self.writer.write(pack({"op": "reply", "id": header["id"], "result": result}))


@contextlib.asynccontextmanager
async def view(**settings: Any) -> AsyncIterator[tuple[ViewServer, FakeNode, str]]:
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(128)
    sock.setblocking(False)
    port = sock.getsockname()[1]
    ours, theirs = socket.socketpair()
    server = ViewServer(
        {"url": f"http://127.0.0.1:{port}", "page": b"<html>__FLOWRT_SESSION__", **settings}
    )
    task = asyncio.ensure_future(server.run(sock, theirs))
    reader, writer = await asyncio.open_unix_connection(sock=ours)
    node = FakeNode(reader, writer)
    talker = asyncio.ensure_future(node.run())
    try:
        yield server, node, f"http://127.0.0.1:{port}"
    finally:
        writer.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 5)
        talker.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await talker


def show(server: ViewServer, name: str, jpeg: bytes) -> None:
    """A new encoded frame of ``name``, as the encoder leaves it."""
    server.names.add(name)
    src = server.shown.source(name)
    src.n += 1
    src.raw = src.processed = jpeg
    server.shown.changed(src)


async def feed(server: ViewServer, name: str, size: int, fps: float) -> None:
    """A camera at ``fps`` whose JPEGs are ``size`` bytes, until cancelled."""
    while True:
        show(server, name, bytes(size))
        await asyncio.sleep(1 / fps)


# --- item 8: deep JSON and huge numbers are refused and counted, never a traceback ---------


def test_a_401_digit_axis_refuses_the_message_whole() -> None:
    assert _joystick({"axes": {"x": 10**400}, "buttons": {}}) is None
    assert _joystick({"axes": {"x": float("nan")}, "buttons": {}}) is None
    assert _joystick({"axes": {"x": "1"}, "buttons": {}}) is None
    assert _joystick({"axes": {"x": 2, "y": -0.5}, "buttons": {"a": 1}}) == {
        "axes": {"x": 1.0, "y": -0.5},
        "buttons": {"a": True},
    }


@pytest.mark.realtime
async def test_deep_json_and_huge_ints_are_refused_and_counted(
    capfd: pytest.CaptureFixture[str],
) -> None:
    async with view() as (_, node, url), aiohttp.ClientSession() as http:
        async with http.post(
            url + "/api/record/start",
            data="[" * 100_000,
            headers={"Content-Type": "application/json"},
        ) as r:
            assert r.status == 400
            assert "nested too deeply" in await r.text()
        async with http.get(url + "/") as r:
            session = (await r.text()).removeprefix("<html>")
        async with http.ws_connect(f"{url}/ws?session={session}") as ws:
            await ws.send_str('{"joy": {"axes": {"x": ' + "9" * 401 + '}, "buttons": {}}}')
            await ws.send_str("[" * 60_000)
            await ws.send_json({"joy": {"axes": {"x": 0.5}, "buttons": {}}})
            for _ in range(100):
                if node.joy:
                    break
                await asyncio.sleep(0.02)
        assert node.joy == [{"axes": {"x": 0.5}, "buttons": {}}]  # only the valid one
        assert node.joy_refused == 1  # the bad axis, told to the node (not the bad JSON)
        await asyncio.sleep(0.3)  # past the statistics' cache
        async with http.get(url + "/stats.json") as r:
            display = (await r.json())["display"]
        assert display["refused_messages"] == 2
        assert display["refused_requests"] == 1
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err


# --- item 5: streams that do not read --------------------------------------------------------


def stalled_stream(port: int, path: str = "/stream/cam.mjpg") -> socket.socket:
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # and never read from
    s.connect(("127.0.0.1", port))
    s.send(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    return s


@pytest.mark.realtime
async def test_a_stream_that_stops_reading_is_dropped_within_seconds() -> None:
    """Small frames (2 KB at 30 fps: the socket's buffers alone would hide 10 s of them): the
    client is dropped once it is more than a second behind, counted."""
    async with view(max_streams_per_peer=8) as (server, _, url):
        camera = asyncio.ensure_future(feed(server, "cam", 2000, 30))
        port = int(url.rsplit(":", 1)[1])
        s = stalled_stream(port)
        t0 = time.monotonic()
        for _ in range(150):  # polled: the server counts, it does not signal
            if server.streams.stalled:
                break
            await asyncio.sleep(0.1)
        took = time.monotonic() - t0
        camera.cancel()
        s.close()
        assert server.streams.stalled == 1
        assert took < 6, f"dropped after {took:.1f} s"
        assert not server.streams.clients


@pytest.mark.realtime
async def test_streams_never_take_the_page_and_api_slots() -> None:
    """40 stalled streams from one address (the cap is 8 connections): at most
    max_streams_per_peer of them are served, the rest refused (counted); the page,
    /stats.json and the record API answer at once, and a reading stream gets frames."""
    async with view(max_clients=8) as (server, _, url):
        camera = asyncio.ensure_future(feed(server, "cam", 20_000, 20))
        port = int(url.rsplit(":", 1)[1])
        socks = [stalled_stream(port) for _ in range(40)]
        await asyncio.sleep(0.5)
        assert len(server.streams.clients) <= 4
        timeout = aiohttp.ClientTimeout(total=2)
        async with aiohttp.ClientSession(timeout=timeout) as http:
            for path in ("/", "/stats.json", "/api/record"):
                t0 = time.monotonic()
                async with http.get(url + path) as r:
                    assert r.status == 200, path
                assert time.monotonic() - t0 < 1.0, path
            async with http.post(url + "/api/record/stop", json={}) as r:
                assert r.status == 409  # the fake node: not recording; answered, not locked out
        # every stream beyond the 4 served is counted: refused with a 503, or its connection
        # refused or evicted at the cap of 8
        assert server.streams.refused + server.refused + server.evicted >= 36
        camera.cancel()
        for s in socks:
            s.close()


@pytest.mark.realtime
async def test_websockets_share_the_stream_slots() -> None:
    """Page WebSockets hold their connections too: with the streams, at most max_streams."""
    async with (
        view(max_clients=8, max_streams=3) as (server, _, url),
        aiohttp.ClientSession() as http,
    ):
        sockets = [await http.ws_connect(url + "/ws") for _ in range(3)]
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await http.ws_connect(url + "/ws")
        assert refused.value.status == 503
        async with http.get(url + "/stream/cam.mjpg") as r:
            assert r.status == 503
        async with http.get(url + "/stats.json") as r:
            assert r.status == 200  # the rest stay free
        assert server.streams.refused == 2
        for ws in sockets:
            await ws.close()
