"""Recording: files the official ``mcap`` reader opens, sessions, the per-stream report, CLI errors.

One short recording of the synthetic scene (module fixture) is read back with the ``mcap``
library's own readers: schemas, counts, timestamps, sequence numbers, pixels, the summary
and its indexes, the metadata and attachments that say how the file was made.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import wait_until
from tiers import uses

import flowrt
from flowrt.cli.record import wait_for_writers
from flowrt.recording import (
    RecordingReport,
    RecordingWriter,
    check_writable,
    new_session,
    nominal_rates,
    report_table,
)
from flowrt.recording.encoding import Decoder
from flowrt.recording.reader import scan

pytestmark = pytest.mark.timeout(90)

REPO = Path(__file__).resolve().parent.parent
SIZE = (160, 120)
SEED = 3


def small_graph(rec_params: dict[str, Any], seconds_fps: int = 20) -> flowrt.GraphBuilder:
    g = flowrt.GraphBuilder("rec-test")
    g.add(
        "cam",
        "capture",
        params={"source": "synthetic:soccer", "fps": seconds_fps, "size": list(SIZE), "seed": SEED},
    )
    g.add(
        "ball",
        "tracker",
        params={"object": "ball"},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "goal",
        "tracker",
        params={"object": "yellow_goal"},
        trigger={"frame": "cam", "period": 2, "phase": 1},
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "rec",
        "recorder",
        params=rec_params,
        inputs={
            t: {"from": t, "policy": "lossless", "size": 16}
            for t in ("cam.frame", "ball.detection", "goal.detection")
        },
    )
    return g


@uses("subprocess")  # the recorder's writer process
async def record(tmp: Path, seconds: float, **params: Any) -> None:
    g = small_graph({"path": str(tmp), "name": "drive", **params})
    async with flowrt.Runtime(g.build()) as rt:
        await rt.run(seconds)
        # a loaded machine makes fewer frames in the time: more of it for the frames asserted
        await wait_until(lambda: rt.stats().node("cam").completions > 10)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import asyncio

    tmp = tmp_path_factory.mktemp("rec")
    asyncio.run(record(tmp, 1.5))
    wait_for_writers()  # a slow (shared) disk may still be finishing the file
    (session,) = sorted(tmp.glob("drive_*"))
    return session


def test_file_reads_back_with_the_official_reader(session: Path) -> None:
    from mcap.reader import make_reader

    report = RecordingReport.model_validate_json((session / "streams.json").read_text())
    written = {s.topic: s.written for s in report.streams}
    assert written["cam.frame"] > 10
    assert all(s.lost == 0 and s.received == s.written for s in report.streams)

    counts: dict[str, int] = {}
    seqs: dict[str, list[int]] = {}
    times: dict[str, list[int]] = {}
    schemas: dict[str, tuple[str, str, str]] = {}
    with open(session / "drive_001.mcap", "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        assert header.profile == "flowrt"
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            t = channel.topic
            counts[t] = counts.get(t, 0) + 1
            seqs.setdefault(t, []).append(message.sequence)
            times.setdefault(t, []).append(message.log_time)
            schemas[t] = (schema.name, schema.encoding, channel.message_encoding)
    assert counts == written
    assert schemas["cam.frame"] == ("foxglove.RawImage", "protobuf", "protobuf")
    assert schemas["ball.detection"][1:] == ("jsonschema", "json")
    assert schemas["ball.detection"][0].endswith("FrameDetection")
    # frames: consecutive sequence numbers from the capture, log times increasing, near now
    frame_seqs = seqs["cam.frame"]
    assert frame_seqs == list(range(frame_seqs[0], frame_seqs[0] + len(frame_seqs)))
    t = times["cam.frame"]
    assert t == sorted(t)
    start = report.start_time
    import datetime as dt

    t0 = dt.datetime.fromisoformat(start).timestamp()
    assert t0 - 1 < t[0] / 1e9 < t[-1] / 1e9 < t0 + 10
    # every detection belongs to a recorded frame (seq and log time = the frame's)
    frame_time = dict(zip(frame_seqs, t, strict=True))
    for s, lt in zip(seqs["ball.detection"], times["ball.detection"], strict=True):
        assert frame_time[s] == lt


def test_pixels_and_detections_decode_to_what_was_recorded(session: Path) -> None:
    """The RawImage pixels are the synthetic scene's own frame, bit for bit."""
    from flowrt.nodes.scene import SoccerScene
    from mcap.reader import make_reader

    scene = SoccerScene(*SIZE, seed=SEED, clutter=0.3, fps=20)  # the capture defaults
    dec = Decoder()
    checked = 0
    with open(session / "drive_001.mcap", "rb") as f:
        for schema, _channel, message in make_reader(f).iter_messages(topics=["cam.frame"]):
            px, fmt = dec.image(schema, message.data)
            assert fmt == "BGR"
            assert px.shape == (SIZE[1], SIZE[0], 3)
            expected, _ = scene.render(message.sequence)
            np.testing.assert_array_equal(px, expected)
            checked += 1
            if checked == 3:
                break
        f.seek(0)
        for schema, _, message in make_reader(f).iter_messages(topics=["ball.detection"]):
            det = dec.message(schema.name, message.data)
            assert type(det).__name__ == "FrameDetection"
            assert det.seq == message.sequence
            break
    assert checked == 3


