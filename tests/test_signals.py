"""``flowrt run`` and signals: every stop is orderly, quiet and leaves no shared memory.

SIGINT, SIGTERM and SIGHUP stop a run in order (exit 0, nodes torn down, /dev/shm clean);
a second signal during teardown is ignored, a third forces the exit; SIGTERM to the whole
process group (systemd, ``kill -- -PGID``) is not a crash of every worker; Ctrl-C while the
command is still importing exits 130 without a traceback; segments of a killed run are
reclaimed at the next start with one log line. Marker files written by the nodes
(tests/signalkinds.py) say when they run and when teardown begins, so no test guesses a time.
"""

from __future__ import annotations

import json
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
from typing import Any

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
    assert _segments(proc.pid) == []  # they waited in /dev/shm for the next start


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


def _flowrt_script(body: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``body`` run as if it were the ``flowrt`` command (``sys.argv[0]``), from tests/."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    argv = ", ".join(repr(a) for a in ("/usr/bin/flowrt", *args))
    script = f"import sys; sys.argv[:] = [{argv}]\nimport flowrt._startup, os, signal\n{body}"
    return subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=30
    )


def test_a_signal_inside_a_class_body_is_no_traceback() -> None:
    """Python 3.11 wraps an exception raised in ``__set_name__`` (pydantic's descriptors) in
    a RuntimeError: the start-up exit must not be an exception there."""
    done = _flowrt_script(
        "class Name:\n"
        "    def __set_name__(self, owner, name):\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        import time; time.sleep(5)\n"
        "class Model:\n"
        "    field = Name()\n"
        "print('not reached')\n"
    )
    assert (done.returncode, done.stderr) == (130, "flowrt: SIGINT while importing: exit 130\n")
    assert done.stdout == ""


def test_a_signal_while_importing_with_json_prints_the_error_document() -> None:
    """``--json``: exactly one document on stdout, whatever happens (even before main())."""
    done = _flowrt_script(
        "os.kill(os.getpid(), signal.SIGTERM)\nimport time; time.sleep(5)\n",
        "run",
        "g.yaml",
        "--json",
    )
    line = "flowrt: SIGTERM while importing: exit 143"
    assert (done.returncode, done.stderr) == (143, line + "\n")
    error = json.loads(done.stdout)["error"]
    assert error == {"message": line, "exit_code": 143, "command": "run", "lines": [line]}


def test_a_forced_exit_with_json_prints_the_error_document() -> None:
    """The third signal's forced exit printed nothing on stdout under ``--json``."""
    done = _flowrt_script(
        "from flowrt.cli.signals import StopSignals\n"
        "s = StopSignals(lambda: 'the drain', lambda: '', 'flowrt run')\n"
        "for _ in range(3): s(signal.SIGINT)\n"
        "print('not reached')\n",
        "run",
        "g.yaml",
        "--json",
    )
    line = "flowrt run: SIGINT: forced exit"
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines()[-1] == line
    assert json.loads(done.stdout)["error"]["message"] == line


def test_a_child_the_command_spawns_ignores_ctrl_c_quietly() -> None:
    """A spawned child gets the command's ``sys.argv``: no start-up line of its own, and a
    Ctrl-C (the whole process group gets one) leaves it to the main process."""
    done = _flowrt_script(
        "import multiprocessing, signalkinds\n"
        "from flowrt.system import _spawned\n"
        "p = multiprocessing.get_context('spawn').Process(target=signalkinds.interrupt_self)\n"
        "_spawned.start(p)\n"
        "p.join(20)\n"
        "print('exit', p.exitcode)\n"
    )
    assert done.stdout.splitlines() == ["child went on", "exit 0"], done.stderr
    assert done.stderr == ""


def test_the_forkserver_ignores_ctrl_c_while_it_preloads() -> None:
    """multiprocessing's forkserver ignores SIGINT only once numpy and OpenCV are imported:
    a Ctrl-C in its first second printed a traceback from inside their imports."""
    done = _flowrt_script(
        "import threading, time\n"
        "from multiprocessing import forkserver\n"
        "from flowrt.workers import start_forkserver\n"
        "t = threading.Thread(target=start_forkserver)\n"
        "t.start(); t.join()\n"
        "pid = forkserver._forkserver._forkserver_pid\n"
        "os.kill(pid, signal.SIGINT)  # while it preloads\n"
        "os.kill(pid, signal.SIGTERM)\n"
        "time.sleep(0.2)\n"
        "print('alive', os.waitpid(pid, os.WNOHANG) == (0, 0))\n",
    )
    assert done.stdout.strip() == "alive True", done.stderr
    assert "Traceback" not in done.stderr


