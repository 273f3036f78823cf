"""``--foxglove``: the running graph served live; a viewer that never reads never slows it.

The clients speak the Foxglove WebSocket protocol over a plain socket (handshake, advertise,
subscribe), so the test sees exactly what the Foxglove app would.
"""

from __future__ import annotations

import asyncio
import base64
import fcntl
import json
import os
import socket
import struct
import termios
from typing import Any

import pytest
from conftest import wait_until

import flowrt
from flowrt.recording.encoding import Decoder, image_schema
from flowrt.recording.live import FoxgloveLive

pytestmark = pytest.mark.timeout(60)


class Client:
    """A minimal Foxglove WebSocket client on a blocking socket."""

    def __init__(self, port: int, rcvbuf: int | None = None) -> None:
        self.sock = socket.socket()
        if rcvbuf is not None:  # a tiny window: the server's sends back up at once
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(30)  # a loaded machine (the full suite on 2 CPUs)
        self.sock.connect(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.channels: dict[str, dict[str, Any]] = {}

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("closed")
            out += chunk
        return out

    def frame(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return b0 & 0x0F, self._exact(n)

    def send_text(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        header = bytes([0x81])
        header += (
            bytes([0x80 | len(data)])
            if len(data) < 126
            else (bytes([0x80 | 126]) + struct.pack(">H", len(data)))
        )
        self.sock.sendall(header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def next_frame(self) -> tuple[int, bytes]:
        """The next frame; channel advertisements are noted on the way, an error the server
        reports (``Unknown channel ID``: a refused subscription) fails the test at once."""
        op, payload = self.frame()
        if op == 1:
            msg = json.loads(payload)
            if msg.get("op") == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
            assert not (msg.get("op") == "status" and msg.get("level") == 2), msg
        return op, payload

    def wait_for_channel(self, topic: str) -> dict[str, Any]:
        while topic not in self.channels:
            self.next_frame()
        return self.channels[topic]

    def subscribe(self, topic: str, sub_id: int = 1) -> None:
        ch = self.wait_for_channel(topic)
        sub = {"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": ch["id"]}]}
        self.send_text(json.dumps(sub))

    def next_message(self) -> bytes:
        """The payload of the next message-data frame (opcode 1 of the binary protocol)."""
        while True:
            op, payload = self.next_frame()
            if op == 2 and payload[0] == 1:
                return payload[1 + 4 + 8 :]


def unread_bytes(c: Client) -> int:
    """What waits in the client's socket, unread."""
    return struct.unpack("i", fcntl.ioctl(c.sock, termios.FIONREAD, b"\0" * 4))[0]


def graph() -> Any:
    g = flowrt.GraphBuilder("live")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20, "size": [320, 240]})
    g.add(
        "ball",
        "tracker",
        params={"object": "ball"},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )
    return g.build()


@pytest.mark.realtime
async def test_live_frames_reach_a_viewer_and_a_stuck_viewer_slows_nothing() -> None:
    live = FoxgloveLive(port=0, image_format="raw")
    async with flowrt.Runtime(graph(), monitors=[live]) as rt:
        stuck = await asyncio.to_thread(Client, live.port, 4096)
        await asyncio.to_thread(stuck.subscribe, "cam.frame")  # ... and never reads again
        reader = await asyncio.to_thread(Client, live.port)
        await asyncio.to_thread(reader.subscribe, "cam.frame")
        payload = await asyncio.to_thread(reader.next_message)
        await asyncio.to_thread(reader.subscribe, "ball.detection", 2)
        await rt.run(2.0)  # 40 frames of 230 kB each toward a viewer with a 4 kB window
        # fewer in 2 s on a loaded machine: more time for what is asserted, the same bars
        await wait_until(lambda: live.sent >= 20 and unread_bytes(stuck) >= 1024)
        stats = rt.stats()
        sent = live.sent
        pending = unread_bytes(stuck)
    for c in (stuck, reader):
        c.sock.close()
    from mcap.records import Schema

    s = image_schema(False)
    px, fmt = Decoder().image(Schema(id=1, name=s.name, encoding=s.encoding, data=s.data), payload)
    assert px.shape == (240, 320, 3)
    assert fmt == "BGR"
    assert sent >= 20  # the frames were offered to both viewers (the stuck one included)
    assert pending >= 1024  # the stuck viewer's socket was full: it truly never read
    # the monitor never held the camera's pool slots hostage, nor an edge of the graph
    assert all(p.dropped == 0 for p in stats.frames)
    assert all(e.dropped == 0 for e in stats.edges if not e.name.endswith("->host"))
    cam = next(n for n in stats.nodes if n.name == "cam")
    ball = next(n for n in stats.nodes if n.name == "ball")
    assert cam.completions > 0
    assert ball.completions > 0