def test_detections_are_drawn_as_image_annotations_on_their_frames(session: Path) -> None:
    """Each detection is also a foxglove.ImageAnnotations on its camera, at its frame's time."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    dec = Decoder()
    proto = DecoderFactory()
    frames: dict[int, tuple[int, Any]] = {}  # seq -> (log time, RawImage timestamp)
    detections: dict[int, Any] = {}  # log time -> the ball's detection
    notes: dict[int, Any] = {}  # log time -> its annotations
    schemas = {}
    with open(session / "drive_001.mcap", "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == "cam.frame":
                image = proto.decoder_for("protobuf", schema)(message.data)
                frames[message.sequence] = (message.log_time, image.timestamp)
            elif channel.topic == "ball.detection":
                detections[message.log_time] = dec.message(schema.name, message.data)
            elif channel.topic == "cam.frame/annotations/ball.detection":
                schemas[channel.topic] = (schema.name, schema.encoding, channel.metadata)
                notes[message.log_time] = proto.decoder_for("protobuf", schema)(message.data)
    name, encoding, meta = schemas["cam.frame/annotations/ball.detection"]
    assert (name, encoding) == ("foxglove.ImageAnnotations", "protobuf")
    assert meta["annotates"] == "cam.frame"
    assert set(notes) == set(detections)  # one per detection, none more
    found = 0
    for log_time, det in detections.items():
        frame_time, stamp = frames[det.seq]
        assert log_time == frame_time  # at its frame's log time...
        ann = notes[log_time]
        assert (ann.timestamp.seconds, ann.timestamp.nanos) == (stamp.seconds, stamp.nanos)
        if not det.found:  # ...and stamped like the frame, so the image panel pairs them
            assert not ann.circles
            continue
        found += 1
        (circle,) = ann.circles
        assert (circle.position.x, circle.position.y) == pytest.approx(
            (det.centroid[0] + 0.5, det.centroid[1] + 0.5)
        )
        assert circle.diameter == max(det.bbox[2], det.bbox[3])
        x, y, w, h = det.bbox
        (box,) = ann.points
        assert [(p.x, p.y) for p in box.points] == [(x, y), (x + w, y), (x + w, y + h), (x, y + h)]
        assert ann.texts[0].text.startswith("ball")
    assert found > 5


def test_summary_and_indexes_read_with_the_seeking_reader(session: Path) -> None:
    from mcap.reader import SeekingReader

    report = RecordingReport.model_validate_json((session / "streams.json").read_text())
    with open(session / "drive_001.mcap", "rb") as f:
        reader = SeekingReader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        by_topic = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
        assert by_topic == {s.topic: s.written for s in report.streams}
        assert summary.chunk_indexes
        assert all(c.message_index_offsets for c in summary.chunk_indexes)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["flowrt"]["graph"] == "rec-test"
        assert meta["flowrt"]["flowrt_version"] == flowrt.__version__
        assert {"host", "start_time"} <= set(meta["flowrt"])
        attached = {a.name: a.data for a in reader.iter_attachments()}
    timing = json.loads(attached["timing.json"])
    assert {n["name"] for n in timing["nodes"]} == {"cam", "ball", "goal", "rec"}
    assert json.loads(attached["streams.json"])["session"] == "drive_001"


def test_info_matches_the_recording(session: Path) -> None:
    info = scan(session / "drive_001.mcap")
    report = RecordingReport.model_validate_json((session / "streams.json").read_text())
    assert info.closed_cleanly
    assert info.summary_ok
    assert info.damage is None
    got = {s.topic: (s.count, s.schema_name) for s in info.streams}
    assert {t: c for t, (c, _) in got.items()} == {s.topic: s.written for s in report.streams}
    frames = next(s for s in info.streams if s.topic == "cam.frame")
    assert frames.bytes >= frames.count * SIZE[0] * SIZE[1] * 3
    assert frames.source == "cam.frame"
    assert frames.rate_mean is not None
    assert 15 < frames.rate_mean < 25


def test_report_expected_from_the_source_rate(session: Path) -> None:
    report = RecordingReport.model_validate_json((session / "streams.json").read_text())
    s = {x.topic: x for x in report.streams}
    assert s["cam.frame"].nominal_hz == pytest.approx(20.0)
    assert s["goal.detection"].nominal_hz == pytest.approx(10.0)  # period 2 of a 20 fps camera
    for x in report.streams:
        assert x.expected is not None
        assert abs(x.expected - x.received) <= 1


# --- the writer's accounting ------------------------------------------------------------------


def test_writer_refuses_and_counts_when_it_cannot_keep_up(tmp_path: Path) -> None:
    """With no room left, a message is refused and counted against its own stream."""
    w = RecordingWriter(tmp_path / "x.mcap", max_frames=2, max_messages=3)  # not opened: no thread
    frame = flowrt.Frame(np.zeros((4, 4, 3), np.uint8))
    results = [w.submit("cam", frame, float(i), i) for i in range(4)]
    assert results == [True, True, False, False]
    results = [w.submit("det", {"x": i}, float(i), i) for i in range(5)]
    assert results == [True, True, True, False, False]
    assert (w.streams["cam"].lost_behind, w.streams["det"].lost_behind) == (2, 2)
    assert (w.streams["cam"].received, w.streams["det"].received) == (4, 5)


def test_report_table_shows_lost_in_red() -> None:
    report = RecordingReport.model_validate(
        {
            "session": "s",
            "files": [],
            "start_time": "2026-01-01T00:00:00+00:00",
            "duration": 1.0,
            "error": None,
            "streams": [
                {
                    "topic": t,
                    "source": t,
                    "nominal_hz": 20.0,
                    "expected": 20,
                    "received": 20,
                    "written": 20 - lost,
                    "lost": lost,
                    "lost_behind": lost,
                    "lost_error": 0,
                    "missing": 0,
                    "rate_mean": 20.0,
                    "rate_min": 19.0,
                    "rate_max": 21.0,
                    "bytes": 1,
                }
                for t, lost in (("ok", 0), ("bad", 3))
            ],
        }
    )
    from rich.console import Console

    console = Console(record=True, width=150, force_terminal=True, color_system="truecolor")
    console.print(report_table(report))
    html = console.export_html(inline_styles=True)
    red_cells = [line for line in html.splitlines() if "color: #800000" in line]
    assert any(re.search(r">\s*3<", line) for line in red_cells)
    assert not any(re.search(r">\s*0<", line) for line in red_cells)


class _Row:
    """A node's statistics as nominal_rates reads them: the numbers, not the shown period."""

    def __init__(
        self,
        name: str,
        trigger: str,
        frames: int | None = None,
        timer_ms: float | None = None,
        changed: float | None = None,
    ) -> None:
        self.name, self.trigger, self.period_frames, self.timer_ms = name, trigger, frames, timer_ms
        self.timing_changed = changed