def test_a_line_said_from_a_signal_handler_is_the_json_error_message() -> None:
    """Handlers write with ``os.write`` (not ``sys.stderr``): ``--json`` still hears them."""
    from flowrt import _startup
    from flowrt.cli.json_output import json_mode

    line = "flowrt run: SIGINT during set-up (in setup() of cam): stopping, exit 130"
    with json_mode("run") as out:
        _startup.say(line)
    error = out.document(130)["error"]
    assert (error["message"], error["lines"]) == (line, [line])
    assert _startup.listeners == []


def _wrapped(inner: BaseException) -> BaseException:
    try:
        try:
            raise inner
        except BaseException as e:
            raise RuntimeError("Error calling __set_name__") from e
    except RuntimeError as outer:
        return outer


@pytest.mark.parametrize(
    ("error", "signum"),
    [
        (ValueError("a bug"), None),
        (KeyboardInterrupt(), signal.SIGINT),
        ("Interrupted(SIGTERM)", signal.SIGTERM),
        ("wrapped Interrupted(SIGHUP)", signal.SIGHUP),
        ("wrapped ValueError", None),
    ],
)
def test_a_wrapped_interruption_is_still_the_signal(error: object, signum: int | None) -> None:
    from flowrt._startup import Interrupted, interrupted_by

    made = {
        "Interrupted(SIGTERM)": Interrupted(signal.SIGTERM),
        "wrapped Interrupted(SIGHUP)": _wrapped(Interrupted(signal.SIGHUP)),
        "wrapped ValueError": _wrapped(ValueError("a bug")),
    }
    e = made[error] if isinstance(error, str) else error
    assert isinstance(e, BaseException)
    assert interrupted_by(e) == signum


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


