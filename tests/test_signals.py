"""``flowrt run`` and signals: every stop is orderly, quiet and leaves no shared memory.

SIGINT, SIGTERM and SIGHUP stop a run in order (exit 0, nodes torn down, /dev/shm clean);
a second signal during teardown is ignored, a third forces the exit; SIGTERM to the whole
process group (systemd, ``kill -- -PGID``) is not a crash of every worker; Ctrl-C while the
command is still importing exits 130 without a traceback; segments of a killed run are
reclaimed at the next start with one log line. Marker files written by the nodes
(tests/signalkinds.py) say when they run and when teardown begins, so no test guesses a time.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
# The console script itself: Ctrl-C during its imports is handled only in the flowrt command.
FLOWRT = [sys.executable, str(Path(sys.executable).with_name("flowrt"))]

pytestmark = [
    pytest.mark.timeout(60),
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals, /dev/shm"),
]


def _segments(pid: int) -> list[str]:
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(f"flowrt_{pid}_"))


def _wait_for(path: Path, proc: subprocess.Popen[str], timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            _out, err = proc.communicate()
            pytest.fail(f"flowrt run ended (rc {proc.returncode}) before {path.name}:\n{err}")
        if time.monotonic() > end:
            pytest.fail(f"{path.name} never appeared")
        time.sleep(0.02)


def _graph(tmp_path: Path, teardown_s: float = 0.0, worker: bool = False) -> Path:
    """A camera into a tracker (frames in shared memory) and a marked node."""
    placement = "process" if worker else "inline"
    text = textwrap.dedent(f"""\
        nodes:
          cam:
            kind: capture
            params: {{size: [64, 48], fps: 50}}
          ball:
            kind: tracker
            placement: process
            inputs: {{frame: cam.frame}}
          marked:
            kind: signalkinds:Marked
            placement: {placement}
            params: {{dir: "{tmp_path}", teardown_s: {teardown_s}}}
            trigger: {{timer: 20ms}}
        """)
    path = tmp_path / "g.yaml"
    path.write_text(text)
    return path


@pytest.fixture
def run(tmp_path: Path) -> Iterator[object]:
    """Start ``flowrt run`` in its own session (a process group of its own)."""
    procs: list[subprocess.Popen[str]] = []

    def start(graph: Path) -> subprocess.Popen[str]:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
        proc = subprocess.Popen(
            [*FLOWRT, "run", str(graph), "--no-ui", "--log-every", "60"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,
        )
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP])
def test_a_signal_stops_the_run_in_order(tmp_path: Path, run: object, sig: int) -> None:
    """SIGTERM: in the next test. SIGHUP (the terminal closed) left every segment behind."""
    proc = run(_graph(tmp_path))  # type: ignore[operator]
    _wait_for(tmp_path / "marked.running", proc)
    assert _segments(proc.pid), "the capture node's frames should be in shared memory"
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert (tmp_path / "marked.done").exists()  # torn down
    assert "Traceback" not in err
    assert _segments(proc.pid) == []


def test_a_second_signal_waits_for_teardown_and_a_third_forces(tmp_path: Path, run: object) -> None:
    proc = run(_graph(tmp_path, teardown_s=1.0))  # type: ignore[operator]
    _wait_for(tmp_path / "marked.running", proc)
    proc.send_signal(signal.SIGTERM)
    _wait_for(tmp_path / "marked.teardown", proc)
    proc.send_signal(signal.SIGTERM)  # during teardown: noted, teardown goes on
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert (tmp_path / "marked.done").exists()
    assert "still stopping" in err
    assert "Traceback" not in err
    assert _segments(proc.pid) == []

    (tmp_path / "marked.running").unlink()
    (tmp_path / "marked.teardown").unlink()
    proc = run(_graph(tmp_path, teardown_s=30.0))  # type: ignore[operator]
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")))
    reader.start()
    _wait_for(tmp_path / "marked.running", proc)
    proc.send_signal(signal.SIGTERM)
    _wait_for(tmp_path / "marked.teardown", proc)
    proc.send_signal(signal.SIGTERM)
    # Signals sent back to back may coalesce into one: the third goes once the second is seen.
    end = time.monotonic() + 30
    while not any("still stopping" in line for line in lines) and time.monotonic() < end:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)
    reader.join(timeout=30)
    err = "".join(lines)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "forced exit" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_to_the_process_group_is_not_a_worker_crash(
    tmp_path: Path, run: object, sig: int
) -> None:
    """Workers leave stopping to the runtime: their nodes are torn down in the worker."""
    proc = run(_graph(tmp_path, worker=True))  # type: ignore[operator]
    _wait_for(tmp_path / "marked.running", proc)
    os.killpg(proc.pid, sig)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert (tmp_path / "marked.done").exists()  # teardown ran in the worker process
    for noise in ("Traceback", "never retrieved", "WorkerError", "worker crashed"):
        assert noise not in err, err
    assert _segments(proc.pid) == []


def test_ctrl_c_while_the_command_imports_exits_130_quietly() -> None:
    """The console script imports the package before main() can catch KeyboardInterrupt."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    # As if SIGINT came while numpy & co. are imported, right after flowrt/_startup: exact.
    script = (
        "import sys; sys.argv[0] = '/usr/bin/flowrt'\n"
        "import flowrt._startup, os, signal\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "import time; time.sleep(5)\n"
        "print('not reached')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=30
    )
    assert done.returncode == 130
    assert done.stderr == "flowrt: SIGINT while importing: exit 130\n"  # what it interrupted
    assert "not reached" not in done.stdout


def test_ctrl_c_at_start_up_of_flowrt_run(tmp_path: Path, run: object) -> None:
    """A real start-up: interrupted while importing or loading, it exits 130, no traceback."""
    proc = run(_graph(tmp_path))  # type: ignore[operator]
    time.sleep(0.3)  # importing numpy/pydantic or loading the graph: both end in 130
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode in (130, 0), err  # 0: it had started already, and stopped in order
    assert "Traceback" not in err
    assert "KeyboardInterrupt" not in err
    assert _segments(proc.pid) == []


def test_segments_of_a_killed_run_are_reclaimed_with_one_line(
    tmp_path: Path, run: object, caplog: pytest.LogCaptureFixture
) -> None:
    proc = run(_graph(tmp_path))  # type: ignore[operator]
    _wait_for(tmp_path / "marked.running", proc)
    left = _segments(proc.pid)
    assert left
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate()
    # Any runtime started on this machine now reclaims them (other test runs too): so the
    # start-up below is checked in this process, at once, on a segment of a dead pid.
    from flowrt.runtime._resources import frame_store

    orphan = Path("/dev/shm", f"flowrt_{proc.pid}_0_cam_99")
    orphan.write_bytes(bytes(64))
    with caplog.at_level(logging.INFO, logger="flowrt"):
        store = frame_store()
    store.close()
    assert not orphan.exists()
    assert _segments(proc.pid) == []
    lines = [r.getMessage() for r in caplog.records if "reclaimed" in r.getMessage()]
    assert len(lines) == 1, lines
    assert re.fullmatch(
        r"reclaimed \d+ shared-memory segments? left in /dev/shm by a runtime that was killed",
        lines[0],
    )
