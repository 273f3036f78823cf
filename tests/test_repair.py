"""``flowrt info --repair``: a repaired recording is what its recorder would have closed.

Found by the audit of killed and truncated recordings:

- a killed ``--profile ros2`` recording was rewritten as a file of header profile ``flowrt``
  and left without ``metadata.yaml`` (a killed rosbag2 recorder writes none): rosbags opened
  neither the folder ("Expected metadata file") nor the file ("Profile is not ros2"). The
  repaired file keeps the original's profile, and a ``ros2`` folder gets the
  ``metadata.yaml`` a clean close writes, its counts those of ``flowrt info``;
- a file cut inside its summary section, or within its first bytes, was described with a raw
  Python error (``error: unpack requires a buffer of 8 bytes``), which ``--repair`` also wrote
  into the file's ``flowrt.repair`` metadata: it is "truncated: the file ends inside a
  record", as a cut inside a chunk is.
"""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from conftest import recorded_counter

from flowrt.recording.reader import scan, scan_session
from flowrt.recording.repair import repair
from flowrt.recording.writer.threads import RecordingWriter

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[1]
TRUNCATED = "truncated: the file ends inside a record"
N = 120  # messages per stream


def record(path: Path, profile: str = "flowrt", n: int = N) -> Path:
    """A finished file of three streams in small chunks (a cut keeps the chunks before it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    w = RecordingWriter(path, profile=profile, epoch_offset=time.time(), chunk_size=2048)
    w.open({})
    for topic in ("wheels.values", "tick.count", "cam.level"):
        w.declare(topic, source=topic)
    for i in range(n):
        t = 0.01 * i
        assert w.submit("wheels.values", {"LeftSpeed": i / 4, "Mode": "drive"}, t, i)
        assert w.submit("tick.count", i, t, i)
        assert w.submit("cam.level", i / 8, t, i)
    w.close()
    assert w.error is None
    return path


def header_profile(path: Path) -> str:
    """The profile the file's header record names (what rosbags checks)."""
    from mcap.records import Header
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as f:
        header = next(iter(StreamReader(f, skip_magic=False).records))
    assert isinstance(header, Header)
    return str(header.profile)


def summary_start(data: bytes) -> int:
    """Where the summary section starts (the footer's first field; 0: none)."""
    return int(struct.unpack("<Q", data[-28:-20])[0])


def cut(src: Path, dst: Path, size: int) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(src.read_bytes()[:size])
    return dst


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record(tmp_path_factory.mktemp("whole") / "rec.mcap")


# --- a file cut anywhere says "truncated" ----------------------------------------------------

# (case, where to cut: f(file size, summary start)): inside a field of a record, each a raw
# struct error before (a cut between two fields was said "truncated" already)
CUTS: list[tuple[str, Callable[[int, int], int]]] = [
    ("inside_the_magic", lambda size, summary: 5),
    ("inside_the_header_length", lambda size, summary: 10),
    ("inside_the_header", lambda size, summary: 20),
    ("inside_the_first_summary_record_length", lambda size, summary: summary + 5),
    ("inside_the_first_summary_record", lambda size, summary: summary + 10),  # its u16 id
    ("inside_the_footer", lambda size, summary: size - 10),  # its CRC
    ("inside_the_closing_magic", lambda size, summary: size - 3),
]


@pytest.mark.parametrize(("case", "where"), CUTS, ids=[c for c, _ in CUTS])
def test_a_cut_file_is_said_truncated_and_repaired_as_such(
    case: str, where: Callable[[int, int], int], whole: Path, tmp_path: Path
) -> None:
    data = whole.read_bytes()
    bad = cut(whole, tmp_path / f"{case}.mcap", where(len(data), summary_start(data)))
    info = scan(bad)
    assert not info.closed_cleanly
    assert info.damage == TRUNCATED
    fixed, kept, _ = repair(bad)
    again = scan(fixed)
    assert again.closed_cleanly
    assert again.messages == kept == info.messages
    assert again.metadata["flowrt.repair"]["damage"] == TRUNCATED


def test_an_empty_file_is_said_empty_and_repaired_as_an_empty_recording(tmp_path: Path) -> None:
    """A recorder killed as it created its file leaves 0 bytes: "truncated: the file ends
    inside a record at byte 0" said it poorly."""
    bad = tmp_path / "rec_001.mcap"
    bad.write_bytes(b"")
    info = scan(bad)
    assert (info.closed_cleanly, info.damage_offset) == (False, None)
    assert info.damage == "empty: not one byte (killed as it was created)"
    fixed, kept, _ = repair(bad)
    again = scan(fixed)
    assert again.closed_cleanly
    assert kept == again.messages == 0


