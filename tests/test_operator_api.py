"""The operator's station over HTTP: record a named session from the live view, review it
(the sessions list, a camera's frame at an instant with its detections drawn), and the
machine and stream health over time; state-changing requests only from the view's own
origin (and with its token); session names from a URL never reach outside the folder."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest
from flowrt.nodes.health_history import ALERT_TEXT, HealthHistory

import flowrt
from flowrt import Frame, Input, Node, Output
from flowrt.recording.seek import SessionIndex
from tests.conftest import flowrt_running, trickled_post

pytestmark = [pytest.mark.timeout(120), pytest.mark.realtime]

W, H = 160, 120


@dataclass(frozen=True)
class Spot:
    """A tracker's detection: where the square is on which frame (recorded, then drawn)."""

    found: bool
    centroid: tuple[float, float] | None
    bbox: tuple[int, int, int, int] | None
    confidence: float
    source: str
    timestamp: float
    object: str = "ball"


class Square(Node):
    """A camera: a blue square moving right on grey, 20 frames a second."""

    frame = Output(Frame)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> Frame:
        frame = self.ctx.new_frame((H, W, 3))
        frame.data[:] = (90, 90, 90)
        x = 10 + (self.n * 2) % (W - 40)
        frame.data[40:70, x : x + 30] = (255, 0, 0)
        self.n += 1
        frame.seq = self.n
        return frame


class Finder(Node):
    frame = Input(Frame)
    detection = Output(object)

    def process(self, frame: Frame) -> Spot:
        ys, xs = np.nonzero(frame.data[..., 0] > 200)
        bbox = (int(xs.min()), int(ys.min()), int(np.ptp(xs)) + 1, int(np.ptp(ys)) + 1)
        centre = (float(xs.mean()), float(ys.mean()))
        return Spot(True, centre, bbox, 0.9, frame.source, frame.timestamp)


def graph(folder: Path, **display: Any) -> flowrt.Graph:
    g = flowrt.GraphBuilder("operator-test")
    g.add("cam", Square, trigger={"timer": "50ms"})
    g.add("finder", Finder, inputs={"frame": "cam.frame"})
    g.add(
        "rec",
        "recorder",
        params={"path": str(folder), "start": False, "log_report": False},
        inputs={
            "cam.frame": {"from": "cam.frame", "policy": "lossless", "size": 16},
            "finder.detection": {"from": "finder.detection", "policy": "lossless"},
        },
    )
    g.add(
        "view",
        "display",
        params={"port": 0, "health_hz": 4, **display},
        inputs={"cam": {"from": "cam.frame", "policy": "latest"}},
    )
    return g.build()


@contextlib.asynccontextmanager
async def station(folder: Path, **display: Any) -> AsyncIterator[tuple[aiohttp.ClientSession, str]]:
    async with flowrt.Runtime(graph(folder, **display)) as rt:
        url = rt.scheduler.runners["view"].executor.node.url  # type: ignore[attr-defined]
        async with aiohttp.ClientSession() as http:
            yield http, url


async def post(http: aiohttp.ClientSession, url: str, body: Any, **headers: str) -> tuple[int, Any]:
    async with http.post(url, json=body, headers=headers) as r:
        text = await r.text()
        return r.status, json.loads(text) if r.content_type == "application/json" else text


async def get(http: aiohttp.ClientSession, url: str) -> Any:
    async with http.get(url) as r:
        assert r.status == 200, await r.text()
        return await r.json()


async def record(http: aiohttp.ClientSession, url: str, name: str, seconds: float) -> Any:
    status, started = await post(http, f"{url}/api/record/start", {"name": name})
    assert status == 200, started
    await asyncio.sleep(seconds)
    status, table = await post(http, f"{url}/api/record/stop", {})
    assert status == 200, table
    return started, table


