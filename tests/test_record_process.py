"""The recorder's writer in a process of its own: off the runtime's GIL, every guarantee kept.

The writer process maps each frame's shared-memory slot; the runtime's process only counts
and sends descriptors. What is checked: no writer thread in the runtime's process, the same
file as the thread writer, every frame's link given back, a stalled writer process losing
frames counted (never silently), and a writer process killed with ``kill -9`` seen at once,
its losses counted against what the file really holds, the graph going on.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
from conftest import wait_until

import flowrt
from flowrt.cli.record import wait_for_writers
from flowrt.frames import FrameStore
from flowrt.recording import ProcessRecordingWriter, RecordingReport
from flowrt.recording.reader import scan
from flowrt.recording.writer import THREAD_PREFIX

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parent.parent


def small_graph(tmp: Path, **rec: Any) -> flowrt.Graph:
    g = flowrt.GraphBuilder("rec-proc")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20, "size": [160, 120]})
    g.add(
        "ball",
        "tracker",
        params={"object": "ball"},
        trigger={"frame": "cam"},
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp), "name": "drive", **rec},
        inputs={
            t: {"from": t, "policy": "lossless", "size": 16}
            for t in ("cam.frame", "ball.detection")
        },
    )
    return g.build()


def writer_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX)]


def the_writer_process(mcap: Path) -> psutil.Process | None:
    """The descendant of this process that has ``mcap`` open (the writer process)."""
    for p in psutil.Process().children(recursive=True):
        try:
            if any(Path(f.path) == mcap for f in p.open_files()):
                return p
        except psutil.Error:
            continue
    return None


async def writer_of(mcap: Path) -> psutil.Process | None:
    """The writer process once it has ``mcap`` open, waited for (bounded): a loaded machine
    starts it later, and an idle-priority one gets its first turn later still."""
    found: list[psutil.Process | None] = [None]

    def opened() -> bool:
        found[0] = the_writer_process(mcap)
        return found[0] is not None

    await wait_until(opened, step=0.2)
    return found[0]


def session_of(tmp: Path) -> tuple[Path, RecordingReport]:
    (session,) = sorted(tmp.glob("drive_*"))
    report = RecordingReport.model_validate_json((session / "streams.json").read_text())
    return session, report


@pytest.mark.subprocess  # a worker (or writer) process, from its graph
async def test_the_runtime_process_holds_no_writer_thread_and_the_file_is_whole(
    tmp_path: Path,
) -> None:
    async with flowrt.Runtime(small_graph(tmp_path)) as rt:
        await rt.run(0.8)
        threads = writer_threads()
        mcap = tmp_path / "drive_001" / "drive_001.mcap"
        writer = await writer_of(mcap)
        await rt.run(0.7)
        # a loaded machine may make fewer frames in 1.5 s: more time, the same bar below
        await wait_until(lambda: rt.stats().node("cam").completions >= 20)
        stats = rt.stats()
    await asyncio.to_thread(wait_for_writers)
    assert threads == []  # nothing of the writing runs beside the event loop
    assert writer is not None
    assert writer.pid != os.getpid()
    session, report = session_of(tmp_path)
    info = scan(session / "drive_001.mcap")
    assert info.closed_cleanly
    counts = {s.topic: s.count for s in info.streams}
    assert report.error is None
    for s in report.streams:
        assert s.lost == 0
        assert s.received == s.written == counts[s.topic]
    assert counts["cam.frame"] >= 20
    cam = next(p for p in stats.frames if p.owner.startswith("cam"))
    assert cam.dropped == 0  # the recorder's links never starved the camera's pool


async def test_the_thread_writer_is_still_there_and_writes_the_same_streams(
    tmp_path: Path,
) -> None:
    async with flowrt.Runtime(small_graph(tmp_path, writer="thread")) as rt:
        await rt.run(0.8)
        threads = writer_threads()
        await rt.run(0.4)
    await asyncio.to_thread(wait_for_writers)
    assert threads  # the fallback: threads of the runtime's process
    session, report = session_of(tmp_path)
    counts = {s.topic: s.count for s in scan(session / "drive_001.mcap").streams}
    assert {s.topic: s.written for s in report.streams} == counts
    assert all(s.lost == 0 for s in report.streams)


def _frames(store: FrameStore, n: int) -> list[flowrt.Frame]:
    pool = store.pool("cam", max_slots=n)
    out = []
    for i in range(n):
        f = pool.reserve((120, 160, 3), np.uint8, source="cam", seq=i, timestamp=1.0 + i / 20)
        assert f is not None
        f.data[:] = i
        out.append(f)
    return out


async def test_a_stalled_writer_process_loses_frames_counted_and_gives_every_slot_back(
    tmp_path: Path,
) -> None:
    loop = asyncio.get_running_loop()
    w = ProcessRecordingWriter(tmp_path / "x.mcap", loop=loop, max_frames=4)
    await asyncio.to_thread(w.open, {"test": {"what": "stall"}}, [])
    assert w.pid is not None
    with FrameStore() as store:
        frames = _frames(store, 30)
        os.kill(w.pid, signal.SIGSTOP)  # the disk (or the process) stalls
        try:
            accepted = 0
            for f in frames:
                f.acquire()  # the writer's link
                if w.submit("cam.frame", f, f.timestamp, f.seq):
                    accepted += 1
                else:
                    f.release()
                await asyncio.sleep(0)
        finally:
            os.kill(w.pid, signal.SIGCONT)
        assert accepted == 4  # at most max_frames in flight; the rest refused, counted
        s = w.streams["cam.frame"]
        assert (s.received, s.lost_behind) == (30, 26)
        w.request_close()
        for _ in range(400):
            while w.done:
                w.done.popleft().release()
            if not w.encoding_frame():
                break
            await asyncio.sleep(0.005)
        assert await asyncio.to_thread(w.join, 30)
        while w.done:
            w.done.popleft().release()
        for f in frames:
            assert f.refs == 1  # only the producer's link: the writer gave back all of its own
            f.release()
        assert all(p.slots_in_use == 0 for p in store.stats())
    assert (s.written, s.lost, w.error) == (4, 26, None)
    info = scan(tmp_path / "x.mcap")
    assert info.closed_cleanly
    assert [x.count for x in info.streams] == [4]


def _start_recording(tmp: Path, seconds: float) -> subprocess.Popen[str]:
    g = tmp / "g.yaml"
    g.write_text(
        "name: crash\n"
        "nodes:\n"
        "  cam:\n"
        "    kind: capture\n"
        '    params: {source: "synthetic:soccer", fps: 20, size: [160, 120]}\n'
        "  ball:\n"
        "    kind: tracker\n"
        "    params: {object: ball}\n"
        "    trigger: {frame: cam}\n"
        "    inputs: {frame: cam.frame}\n"
    )
    return subprocess.Popen(
        [
            *(sys.executable, "-m", "flowrt.cli", "record", str(g), "-o", str(tmp / "out")),
            *("--name", "drive", "--no-ui", "--duration", str(seconds)),
        ],
        cwd=REPO,
        env=dict(os.environ, COLUMNS="200"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_kill_9_of_the_writer_process_is_seen_counted_and_the_run_goes_on(
    tmp_path: Path,
) -> None:
    proc = _start_recording(tmp_path, 5)
    mcap = tmp_path / "out" / "drive_001" / "drive_001.mcap"
    end = time.monotonic() + 60
    writer = None
    while time.monotonic() < end and proc.poll() is None:
        if mcap.exists() and mcap.stat().st_size > 1_500_000:  # a chunk or more on disk
            runtime = psutil.Process(proc.pid)
            for p in runtime.children(recursive=True):
                try:
                    if any(Path(f.path) == mcap for f in p.open_files()):
                        writer = p
                except psutil.Error:
                    continue
            if writer is not None:
                break
        time.sleep(0.05)
    assert writer is not None, proc.communicate()
    writer.send_signal(signal.SIGKILL)
    _out, err = proc.communicate(timeout=60)
    flat = " ".join(err.split())
    assert proc.returncode == 1, err
    assert "Traceback" not in err
    assert "recording stopped early" in flat
    assert "writer process died (killed by SIGKILL)" in flat
    report = json.loads((mcap.parent / "streams.json").read_text())
    info = scan(mcap)
    assert not info.closed_cleanly
    in_file = {s.topic: s.count for s in info.streams}
    for s in report["streams"]:
        # nothing lost silently: every message received is written or counted lost, and
        # "written" is what a reader finds in the file
        assert s["received"] == s["written"] + s["lost"], s
        assert s["written"] == in_file.get(s["topic"], 0), (s, in_file)
    frames = next(s for s in report["streams"] if s["topic"] == "cam.frame")
    assert frames["lost_error"] > 0  # the run went on after the kill: frames kept coming
    assert frames["written"] > 0
    r = subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "info", str(mcap.parent), "--repair", "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    (fixed,) = json.loads(r.stdout)["files"]
    assert fixed["closed_cleanly"] is True
    assert fixed["messages"] == sum(in_file.values())


@dataclass
class Pose:
    """A value whose class the writer process imports (this module): pickled, encoded there."""

    x: float
    y: float
    timestamp: float = 0.0


async def test_heap_frames_and_values_of_any_class_are_written(tmp_path: Path) -> None:
    @dataclass
    class Local:  # not importable anywhere else: encoded on the recorder's side
        v: int

    loop = asyncio.get_running_loop()
    w = ProcessRecordingWriter(tmp_path / "z.mcap", loop=loop)
    await asyncio.to_thread(w.open, {}, [])
    heap = flowrt.Frame(np.full((12, 16, 3), 7, np.uint8), source="c", seq=1, timestamp=1.0)
    assert w.submit("heap.frame", heap, 1.0, 1)
    assert w.submit("pose", Pose(1.0, 2.0, 1.0), 1.0, 0)
    assert w.submit("local", Local(3), 1.0, 0)
    assert w.submit("dict", {"a": [1, 2]}, 1.0, 0)
    w.request_close()
    assert await asyncio.to_thread(w.join, 30)
    assert w.error is None
    assert w.notes == []
    assert {t: (s.written, s.lost) for t, s in w.streams.items()} == {
        "heap.frame": (1, 0),
        "pose": (1, 0),
        "local": (1, 0),
        "dict": (1, 0),
    }
    got = {m.topic: m.data for m in _messages(tmp_path / "z.mcap")}
    assert json.loads(got["pose"])["x"] == 1.0
    assert json.loads(got["local"]) == {"v": 3}
    assert json.loads(got["dict"]) == {"a": [1, 2]}
    assert got["heap.frame"].endswith(bytes([7]) * 12 * 16 * 3)


def _messages(path: Path) -> list[Any]:
    from mcap.reader import make_reader

    class M:
        def __init__(self, topic: str, data: bytes) -> None:
            self.topic, self.data = topic, data

    with open(path, "rb") as f:
        return [M(c.topic, m.data) for _s, c, m in make_reader(f).iter_messages()]


@pytest.mark.subprocess  # a worker (or writer) process, from its graph
@pytest.mark.parametrize(
    ("priority", "policy"), [("normal", os.SCHED_OTHER), ("idle", os.SCHED_IDLE)]
)
async def test_the_writer_process_runs_at_the_priority_asked_every_thread_of_it(
    tmp_path: Path, priority: str, policy: int
) -> None:
    async with flowrt.Runtime(small_graph(tmp_path, writer_priority=priority)) as rt:
        await rt.run(0.8)
        writer = await writer_of(tmp_path / "drive_001" / "drive_001.mcap")
        assert writer is not None
        # its threads start as it opens the file: later on a loaded machine (or at idle
        # priority), so they are waited for (bounded) before they are read
        await wait_until(lambda: len(os.listdir(f"/proc/{writer.pid}/task")) >= 3)
        tids = [int(t) for t in os.listdir(f"/proc/{writer.pid}/task")]
        policies = {os.sched_getscheduler(t) for t in tids}
        await rt.run(0.4)
    await asyncio.to_thread(wait_for_writers)
    assert len(tids) >= 3  # the main one, the writer's threads, the acknowledgements'
    assert policies == {policy}
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the runtime's own is untouched
    _, report = session_of(tmp_path)
    assert all(s.written + s.lost == s.received for s in report.streams)  # each loss counted
    if policy != os.SCHED_IDLE:  # an idle writer runs only when no other program wants a CPU
        assert report.lost == 0


def test_an_idle_priority_for_writer_threads_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(flowrt.GraphError, match="writer_priority idle needs writer: process"):
        small_graph(tmp_path, writer="thread", writer_priority="idle")


def test_the_cli_refuses_an_idle_priority_for_writer_threads_in_one_line(
    tmp_path: Path, flowrt_cli: Any
) -> None:
    r = flowrt_cli(
        "record", "graphs/video.yaml", "-o", str(tmp_path), "--writer", "thread",
        "--writer-priority", "idle", "--duration", "1",
    )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.strip() == "flowrt record: --writer-priority idle needs --writer process"
    assert list(tmp_path.iterdir()) == []  # refused before a session folder was made


def _refuse(*_: Any) -> None:
    raise PermissionError(1, "Operation not permitted")


@pytest.mark.parametrize(
    ("priority", "setter", "said"),
    [
        ("normal", _refuse, None),  # nothing asked, nothing tried
        ("idle", lambda *_: None, None),
        ("idle", _refuse, "cannot set SCHED_IDLE"),  # said in the recording's notes
    ],
)
def test_a_priority_the_system_refuses_is_said_not_dropped(
    monkeypatch: pytest.MonkeyPatch, priority: str, setter: Any, said: str | None
) -> None:
    from flowrt.recording.writer.child import _set_priority

    monkeypatch.setattr(os, "sched_setscheduler", setter)
    note = _set_priority(priority)
    if said is None:
        assert note is None
    else:
        assert note is not None
        assert said in note
