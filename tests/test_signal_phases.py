"""Signals at every phase (issue 37 item 4): INT, TERM and HUP at 0.3, 0.8 and 1.5 s after
the start (importing, loading, setting up), mid-run and mid-drain each end ``flowrt run``
within 2 s with the documented exit code, naming what was interrupted, and leave no process
and no shared-memory segment behind.

Documented codes (README "Signals"): before the run runs (importing, loading the graph,
set-up) 128 + N (130, 143, 129) and one line ``... while/during PHASE ... exit CODE``; from
the run on, the run's own verdict (0 here) after an orderly stop; a signal during the drain
cuts it short, what it held counted as dropped (reason ``interrupted``).

The graph is small but has every part a signal can catch: a capture (frames in shared
memory), a tracker in a worker process, and a fast source on a lossless edge into a slow
sink, whose backlog makes the drain at stop last seconds (``--drain-timeout 60``): a drain
that was not cut would blow the 2 s bound.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = [
    pytest.mark.slow,
    pytest.mark.subprocess,
    pytest.mark.timeout(120),
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals, /dev/shm"),
]

TESTS = Path(__file__).resolve().parent
FLOWRT = [sys.executable, str(Path(sys.executable).with_name("flowrt"))]
LIMIT_S = 2.0  # the bound from the signal to the exit
# From the run on, the orderly stop's teardowns come on top (README "Signals": 2 s each at
# most): a worker that has not exited by then is killed. Its exit takes ~0.15 s, but once
# in CI (a loaded machine) the mid-drain exit took 2.10 s; a hang is far beyond either.
STOP_S = LIMIT_S + 2.0
# What outlives the main process (the forkserver, multiprocessing's resource tracker) ends
# on end of file once it is gone; on a loaded machine their own interpreter shutdown took
# over 2 s once (CI). A leak never ends: 10 s tells one from the other.
LEFTOVER_S = 10.0
SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP]


def _graph(tmp_path: Path, slow_setup: bool = False, backlog: int = 20) -> Path:
    """``backlog``: the lossless edge's size, what the drain has to deliver (10 ms each);
    small but for the drain test: an orderly stop delivers it all (README "the drain")."""
    extra = (
        "  slow:\n"
        "    kind: signalkinds:SlowSetup\n"
        "    placement: process\n"
        f'    params: {{dir: "{tmp_path}", setup_s: 60}}\n'
        "    trigger: {timer: 100ms}\n"
        if slow_setup
        else ""
    )
    text = (
        textwrap.dedent(f"""\
        nodes:
          cam:
            kind: capture
            params: {{size: [64, 48], fps: 50}}
          ball:
            kind: tracker
            placement: process
            inputs: {{frame: cam.frame}}
          src:
            kind: counter
            trigger: {{timer: 2ms}}
          sink:
            kind: signalkinds:SlowSink
            params: {{dir: "{tmp_path}", delay_s: 0.01}}
            inputs: {{value: {{from: src.value, policy: lossless, size: {backlog}}}}}
        """)
        + extra
    )
    path = tmp_path / "g.yaml"
    path.write_text(text)
    return path


@pytest.fixture
def start(tmp_path: Path) -> Iterator[object]:
    """``flowrt run`` (the console script) in a session of its own."""
    procs: list[subprocess.Popen[str]] = []

    def run(graph: Path, *options: str) -> subprocess.Popen[str]:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
        proc = subprocess.Popen(
            [*FLOWRT, "run", str(graph), "--no-ui", "--log-every", "60", *options],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,
        )
        procs.append(proc)
        return proc

    yield run
    for proc in procs:
        if proc.poll() is None or _group_alive(proc.pid):
            with _suppress():
                os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()


class _suppress:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return exc[0] is ProcessLookupError


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _group_members(pgid: int) -> list[str]:
    """The command lines of the group's processes still alive (what outlived the run)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if os.getpgid(int(entry.name)) == pgid:
                cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                alive.append(f"{entry.name}: {cmd.strip()[:120]}")
        except (ProcessLookupError, FileNotFoundError, PermissionError):
            continue
    return alive


def _wait_for(path: Path, proc: subprocess.Popen[str], timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"flowrt run ended (rc {proc.returncode}) before {path.name}")
        if time.monotonic() > end:
            pytest.fail(f"{path.name} never appeared")
        time.sleep(0.02)