async def test_record_review_and_health_over_http(tmp_path: Path) -> None:
    async with station(tmp_path) as (http, url):
        state = await get(http, f"{url}/api/record")
        assert state["recorders"] == ["rec"]
        assert not state["recording"]

        status, started = await post(http, f"{url}/api/record/start", {"name": "drive"})
        assert status == 200, started
        assert started["session"] == "drive_001"
        await asyncio.sleep(1.2)
        live = await get(http, f"{url}/api/record")
        assert live["recording"]
        assert live["session"] == "drive_001"
        assert live["elapsed_s"] > 0.5
        assert live["size_bytes"] > 0
        assert {s["topic"] for s in live["streams"]} >= {"cam.frame", "finder.detection"}
        # one session at a time
        status, busy = await post(http, f"{url}/api/record/start", {"name": "other"})
        assert status == 409
        assert "drive_001" in busy["error"]
        await asyncio.sleep(0.8)
        status, table = await post(http, f"{url}/api/record/stop", {})
        assert status == 200, table
        assert table["session"] == "drive_001"
        assert table["lost"] == 0
        cam = next(s for s in table["streams"] if s["topic"] == "cam.frame")
        assert cam["received"] == cam["written"] >= 25
        assert cam["lost"] == 0
        assert cam["expected"] is not None
        assert abs(cam["rate_mean"] - 20) < 3
        status, idle = await post(http, f"{url}/api/record/stop", {})
        assert status == 409
        assert idle["error"] == "not recording"

        listed = await get(http, f"{url}/api/sessions")
        assert listed["folders"] == [str(tmp_path)]
        (row,) = listed["sessions"]
        assert row["name"] == "drive_001"
        assert not row["recording"]
        assert row["lost"] == 0
        assert row["start"]
        assert 1.5 < row["duration_s"] < 4
        assert row["size_bytes"] > 25 * W * H * 3
        frames = next(s for s in row["streams"] if s["topic"] == "cam.frame")
        assert frames["frames"] == cam["written"]
        assert abs(frames["rate"] - 20) < 3

        detail = await get(http, f"{url}/api/sessions/drive_001")
        assert detail["cameras"] == ["cam.frame"]
        # issue 43: one length per session, whichever answer gives it (first to last message)
        assert abs(detail["duration_s"] - row["duration_s"]) < 0.1
        assert abs(detail["duration_s"] - table["duration_s"]) < 0.1
        det = next(s for s in detail["streams"] if s["topic"] == "cam.frame")
        assert det["written"] == det["frames"] == cam["written"]
        assert det["gaps"] == []

        # the frame at 1.0 s: the square at its recorded place, the detection box drawn round it
        async with http.get(
            f"{url}/api/sessions/drive_001/frame", params={"topic": "cam.frame", "t": "1.0"}
        ) as r:
            assert r.status == 200
            assert r.content_type == "image/jpeg"
            at = float(r.headers["X-Frame-Time"])
            jpeg = await r.read()
        assert jpeg[:2] == b"\xff\xd8"
        assert 0.9 <= at <= 1.0
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (H, W, 3)
        cols = np.nonzero(img[48, :, 0] > 200)[0]  # the blue square, decoded from the file
        assert 24 <= len(cols) <= 32, cols
        x = int(cols.min())
        # the detection's box drawn round it in the ball's colour (BGR 0, 140, 255): red where
        # the recorded frame has none (grey 90 around, blue 0 inside)
        assert (img[40, x + 3 : x + 25, 2] > 150).mean() > 0.8, img[40, x : x + 28]
        assert (img[48, x + 3 : x + 25, 2] < 60).all()
        assert int(r.headers["X-Frame-Seq"]) > 0

        health = await get(http, f"{url}/api/health/history?seconds=5")
        assert len(health["t"]) >= 3
        assert health["interval_s"] == 0.25
        names = {s["name"] for s in health["series"]}
        assert {"cpu.0", "memory", "swap", "disk", "disk.write", "net.sent"} <= names
        assert {"stream.cam.fps", "stream.cam.drops", "stream.cam.age"} <= names
        for s in health["series"]:
            assert sum(v is not None for v in s["values"]) >= 3, s["name"]
        fps = next(s for s in health["series"] if s["name"] == "stream.cam.fps")
        assert abs(fps["values"][-1] - 20) < 3