@pytest.mark.parametrize(
    ("rows", "expected"),
    [
        ([_Row("cam", "timer", timer_ms=50)], {"cam": 20.0}),
        (
            [_Row("cam", "timer", timer_ms=50), _Row("t", "frame cam", frames=4)],
            {"cam": 20, "t": 5},
        ),
        ([_Row("cam", "loop"), _Row("t", "frame cam", frames=1)], {}),
        ([_Row("s", "input")], {}),
        ([_Row("cam", "timer", timer_ms=1000 / 15)], {"cam": pytest.approx(15, rel=1e-12)}),
    ],
)
def test_nominal_rates(rows: list[_Row], expected: dict[str, float]) -> None:
    class Stats:
        nodes = rows

    assert nominal_rates(Stats()) == pytest.approx(expected)


CAM = _Row("cam", "timer", timer_ms=50)


@pytest.mark.parametrize(
    ("rows", "since", "expected"),
    [
        # a mode switched the tracker between periods during the session: no one rate
        ([CAM, _Row("t", "frame cam", frames=2, changed=5.0)], 1.0, {"cam": 20, "t": None}),
        # ... before it began: the rate it has now is the session's
        ([CAM, _Row("t", "frame cam", frames=2, changed=0.5)], 1.0, {"cam": 20, "t": 10}),
        # the camera's timer changed: its readers have no one rate either
        (
            [_Row("cam", "timer", timer_ms=50, changed=3.0), _Row("t", "frame cam", frames=2)],
            1.0,
            {"cam": None},  # (t: none either, stream_rate's get)
        ),
    ],
)
def test_no_nominal_rate_across_a_timing_change(
    rows: list[_Row], since: float, expected: dict[str, float | None]
) -> None:
    """``expected 36, received 41`` for a tracker a mode switched between periods 1 and 2
    while recording (a new-user pass)."""

    class Stats:
        nodes = rows

    assert nominal_rates(Stats(), since) == expected