def _ended(proc: subprocess.Popen[str], sig: int) -> tuple[int, str, float]:
    """Send ``sig``; the exit code, stderr and the seconds the exit took."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=60)
    took = time.monotonic() - t0
    return proc.returncode, err, took


def _nothing_left(pid: int) -> None:
    """No process of its group (workers, forkserver) and no shared-memory segment."""
    end = time.monotonic() + LEFTOVER_S
    while _group_alive(pid) and time.monotonic() < end:
        time.sleep(0.05)
    assert not _group_alive(pid), f"a process of the run outlived it: {_group_members(pid)}"
    assert [n for n in os.listdir("/dev/shm") if n.startswith(f"flowrt_{pid}_")] == []


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("after_s", [0.3, 0.8, 1.5])
def test_a_signal_at_start_up(tmp_path: Path, start: object, sig: int, after_s: float) -> None:
    proc = start(_graph(tmp_path))  # type: ignore[operator]
    time.sleep(after_s)
    code, err, took = _ended(proc, sig)
    name = signal.Signals(sig).name
    assert "Traceback" not in err, err
    if code == 128 + sig:  # before the run ran: importing, loading or setting up
        said = (f"{name} while ", f"{name} during ", f"{name} before the start")
        assert any(s in err for s in said), err
        assert f"exit {128 + sig}" in err
    else:  # it was running already (a fast machine): an orderly stop
        assert code == 0, err
        assert f"{name}: stopping the run" in err, err
    assert took < STOP_S, f"exit took {took:.2f} s:\n{err}"
    _nothing_left(proc.pid)


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_mid_run_stops_in_order(tmp_path: Path, start: object, sig: int) -> None:
    proc = start(_graph(tmp_path))  # type: ignore[operator]
    _wait_for(tmp_path / "sink.started", proc)
    time.sleep(0.3)
    code, err, took = _ended(proc, sig)
    assert code == 0, err
    assert f"{signal.Signals(sig).name}: stopping the run" in err
    assert "Traceback" not in err, err
    assert took < STOP_S, f"exit took {took:.2f} s:\n{err}"
    _nothing_left(proc.pid)


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_mid_drain_cuts_it_short(tmp_path: Path, start: object, sig: int) -> None:
    """``--duration`` ends the run; the sink's backlog (300 values at 10 ms each) keeps the
    drain busy for 3 s or more; the signal comes in the middle of it."""
    stats = tmp_path / "stats.json"
    options = ("--duration", "1", "--drain-timeout", "60", "--stats-json", str(stats))
    proc = start(_graph(tmp_path, backlog=300), *options)  # type: ignore[operator]
    _wait_for(tmp_path / "sink.started", proc)
    time.sleep(1.0 + 1.2)  # the run's second, then into the drain
    assert proc.poll() is None, "the drain should still be running"
    code, err, took = _ended(proc, sig)
    assert code == 0, err
    assert "during the drain: cut short" in err, err
    assert "Traceback" not in err, err
    assert took < STOP_S, f"exit took {took:.2f} s:\n{err}"
    edges = json.loads(stats.read_text())["edges"]
    edge = next(e for e in edges if e["name"].endswith("sink.value"))
    assert edge["drop_reasons"].get("interrupted", 0) > 0, edge
    assert edge["published"] == edge["delivered"] + edge["dropped"]
    _nothing_left(proc.pid)


def test_ctrl_c_in_a_slow_worker_setup_names_it(tmp_path: Path, start: object) -> None:
    """A worker's ``setup()`` that takes a minute: Ctrl-C ends the start at once, naming the
    node whose set-up it cut (it printed nothing for 25 s, then blamed the camera)."""
    proc = start(_graph(tmp_path, slow_setup=True))  # type: ignore[operator]
    _wait_for(tmp_path / "slow.setup", proc)
    code, err, took = _ended(proc, signal.SIGINT)
    assert code == 130, err
    assert re.search(r"SIGINT during set-up \(in setup\(\) of [\w, ]*\bslow\b", err), err
    assert "never delivered" not in err
    assert took < LIMIT_S, f"exit took {took:.2f} s:\n{err}"
    _nothing_left(proc.pid)


def test_kill_int_at_0_8_s_with_sigint_ignored_by_the_shell(tmp_path: Path) -> None:
    """The regression of issue 37 item 4: ``flowrt run graphs/cambada.yaml &`` from a script
    starts with SIGINT ignored (a non-interactive shell's background job); ``kill -INT`` at
    0.8 s was lost until the run's own handlers came, and the run went on to its end, exit 0.
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    proc = subprocess.Popen(
        [*FLOWRT, "run", str(_graph(tmp_path)), "--no-ui", "--duration", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        time.sleep(0.8)
        code, err, took = _ended(proc, signal.SIGINT)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert code in (130, 0), err
    assert "SIGINT" in err, err
    assert took < LIMIT_S, f"exit took {took:.2f} s:\n{err}"
    _nothing_left(proc.pid)


def test_nohup_keeps_sighup_ignored(tmp_path: Path) -> None:
    """``nohup flowrt run``: SIGHUP (the terminal closed) must not end the run."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    proc = subprocess.Popen(
        [*FLOWRT, "run", str(_graph(tmp_path)), "--no-ui", "--duration", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN),
    )
    try:
        _wait_for(tmp_path / "sink.started", proc)
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert proc.poll() is None, "SIGHUP ended a run started under nohup"
        code, err, _took = _ended(proc, signal.SIGTERM)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert code == 0, err
    assert "SIGHUP" not in err
    _nothing_left(proc.pid)


def test_a_signal_while_a_call_holds_the_loop_starts_no_call_after_it(
    tmp_path: Path, start: object
) -> None:
    """SIGINT during a 30 s call took 56 s: the source's timer, due behind the held loop,
    ran before the interrupt it was handed, and the drain called the node again on it."""
    graph = tmp_path / "held.yaml"
    graph.write_text(
        "nodes:\n"
        "  src: {kind: counter, trigger: {timer: 50ms}}\n"
        "  n:\n"
        "    kind: signalkinds:Holding\n"
        f'    params: {{dir: "{tmp_path}", hold_s: 0.6}}\n'
        "    inputs: {value: src.value}\n"
    )
    proc = start(graph)  # type: ignore[operator]
    calls = tmp_path / "n.calls"
    _wait_for(calls, proc)
    time.sleep(0.9)  # into the second call
    sent = time.time()
    code, err, took = _ended(proc, signal.SIGINT)
    assert code == 0, err
    starts = [float(x) for x in calls.read_text().split()]
    assert all(t < sent for t in starts), (sent, starts)
    assert took < 0.6 + STOP_S, err
