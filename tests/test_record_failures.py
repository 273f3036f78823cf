"""A recording that cannot start, or a disk that fills up (issue 37 item 10, issue 43 item 4).

A full disk is simulated by a writer whose ``open`` raises ENOSPC as the disk would (real
files, a real runtime): the recorder says so in one line (no ``FileExistsError`` from the
half-made file of a first attempt, no traceback), is given up (restarting cannot free the
disk) and leaves nothing behind. ``flowrt record`` that fails before it starts does not say
it is recording and leaves no folder; a report left unreadable by a full disk is one line.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.recording import RecordingWriter

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parents[1]
RECORD = [sys.executable, "-m", "flowrt.cli", "record", "--no-ui"]


def _full_disk(self: Any, *args: Any, **kwargs: Any) -> None:
    """What ``open`` meets on a full disk: the file was created, its header cannot go in."""
    Path(self.path).write_bytes(b"\x89MCAP0\r\n")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))


@pytest.mark.parametrize("session_given", [True, False], ids=["session", "numbered"])
async def test_a_full_disk_is_said_as_such_and_leaves_nothing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    session_given: bool,
) -> None:
    monkeypatch.setattr(RecordingWriter, "open", _full_disk)
    out = tmp_path / "out"
    params: dict[str, Any] = {"path": str(out), "writer": "thread"}
    if session_given:
        params["session"] = str(out / "rec_001")
    g = GraphBuilder()
    g.add("src", "counter", trigger={"timer": "10ms"})
    g.add("rec", "recorder", params=params, inputs={"value": "src.value"})
    clock = VirtualClock()
    with caplog.at_level(logging.INFO, logger="flowrt"):
        async with Runtime(g.build(), clock=clock) as rt:
            await clock.advance(2.0)
    rec = rt.stats().node("rec")
    assert rec.state == "failed"
    assert rec.errors == 1  # given up at once: no restart meeting its own half-made file
    assert "no space left on device (the disk is full)" in rec.reason
    assert "FileExistsError" not in caplog.text
    assert "Traceback" not in caplog.text
    assert list(out.rglob("*")) == []  # no session folder, no file


def test_an_unreadable_report_is_one_line(tmp_path: Path) -> None:
    """A disk that filled up as ``streams.json`` was written left it empty."""
    from flowrt.cli.record import _report

    session = tmp_path / "rec_001"
    session.mkdir()
    (session / "streams.json").write_text("")
    out = Console(file=open(os.devnull, "w"))  # noqa: SIM115
    err = Console(record=True, width=200)
    assert _report(out, err, session) == 1
    assert "the recording's report is unreadable (not valid JSON)" in err.export_text()


@pytest.mark.subprocess
@pytest.mark.parametrize("exists", [False, True], ids=["new-folder", "existing-folder"])
def test_a_record_that_fails_to_start_says_nothing_and_leaves_nothing(
    tmp_path: Path, exists: bool
) -> None:
    """A taken control port: before, ``recording 3 stream(s) into OUT/rec_001``, then the
    error, and an empty folder."""
    out = tmp_path / "deep" / "out"
    if exists:
        out.mkdir(parents=True)
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  src: {kind: counter, trigger: {timer: 10ms}}\n")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run(
            [*RECORD, str(graph), "-o", str(out), "--duration", "1", "--control", str(port)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 1, r.stderr
    assert "recording" not in r.stdout
    assert "Address already in use" in r.stderr
    assert "Traceback" not in r.stderr
    if exists:
        assert list(out.iterdir()) == []
    else:
        assert not (tmp_path / "deep").exists()


@pytest.mark.subprocess
def test_a_record_that_starts_says_so(tmp_path: Path) -> None:
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  src: {kind: counter, trigger: {timer: 10ms}}\n")
    out = tmp_path / "out"
    r = subprocess.run(
        [*RECORD, str(graph), "-o", str(out), "--duration", "1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert f"recording 1 stream(s) into {out / 'rec_001'}" in r.stdout
    assert (out / "rec_001" / "streams.json").exists()
