"""The capture node: every source kind, pixel formats, pacing, end of stream, and bad input.

Runs real runtimes for short times; counts are checked with tolerances, never tight timing.
"""

from __future__ import annotations

import asyncio
import hashlib
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import pytest
from flowrt.nodes.capture import node as capture
from flowrt.nodes.capture import sources as capture_sources
from flowrt.nodes.capture import stderr as capture_stderr
from flowrt.nodes.capture.node import (
    Capture,
    CaptureParams,
    SourceError,
    convert_into,
    encode_raw,
    parse_source,
)
from flowrt.nodes.scene import SoccerScene
from pydantic import BaseModel, ValidationError

import flowrt
from flowrt import Frame, HealthAlert, Input, LoopTrigger, Node, NodeFailed, TimerTrigger

# Real footage on the dev machines (optional: its tests skip without it), and the clip the
# repository ships (graphs/sample.avi, rendered by graphs/make_sample_video.py).
VIDEO = Path("/work/shared/data/sample_720x528.avi")
SAMPLE = Path(__file__).resolve().parents[1] / "graphs" / "sample.avi"


# ---------------------------------------------------------------- helpers


class Recorder(Node):
    """Keeps what it sees of each frame (a copy of small ones, a digest of all)."""

    class Params(BaseModel):
        key: str = "rec"
        keep: int = 0  # copies of the first `keep` frames

    frame = Input(Frame)
    store: dict[str, list[dict[str, Any]]] = {}

    def setup(self) -> None:
        self.rows = Recorder.store.setdefault(self.params.key, [])

    def process(self, frame: Frame) -> None:
        row = {
            "seq": frame.seq,
            "shape": frame.shape,
            "format": frame.pixel_format,
            "source": frame.source,
            "timestamp": frame.timestamp,
            "digest": hashlib.blake2b(frame.data.tobytes(), digest_size=8).hexdigest(),
            "shared": frame.shared,
        }
        if len(self.rows) < self.params.keep:
            row["data"] = frame.data.copy()
        self.rows.append(row)


class Run:
    """A finished short run: what the recorder saw, the events, the statistics."""

    def __init__(
        self, rows: list[dict[str, Any]], events: list[Any], stats: Any, truths: list[Any]
    ):
        self.rows = rows
        self.events = events
        self.stats = stats
        self.truths = truths
        self.verdict: list[tuple[str, str, str]] = []
        self.pools: list[Any] = []  # the frame pools' figures after the run (teardown done)

    def alerts(self, name: str | None = None) -> list[HealthAlert]:
        """The source's own alerts (all but the node-state ones), or those named ``name``."""
        return [
            e
            for e in self.events
            if isinstance(e, HealthAlert)
            and (e.alert == name if name else e.alert not in NODE_STATE_ALERTS)
        ]

    def node_states(self) -> list[str]:
        """The node's error-state changes (ctx.set_error / clear_error), in order."""
        return [
            e.alert
            for e in self.events
            if isinstance(e, HealthAlert) and e.alert in NODE_STATE_ALERTS
        ]

    def problems(self) -> list[str]:
        """Alerts other than a slow read on a loaded machine (reported, then recovered)."""
        return [
            a.alert
            for a in self.alerts()
            if a.alert != "source-recovered"
            and not (a.alert == "grab-timeout" and a.detail.endswith("; waiting"))
        ]

    @property
    def failures(self) -> list[Any]:
        return [e for e in self.events if isinstance(e, NodeFailed)]


NODE_STATE_ALERTS = ("node-error", "node-recovered")


async def run_capture(
    params: dict[str, Any],
    seconds: float,
    *,
    keep: int = 0,
    extra: Callable[[flowrt.GraphBuilder], None] | None = None,
    until: Callable[[Run], bool] | None = None,
    built: Callable[[], None] | None = None,
) -> Run:
    """Run a capture node ``cam`` with a recorder for ``seconds`` (or until ``until``).

    ``built`` runs between validation and the run: e.g. to remove a file that validation
    saw, so that the run-time path of a missing source is what is tested."""
    key = f"rec{id(params)}-{len(Recorder.store)}"
    g = flowrt.GraphBuilder("capture-test")
    g.add("cam", "capture", params=params)
    g.add(
        "rec",
        Recorder,
        params={"key": key, "keep": keep},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )
    if extra:
        extra(g)
    rt = flowrt.Runtime(g.build())
    if built is not None:
        built()
    events: list[Any] = []
    rt.on_event(events.append)
    truths: list[Any] = []
    async with rt:
        sub = rt.subscribe("cam.truth", size=100_000)
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds
        while loop.time() < end:
            await asyncio.sleep(0.02)
            if until and until(Run(Recorder.store.get(key, []), events, rt.stats(), truths)):
                break
        stats = rt.stats()
        truths.extend(sub.drain())
    run = Run(Recorder.store.pop(key, []), events, stats, truths)
    run.verdict = [(n.name, n.state, n.reason) for n in rt.failures()]  # after teardown
    run.pools = rt.stats().frames
    return run