def test_every_cut_in_the_summary_and_footer_says_truncated(whole: Path, tmp_path: Path) -> None:
    data = whole.read_bytes()
    start = summary_start(data)
    assert 0 < start < len(data) - 28
    bad = tmp_path / "cut.mcap"
    said = {}
    for size in range(start, len(data), 3):
        bad.write_bytes(data[:size])
        said[size] = scan(bad).damage
    assert set(said.values()) == {TRUNCATED}, {k: v for k, v in said.items() if v != TRUNCATED}


def test_flowrt_info_says_truncated_in_words(whole: Path, tmp_path: Path, flowrt_cli: Any) -> None:
    data = whole.read_bytes()
    bad = cut(whole, tmp_path / "cut.mcap", summary_start(data) + 5)
    r = flowrt_cli("info", str(bad), cwd=tmp_path, timeout=60)
    assert r.returncode == 1
    assert f"NOT closed cleanly: {TRUNCATED} at byte" in " ".join(r.stdout.split())
    assert "unpack" not in r.stdout + r.stderr


# --- a repaired file keeps its profile; a ros2 folder gets its metadata.yaml ------------------


def _cut_in_the_last_chunks(src: Path, dst: Path) -> Path:
    """As a ``kill -9`` leaves a file: its summary gone and the last chunk cut."""
    return cut(src, dst, summary_start(src.read_bytes()) * 3 // 4)


def _foreign(path: Path, profile: str) -> Path:
    """Another writer's file (mcap's own), of any profile."""
    from mcap.writer import Writer

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=512)
        w.start(profile=profile, library="other")
        cid = w.register_channel("/x", "json", w.register_schema("X", "jsonschema", b"{}"))
        for i in range(3 * N):
            w.add_message(cid, i * 1_000_000, b'{"i": %d}' % i, i * 1_000_000)
        w.finish()  # type: ignore[no-untyped-call]
    return path


@pytest.mark.parametrize(
    ("profile", "write"),
    [("flowrt", record), ("ros2", record), ("", _foreign), ("x-robot", _foreign)],
    ids=["flowrt", "ros2", "none", "another_writer_s"],
)
def test_the_repaired_file_keeps_the_original_profile(
    profile: str, write: Callable[[Path, str], Path], tmp_path: Path
) -> None:
    src = write(tmp_path / "src" / "rec.mcap", profile)
    bad = _cut_in_the_last_chunks(src, tmp_path / "bag" / "rec_001.mcap")
    fixed, kept, original = repair(bad)
    assert 0 < kept < 3 * N
    assert header_profile(original) == header_profile(fixed) == profile
    assert (bad.parent / "metadata.yaml").exists() is (profile == "ros2")


def _anyreader_counts(path: Path) -> dict[str, int]:
    """Every message deserialized by rosbags' AnyReader, counted per topic."""
    from rosbags.highlevel import AnyReader

    counts: dict[str, int] = {}
    with AnyReader([path]) as r:
        for c, _, raw in r.messages():
            r.deserialize(raw, c.msgtype)
            counts[c.topic] = counts.get(c.topic, 0) + 1
    return counts


def _one_cut(tmp: Path, bag: Path) -> list[Path]:
    return [_cut_in_the_last_chunks(record(tmp / "a.mcap", "ros2"), bag / "b_001.mcap")]


def _parts_last_cut(tmp: Path, bag: Path) -> list[Path]:
    """A split recording killed in its second part: the first one is finished."""
    first = record(bag / "b_001_000.mcap", "ros2")
    return [first, _cut_in_the_last_chunks(record(tmp / "b.mcap", "ros2"), bag / "b_001_001.mcap")]