async def test_refusals(tmp_path: Path) -> None:
    async with station(tmp_path) as (http, url):
        host = re.sub(r"^http://", "", url)
        # another web page: refused before anything is done
        status, _ = await post(
            http, f"{url}/api/record/start", {"name": "x"}, Origin="http://evil.example"
        )
        assert status == 403
        # a form (no JSON): a cross-site form cannot send application/json without asking
        async with http.post(f"{url}/api/record/start", data={"name": "x"}) as r:
            assert r.status == 415
        status, bad = await post(http, f"{url}/api/record/start", {"name": "../x"})
        assert status == 400
        assert "name" in bad["error"]
        status, same = await post(
            http, f"{url}/api/record/start", {"name": "ok"}, Origin=f"http://{host}"
        )
        assert status == 200
        assert same["session"] == "ok_001"
        await post(http, f"{url}/api/record/stop", {})
        assert not await asyncio.to_thread(lambda: list(tmp_path.glob("x_*")))

        for path in ("..%2F..%2Fetc", "..", ".hidden", "a%2Fb", "ok_001%00"):
            async with http.get(f"{url}/api/sessions/{path}/frame?topic=cam.frame") as r:
                assert r.status in (400, 404), path
        async with http.get(f"{url}/api/sessions/ok_999") as r:
            assert r.status == 404
        async with http.get(f"{url}/api/sessions/ok_001/frame?topic=finder.detection") as r:
            assert r.status == 404
            assert "cam.frame" in await r.text()
        for t in ("nan", "1e308", "-1e308"):  # 1e308: 422 with a Python overflow message
            async with http.get(f"{url}/api/sessions/ok_001/frame?topic=cam.frame&t={t}") as r:
                assert r.status == 400, t
                text = await r.text()
                assert text.startswith("t is seconds from the session's start"), text
        async with http.get(f"{url}/api/health/history?seconds=-1") as r:
            assert r.status == 400


async def test_the_token_guards_the_record_api(tmp_path: Path) -> None:
    async with station(tmp_path, token="s3cret-token") as (http, url):
        status, _ = await post(http, f"{url}/api/record/start", {"name": "x"})
        assert status == 401
        auth = {"Authorization": "Bearer s3cret-token"}
        status, ok = await post(http, f"{url}/api/record/start", {"name": "x"}, **auth)
        assert status == 200
        assert ok["session"] == "x_001"
        status, table = await post(http, f"{url}/api/record/stop", {}, **auth)
        assert status == 200
        assert table["session"] == "x_001"
        async with http.get(f"{url}/api/sessions") as r:
            assert r.status == 401


async def test_a_graph_without_recorder_says_so(tmp_path: Path) -> None:
    g = flowrt.GraphBuilder("no-recorder")
    g.add("cam", Square, trigger={"timer": "50ms"})
    g.add("view", "display", params={"port": 0}, inputs={"cam": "cam.frame"})
    async with flowrt.Runtime(g.build()) as rt:
        url = rt.scheduler.runners["view"].executor.node.url  # type: ignore[attr-defined]
        async with aiohttp.ClientSession() as http:
            status, answer = await post(http, f"{url}/api/record/start", {"name": "x"})
            assert status == 404
            assert "--recordings" in answer["error"]
            assert (await get(http, f"{url}/api/record"))["recorders"] == []
            assert (await get(http, f"{url}/api/sessions"))["sessions"] == []


# --- the parts, without a runtime ----------------------------------------------------------


def stats(fps: float, skipped: int = 0) -> dict[str, Any]:
    return {
        "runtime": {"nodes": [{"name": "cam", "skipped": skipped, "dropped": 0}], "frames": []},
        "display": {"sources": [{"name": "cam", "node": "cam", "fps": fps, "age": 0.01}]},
    }


def test_a_rate_drop_is_alerted_once_when_it_starts() -> None:
    h = HealthHistory(keep_s=60, hz=1)
    t0 = time.time()
    for i in range(10):
        h.sample(stats(20.0), now=t0 + i)
    assert not h.alerts
    for i in range(10, 14):
        h.sample(stats(9.0), now=t0 + i)  # half the usual rate, four samples long
    (alert,) = h.alerts
    assert alert["text"] == ALERT_TEXT == "ALERT - FRAME DROPS"
    assert alert["stream"] == "cam"
    assert alert["t"] == t0 + 10
    assert alert["usual_fps"] == 20
    for i in range(14, 16):
        h.sample(stats(20.0), now=t0 + i)
    h.sample(stats(20.0, skipped=3), now=t0 + 16)  # frames dropped at the camera
    assert len(h.alerts) == 2
    assert h.alerts[-1]["drops"] == 3
    window = h.window(5)
    assert len(window["t"]) == 5
    assert [a["t"] for a in window["alerts"]] == [t0 + 16]
    drops = next(s for s in window["series"] if s["name"] == "stream.cam.drops")
    assert drops["values"] == [0, 0, 0, 0, 3]


def test_the_ring_keeps_its_length() -> None:
    h = HealthHistory(keep_s=10, hz=2)
    for i in range(100):
        h.sample(None, now=1000.0 + i / 2)
    assert len(h.samples) == 21
    assert h.window(1e9)["t"][0] == 1000.0 + 79 / 2


