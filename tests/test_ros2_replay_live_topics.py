"""``flowrt replay REC`` without ``--graph`` publishes each stream under its recorded name,
``flowrt`` and ``ros2`` profile alike: what a live view serves is what was recorded.

Found by the audit: ``flowrt replay SESSION --foxglove PORT`` served ``wheels.values`` as
``wheels.message``; a node's several recorded streams (``chassis.Battery``,
``chassis.Infrared``, ``chassis.WheelSpeeds``, ``chassis.status``) shared one channel
``chassis.message`` whose schema was guessed from the first message; and an empty
``NODE.frame`` image channel was advertised for every node without images. Each replay node
standing for a recorded node now has that node's recorded ports (a recording made by another
writer, whose topics name no ``node.port``, keeps the generic ``frame``/``message``), and a
value recorded as a dataclass of a built-in kind (``CanMessage``) comes back as it, so the
live schema is the recorded one.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import flowrt_running

import flowrt
from flowrt import AudioBlock, Frame
from flowrt.recording.reader import scan_session
from flowrt.recording.streams import split_set
from flowrt.recording.writer.threads import RecordingWriter

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[1]
N = 5


def _frame(seq: int) -> Frame:
    return Frame(np.full((8, 8, 3), seq, np.uint8), source="cam", seq=seq, timestamp=0.1 * seq)


def _streams(i: int) -> list[tuple[str, Any]]:
    """(topic, value) of one round: a node of several streams, images, audio, a sync set."""
    t = 0.1 * i
    pair = {"a": _frame(i), "b": _frame(i), "stamp": t, "spread_ms": 0.5}
    index, members = split_set("pair.set", pair)
    return [
        ("wheels.values", {"LeftSpeed": i / 4, "RightSpeed": -i / 4}),
        ("chassis.Battery", {"name": "Battery", "signals": {"Voltage": 24.2}, "timestamp": t}),
        ("chassis.WheelSpeeds", {"name": "WheelSpeeds", "signals": {"Left": i}, "timestamp": t}),
        ("chassis.status", {"received": i, "bus_off": False, "timestamp": t}),
        ("cam.frame", _frame(i)),
        ("mic.audio", AudioBlock(np.zeros((64, 1), np.float32), 16_000, t, i)),
        *members,
        ("pair.set", index),
    ]


def record(path: Path, profile: str) -> Path:
    """A session as the recorder writes it (a set's members with their set's source)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    w = RecordingWriter(path, profile=profile, epoch_offset=time.time())
    w.open({})
    for i in range(N):
        for topic, value in _streams(i):
            w.declare(topic, source=topic)
            assert w.submit(topic, value, 0.1 * i + 0.001, i)
    w.close()
    assert w.error is None
    assert not w.notes
    return path


def replay_graph(path: Path, monkeypatch: pytest.MonkeyPatch) -> Any:
    """The graph ``flowrt replay PATH`` (no graph) runs, taken instead of run."""
    import flowrt.cli.replay as replay_cli
    from flowrt.cli import main

    taken: list[Any] = []

    def run_graph(graph: Any, *args: Any, **kw: Any) -> int:
        taken.append(graph)
        return 0

    monkeypatch.setattr(replay_cli, "run_graph", run_graph)
    assert main(["replay", str(path), "--no-ui", "--no-display"]) == 0
    (graph,) = taken
    return graph


def served(graph: Any) -> dict[str, Any]:
    """``node.port`` -> declared type of every output: the channels a live view serves."""
    return {
        f"{name}.{port}": out.type
        for name, node in graph.nodes.items()
        for port, out in {**node.cls.outputs, **node.cls.params_outputs(node.params)}.items()
    }


RECORDED = {
    "wheels.values": object,
    "chassis.Battery": object,
    "chassis.WheelSpeeds": object,
    "chassis.status": object,
    "cam.frame": Frame,
    "mic.audio": AudioBlock,
    "pair.set": object,  # its members are joined into it, not streams of their own
}