# --- sessions ---------------------------------------------------------------------------------


def test_sessions_take_the_next_free_number(tmp_path: Path) -> None:
    assert new_session(tmp_path, "drive").name == "drive_001"
    assert new_session(tmp_path, "drive").name == "drive_002"
    (tmp_path / "drive_007").mkdir()
    (tmp_path / "cal_001").mkdir()
    assert new_session(tmp_path, "drive").name == "drive_008"
    assert new_session(tmp_path, "cal").name == "cal_002"
    with pytest.raises(ValueError, match="session name"):
        new_session(tmp_path, "../x")


def test_check_writable(tmp_path: Path) -> None:
    assert check_writable(tmp_path / "new" / "dir") is None
    blocker = tmp_path / "file"
    blocker.write_text("")
    problem = check_writable(blocker / "sub")
    assert problem is not None
    assert "cannot create" in problem
    assert "not a directory" in (check_writable(blocker) or "")


# --- the CLI ----------------------------------------------------------------------------------


def flowrt_cli(*args: str, timeout: float = 60, **kw: Any) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )


GRAPH = """\
name: cli-rec
nodes:
  cam:
    kind: capture
    params: {source: "synthetic:soccer", fps: 20, size: [160, 120]}
  ball:
    kind: tracker
    params: {object: ball}
    trigger: {frame: cam}
    inputs: {frame: cam.frame}
"""


@pytest.fixture
def graph_file(tmp_path: Path) -> Path:
    p = tmp_path / "g.yaml"
    p.write_text(GRAPH)
    return p


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--topics", "cam.frame,nope.*"], "'nope.*' matches no output"),
        (["--images", "cam.truth=gif"], "raw, jpeg or png"),
        (["--name", "a/b"], "session name"),
    ],
)
def test_record_bad_arguments_exit_2_in_one_line(
    graph_file: Path, tmp_path: Path, extra: list[str], message: str
) -> None:
    out = tmp_path / "out"
    r = flowrt_cli("record", str(graph_file), "-o", str(out), "--duration", "5", *extra)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1
    assert message in lines[0]
    assert "Traceback" not in r.stderr
    assert not any(out.glob("rec_*"))  # nothing ran, no empty session left