async def test_live_detections_are_drawn_on_their_camera() -> None:
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    from flowrt.recording.encoding import annotations_schema

    live = FoxgloveLive(port=0, image_format="raw")
    async with flowrt.Runtime(graph(), monitors=[live]) as rt:
        viewer = await asyncio.to_thread(Client, live.port)
        run = asyncio.ensure_future(rt.run(30.0))  # stopped as soon as a message came
        topic = "cam.frame/annotations/ball.detection"
        await asyncio.to_thread(viewer.subscribe, topic)
        payload = await asyncio.to_thread(viewer.next_message)
        rt.request_stop()
        await run
    viewer.sock.close()
    assert viewer.channels[topic]["schemaName"] == "foxglove.ImageAnnotations"
    s = annotations_schema()
    decode = DecoderFactory().decoder_for(
        "protobuf", Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    )
    assert decode is not None
    ann = decode(payload)
    assert ann.timestamp.seconds > 1_600_000_000  # the frame's time, as Unix time


async def test_live_events_carry_unix_time() -> None:
    """An event's ``t`` (seconds since the run's start) is served as Unix time, as every
    recorded and live time is; it was off by the clock's origin (the machine's uptime)."""
    import time

    live = FoxgloveLive(port=0)
    async with flowrt.Runtime(graph(), monitors=[live]) as rt:
        viewer = await asyncio.to_thread(Client, live.port)
        await asyncio.to_thread(viewer.subscribe, "/flowrt/events")
        await asyncio.sleep(0.5)  # the subscription reaches the server
        rt.set_timing("ball", priority=30)  # a TimingChanged event
        payload = await asyncio.to_thread(viewer.next_message)
    viewer.sock.close()
    event = json.loads(payload)
    assert event["kind"] == "TimingChanged"
    assert abs(event["t"] - time.time()) < 30


def test_a_late_channel_reaches_viewers_once_it_can_be_subscribed() -> None:
    """The SDK's server queues a new channel's advertisement before it takes subscriptions to
    it: a viewer that subscribed at once was told ``Unknown channel ID`` and got nothing (the
    flaky detections test). The bridge relays nothing while a channel is being added."""
    import foxglove

    live = FoxgloveLive(port=0)
    live.open()
    viewer = None
    try:
        viewer = Client(live.port)
        _, info = viewer.next_frame()
        assert json.loads(info)["op"] == "serverInfo"  # nothing else is on its way
        with live._bridge.holding():
            foxglove.Channel("late", message_encoding="json", context=live._ctx)
            viewer.sock.settimeout(0.5)  # the advertisement is queued: the bridge holds it
            with pytest.raises(TimeoutError):
                viewer.next_frame()
            viewer.sock.settimeout(30)
        assert viewer.wait_for_channel("late")["encoding"] == "json"
    finally:
        if viewer is not None:
            viewer.sock.close()
        live.stopped(None)  # type: ignore[arg-type]  # no runtime: only the server to stop


def test_run_foxglove_port_taken_is_one_line() -> None:
    import subprocess
    import sys
    from pathlib import Path

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        repo = Path(__file__).resolve().parent.parent
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "flowrt.cli",
                "run",
                "graphs/cambada.yaml",
                "--no-ui",
                "--no-display",  # the view's port is not what this test is about
                "--duration",
                "5",
                "--foxglove",
                str(port),
            ],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 1  # a taken port is a runtime failure, like --control's
    assert "foxglove server" in r.stderr
    assert "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


async def test_a_viewer_nobody_watches_shows_no_drops() -> None:
    """Issue 24: with --foxglove and no app connected, the live server's buffers showed red
    drops; values nobody asked for are ``unread`` (sampled), not lost."""
    import flowrt
    from flowrt.recording.live import FoxgloveLive

    live = FoxgloveLive(port=0)
    g = flowrt.GraphBuilder("fox")
    g.add("tick", "counter", trigger={"timer": 10})
    async with flowrt.Runtime(g.build(), monitors=[live]) as rt:
        await rt.run(0.5)

        def unread() -> int:  # a loaded machine may tick fewer times in 0.5 s: more time
            return sum(e.unread for e in rt.stats().edges if e.name.endswith("->host"))

        await wait_until(lambda: unread() > 10)
        stats = rt.stats()
    host = [e for e in stats.edges if e.name.endswith("->host")]
    assert host
    assert all(e.dropped == 0 for e in host), host
    assert sum(e.unread for e in host) > 10


def test_ctl_durations_take_units() -> None:
    from flowrt.cli.ctl import duration_ms_arg

    assert duration_ms_arg("80ms") == 80
    assert duration_ms_arg("0.1s") == 100
    assert duration_ms_arg("500us") == 0.5
    assert duration_ms_arg("5") == 5