def test_after_the_final_output_a_signal_is_ignored_not_fatal() -> None:
    """The interpreter's finalization puts a Python handler back to the default action: a
    second Ctrl-C 0.2-0.5 s after the final table killed the run (exit 130) that had
    reported exit 0. At exit the handlers become SIG_IGN, which finalization leaves."""
    from flowrt.cli.signals import StopSignals

    saved = {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    try:
        stop = StopSignals(lambda: "the run", lambda: "")
        stop.install()
        assert signal.getsignal(signal.SIGINT) == stop._handler
        stop._ignore_from_now()  # what atexit calls
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_signal_raised_where_it_was_ignored_still_stops_the_command() -> None:
    """CI: SIGINT 0.3 s after ``flowrt run`` was raised inside importlib's weakref callback
    ("Exception ignored in: <function _get_module_lock.<locals>.cb>"): lost, the run went
    on for 60 s. The handler notes it; the run's handlers take it before the start."""
    import weakref

    from flowrt import _startup
    from flowrt.cli.signals import StopSignals

    class Lock:
        pass

    saved = {s: signal.getsignal(s) for s in StopSignals.SIGNALS}
    said: list[str] = []
    _startup.listeners.append(said.append)
    try:
        lock = Lock()
        # the signal arrives while a weakref callback runs: its exception is ignored
        ref = weakref.ref(lock, lambda r: _startup._raise_interrupted(signal.SIGINT, None))
        del lock
        assert ref() is None
        assert _startup.received == signal.SIGINT  # lost, but noted
        stop = StopSignals(lambda: "the start", lambda: "")
        stop.install()
        assert stop.before_start == signal.SIGINT  # the run does not start: exit 130
        assert _startup.received is None
        assert "SIGINT" in said[-1]
    finally:
        _startup.listeners.remove(said.append)
        _startup.received = None
        for s, h in saved.items():
            signal.signal(s, h)


def said_by(stop: Any, *signals: int) -> list[str]:
    """What ``stop`` (a StopSignals, its loop open) says for each of ``signals`` in turn."""
    import asyncio

    from flowrt import _startup

    said: list[str] = []
    loop = asyncio.new_event_loop()
    stop.loop = loop
    _startup.listeners.append(said.append)
    try:
        for sig in signals:
            stop(sig)
    finally:
        _startup.listeners.remove(said.append)
        loop.close()
    return said


def test_a_signal_after_the_set_up_was_cut_is_still_stopping() -> None:
    """A second SIGTERM while a cut set-up is undone said "stopping the run (drain, then
    teardown)": there is no run to drain."""
    from flowrt.cli.signals import StopSignals

    phases = iter(["set-up (in setup() of slow)", "the run"])
    said = said_by(StopSignals(lambda: next(phases), lambda: ""), signal.SIGTERM, signal.SIGTERM)
    assert "during set-up (in setup() of slow): stopping, exit 143" in said[0]
    assert "still stopping" in said[1]


def test_a_second_signal_while_the_loop_is_held_says_it_cuts_the_drain() -> None:
    """A slow call holds the loop: the first signal's stop has not begun when the second
    comes, which said "stopping the run" again; it cuts the drain that follows. The first
    also marks the instant (no source released after it)."""
    from flowrt.cli.signals import StopSignals

    marked: list[bool] = []
    stop = StopSignals(lambda: "the run", lambda: "", stop_now=lambda: marked.append(True))
    said = said_by(stop, signal.SIGINT, signal.SIGINT)
    assert "SIGINT: stopping the run" in said[0]
    assert "SIGINT during the drain: cut short" in said[1]
    assert marked == [True]


def _interrupted(args: list[str], cue: Path) -> tuple[int, str, str]:
    """``flowrt ARGS`` in a session of its own, SIGINT once ``cue`` exists: (code, out, err)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    proc = subprocess.Popen(
        [*FLOWRT, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        _wait_for(cue, proc)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return proc.returncode, out, err


@pytest.mark.slow
@pytest.mark.subprocess
def test_ctrl_c_in_a_measuring_run_gives_no_verdict(tmp_path: Path) -> None:
    """``flowrt check --measure 10s`` cut after a second printed a whole response-time
    verdict from half a second of budgets, exit 1 ("timing does not hold")."""
    args = ["check", str(_graph(tmp_path)), "--measure", "30s", "--no-ui"]
    code, out, err = _interrupted(args, tmp_path / "marked.running")
    assert code == 130, err
    assert "the measuring run was interrupted: no verdict from a cut run" in err
    assert "schedulable" not in out + err
    assert "Traceback" not in err


def _replay_graph(tmp_path: Path, marks: Path) -> Path:
    marks.mkdir(exist_ok=True)
    text = textwrap.dedent(f"""\
        nodes:
          src: {{kind: counter, trigger: {{timer: 50ms}}}}
          double:
            kind: signalkinds:SlowDouble
            placement: process
            params: {{dir: "{marks}"}}
            inputs: {{value: src.value}}
        """)
    path = marks / "g.yaml"
    path.write_text(text)
    return path


def test_ctrl_c_during_a_deterministic_replay_gives_no_verdict(tmp_path: Path) -> None:
    """``flowrt replay --deterministic --check`` had no handlers of its own: the start-up's
    KeyboardInterrupt came out of a worker's socket callback (a traceback), the worker was
    taken for crashed and the replay said it diverged (exit 1); once it hung."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    graph = _replay_graph(tmp_path, tmp_path / "rec")
    out_dir = str(tmp_path / "out")
    options = ["--deterministic", "-o", out_dir, "--duration", "2", "--no-display", "--no-ui"]
    recorded = subprocess.run(
        [*FLOWRT, "record", str(graph), *options],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert recorded.returncode == 0, recorded.stderr
    (session,) = (tmp_path / "out").iterdir()
    replay = tmp_path / "replay"
    again = _replay_graph(tmp_path, replay)
    args = ["replay", str(session), "--graph", str(again), "--deterministic", "--check"]
    code, out, err = _interrupted(args, replay / "double.running")
    assert code == 130, out + err
    assert "SIGINT during the re-execution: stopping, exit 130" in err
    assert "Traceback" not in err
    assert "diverged" not in out
    assert "identical" not in out