def _assert_quiet_failure(run: Run) -> None:
    """Bad input: health events, but no node failure, no traceback, no frames."""
    assert not run.failures
    assert run.stats.node("cam").errors == 0
    assert run.rows == []


# ---------------------------------------------------------------- params


def test_parse_source() -> None:
    assert parse_source("synthetic:soccer") == ("synthetic", "soccer")
    assert parse_source("synthetic") == ("synthetic", "soccer")
    assert parse_source("camera:0") == ("camera", 0)
    assert parse_source("camera:/dev/video2") == ("camera", "/dev/video2")
    assert parse_source("file:/data/a.avi") == ("file", "/data/a.avi")
    assert parse_source("/data/a.avi") == ("file", "/data/a.avi")
    assert parse_source("rtsp://cam.local/stream") == ("file", "rtsp://cam.local/stream")
    assert parse_source("images:/d/*.png") == ("images", "/d/*.png")
    assert parse_source("/d/frame_??.png") == ("images", "/d/frame_??.png")
    for bad in ("", "camera:", "synthetic:tennis", "webcam:0", "file:"):
        with pytest.raises(ValueError):  # noqa: PT011
            parse_source(bad)


def test_params_defaults_and_validation() -> None:
    p = CaptureParams()
    assert p.source == "synthetic:soccer"
    assert p.fps == 20
    assert p.pixel_format == "BGR"
    assert p.grab_timeout_s == pytest.approx(0.1)  # two frame periods
    assert CaptureParams(grab_timeout="250ms").grab_timeout_s == pytest.approx(0.25)
    assert CaptureParams(fps=10).grab_timeout_s == pytest.approx(0.2)
    bad: list[dict[str, Any]] = [
        {"pixel_format": "YUYV"},  # not an output format
        {"input_format": "RGB565"},
        {"source": "file:/a.avi", "input_format": "I420"},  # decoded video is BGR
        {"input_format": "I420", "size": [321, 240]},  # odd width
        {"size": [16, 16]},  # too small for the scene
        {"fps": 0},
        {"pacing": "slow"},
        {"on_eof": "rewind"},
        {"grab_timeout": "soon"},
        {"bogus": 1},
    ]
    for params in bad:
        with pytest.raises(ValidationError):
            CaptureParams.model_validate(params)


@pytest.mark.parametrize("field", ["grab_timeout", "open_timeout", "backoff", "flash_on"])
def test_durations_follow_the_graphs_rule(field: str) -> None:
    """A capture duration is read by the graph's own rule (flowrt.parse_duration_ms): the
    same strings mean the same milliseconds, and the same mistakes get the same message."""
    for good in ("250ms", "1.5s", "500us", " 2 s ", 40, 2.5, "1e3"):
        p = CaptureParams.model_validate({field: good, "max_backoff": "3600s"})
        assert getattr(p, field) == pytest.approx(flowrt.parse_duration_ms(good)), good
    for bad in ("soon", "10 parsecs", "1e999", "nan", True, [5], {"ms": 5}):
        with pytest.raises(ValueError) as graph:  # noqa: PT011
            flowrt.parse_duration_ms(bad)
        with pytest.raises(ValidationError) as info:
            CaptureParams.model_validate({field: bad})
        [error] = info.value.errors()
        assert error["loc"] == (field,)
        assert error["msg"] == f"Value error, {graph.value}", bad
    # The range is a capture timeout's: positive, at most an hour.
    for out_of_range in (0, "0ms", "2h", 3_600_001):
        with pytest.raises(ValidationError):
            CaptureParams.model_validate({field: out_of_range, "max_backoff": "3600s"})


def test_default_trigger() -> None:
    assert Capture.default_trigger(CaptureParams()) == TimerTrigger(timer=50)
    assert Capture.default_trigger(CaptureParams(fps=25)) == TimerTrigger(timer=40)
    assert isinstance(Capture.default_trigger(CaptureParams(pacing="fast")), LoopTrigger)
    # A camera paces itself.
    assert isinstance(Capture.default_trigger(CaptureParams(source="camera:0")), LoopTrigger)


def test_unsupported_pixel_format_is_a_located_load_error(tmp_path: Path) -> None:
    (tmp_path / "clip.avi").write_bytes(b"")  # exists: only its pixel format is wrong
    text = """\
nodes:
  cam:
    kind: capture
    params:
      pixel_format: YUV9
  cam2:
    kind: capture
    params: {source: "clip.avi", input_format: NV12}
"""
    with pytest.raises(flowrt.GraphError) as info:
        flowrt.Graph.from_text(text, "bad.yaml", base_dir=tmp_path)
    msg = str(info.value)
    assert (
        "bad.yaml:5:7: error: nodes.cam.params.pixel_format: Input should be 'BGR', 'RGB' or 'GRAY'"
        in msg
    )
    assert "nodes.cam2.params.input_format: NV12 needs a raw source" in msg


