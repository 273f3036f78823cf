"""Replay: recorded streams stand in for a graph's sources, frame for frame.

The synthetic scene is recorded together with the detections of two trackers; the recording
is then replayed through the same trackers and must give the same detections for every frame
(the trackers are stateful, so this also checks that no frame is dropped or reordered).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from mcap.reader import make_reader

import flowrt
from flowrt.cli.record import wait_for_writers
from flowrt.graph._registry import resolve_kind
from flowrt.recording.encoding import Decoder, to_jsonable
from flowrt.recording.reader import scan

pytestmark = pytest.mark.timeout(90)

TRACKERS = {"ball": "ball", "avoid": "obstacle", "goal": "yellow_goal"}


def build(source: dict[str, Any], recorder: dict[str, Any] | None) -> flowrt.GraphBuilder:
    g = flowrt.GraphBuilder("exact")
    g.add("cam", source.pop("kind"), **source)
    for name, obj in TRACKERS.items():
        g.add(
            name,
            "tracker",
            params={"object": obj},
            trigger={"frame": "cam"},
            inputs={"frame": "cam.frame"},
        )
    g.add("sink", "sink", inputs={"input": {"from": "cam.frame", "policy": "queue", "size": 64}})
    if recorder is not None:
        topics = ["cam.frame", *(f"{n}.detection" for n in TRACKERS)]
        g.add(
            "rec",
            "recorder",
            params=recorder,
            inputs={t: {"from": t, "policy": "lossless", "size": 16} for t in topics},
        )
    return g


CAPTURE = {
    "kind": "capture",
    "params": {"source": "synthetic:soccer", "fps": 20, "size": [320, 240], "seed": 5},
}


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("replay")

    async def main() -> None:
        g = build(dict(CAPTURE), {"path": str(tmp), "name": "exact"})
        async with flowrt.Runtime(g.build()) as rt:
            await rt.run(2.0)
            # a loaded machine makes fewer frames in 2 s: more time for the 20 asserted below
            await wait_until(lambda: min(rt.stats().node(n).completions for n in TRACKERS) >= 20)

    asyncio.run(main())
    wait_for_writers()  # a slow (shared) disk may still be finishing the file
    return tmp / "exact_001" / "exact_001.mcap"


def stand_in(path: Path, **params: Any) -> dict[str, Any]:
    """The capture replaced by a replay node with the capture's own ports."""
    from flowrt.nodes.capture.node import Capture

    cls = resolve_kind("replay").standing_in_for(Capture, "cam")  # type: ignore[attr-defined]
    return {"kind": cls, "params": {"path": str(path), "node": "cam", **params}}


async def replay(path: Path, **params: Any) -> tuple[dict[str, list[Any]], Any]:
    g = build(stand_in(path, **params), None)
    out: dict[str, list[Any]] = {n: [] for n in TRACKERS}
    async with flowrt.Runtime(g.build()) as rt:
        subs = {n: rt.subscribe(f"{n}.detection", size=1024) for n in TRACKERS}
        await asyncio.wait_for(rt.run(), timeout=30)  # the replay stops the runtime at its end
        for n, sub in subs.items():
            out[n] = sub.drain()
        stats = rt.stats()
    return out, stats


def recorded(path: Path) -> dict[str, dict[int, Any]]:
    dec = Decoder()
    out: dict[str, dict[int, Any]] = {n: {} for n in TRACKERS}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            node = channel.topic.split(".")[0]
            if node in out:
                det = dec.message(schema.name, message.data)
                out[node][det.seq] = det
    return out


def comparable(det: Any) -> dict[str, Any]:
    d = to_jsonable(det)
    d.pop("timestamp")  # the replayed frame is stamped when it is replayed
    return d


def test_replay_gives_the_same_detections_frame_by_frame(recording: Path) -> None:
    before = recorded(recording)
    assert all(len(v) >= 20 for v in before.values())
    after, stats = asyncio.run(replay(recording))
    for name in TRACKERS:
        got = {d.seq: d for d in after[name]}
        assert sorted(got) == sorted(before[name]), name  # every frame, none more
        for seq, det in before[name].items():
            assert comparable(got[seq]) == comparable(det), (name, seq)
    assert any(d.found for d in after["ball"])  # a non-trivial scene
    # the replayed frames ticked the trackers' frame triggers like the camera did
    tracker = next(n for n in stats.nodes if n.name == "ball")
    assert tracker.skipped == 0


def test_replay_from_an_offset_publishes_only_what_follows(recording: Path) -> None:
    with open(recording, "rb") as f:
        frames = [m.log_time for _, _, m in make_reader(f).iter_messages(topics=["cam.frame"])]
    origin = scan(recording).start
    assert origin is not None
    expected = sum(1 for t in frames if t >= round(origin * 1e9) + 1_000_000_000)
    assert 0 < expected < len(frames)
    _, stats = asyncio.run(replay(recording, start=1.0, rate=4.0))
    edge = next(e for e in stats.edges if e.name == "cam.frame->sink.input")
    assert edge.published == expected


def test_truncated_file_replays_up_to_the_damage(recording: Path, tmp_path: Path) -> None:
    data = recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    info = scan(cut)
    assert not info.closed_cleanly
    assert info.damage is not None
    frames = next(s.count for s in info.streams if s.topic == "cam.frame")
    assert 0 < frames < next(s.count for s in scan(recording).streams if s.topic == "cam.frame")
    _, stats = asyncio.run(replay(cut, rate=4.0))
    edge = next(e for e in stats.edges if e.name == "cam.frame->sink.input")
    assert edge.published == frames
    cam = next(n for n in stats.nodes if n.name == "cam")
    assert "damage" in cam.reason