@pytest.mark.parametrize("profile", ["flowrt", "ros2"])
def test_each_recorded_stream_is_published_under_its_own_name(
    profile: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = record(tmp_path / "s_001" / "s_001.mcap", profile)
    graph = replay_graph(rec.parent, monkeypatch)
    assert served(graph) == RECORDED


@pytest.mark.parametrize("profile", ["flowrt", "ros2"])
def test_each_port_publishes_its_own_stream(
    profile: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = record(tmp_path / "s_001" / "s_001.mcap", profile)
    graph = replay_graph(rec.parent, monkeypatch)

    async def run() -> dict[str, list[Any]]:
        async with flowrt.Runtime(graph) as rt:
            subs = {t: rt.subscribe(t, size=64) for t in RECORDED}
            await asyncio.wait_for(rt.run(), timeout=30)  # the replay stops at its end
            return {t: list(s.drain()) for t, s in subs.items()}

    got = asyncio.run(run())
    assert {t: len(v) for t, v in got.items()} == dict.fromkeys(RECORDED, N)
    assert [v["name"] for v in got["chassis.Battery"]] == ["Battery"] * N
    assert [v["signals"] for v in got["chassis.WheelSpeeds"]][-1]["Left"] == N - 1
    assert [v["received"] for v in got["chassis.status"]] == list(range(N))
    assert [f.seq for f in got["cam.frame"]] == list(range(N))
    assert all(isinstance(b, AudioBlock) for b in got["mic.audio"])
    if profile == "flowrt":  # (a ros2 bag's set index names its members by flowrt names)
        assert all(isinstance(s["a"], Frame) for s in got["pair.set"])


def test_ports_named_like_a_replay_node_s_own_parts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A recorded port name is data: ``process``, ``run`` or ``params`` is a port, and the
    replay node's own method and state stay what they are."""
    path = tmp_path / "odd.mcap"
    w = RecordingWriter(path, epoch_offset=time.time())
    w.open({})
    for port in ("process", "run", "params"):
        w.declare(f"odd.{port}", source=f"odd.{port}")
        for i in range(N):
            assert w.submit(f"odd.{port}", {"port": port, "i": i}, 0.1 * i, i)
    w.close()
    graph = replay_graph(path, monkeypatch)
    assert set(served(graph)) == {"odd.process", "odd.run", "odd.params"}

    async def run() -> dict[str, list[Any]]:
        async with flowrt.Runtime(graph) as rt:
            subs = {t: rt.subscribe(t, size=64) for t in served(graph)}
            await asyncio.wait_for(rt.run(), timeout=30)
            return {t: list(s.drain()) for t, s in subs.items()}

    got = asyncio.run(run())
    for topic, values in got.items():
        assert [(v["port"], v["i"]) for v in values] == [(topic[4:], i) for i in range(N)]


def test_a_foreign_recording_keeps_the_generic_ports(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Topics that name no ``node.port`` (another writer's, a ROS bag's): ``frame`` for
    images and ``message`` for the rest, as before."""
    from mcap.writer import Writer

    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        sid = w.register_schema("Num", "jsonschema", b'{"type":"object"}')
        cid = w.register_channel("/imu/data", "json", sid)
        for i in range(3):
            w.add_message(cid, i * 1_000_000, json.dumps({"x": i}).encode(), i * 1_000_000)
        w.finish()  # type: ignore[no-untyped-call]
    assert set(served(replay_graph(path, monkeypatch))) == {"_imu_data.frame", "_imu_data.message"}


# --- end to end: flowrt record, then flowrt replay --foxglove, a client reads the channels ----


async def _advertised(url: str, seconds: float) -> dict[str, dict[str, Any]]:
    import aiohttp

    channels: dict[str, dict[str, Any]] = {}
    async with (
        aiohttp.ClientSession() as s,
        s.ws_connect(url, protocols=["foxglove.websocket.v1"]) as ws,
    ):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            with contextlib.suppress(asyncio.TimeoutError):
                msg = await ws.receive(timeout=max(0.05, end - time.monotonic()))
                if msg.type == aiohttp.WSMsgType.TEXT:
                    op = json.loads(msg.data)
                    if op.get("op") == "advertise":
                        channels.update({c["topic"]: c for c in op["channels"]})
    return channels


@pytest.mark.slow
async def test_replay_without_a_graph_serves_the_recorded_channels(
    tmp_path: Path, flowrt_cli: Any
) -> None:
    r = flowrt_cli(
        "record", "graphs/can.yaml", "-o", str(tmp_path), "--name", "c", "--duration", "2",
        "--no-ui", "--no-display", timeout=120,
    )  # fmt: skip
    assert r.returncode == 0 or "message(s) lost" in r.stderr, r.stderr
    session = tmp_path / "c_001"
    recorded = {s.topic: s.schema_name for s in scan_session(session).streams}
    args = ("replay", str(session), "--no-ui", "--no-display", "--loop", "--foxglove", "0")
    async with flowrt_running(*args, cwd=tmp_path) as run:
        found = await run.addresses(url=r"foxglove: open (ws://\S+)")
        channels = await _advertised(found["url"], 4.0)
        await run.stop()
    live = {t: c["schemaName"] for t, c in channels.items() if not t.startswith("/flowrt/")}
    assert live == recorded
    assert not [t for t in channels if re.search(r"\.(frame|message)$", t)]
