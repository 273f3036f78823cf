"""Recording under failure: kill -9, SIGINT/SIGTERM, a full disk, a damaged file.

Each case runs the real ``flowrt record`` in a subprocess, as a user would, and checks what
is left on disk with flowrt's reader and the official ``mcap`` readers.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import SeekingReader

from flowrt.recording.reader import scan

pytestmark = pytest.mark.timeout(90)

REPO = Path(__file__).resolve().parent.parent
GRAPH = """\
name: crash
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


def env() -> dict[str, str]:
    return dict(os.environ, COLUMNS="200")


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env=env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def start_recording(tmp: Path, *extra: str, preexec=None) -> subprocess.Popen[str]:  # type: ignore[no-untyped-def]
    g = tmp / "g.yaml"
    g.write_text(GRAPH)
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flowrt.cli",
            "record",
            str(g),
            "-o",
            str(tmp / "out"),
            "--name",
            "drive",
            "--no-ui",
            *extra,
        ],
        cwd=REPO,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=preexec,
    )


def wait_for_bytes(path: Path, proc: subprocess.Popen[str], n: int, limit: float = 30) -> None:
    """Until ``path`` holds ``n`` bytes (chunks are written at least once a second)."""
    end = time.monotonic() + limit
    while time.monotonic() < end:
        if path.exists() and path.stat().st_size >= n:
            return
        if proc.poll() is not None:
            raise AssertionError(f"recorder exited early: {proc.communicate()}")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"{path} never reached {n} bytes")


def test_kill_9_leaves_a_file_readable_up_to_the_last_chunk(tmp_path: Path) -> None:
    proc = start_recording(tmp_path)
    mcap = tmp_path / "out" / "drive_001" / "drive_001.mcap"
    wait_for_bytes(mcap, proc, 1_500_000)  # ~1 s of 160x120 frames: at least one chunk
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    info = scan(mcap)
    assert not info.closed_cleanly
    assert not info.summary_ok
    frames = next(s for s in info.streams if s.topic == "cam.frame")
    assert frames.count > 0
    assert frames.count * 160 * 120 * 3 <= mcap.stat().st_size  # what it says it has, it has

    r = cli("info", str(mcap.parent))
    assert r.returncode == 1
    assert "NOT closed cleanly" in " ".join(r.stdout.split())
    assert "Traceback" not in r.stderr

    r = cli("info", str(mcap.parent), "--repair", "--json")
    assert r.returncode == 0, r.stderr
    assert "damaged.mcap" in r.stderr
    (fixed,) = json.loads(r.stdout)["files"]  # the original is not a part of the session
    assert fixed["closed_cleanly"] is True
    assert fixed["messages"] == info.messages
    with open(mcap, "rb") as f:  # the official summary reader agrees after the repair
        summary = SeekingReader(f, validate_crcs=True).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    assert summary.statistics.message_count == info.messages
    assert (mcap.parent / "drive_001.damaged.mcap").exists()  # the original is kept


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_sigint_and_sigterm_close_the_file_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    proc = start_recording(tmp_path)
    mcap = tmp_path / "out" / "drive_001" / "drive_001.mcap"
    wait_for_bytes(mcap, proc, 300_000)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    info = scan(mcap)
    assert info.closed_cleanly
    assert info.summary_ok
    report = json.loads((mcap.parent / "streams.json").read_text())
    assert {s["topic"]: s["written"] for s in report["streams"]} == {
        s.topic: s.count for s in info.streams
    }
    assert all(s["lost"] == 0 for s in report["streams"])


def _small_disk() -> None:
    """In the child: files may not grow past 2 MB (EFBIG, as a full disk gives ENOSPC)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2_000_000, 2_000_000))


def test_disk_full_stops_the_recording_keeps_the_file_and_the_graph_goes_on(
    tmp_path: Path,
) -> None:
    proc = start_recording(tmp_path, "--duration", "3", preexec=_small_disk)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert "recording stopped early" in err
    assert "File too large" in err
    assert "Traceback" not in err
    session = tmp_path / "out" / "drive_001"
    report = json.loads((session / "streams.json").read_text())
    frames = next(s for s in report["streams"] if s["topic"] == "cam.frame")
    assert report["error"] is not None
    assert frames["lost_error"] > 0
    assert frames["written"] > 0
    # the graph went on: frames kept arriving after the disk was full, and were counted
    assert frames["received"] == frames["written"] + frames["lost_error"]
    assert frames["received"] >= (frames["expected"] or 0) - 1
    info = scan(session / "drive_001.mcap")
    assert next(s.count for s in info.streams if s.topic == "cam.frame") <= frames["written"]
    assert info.messages > 0


def test_corrupt_chunk_is_reported_and_replay_stops_there(tmp_path: Path) -> None:
    proc = start_recording(tmp_path, "--duration", "2")
    proc.communicate(timeout=60)
    assert proc.returncode == 0
    mcap = tmp_path / "out" / "drive_001" / "drive_001.mcap"
    whole = scan(mcap)
    with open(mcap, "rb") as f:
        summary = SeekingReader(f).get_summary()
    assert summary is not None
    # the last chunk holding frames: the chunks before it stay good, so there is something
    # to replay up to the damage
    chunk = max(
        (c for c in summary.chunk_indexes if c.chunk_length > 100_000),
        key=lambda c: c.chunk_start_offset,
    )
    data = bytearray(mcap.read_bytes())
    mid = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[mid : mid + 64] = bytes(64)  # zeroed pixels inside a chunk: its CRC no longer holds
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    info = scan(bad)
    assert not info.closed_cleanly
    assert info.damage is not None
    assert "CRC" in info.damage
    assert 0 < info.messages < whole.messages
    r = cli("info", str(bad))
    assert r.returncode == 1
    r = cli("replay", str(bad), "--rate", "8", "--no-ui")
    assert r.returncode == 1
    flat = " ".join(r.stderr.split())
    assert "not closed cleanly" in flat
    assert f"replaying the {info.messages} messages before the damage" in flat
    assert "Traceback" not in r.stderr