def test_record_unwritable_output_is_one_line_before_anything_runs(
    graph_file: Path, tmp_path: Path
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    r = flowrt_cli("record", str(graph_file), "-o", str(blocker / "rec"), "--duration", "30")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0
    assert "cannot create" in r.stderr
    assert "recording" not in r.stdout


def test_record_then_info_and_replay_from_the_cli(graph_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "recs"
    r = flowrt_cli(
        "record",
        str(graph_file),
        "-o",
        str(out),
        "--name",
        "drive",
        "--topics",
        "cam.*",
        "--images",
        "cam.frame=jpeg",
        "--duration",
        "1.5",
        "--no-ui",
        "--stats-json",
        str(tmp_path / "stats.json"),
    )
    assert r.returncode == 0, r.stderr
    assert "cam.frame" in r.stdout
    assert "ball.detection" not in r.stdout
    session = out / "drive_001"
    # the per-stream table is in stats.json too, the same as the session's streams.json
    reports = json.loads((tmp_path / "stats.json").read_text())["reports"]
    (table,) = next(iter(reports.values()))
    assert table == json.loads((session / "streams.json").read_text())
    assert {s["topic"] for s in table["streams"]} == {"cam.frame", "cam.truth"}
    r = flowrt_cli("info", str(session), "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)  # the session as one recording, its one file in "files"
    assert [Path(f["path"]).name for f in info["files"]] == ["drive_001.mcap"]
    assert info["closed_cleanly"] is True
    assert {s["topic"]: s["schema_name"] for s in info["streams"]} == {
        "cam.frame": "foxglove.CompressedImage",
        "cam.truth": "flowrt.nodes.scene.SceneTruth",
    }
    assert "kind: capture" in info["graph"]
    r = flowrt_cli("info", str(session))
    assert r.returncode == 0
    assert "closed cleanly: yes" in r.stdout
    assert "recorded graph" in r.stdout
    r = flowrt_cli("replay", str(session), "--graph", str(graph_file), "--rate", "4", "--no-ui")
    assert r.returncode == 0, r.stderr
    assert "replaying" in r.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["info", "/nonexistent/x"], "no such file"),
        (["replay", "/nonexistent/x"], "no such file"),
        (["info", "{notmcap}"], "not an MCAP file"),
        (["replay", "{notmcap}"], "not an MCAP file"),
        (["info", "{ros1}"], "a ROS 1 bag, not read: convert it with rosbags-convert"),
        (["replay", "{ros1}"], "a ROS 1 bag, not read: convert it with rosbags-convert"),
    ],
)
def test_info_and_replay_bad_input(tmp_path: Path, args: list[str], message: str) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    ros1 = tmp_path / "old.bag"  # what rosbag (ROS 1) writes first
    ros1.write_bytes(b"#ROSBAG V2.0\nE\x00\x00\x00")
    r = flowrt_cli(*[a.replace("{notmcap}", str(bad)).replace("{ros1}", str(ros1)) for a in args])
    assert r.returncode == 2
    assert message in r.stderr
    assert "Traceback" not in r.stderr


# --- flowrt ctl record start|stop -------------------------------------------------------------