# ---------------------------------------------------------------- pixel formats


def _blocks() -> np.ndarray:
    """A 16x16 BGR image of solid 4x4 blocks (chroma subsampling loses nothing on it)."""
    colours = [
        (0, 0, 255), (0, 255, 0), (255, 0, 0), (255, 255, 255),
        (0, 0, 0), (128, 128, 128), (0, 200, 255), (200, 90, 20),
    ]  # fmt: skip
    img = np.zeros((16, 16, 3), np.uint8)
    for i in range(16):
        img[(i // 4) * 4 : (i // 4) * 4 + 4, (i % 4) * 4 : (i % 4) * 4 + 4] = colours[
            i % len(colours)
        ]
    return img


@pytest.mark.parametrize("fmt", ["BGR", "RGB", "GRAY", "YUYV", "UYVY", "I420", "NV12"])
def test_raw_formats_decode_to_bgr_and_gray(fmt: str) -> None:
    img = _blocks()
    raw = encode_raw(img, fmt)
    grey_ref = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(int)
    out = convert_into(raw, fmt, "BGR", np.empty((16, 16, 3), np.uint8))
    if fmt == "GRAY":
        assert np.array_equal(out, cv2.cvtColor(grey_ref.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    else:
        assert np.abs(out.astype(int) - img).max() <= 3, fmt  # YUV is video range, rounding only
    grey = convert_into(raw, fmt, "GRAY", np.empty((16, 16), np.uint8))
    assert np.abs(grey.astype(int) - grey_ref).max() <= 3, fmt
    rgb = convert_into(raw, fmt, "RGB", np.empty((16, 16, 3), np.uint8))
    assert np.array_equal(rgb, out[..., ::-1])


def test_known_raw_values() -> None:
    # YUYV: Y0 U Y1 V; white is Y=235, black Y=16, no chroma U=V=128 (BT.601 video range).
    yuyv = np.array([[[235, 128], [16, 128]]], np.uint8)  # one row, two pixels
    out = convert_into(yuyv, "YUYV", "BGR", np.empty((1, 2, 3), np.uint8))
    assert out[0, 0].tolist() == [255, 255, 255]
    assert out[0, 1].tolist() == [0, 0, 0]
    # I420 2x2: four Y, then one U and one V; pure grey.
    i420 = np.array([[126, 126], [126, 126], [128, 128]], np.uint8)
    out = convert_into(i420, "I420", "BGR", np.empty((2, 2, 3), np.uint8))
    assert np.abs(out.astype(int) - 128).max() <= 1
    # RGB -> BGR is an exact swap; GRAY -> BGR replicates.
    rgb = np.array([[[10, 20, 30]]], np.uint8)
    assert convert_into(rgb, "RGB", "BGR", np.empty((1, 1, 3), np.uint8)).tolist() == [
        [[30, 20, 10]]
    ]
    grey = np.array([[7]], np.uint8)
    assert convert_into(grey, "GRAY", "BGR", np.empty((1, 1, 3), np.uint8)).tolist() == [
        [[7, 7, 7]]
    ]


def test_convert_resizes_once_and_rejects_wrong_buffers() -> None:
    img = np.zeros((40, 60, 3), np.uint8)
    img[:, 30:] = (0, 0, 255)
    out = convert_into(img, "BGR", "BGR", np.empty((20, 30, 3), np.uint8))
    assert out[:, :14].max() == 0
    assert (out[:, 16:, 2] == 255).all()
    # A flat device buffer needs the device's size, and must fit it.
    flat = encode_raw(_blocks(), "YUYV").reshape(1, -1)
    out = convert_into(flat, "YUYV", "BGR", np.empty((16, 16, 3), np.uint8), dims=(16, 16))
    assert np.abs(out.astype(int) - _blocks()).max() <= 3
    with pytest.raises(SourceError, match="does not fit YUYV"):
        convert_into(flat, "YUYV", "BGR", np.empty((16, 16, 3), np.uint8), dims=(16, 12))
    with pytest.raises(SourceError, match="needs the device's width and height"):
        convert_into(flat, "YUYV", "BGR", np.empty((16, 16, 3), np.uint8))


# ---------------------------------------------------------------- synthetic source


async def test_synthetic_frames_truth_and_determinism() -> None:
    params = {"pacing": "fast", "seed": 3, "clutter": 0.3}
    run = await run_capture(params, 5.0, keep=3, until=lambda r: len(r.rows) >= 40)
    rows = run.rows
    assert len(rows) >= 40
    assert [r["seq"] for r in rows] == list(range(len(rows)))
    assert {r["shape"] for r in rows} == {(240, 320, 3)}
    assert {r["format"] for r in rows} == {"BGR"}
    assert {r["source"] for r in rows} == {"cam"}
    assert all(b["timestamp"] > a["timestamp"] for a, b in itertools.pairwise(rows))
    # The frames are the scene's, pixel for pixel; the truth of each frame is published.
    scene = SoccerScene(320, 240, seed=3, clutter=0.3, fps=20)
    for r in rows[:3]:
        assert np.array_equal(r["data"], scene.render(r["seq"])[0])
    truth = {t.index: t for t in run.truths}
    assert set(range(len(rows))) <= set(truth)
    assert truth[5]["ball"] == scene.render(5)[1]["ball"]
    # Same seed, same frames; another seed, another game.
    again = await run_capture(params, 5.0, until=lambda r: len(r.rows) >= 10)
    assert [r["digest"] for r in again.rows[:10]] == [r["digest"] for r in rows[:10]]
    other = await run_capture({**params, "seed": 4}, 5.0, until=lambda r: len(r.rows) >= 10)
    assert [r["digest"] for r in other.rows[:10]] != [r["digest"] for r in rows[:10]]


async def test_synthetic_size_and_pixel_formats() -> None:
    # A simulated raw YUYV camera, published as GRAY at 160x120.
    params = {"pacing": "fast", "size": [160, 120], "input_format": "YUYV", "pixel_format": "GRAY"}
    run = await run_capture(params, 5.0, keep=2, until=lambda r: len(r.rows) >= 5)
    assert {r["shape"] for r in run.rows} == {(120, 160)}
    assert {r["format"] for r in run.rows} == {"GRAY"}
    scene = SoccerScene(160, 120, seed=0, clutter=0.3)
    ref = cv2.cvtColor(scene.render(0)[0], cv2.COLOR_BGR2GRAY).astype(int)
    assert np.abs(run.rows[0]["data"].astype(int) - ref).mean() < 2.0
    # RGB output: the BGR frame with its channels swapped.
    run = await run_capture(
        {"pacing": "fast", "pixel_format": "RGB"}, 5.0, keep=1, until=lambda r: len(r.rows) >= 1
    )
    assert np.array_equal(
        run.rows[0]["data"], SoccerScene(seed=0, clutter=0.3).render(0)[0][..., ::-1]
    )


@pytest.mark.slow  # real-time pacing: a second of frames at their rate (~1 s of CPU)
async def test_pacing_realtime_vs_fast() -> None:
    realtime = await run_capture({"fps": 20}, 1.0)
    assert 14 <= len(realtime.rows) <= 23  # 20 expected; generous for a loaded machine
    fast = await run_capture({"fps": 20, "pacing": "fast"}, 0.5)
    # renders take ~1 ms: hundreds expected on a quiet machine; at least 3x the paced rate
    # on a loaded one
    assert len(fast.rows) / 0.5 >= 3 * len(realtime.rows) / 1.0, len(fast.rows)


# ---------------------------------------------------------------- files and image sequences


def _write_video(path: Path, n: int, size: tuple[int, int] = (64, 48)) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 20, size)
    assert w.isOpened()
    for i in range(n):
        w.write(np.full((size[1], size[0], 3), (20 * i) % 256, np.uint8))
    w.release()


def _lamp_tracker(g: flowrt.GraphBuilder) -> None:
    """A tracker of the lamp (the "candle" class) on every frame of ``cam``."""
    g.add(
        "lamp",
        "tracker",
        params={"object": "candle"},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )


@pytest.mark.slow  # a real video decoded and tracked: ~0.9 s of CPU alone (1 s fast-tier limit)
@pytest.mark.skipif(not VIDEO.exists(), reason=f"{VIDEO} not available")
async def test_real_video_frames_and_tracker() -> None:
    """The sample video through a file source, tracked (its glowing table lamp) inline."""

    got: list[Any] = []

    def done(r: Run) -> bool:
        return bool(r.alerts("end-of-stream"))

    run = await _run_with_detections(f"file:{VIDEO}", _lamp_tracker, got, done)
    assert len(run.rows) == 270
    assert {r["shape"] for r in run.rows} == {(528, 720, 3)}
    assert [r["seq"] for r in run.rows] == list(range(270))
    assert len(run.alerts("end-of-stream")) == 1
    assert not run.alerts("source-error")
    # The lamp is in view in frames 1..199 (see tests/test_colour.py): found in most of them.
    by_seq = {d.seq: d for d in got}
    with_lamp = [by_seq[i] for i in range(1, 200) if i in by_seq]
    assert len(with_lamp) >= 190
    assert sum(d.found for d in with_lamp) >= 0.8 * len(with_lamp)
    assert all(d.source == "cam" for d in got)


async def test_a_file_is_decoded_straight_into_the_frames_slots(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Offline, a video published as decoded (same format, same size) is decoded by the reader
    thread into slots lent to it: the loop copies only the frames read before the first lend,
    every frame arrives intact and in order, and no slot is still held after the run."""
    clip = tmp_path / "clip.avi"
    _write_video(clip, 30)
    cap = cv2.VideoCapture(str(clip))
    decoded = [hashlib.blake2b(img.tobytes(), digest_size=8).hexdigest() for img in _frames(cap)]
    copies: list[int] = []
    real = capture.convert_into

    def counted(*args: Any, **kwargs: Any) -> Any:
        copies.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(capture, "convert_into", counted)
    run = await run_capture(
        {"source": str(clip), "pacing": "fast"},
        10.0,
        until=lambda r: bool(r.alerts("end-of-stream")),
    )
    assert [r["seq"] for r in run.rows] == list(range(30))
    assert [r["digest"] for r in run.rows] == decoded
    assert all(r["shared"] for r in run.rows)
    assert 1 <= len(copies) <= capture.LEND  # the read-ahead before the first lend
    (pool,) = [p for p in run.pools if p.owner == "cam"]
    assert (pool.slots_in_use, pool.dropped) == (0, 0)


async def test_frames_decoded_in_place_and_discarded_at_a_firm_deadline_are_freed_once(
    tmp_path: Path,
) -> None:
    """A capture whose results are discarded (a firm deadline it always misses) gives every
    slot back exactly once: neither leaked (held by the node for good) nor released twice
    (which would fail the node)."""
    clip = tmp_path / "clip.avi"
    _write_video(clip, 12)
    g = flowrt.GraphBuilder("firm-capture")
    g.add(
        "cam",
        "capture",
        params={"source": str(clip), "pacing": "fast", "on_eof": "exit"},
        deadline="0.01ms",
        miss_policy="discard",
    )
    events: list[Any] = []
    rt = flowrt.Runtime(g.build())
    rt.on_event(events.append)
    async with rt:
        await rt.run(10.0)
    cam = rt.stats().node("cam")
    assert cam.discarded >= 10  # the path under test was taken
    assert cam.errors == 0
    assert not [e for e in events if isinstance(e, NodeFailed)]
    (pool,) = [p for p in rt.stats().frames if p.owner == "cam"]
    assert pool.slots_in_use == 0


def _frames(cap: Any) -> list[np.ndarray]:
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            cap.release()
            return out
        out.append(img)


async def test_the_repository_clip_through_a_file_source_and_tracker() -> None:
    """graphs/sample.avi (what graphs/video.yaml plays): every frame read, the lamp found."""

    got: list[Any] = []
    run = await _run_with_detections(
        f"file:{SAMPLE}", _lamp_tracker, got, lambda r: bool(r.alerts("end-of-stream"))
    )
    assert len(run.rows) == 200
    assert {r["shape"] for r in run.rows} == {(240, 320, 3)}
    assert [r["seq"] for r in run.rows] == list(range(200))
    assert len(got) >= 190
    assert sum(d.found for d in got) >= 0.95 * len(got)


async def _run_with_detections(
    source: str,
    extra: Callable[[flowrt.GraphBuilder], None],
    got: list[Any],
    until: Callable[[Run], bool],
) -> Run:
    key = f"video-{len(Recorder.store)}"
    g = flowrt.GraphBuilder("video")
    g.add("cam", "capture", params={"source": source, "pacing": "fast"})
    g.add(
        "rec",
        Recorder,
        params={"key": key},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )
    extra(g)
    events: list[Any] = []
    rt = flowrt.Runtime(g.build())
    rt.on_event(events.append)
    async with rt:
        sub = rt.subscribe("lamp.detection", size=100_000)
        for _ in range(500):
            await asyncio.sleep(0.02)
            if until(Run([], events, None, [])):
                break
        await asyncio.sleep(0.05)
        stats = rt.stats()
        got.extend(sub.drain())
    return Run(Recorder.store.pop(key, []), events, stats, [])


async def test_file_on_eof_stop_and_loop(tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    _write_video(clip, 10)
    stop = await run_capture(
        {"source": str(clip), "pacing": "fast"},
        5.0,
        until=lambda r: bool(r.alerts("end-of-stream")),
    )
    assert len(stop.rows) == 10
    assert len(stop.alerts("end-of-stream")) == 1
    assert stop.alerts("end-of-stream")[0].severity == "info"
    assert {r["shape"] for r in stop.rows} == {(48, 64, 3)}
    loop = await run_capture(
        {"source": f"file:{clip}", "pacing": "fast", "on_eof": "loop", "size": [32, 24]},
        5.0,
        until=lambda r: len(r.rows) >= 35,
    )
    assert len(loop.rows) >= 35
    assert not loop.problems()
    assert [r["seq"] for r in loop.rows] == list(range(len(loop.rows)))
    assert {r["shape"] for r in loop.rows} == {(24, 32, 3)}
    # The content repeats with the clip's period.
    digests = [r["digest"] for r in loop.rows]
    assert digests[:10] == digests[10:20] == digests[20:30]


async def test_file_realtime_pacing(tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    _write_video(clip, 100)
    run = await run_capture({"source": str(clip), "fps": 25}, 0.8)
    assert 12 <= len(run.rows) <= 22
    assert not run.problems()


async def test_image_sequence(tmp_path: Path) -> None:
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (9, 9, 9)]
    for i, c in enumerate(colours):
        cv2.imwrite(str(tmp_path / f"img_{i:02d}.png"), np.full((30, 40, 3), c, np.uint8))
    (tmp_path / "img_01b.png").write_bytes(b"not a png at all")  # sorted between 01 and 02
    run = await run_capture(
        {"source": f"images:{tmp_path}/img_*.png", "pacing": "fast", "size": [20, 15]},
        5.0,
        keep=10,
        until=lambda r: bool(r.alerts("end-of-stream")),
    )
    assert len(run.rows) == 4
    assert [tuple(int(v) for v in r["data"][7, 10]) for r in run.rows] == colours
    assert {r["shape"] for r in run.rows} == {(15, 20, 3)}
    bad = run.alerts("source-error")
    assert len(bad) == 1
    assert "img_01b.png" in bad[0].detail
    assert not run.failures
    # As grey, from a bare glob, looping.
    grey = await run_capture(
        {
            "source": f"{tmp_path}/img_0?.png",
            "pacing": "fast",
            "input_format": "GRAY",
            "pixel_format": "GRAY",
            "on_eof": "loop",
        },
        5.0,
        until=lambda r: len(r.rows) >= 9,
    )
    assert len(grey.rows) >= 9
    assert {r["shape"] for r in grey.rows} == {(30, 40)}


# ---------------------------------------------------------------- bad sources


@pytest.mark.parametrize(
    ("source", "detail"),
    [
        ("file:{tmp}/missing.avi", "video file not found"),
        ("{tmp}/garbage.avi", "cannot open"),
        ("{tmp}", "is a directory"),
        ("camera:99", "cannot open camera 99"),
        ("camera:/dev/video-none", "does not exist"),
        ("images:{tmp}/*.jpg", "no image files match"),
    ],
)
async def test_bad_sources_raise_health_events(tmp_path: Path, source: str, detail: str) -> None:
    (tmp_path / "garbage.avi").write_bytes(
        np.random.default_rng(0).integers(0, 256, 100_000, np.uint8).tobytes()
    )

    def counter(g: flowrt.GraphBuilder) -> None:
        g.add("tick", "counter", trigger={"timer": "20ms"})

    src = source.format(tmp=tmp_path)
    vanish: Callable[[], None] | None = None
    # Validation refuses a missing file or a directory; at run time it happens when the file
    # goes away after validation (an unmounted disk): created for validation, then removed.
    target = tmp_path / "missing.avi"
    if detail == "video file not found":
        target.write_bytes(b"")
        vanish = target.unlink
    elif detail == "is a directory":
        src = str(target)
        target.write_bytes(b"")

        def vanish() -> None:
            target.unlink()
            target.mkdir()
    elif detail == "no image files match":  # validation refuses a glob matching nothing
        (tmp_path / "gone.jpg").write_bytes(b"")
        vanish = (tmp_path / "gone.jpg").unlink

    def seen(r: Run) -> bool:  # what is asserted below: a loaded machine may need over 0.6 s
        return len(r.alerts("source-error")) >= 3 and r.stats.node("tick").completions >= 15

    run = await run_capture(
        {"source": src, "backoff": "50ms", "max_backoff": "100ms"},
        10.0,
        extra=counter,
        until=seen,
        built=vanish,
    )
    _assert_quiet_failure(run)
    errors = run.alerts("source-error")
    assert len(errors) >= 3  # reopened with backoff, again and again
    assert all(detail in e.detail and e.node == "cam" and e.severity == "error" for e in errors)
    assert "reopening in 50 ms (attempt 2)" in errors[0].detail
    assert "reopening in 100 ms (attempt 3)" in errors[1].detail
    assert run.stats.node("tick").completions >= 15  # the runtime kept running
    # The node is in an error state with the reason (red in the table), once, and the run's
    # verdict is a failure: it never delivered a frame.
    cam = run.stats.node("cam")
    assert cam.state == "error"
    assert detail in cam.reason
    # once when it failed (the same reason each time after), once at the end with the verdict
    assert run.node_states() == ["node-error", "node-error"]
    [(name, state, reason)] = run.verdict
    assert (name, state) == ("cam", "error")
    assert "never delivered a frame" in reason
    assert f"attempts failed; last error: {errors[0].detail.split(';')[0]}" in reason


def _truncated_sample(tmp_path: Path) -> Path | None:
    data = SAMPLE.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 5])
    return cut


async def test_corrupt_and_truncated_videos(tmp_path: Path) -> None:
    # The sample cut short: the frames up to the cut, then end of stream.
    cut = _truncated_sample(tmp_path)
    if cut is not None:
        run = await run_capture(
            {"source": str(cut), "pacing": "fast"},
            5.0,
            until=lambda r: bool(r.alerts("end-of-stream")),
        )
        assert 10 <= len(run.rows) < 270
        assert not run.failures
        assert run.problems() == ["end-of-stream"]
    # A video whose index is cut off (OpenCV's own AVI reader refuses it): a clear error.
    clip = tmp_path / "clip.avi"
    _write_video(clip, 30, (160, 120))
    data = clip.read_bytes()
    cut = tmp_path / "cut_mjpg.avi"
    cut.write_bytes(data[: len(data) // 3])
    run = await run_capture({"source": str(cut), "backoff": "50ms"}, 0.3)
    _assert_quiet_failure(run)
    assert "cannot open" in run.alerts("source-error")[0].detail
    # An empty file: a clear error, then retries.
    empty = tmp_path / "empty.avi"
    empty.write_bytes(b"")
    run = await run_capture({"source": str(empty), "backoff": "50ms"}, 0.3)
    _assert_quiet_failure(run)
    assert run.alerts("source-error")


async def test_max_retries_gives_up(tmp_path: Path) -> None:
    nope = tmp_path / "nope.avi"
    nope.write_bytes(b"")
    params = {"source": str(nope), "backoff": "20ms", "max_retries": 2, "pacing": "fast"}
    run = await run_capture(params, 0.5, built=nope.unlink)
    assert [a.alert for a in run.alerts()] == ["source-error"] * 3 + ["source-gave-up"]
    assert run.rows == []
    # retries exhausted: failed for good, said once (no traceback), not restarted
    cam = run.stats.node("cam")
    assert (cam.state, cam.errors, cam.restarts) == ("failed", 1, 0)
    assert "3 consecutive failures, max_retries 2 exhausted; last error: video file" in cam.reason
    assert [f.error.split(":")[0] for f in run.failures] == ["FatalError"]


async def test_slow_file_is_reported_then_resumed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file read that hangs: reported at the grab timeout, reopened after open_timeout at
    the frame it stalled on (not from the start)."""
    clip = tmp_path / "clip.avi"
    _write_video(clip, 10)
    release = threading.Event()
    opened: list[Any] = []
    original_init = capture_sources.VideoDevice.__init__
    original_read = capture_sources.VideoDevice.read

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        opened.append(self)

    def read(self: Any, into: Any = None) -> Any:
        if self is opened[0] and self.frames == 3:
            release.wait(10)  # the first device hangs after three frames
        return original_read(self, into)

    monkeypatch.setattr(capture_sources.VideoDevice, "__init__", init)
    monkeypatch.setattr(capture_sources.VideoDevice, "read", read)
    try:
        run = await run_capture(
            {"source": str(clip), "fps": 50, "open_timeout": "300ms", "backoff": "30ms"},
            5.0,
            keep=10,
            until=lambda r: bool(r.alerts("end-of-stream")) and not release.set(),
        )
    finally:
        release.set()  # the abandoned reader returns and ends: nothing left behind
    assert not run.failures
    kinds = [a.alert for a in run.alerts()]
    assert kinds[:3] == ["grab-timeout", "grab-timeout", "source-recovered"]
    assert kinds[-1] == "end-of-stream"
    slow, reopened = run.alerts("grab-timeout")[:2]
    assert slow.detail.endswith("within 40 ms; waiting")  # two periods at 50 fps
    assert slow.severity == "warning"
    assert "resuming at frame 3; reopening in 30 ms" in reopened.detail
    assert len(opened) >= 2
    # Every frame of the clip exactly once, in order: the reopened file resumed at frame 3.
    assert [r["seq"] for r in run.rows] == list(range(10))
    levels = [int(r["data"].mean()) for r in run.rows]
    assert all(abs(v - 20 * i) <= 3 for i, v in enumerate(levels)), levels


class FakeCamera:
    """Stands in for cv2.VideoCapture on camera 0: 64x48 frames at ~100 fps, raw YUYV when
    asked (as V4L2 delivers it: a flat buffer), and a first instance that hangs."""

    instances: ClassVar[list[FakeCamera]] = []
    hang = threading.Event()

    def __init__(self, target: Any, *args: Any) -> None:
        self.target = target
        self.props: dict[int, float] = {}
        self.n = 0
        FakeCamera.instances.append(self)

    def isOpened(self) -> bool:
        return self.target == 0

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_FRAME_WIDTH: 64, cv2.CAP_PROP_FRAME_HEIGHT: 48}.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray]:
        time.sleep(0.01)
        if self is FakeCamera.instances[0] and self.n == 5:
            FakeCamera.hang.wait(10)
        self.n += 1
        img = cv2.resize(_blocks(), (64, 48), interpolation=cv2.INTER_NEAREST)
        if self.props.get(cv2.CAP_PROP_CONVERT_RGB) == 0:
            return True, encode_raw(img, "YUYV").reshape(1, -1)
        return True, img

    def release(self) -> None:
        pass


async def test_stalled_camera_is_reopened(monkeypatch: pytest.MonkeyPatch) -> None:
    FakeCamera.instances.clear()
    FakeCamera.hang.clear()
    monkeypatch.setattr(capture_sources.cv2, "VideoCapture", FakeCamera)
    try:
        run = await run_capture(
            {
                "source": "camera:0",
                "input_format": "YUYV",
                "grab_timeout": "50ms",
                "backoff": "30ms",
            },
            5.0,
            keep=1,
            until=lambda r: len(r.rows) >= 10,
        )
    finally:
        FakeCamera.hang.set()
    # The first camera hung for good: teardown left its thread behind, bounded, and said so.
    assert not run.failures
    assert [a.alert for a in run.alerts()][:2] == ["grab-timeout", "source-recovered"]
    assert run.node_states()[:2] == ["node-error", "node-recovered"]  # red, then no more
    assert run.stats.node("cam").state != "error"
    assert run.verdict == []
    timeout = run.alerts("grab-timeout")[0]
    assert timeout.detail == "no frame from camera:0 within 50 ms; reopening in 30 ms (attempt 2)"
    assert len(FakeCamera.instances) >= 2
    cam = FakeCamera.instances[0]
    assert cam.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc(*"YUYV")
    assert cam.props[cv2.CAP_PROP_CONVERT_RGB] == 0
    # The flat raw buffer was decoded with the device's size, once, to BGR.
    assert {r["shape"] for r in run.rows} == {(48, 64, 3)}
    ref = cv2.resize(_blocks(), (64, 48), interpolation=cv2.INTER_NEAREST)
    assert np.abs(run.rows[0]["data"].astype(int) - ref).max() <= 3
    assert [r["seq"] for r in run.rows] == list(range(len(run.rows)))
    # A missing camera index through the same path: a clear error, retried.
    monkeypatch.setattr(capture_sources.cv2, "VideoCapture", FakeCamera)
    missing = await run_capture({"source": "camera:3", "backoff": "50ms"}, 0.3)
    _assert_quiet_failure(missing)
    assert missing.alerts("source-error")[0].detail.startswith("cannot open camera 3")


@pytest.mark.parametrize(
    ("source", "said"),
    [("camera:99", "camera by index"), ("{tmp}/garbage.mp4", "moov atom not found")],
)
async def test_opencv_messages_go_to_the_node_log(
    tmp_path: Path,
    source: str,
    said: str,
    capfd: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """What OpenCV, V4L2 and FFmpeg print on fd 2 while a device opens: in the node's log
    (each kind of line once at INFO), never raw on the terminal."""
    (tmp_path / "garbage.mp4").write_bytes(b"\0" * 4000)
    caplog.set_level(logging.DEBUG, logger="flowrt")
    run = await run_capture({"source": source.format(tmp=tmp_path), "backoff": "30ms"}, 0.4)
    assert len(run.alerts("source-error")) >= 2
    _, err = capfd.readouterr()
    assert said not in err
    logged = [r for r in caplog.records if r.name == "flowrt.node.cam" and said in r.getMessage()]
    assert logged, [r.getMessage() for r in caplog.records]
    assert logged[0].getMessage().startswith("cam: opencv: ")
    assert [r.levelno for r in logged][:2] == [logging.INFO, logging.DEBUG]  # then quieter


def test_a_hung_open_gives_stderr_back(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """A driver stuck in its open must not keep the process's stderr (nor the other sources'
    opens) for good: fd 2 comes back after the bound, and the stuck open's lines are still
    collected when it returns."""
    monkeypatch.setattr(capture_stderr, "REDIRECT_MAX", 0.2)
    release, inside = threading.Event(), threading.Event()
    lines: list[str] = []

    def stuck_open() -> None:
        with capture_stderr.native_stderr(lines):
            os.write(2, b"said while opening\n")
            inside.set()
            release.wait(10)

    t = threading.Thread(target=stuck_open)
    t.start()
    try:
        assert inside.wait(10)
        # the lock is free again once fd 2 was given back (a bound, not a timing threshold)
        assert capture_stderr.STDERR_LOCK.acquire(timeout=10)
        capture_stderr.STDERR_LOCK.release()
        os.write(2, b"said after the bound\n")
    finally:
        release.set()
        t.join(10)
    err = capfd.readouterr().err
    assert "said after the bound" in err
    assert "said while opening" not in err
    assert lines == ["said while opening"]