def test_a_killed_recording_is_indexed_up_to_its_damage(tmp_path: Path) -> None:
    from flowrt.recording import RecordingWriter

    path = tmp_path / "cut.mcap"
    w = RecordingWriter(path, chunk_size=64 << 10, max_frames=64)
    w.open({}, [])
    w.declare("cam.frame", "cam.frame")
    for i in range(30):
        pixels = np.full((H, W, 3), i, np.uint8)
        frame = Frame(pixels, source="cam", seq=i, timestamp=100.0 + i / 20)
        assert w.submit("cam.frame", frame, frame.timestamp, i)
    w.request_close(lambda: [], lambda: None)
    assert w.join(10)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])  # killed: no summary, a chunk cut short
    index = SessionIndex(path)
    topic = index.topics["cam.frame"]
    assert 5 < len(topic.times) < 30
    assert index.damage
    last = index.message("cam.frame", len(topic.times) - 1)
    assert last.sequence == len(topic.times) - 1
    assert topic.at(index.start_ns + 250_000_000) == 5  # 0.25 s at 20 Hz


# --- the scenario, as a user runs it ------------------------------------------------


@pytest.mark.subprocess
async def test_cambada_with_recordings_start_three_seconds_stop(tmp_path: Path, repo: Path) -> None:
    """``flowrt run graphs/cambada.yaml --recordings DIR``: start, 3 s, stop: both cameras at
    about 20 fps and nothing lost; the session listed, a frame at 1.0 s, a cross-origin POST
    refused, 5 s of health with at least 3 samples of every series."""
    run_args = ("run", "graphs/cambada.yaml", "--recordings", str(tmp_path / "rec"))
    async with flowrt_running(*run_args, "--no-ui", "--display-port", "0", cwd=repo) as run:
        url = (await run.addresses(view=r"display: (http://127\.0\.0\.1:\d+)"))["view"]
        async with aiohttp.ClientSession() as http:
            for _ in range(100):  # the recorder says it is there once it is set up
                state = await get(http, f"{url}/api/record")
                if state["recorders"]:
                    break
                await asyncio.sleep(0.1)
            assert state["recorders"] == ["recorder"]
            assert not state["recording"]
            started, table = await record(http, url, "cambada", 3.0)
            assert started["session"] == "cambada_001"
            assert table["error"] is None
            lost = 0
            for cam in ("front_cam.frame", "omni_cam.frame"):
                row = next(s for s in table["streams"] if s["topic"] == cam)
                assert abs(row["rate_mean"] - 20) < 2, row
                # every frame received is written or counted lost: a writer behind a machine
                # loaded by the whole suite may refuse a few (CI: 2), never silently
                assert row["written"] + row["lost"] == row["received"] >= 55, row
                assert row["lost"] <= row["received"] // 10, row
                lost += row["lost"]
            assert table["lost"] >= lost

            listed = await get(http, f"{url}/api/sessions")
            assert [s["name"] for s in listed["sessions"]] == ["cambada_001"]
            async with http.get(
                f"{url}/api/sessions/cambada_001/frame",
                params={"topic": "omni_cam.frame", "t": "1.0"},
            ) as r:
                assert r.status == 200
                assert r.content_type == "image/jpeg"
                assert (await r.read())[:2] == b"\xff\xd8"
            status, _ = await post(
                http, f"{url}/api/record/start", {"name": "x"}, Origin="http://evil.example"
            )
            assert status == 403
            health = await get(http, f"{url}/api/health/history?seconds=5")
            assert len(health["series"]) >= 2 + 6 + 3 * 2  # 2 cores, machine, 2 cameras
            for s in health["series"]:
                assert sum(v is not None for v in s["values"]) >= 3, s["name"]
        await run.stop()


async def test_a_record_request_body_sent_a_byte_at_a_time_is_408(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The page's state-changing requests read their body within BODY_TIMEOUT (there was no
    limit: a client trickling a body held its connection's slot as long as it liked)."""
    from aiohttp import web
    from flowrt.nodes.station import record as operator_record

    monkeypatch.setattr(operator_record, "BODY_TIMEOUT", 0.3)

    async def echo(request: web.Request) -> web.Response:
        return web.json_response(await operator_record._body(request))

    app = web.Application()
    app.router.add_post("/api/record/start", echo)
    runner = web.AppRunner(app, shutdown_timeout=0.5)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    try:
        status = await trickled_post(runner.addresses[0][1], "/api/record/start", b'{"na')
        assert status.startswith(b"HTTP/1.1 408"), status
    finally:
        await runner.cleanup()
