"""rosbag2 in: folders written by ``rosbags`` (MCAP and SQLite3 storage) read like a session.

The bags are written in the test by rosbags' own ``Writer``; flowrt must list their topics
with types and counts, decode every message (images into pixels with their header.stamp,
Twist into a plain mapping), and a ``replay`` -> ``tracker`` graph must track every frame of a
rendered clip exactly as ``capture file:`` of the same clip does.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_data import STAMP_LEAD, T0, clip_frames, write_bag

import flowrt
from flowrt.recording.decoding import MessageDecoder, undecodable
from flowrt.recording.encoding import to_jsonable
from flowrt.recording.reader import iter_session, scan_session
from flowrt.recording.session import mcap_files

pytestmark = pytest.mark.timeout(120)

N = 30  # frames of the clip
VIDEO = Path("/work/shared/data/sample_720x528.avi")  # real footage on the dev machines
STORAGES = ["mcap", "sqlite3"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[np.ndarray]]:
    return clip_frames(tmp_path_factory.mktemp("clip"), N)


@pytest.fixture(scope="module", params=STORAGES)
def bag(request: Any, tmp_path_factory: pytest.TempPathFactory, clip: Any) -> Path:
    return write_bag(tmp_path_factory.mktemp("bags") / request.param, request.param, clip[1])


def test_info_lists_the_topics_with_types_and_counts(bag: Path) -> None:
    info = scan_session(bag)
    got = {s.topic: (s.schema_name, s.count) for s in info.streams}
    assert got == {
        "/camera/image_raw": ("sensor_msgs/msg/Image", N),
        "/camera/mono": ("sensor_msgs/msg/Image", N),
        "/camera/compressed": ("sensor_msgs/msg/CompressedImage", N),
        "/cmd_vel": ("geometry_msgs/msg/Twist", N),
    }
    assert info.closed_cleanly
    assert info.start == pytest.approx(T0 / 1e9)
    assert info.duration == pytest.approx((N - 1) / 25)


def test_the_last_message_time_is_known_for_the_progress_line(bag: Path) -> None:
    """A ``.db3`` bag's replay showed no progress total (``duration_s: null``); the same bag
    as ``.mcap`` had one."""
    from flowrt.recording.reader import last_log_time

    (last,) = {last_log_time(f) for f in mcap_files(bag)[-1:]}
    assert last is not None
    assert (last - T0) / 1e9 == pytest.approx((N - 1) / 25)


def test_every_message_decodes(bag: Path, clip: Any) -> None:
    frames = clip[1]
    files = mcap_files(bag)
    assert undecodable(files, [s.topic for s in scan_session(bag).streams]) == {}
    dec = MessageDecoder()
    seen: dict[str, int] = {}
    for m in iter_session(files):
        i = seen[m.topic] = seen.get(m.topic, -1) + 1
        d = dec.decode(m.encoding, m.schema, m.data)
        if m.topic == "/cmd_vel":
            assert d.kind == "value"
            assert d.value["linear"]["x"] == pytest.approx(0.1 * i)
            assert d.value["angular"] == {"x": 0.0, "y": 0.0, "z": -0.5}
            continue
        assert d.kind == "image"
        assert d.stamp == m.log_time - STAMP_LEAD  # header.stamp, not the log time
        px, fmt = d.value
        if m.topic == "/camera/image_raw":
            assert fmt == "BGR"
            assert np.array_equal(px, frames[i])
        elif m.topic == "/camera/mono":
            assert fmt == "GRAY"
            assert px.shape == frames[i].shape[:2]
        else:  # jpeg: close to the original, not equal
            assert fmt == "BGR"
            assert np.abs(px.astype(int) - frames[i]).mean() < 8
    assert seen == dict.fromkeys(seen, N - 1)
    assert len(seen) == 4


def _lamp(g: flowrt.GraphBuilder) -> None:
    g.add(
        "lamp",
        "tracker",
        params={"object": "candle", "space": "hsv"},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )


async def _detections(source: dict[str, Any], end: float) -> list[Any]:
    g = flowrt.GraphBuilder("ros-bag")
    g.add("cam", source.pop("kind"), **source)
    _lamp(g)
    async with flowrt.Runtime(g.build()) as rt:
        sub = rt.subscribe("lamp.detection", size=1024)
        await asyncio.wait_for(rt.run(end), timeout=60)
        return list(sub.drain())


def _comparable(det: Any) -> dict[str, Any]:
    d = to_jsonable(det)
    d.pop("timestamp")  # when the frame was stamped: a run's own clock
    return d


@pytest.mark.realtime
def test_replay_of_a_bag_tracks_like_capture_of_the_clip(bag: Path, clip: Any) -> None:
    _same_tracking(bag, clip[0], N)


@pytest.mark.realtime
@pytest.mark.skipif(not VIDEO.exists(), reason=f"{VIDEO} not available")
def test_a_bag_of_real_camera_images_goes_through_the_tracker(tmp_path: Path) -> None:
    n = 20
    path, frames = clip_frames(tmp_path, n, VIDEO)
    bag = write_bag(tmp_path / "real", "mcap", frames)
    _same_tracking(bag, path, n, found=0.5)


def _same_tracking(bag: Path, path: Path, n: int, found: float = 0.9) -> None:
    """``replay`` of the bag and ``capture file:`` of the clip: the same detections."""
    live = asyncio.run(
        _detections(
            {"kind": "capture", "params": {"source": f"file:{path}", "fps": 25, "on_eof": "exit"}},
            n / 25 + 3,
        )
    )
    replayed = asyncio.run(
        _detections(
            {"kind": "replay", "params": {"path": str(bag), "topic": "/camera/image_raw"}},
            n / 25 + 3,
        )
    )
    want = {d.seq: _comparable(d) for d in live}
    got = {d.seq: _comparable(d) for d in replayed}
    assert sorted(want) == list(range(n))  # the clip read whole, every frame tracked
    assert got == want
    assert sum(d.found for d in replayed) >= found * n  # the lamp is there: a real result


@pytest.mark.subprocess
def test_flowrt_info_and_replay_of_a_bag(bag: Path, flowrt_cli: Any) -> None:
    import json

    r = flowrt_cli("info", str(bag))
    assert r.returncode == 0, r.stderr
    if bag.suffix == ".db3" or any(bag.glob("*.db3")):  # said in the bag's words, not MCAP's
        assert "closed cleanly: yes (its SQLite3 database read)" in r.stdout
    for line in ("/camera/image_raw   sensor_msgs/msg/Image", "/cmd_vel   geometry_msgs/msg/Twist"):
        topic, typ = line.split()
        assert any(topic in row and typ in row and f" {N} " in row for row in r.stdout.splitlines())
    got = json.loads(flowrt_cli("info", str(bag), "--json").stdout)
    assert {s["topic"]: s["count"] for s in got["streams"]}["/camera/compressed"] == N
    rep = flowrt_cli("replay", str(bag), "--no-ui", timeout=90)  # to its end: 1.2 s
    assert rep.returncode == 0, rep.stderr
    assert "Traceback" not in rep.stderr