def _damaged_after_a_clean_close(tmp: Path, bag: Path) -> list[Path]:
    """A bag closed cleanly (its metadata.yaml written), its file damaged since."""
    from flowrt.recording.rosbag2 import write_metadata

    f = record(bag / "b_001.mcap", "ros2")
    write_metadata(bag, [f])
    data = f.read_bytes()
    f.write_bytes(data[: summary_start(data) * 3 // 4])
    return [f]


def _summary_cut(tmp: Path, bag: Path) -> list[Path]:
    src = record(tmp / "c.mcap", "ros2")
    data = src.read_bytes()
    return [cut(src, bag / "b_001.mcap", len(data) - 100)]


BAGS = [
    ("killed", _one_cut),
    ("killed_in_its_second_part", _parts_last_cut),
    ("damaged_after_a_clean_close", _damaged_after_a_clean_close),
    ("cut_inside_its_summary", _summary_cut),
]


@pytest.mark.parametrize(("case", "make"), BAGS, ids=[c for c, _ in BAGS])
def test_a_repaired_ros2_bag_opens_in_rosbags_with_flowrt_s_counts(
    case: str, make: Callable[[Path, Path], list[Path]], tmp_path: Path
) -> None:
    bag = tmp_path / "b_001"
    bag.mkdir()
    files = make(tmp_path, bag)
    for f in files:
        if not scan(f).closed_cleanly:
            repair(f)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [f.name for f in files]  # not the .damaged originals
    info = scan_session(bag)
    assert info.closed_cleanly
    want = {s.topic: s.count for s in info.streams}
    assert set(want) == {"/wheels/values", "/tick/count", "/cam/level"}
    assert _anyreader_counts(bag) == want
    listed = {
        t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]
    }
    assert listed == want
    assert meta["message_count"] == info.messages
    if len(files) == 1:
        assert _anyreader_counts(files[0]) == want  # the file alone too: profile ros2


def test_a_ros2_file_among_flowrt_files_makes_no_bag(tmp_path: Path) -> None:
    """The folder is not the ros2 file's bag: no metadata.yaml lists files of another kind."""
    record(tmp_path / "x_001.mcap", "flowrt")
    src = record(tmp_path / "src" / "y.mcap", "ros2")
    bad = _cut_in_the_last_chunks(src, tmp_path / "x_002.mcap")
    fixed, _, _ = repair(bad)
    assert header_profile(fixed) == "ros2"
    assert not (tmp_path / "metadata.yaml").exists()


def test_the_first_of_two_killed_parts_waits_for_the_second(tmp_path: Path) -> None:
    """``info --repair`` goes through the parts in turn: the bag's metadata.yaml is written
    once every part is finished, by the last repair, not from a part still unfinished."""
    bag = tmp_path / "b_001"
    one = _cut_in_the_last_chunks(record(tmp_path / "1.mcap", "ros2"), bag / "b_001_000.mcap")
    two = _cut_in_the_last_chunks(record(tmp_path / "2.mcap", "ros2"), bag / "b_001_001.mcap")
    repair(one)
    assert not (bag / "metadata.yaml").exists()
    repair(two)
    assert _anyreader_counts(bag) == {s.topic: s.count for s in scan_session(bag).streams}


# --- end to end: flowrt record --profile ros2, kill -9, flowrt info --repair -----------------


@pytest.mark.slow
def test_repair_of_a_killed_ros2_recording_opens_in_rosbags(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "flowrt.cli", "record", str(REPO / "graphs" / "can.yaml"),
            "-o", str(tmp_path),
            "--name", "b", "--profile", "ros2", "--duration", "30", "--no-ui", "--no-display",
        ],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    mcap = tmp_path / "b_001" / "b_001.mcap"
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end and (not mcap.exists() or mcap.stat().st_size < 60_000):
            assert proc.poll() is None, "the recorder ended early"
            time.sleep(0.1)  # two finished chunks or so: one a second
        time.sleep(1.5)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert not (mcap.parent / "metadata.yaml").exists()  # killed: never closed
    r = subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "info", "--repair", str(mcap.parent)],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert header_profile(mcap) == "ros2"
    info = scan_session(mcap.parent)
    assert info.messages > 0
    assert _anyreader_counts(mcap.parent) == {s.topic: s.count for s in info.streams}
    assert _anyreader_counts(mcap) == {s.topic: s.count for s in info.streams}


@pytest.mark.parametrize("writer", ["thread", "process"])
async def test_a_file_being_recorded_is_not_damaged_nor_repaired(
    tmp_path: Path, writer: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``flowrt info`` of a live session said "NOT closed cleanly ... --repair rewrites the
    summary", and ``--repair`` renamed the file under its writer: the writer went on in
    ``.damaged.mcap``, a copy cut at that instant took the session's name and was "clean"."""
    import os

    import flowrt
    from flowrt import cli
    from flowrt.recording.inuse import being_recorded

    g = recorded_counter(tmp_path, "10ms", writer=writer)
    async with flowrt.Runtime(g.build()) as rt:
        await rt.run(1.5)  # the writer has written its first chunk
        (session,) = [tmp_path / n for n in os.listdir(tmp_path)]
        (mcap,) = session.glob("*.mcap")
        assert being_recorded(mcap)
        with pytest.raises(OSError, match="still being recorded"):
            repair(mcap)
        assert cli.main(["info", str(session)]) == 0
        out, err = capsys.readouterr()
        assert "still being recorded" in out + err
        assert "NOT closed cleanly" not in out
        assert cli.main(["info", str(session), "--repair"]) == 1
        assert "cannot repair: still being recorded" in capsys.readouterr().err
        assert sorted(os.listdir(session)) == [mcap.name]  # untouched: nothing renamed
    assert not being_recorded(mcap)
    assert scan(mcap).closed_cleanly