@pytest.mark.subprocess  # a worker (or writer) process, from its graph
async def test_ctl_record_starts_and_stops_sessions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from flowrt import cli

    g = flowrt.GraphBuilder("ctl")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20, "size": [80, 60]})
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp_path), "name": "drive", "start": False},
        inputs={"cam.frame": {"from": "cam.frame", "policy": "lossless"}},
    )
    config = flowrt.ControlConfig("127.0.0.1", 0)
    async with flowrt.Runtime(g.build()) as rt, flowrt.ControlServer(rt, config) as server:
        url = ["ctl", "--url", server.url]
        await rt.run(0.3)
        assert not os.listdir(tmp_path)  # start: false records nothing yet
        for _ in range(2):
            assert await asyncio.to_thread(cli.main, [*url, "record", "start"]) == 0
            await rt.run(0.5)
            assert await asyncio.to_thread(cli.main, [*url, "record", "stop"]) == 0
        assert await asyncio.to_thread(cli.main, [*url, "record", "start", "--node", "cam"]) == 1
    await asyncio.to_thread(wait_for_writers)
    out = capsys.readouterr()
    assert "rec: recording into" in out.out
    assert "rec: stopped" in out.out
    assert "not a recorder node" in out.err
    sessions = sorted(os.listdir(tmp_path))
    assert sessions == ["drive_001", "drive_002"]
    for name in sessions:
        info = scan(tmp_path / name / f"{name}.mcap")
        assert info.closed_cleanly
        assert info.messages > 0
        assert (tmp_path / name / "streams.json").exists()


@pytest.mark.parametrize(
    ("shape", "dtype", "fmt", "encoding"),
    [
        ((6, 5, 3), np.uint8, "BGR", "bgr8"),
        ((6, 5, 3), np.uint8, "RGB", "rgb8"),
        ((6, 5), np.uint8, "GRAY", "mono8"),
        ((6, 5), np.uint16, "GRAY", "mono16"),
    ],
)
def test_raw_image_encoding_matches_foxglove_sdk(
    shape: tuple[int, ...], dtype: Any, fmt: str, encoding: str
) -> None:
    """flowrt writes the RawImage head itself (one pixel copy): it decodes as the SDK's own."""
    from foxglove.messages import RawImage, Timestamp
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    from flowrt.recording.encoding import encode_frame

    data = np.arange(np.prod(shape), dtype=dtype).reshape(shape)
    frame = flowrt.Frame(data, source="cam", pixel_format=fmt)
    ours = encode_frame(frame, 1700000000.25)
    theirs = RawImage(
        timestamp=Timestamp(sec=1700000000, nsec=250000000),
        frame_id="cam",
        width=shape[1],
        height=shape[0],
        encoding=encoding,
        step=data.strides[0],
        data=data.tobytes(),
    ).encode()
    s = ours.schema
    decode = DecoderFactory().decoder_for(
        "protobuf", Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    )
    assert decode is not None
    assert decode(ours.data) == decode(theirs)
    px, got_fmt = Decoder().image(
        Schema(id=1, name=s.name, encoding=s.encoding, data=s.data), ours.data
    )
    np.testing.assert_array_equal(px, data)
    assert got_fmt == fmt


@pytest.mark.subprocess  # the recorder's writer process
async def test_a_session_named_again_never_removes_its_recording(tmp_path: Path) -> None:
    """A recorder given the session name of a finished recording (a swap's ``session``)
    cannot start there, and the finished recording stays: it was unlinked as 'half-made'."""
    import flowrt.recording.session as session_module

    def graph() -> Any:
        g = flowrt.GraphBuilder("again")
        g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20, "size": [80, 60]})
        g.add(
            "rec",
            "recorder",
            params={"path": str(tmp_path), "session": str(tmp_path / "day1")},
            inputs={"cam.frame": {"from": "cam.frame", "policy": "lossless"}},
        )
        return g.build()

    async with flowrt.Runtime(graph()) as rt:
        await rt.run(0.5)
    wait_for_writers()
    mcap = tmp_path / "day1" / "day1.mcap"
    size = mcap.stat().st_size
    assert size > 0
    async with flowrt.Runtime(graph()) as rt:
        await rt.run(0.5)
        state = rt.stats().node("rec").state
    assert state in ("error", "failed", "backoff")  # it cannot start there (retrying)
    assert mcap.stat().st_size == size
    assert session_module.SESSION_NAME.match("abc\n") is None  # "$" took a trailing newline
