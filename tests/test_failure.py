"""Supervision (flowrt.supervision) and failure verdicts: back-off, give-up, log rate limit,
``Runtime.failures()``, ``stop_on_failure`` and the exit codes of ``flowrt run``.

Scheduler tests run on virtual time, so thousands of failures take milliseconds and nothing
depends on the machine's speed.
"""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.graph.spec import RestartPolicy
from flowrt.supervision import SUMMARY_INTERVAL, backoff_s, give_up_reason

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

from failkinds import AlwaysFails, FailsEveryOther, GivesUp, SetupFails  # noqa: E402

pytestmark = pytest.mark.timeout(60)


# --- the rule, as pure functions -------------------------------------------------------------


@pytest.mark.parametrize(
    ("consecutive", "expected_ms"),
    [(1, 100.0), (2, 200.0), (3, 400.0), (6, 3200.0), (7, 5000.0), (1025, 5000.0), (10**9, 5000.0)],
)
def test_backoff_doubles_then_caps_and_never_overflows(
    consecutive: int, expected_ms: float
) -> None:
    assert backoff_s(RestartPolicy(), consecutive) * 1000 == pytest.approx(expected_ms)


@pytest.mark.parametrize(
    ("policy", "consecutive", "restarts", "fatal", "gives_up"),
    [
        ({}, 1, 0, False, None),
        ({}, 9, 100, False, None),
        ({}, 10, 9, False, "10 consecutive failures"),
        ({"max_failures": 3}, 3, 2, False, "3 consecutive failures"),
        ({"max_failures": None}, 10**6, 10**6, False, None),
        ({"policy": "never"}, 1, 0, False, "restart policy never"),
        ({"max_restarts": 5}, 1, 5, False, "max_restarts 5"),
        ({}, 1, 0, True, "restarting cannot help"),
    ],
)
def test_give_up_reason(
    policy: dict[str, Any], consecutive: int, restarts: int, fatal: bool, gives_up: str | None
) -> None:
    why = give_up_reason(RestartPolicy(**policy), consecutive, restarts, fatal)
    if gives_up is None:
        assert why is None
    else:
        assert why is not None
        assert gives_up in why


# --- the scheduler applies it ----------------------------------------------------------------


async def test_1025th_consecutive_failure_does_not_overflow() -> None:
    """Driven by the failure count, not by waiting 85 minutes."""
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("bad", AlwaysFails, trigger={"timer": "10ms"}, restart={"max_failures": None})
    async with Runtime(g.build(), clock=clock) as rt:
        runner = rt.scheduler.runners["bad"]
        runner.supervisor.consecutive = 1023
        await clock.advance(0.015)  # the first activation fails: failure number 1024
        assert runner.supervisor.consecutive == 1024
        restarts = [e for e in rt.events if isinstance(e, flowrt.NodeRestarted)]
        await clock.advance(5.02)
        s = rt.stats().node("bad")
        restarts = [e for e in rt.events if isinstance(e, flowrt.NodeRestarted)]
        await clock.advance(5.02)
        assert rt.stats().node("bad").errors >= 2  # failure 1025 and on: still supervised
    assert s.state in ("backoff", "idle")
    assert restarts
    assert restarts[0].backoff_ms == pytest.approx(5000.0)


async def test_crash_loop_at_startup_is_given_up() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("dev", SetupFails, trigger={"timer": "10ms"}, restart={"max_failures": 3})
    g.add("ok", "counter", trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(15.0)
        before = rt.stats().node("dev")
        await clock.advance(15.0)
        s = rt.stats()
        failures = rt.failures()
        gave_up = [e for e in rt.events if isinstance(e, flowrt.NodeGaveUp)]
    dev = s.node("dev")
    assert dev.state == "failed"
    assert dev.errors == 3
    assert dev.restarts == 2
    assert "3 consecutive failures" in dev.reason
    assert "cannot open the device" in dev.reason
    assert [e.node for e in gave_up] == ["dev"]
    assert gave_up[0].reason == dev.reason
    assert [n.name for n in failures] == ["dev"]
    assert s.node("ok").completions >= 2990  # the rest of the graph kept running
    assert (dev.errors, dev.restarts) == (before.errors, before.restarts)  # down for good


@pytest.mark.parametrize("placement", ["process", "pool"])
async def test_crash_loop_in_a_worker_is_given_up(
    placement: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Real worker processes (real time): setup raising in the worker, bounded the same way,
    the worker's own traceback logged once."""
    caplog.set_level(logging.ERROR, logger="flowrt")
    g = GraphBuilder()
    policy = {"backoff": "10ms", "max_failures": 3}
    g.add("dev", SetupFails, trigger={"timer": "20ms"}, placement=placement, restart=policy)
    async with Runtime(g.build(), stop_on_failure=True) as rt:
        await rt.run(20.0)  # returns when the node is given up
        dev = rt.stats().node("dev")
    assert dev.state == "failed"
    assert dev.errors == 3
    assert "3 consecutive failures" in dev.reason
    assert "RuntimeError: cannot open the device" in dev.reason
    tracebacks = [r.getMessage() for r in caplog.records if "Traceback" in r.getMessage()]
    assert len(tracebacks) == 1
    assert "failkinds.py" in tracebacks[0]  # the worker's own stack, not the transport's


@pytest.mark.parametrize("placement", ["inline", "process"])
async def test_fatal_error_is_given_up_at_once(
    placement: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, logger="flowrt")
    g = GraphBuilder()
    g.add("cal", GivesUp, trigger={"timer": "20ms"}, placement=placement)
    async with Runtime(g.build(), stop_on_failure=True) as rt:
        await rt.run(20.0)  # returns when the node is given up
        cal = rt.stats().node("cal")
    assert (cal.state, cal.errors, cal.restarts) == ("failed", 1, 0)
    assert cal.reason == "FatalError: calibration file unusable"
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["node cal given up: FatalError: calibration file unusable"]


async def test_persistent_failure_is_given_up_by_default() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("bad", AlwaysFails, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(120.0)  # back-offs 0.1+0.2+...+5 s: given up after ~22 s
        bad = rt.stats().node("bad")
    assert bad.state == "failed"
    assert bad.errors == RestartPolicy().max_failures == 10
    assert "10 consecutive failures" in bad.reason


async def test_intermittent_failure_is_never_given_up() -> None:
    FailsEveryOther.calls = 0
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("flaky", FailsEveryOther, trigger={"timer": "10ms"}, restart={"max_failures": 2})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(5.0)
        flaky = rt.stats().node("flaky")
        assert rt.failures() == []
    assert flaky.state != "failed"
    assert flaky.errors >= 10
    assert flaky.completions >= 10


@pytest.mark.parametrize(
    ("kind", "seconds", "listed"),
    [
        (AlwaysFails, 0.5, True),  # 3 failures, in back-off, 7 short of its give-up
        (FailsEveryOther, 0.5, False),  # fails, and completes in between
    ],
)
async def test_a_node_that_never_completed_fails_the_run_before_its_give_up(
    kind: type[flowrt.Node], seconds: float, listed: bool
) -> None:
    """A run shorter than the give-up (10 failures, ~22 s of back-off) ended with exit 0
    while a node had failed every activation (a typo in an output name): no success."""
    FailsEveryOther.calls = 0
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("n", kind, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(seconds)
        failures = rt.failures()
    assert [n.name for n in failures] == (["n"] if listed else [])
    if listed:
        assert failures[0].state == "backoff"
        assert failures[0].reason == "last error: ValueError: boom"


async def test_failures_log_one_traceback_then_rate_limited_summaries(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    policy = {"backoff": "1ms", "max_backoff": "1ms", "max_failures": None}
    g.add("ball_fr", AlwaysFails, trigger={"timer": "10ms"}, restart=policy)
    caplog.set_level(logging.ERROR, logger="flowrt")
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(2.5 * SUMMARY_INTERVAL)
        errors = rt.stats().node("ball_fr").errors
    assert errors >= 2000  # one failure per 10 ms tick for 25 s
    texts = [r.getMessage() for r in caplog.records if r.name.startswith("flowrt")]
    tracebacks = [t for t in texts if "Traceback" in t]
    assert len(tracebacks) == 1
    assert "ValueError: boom" in tracebacks[0]
    summaries = [
        re.match(r"ball_fr: (\d+) more failures of the same kind in the last (\d+) s", t)
        for t in texts
    ]
    counts = [int(m.group(1)) for m in summaries if m]
    assert len(counts) == 3  # at 10 s and 20 s, then the rest at stop
    assert sum(counts) + 1 == errors  # every failure accounted for, none lost
    assert len(texts) <= 5


async def test_stop_on_failure_ends_run_at_once() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("dev", SetupFails, trigger={"timer": "10ms"}, restart={"policy": "never"})
    g.add("ok", "counter", trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock, stop_on_failure=True) as rt:
        await rt.run()  # no duration: returns only because the node failed
        assert [n.name for n in rt.failures()] == ["dev"]
    assert rt.failures()[0].state == "failed"  # still the verdict after stop


async def test_error_state_is_a_failure_until_cleared() -> None:
    class Source(flowrt.Node):
        tick = flowrt.Output(int)

        def process(self) -> int:
            if self.ctx.now() < 0.1:
                self.ctx.set_error("device unplugged")
            else:
                self.ctx.clear_error()
            return 1

    clock = VirtualClock()
    g = GraphBuilder()
    g.add("src", Source, trigger={"timer": "10ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.05)
        assert [(n.name, n.state, n.reason) for n in rt.failures()] == [
            ("src", "error", "device unplugged")
        ]
        await clock.advance(0.2)
        assert rt.failures() == []


# --- flowrt run: exit codes ------------------------------------------------------------------


def _run(args: list[str], timeout: float = 40) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(TESTS), "COLUMNS": "200"}
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


GRAPH = """\
nodes:
  src: {kind: counter, trigger: {timer: 20ms}}
  bad:
    kind: failkinds:%s
    trigger: {timer: 20ms}
    restart: {backoff: 10ms, max_failures: 3}
"""


@pytest.mark.parametrize(
    ("kind", "extra", "code", "stops_early"),
    [
        ("SetupFails", [], 1, True),
        ("AlwaysFails", [], 1, True),
        ("SetupFails", ["--keep-going"], 1, False),
        ("FailsEveryOther", [], 0, False),
    ],
)
def test_run_exit_codes(
    tmp_path: Path, kind: str, extra: list[str], code: int, stops_early: bool
) -> None:
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH % kind)
    stats = tmp_path / "stats.json"
    proc = _run(
        ["run", str(graph), "--duration", "3", "--no-ui", "--stats-json", str(stats), *extra]
    )
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stdout
    data = json.loads(stats.read_text())
    uptime = data["uptime"]
    bad = next(n for n in data["nodes"] if n["name"] == "bad")
    if code:
        assert "flowrt run: node bad failed: 3 consecutive failures" in proc.stderr
        assert bad["state"] == "failed"
        assert proc.stderr.count("Traceback") == 1  # one full traceback, then counted
        assert "NodeGaveUp bad 3 consecutive failures" in " ".join(proc.stdout.split())
    else:
        assert "flowrt run: node" not in proc.stderr
    if stops_early:
        assert uptime < 2.5
    else:
        assert uptime >= 2.9


# --- a process-placed node defined in a script without a __main__ guard ----------------------

SCRIPT = """\
import sys
import flowrt
from flowrt import Input, Node


class MySink(Node):
    value = Input(object)

    def process(self, value):
        return None


def main():
    g = flowrt.GraphBuilder("demo")
    g.add("src", "counter", trigger={"timer": "20ms"})
    g.add("sink", MySink, inputs={"value": "src.value"}, placement="%s")

    async def run():
        async with flowrt.Runtime(g.build(), stop_on_failure=True) as rt:
            await rt.run(1.0)
            print("completions", rt.stats().node("sink").completions)
            return rt.failures()

    failures = flowrt.run(run())
    for n in failures:
        print(f"{n.name} {n.state}: {n.reason}", file=sys.stderr)
    sys.exit(1 if failures else 0)


%s
"""


@pytest.mark.parametrize("placement", ["process", "pool"])
@pytest.mark.parametrize("guarded", [True, False])
def test_process_node_in_script_without_main_guard(
    tmp_path: Path, placement: str, guarded: bool
) -> None:
    script = tmp_path / "user_script.py"
    call = 'if __name__ == "__main__":\n    main()' if guarded else "main()"
    script.write_text(SCRIPT % (placement, call))
    proc = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=40, cwd=tmp_path
    )
    assert "Traceback" not in proc.stderr
    if guarded:
        assert proc.returncode == 0, proc.stderr
        assert int(proc.stdout.split()[-1]) >= 10
        return
    assert proc.returncode == 1
    # one clear message, logged once, then reported by the script: what to add, and where
    lines = [ln for ln in proc.stderr.splitlines() if "its node class is defined in" in ln]
    assert len(lines) == 2, proc.stderr
    assert 'under `if __name__ == "__main__":`' in lines[0]
    assert str(script) in lines[0]
    assert lines[1].startswith("sink failed: its node class is defined in")


# --- sources that are missing or fail look failed ---------------------------------------------


def _write_video(path: Path, n: int) -> None:
    import cv2
    import numpy as np

    w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 20, (64, 48))
    assert w.isOpened()
    for i in range(n):
        w.write(np.full((48, 64, 3), 10 * i, np.uint8))
    w.release()


SOURCE_GRAPH = """\
nodes:
  cam:
    kind: capture
    params: {source: "%s", fps: 20, pacing: fast, on_eof: exit, backoff: 50ms}
  sink: {kind: sink, inputs: {input: cam.frame}}
"""


@pytest.mark.parametrize(
    ("source", "message"),
    [
        (
            "file:missing.avi",
            "video file not found: {dir}/missing.avi (a relative path resolves "
            "against the graph file's directory, {dir})",
        ),
        ("file:{dir}/gone.avi", "video file not found: {dir}/gone.avi"),
        ("data/missing.avi", "video file not found: {dir}/data/missing.avi"),
        ("file:data", "{dir}/data is a directory, not a video file"),
    ],
)
def test_validate_reports_a_missing_file_source_located(
    tmp_path: Path, source: str, message: str
) -> None:
    (tmp_path / "data").mkdir()
    graph = tmp_path / "g.yaml"
    graph.write_text(SOURCE_GRAPH % source.format(dir=tmp_path))
    proc = _run(["validate", str(graph)])
    assert proc.returncode == 2
    want = f"{graph}:4:14: error: nodes.cam.params.source: {message.format(dir=tmp_path)}"
    assert want in " ".join(proc.stderr.split()), proc.stderr
    assert "Traceback" not in proc.stderr


def test_relative_paths_resolve_against_the_graph_file(tmp_path: Path) -> None:
    """The same graph runs from any working directory: its clip is found beside it."""
    (tmp_path / "media").mkdir()
    _write_video(tmp_path / "media" / "clip.avi", 12)
    graph = tmp_path / "g.yaml"
    graph.write_text(SOURCE_GRAPH % "file:media/clip.avi")
    stats = tmp_path / "stats.json"
    proc = _run(["run", str(graph), "--no-ui", "--duration", "20", "--stats-json", str(stats)])
    assert proc.returncode == 0, proc.stderr
    data = json.loads(stats.read_text())
    assert next(n for n in data["nodes"] if n["name"] == "sink")["completions"] == 12
    assert data["uptime"] < 15  # on_eof: exit ended the run


def test_source_that_never_delivers_fails_the_run(tmp_path: Path) -> None:
    graph = tmp_path / "g.yaml"
    graph.write_text(SOURCE_GRAPH % "camera:99")
    stats = tmp_path / "stats.json"
    proc = _run(["run", str(graph), "--no-ui", "--duration", "1", "--stats-json", str(stats)])
    assert proc.returncode == 1
    flat = " ".join(proc.stderr.split())
    assert "flowrt run: node cam in error: camera:99: never delivered a frame (" in flat
    assert "attempts failed; last error: cannot open camera 99" in flat
    assert "Traceback" not in proc.stderr
    assert "[ WARN" not in proc.stderr.replace("cam: opencv: [ WARN", "")  # never raw
    cam = next(n for n in json.loads(stats.read_text())["nodes"] if n["name"] == "cam")
    assert cam["state"] == "error"
    assert "never delivered a frame" in cam["reason"]


def test_process_node_defined_in_python_c_is_given_up_at_once() -> None:
    code = (SCRIPT % ("process", "main()")).replace("await rt.run(1.0)", "await rt.run(20.0)")
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=40, cwd=REPO
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr
    assert "sink failed: its node class is defined in an interactive session" in proc.stderr


async def test_params_changed_at_run_time_resolve_like_the_graph_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A mode (and set_params) that names a relative file: the graph file's directory too,
    whatever the working directory."""
    (tmp_path / "media").mkdir()
    for name in ("a.avi", "b.avi"):
        _write_video(tmp_path / "media" / name, 3)
    graph = tmp_path / "g.yaml"
    graph.write_text(
        (SOURCE_GRAPH % "file:media/a.avi").replace("on_eof: exit", "on_eof: loop")
        + "modes:\n  other:\n    nodes:\n      cam: {params: {source: file:media/b.avi}}\n"
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    async with Runtime.from_file(graph) as rt:
        cam = rt.scheduler.runners["cam"]
        assert cam.rnode.params.source == f"file:{tmp_path}/media/a.avi"  # type: ignore[attr-defined]
        rt.set_mode("other")
        assert cam.rnode.params.source == f"file:{tmp_path}/media/b.avi"  # type: ignore[attr-defined]
        rt.set_params("cam", {"source": "file:media/a.avi"})
        assert cam.rnode.params.source == f"file:{tmp_path}/media/a.avi"  # type: ignore[attr-defined]


async def _until(check: Any, seconds: float = 10.0) -> None:
    for _ in range(int(seconds / 0.02)):  # a bound, not a timing threshold
        if check():
            return
        await asyncio.sleep(0.02)


async def test_a_source_swapped_for_a_working_one_leaves_the_error_state(tmp_path: Path) -> None:
    """The verdict follows the node, not the instance: a camera that never delivered, swapped
    for a working file, is no longer in error once frames flow."""
    _write_video(tmp_path / "clip.avi", 5)
    g = GraphBuilder()
    params = {"source": "camera:99", "backoff": "30ms"}
    g.add("cam", "capture", params=params, trigger={"timer": "50ms"})
    async with Runtime(g.build()) as rt:
        await _until(lambda: rt.failures())
        assert [n.name for n in rt.failures()] == ["cam"]
        await rt.swap("cam", "capture", {"source": f"file:{tmp_path}/clip.avi", "on_eof": "loop"})
        await _until(lambda: not rt.failures())
        assert rt.failures() == []
        assert rt.stats().node("cam").completions > 0
    assert rt.failures() == []


class _OutOfDescriptors(flowrt.Node):
    """set-up fails with EMFILE for the first ``failures`` instances (a descriptor flood)."""

    tick = flowrt.Output(int)
    starts = 0

    def setup(self) -> None:
        type(self).starts += 1
        if type(self).starts <= 6:
            raise OSError(errno.EMFILE, "Too many open files")

    def process(self) -> int:
        return 1


@pytest.mark.parametrize(
    ("exc", "expected"),
    [
        (OSError(errno.EMFILE, "Too many open files"), True),
        (OSError(errno.ENOMEM, "Cannot allocate memory"), True),
        (OSError(errno.ENOENT, "No such file"), False),
        (ValueError("boom"), False),
    ],
)
def test_out_of_resources(exc: BaseException, expected: bool) -> None:
    from flowrt.supervision import out_of_resources

    assert out_of_resources(exc) is expected
    wrapped = RuntimeError("worker start failed")  # found through the cause too
    wrapped.__cause__ = exc
    assert out_of_resources(wrapped) is expected


async def test_out_of_descriptors_is_retried_until_it_recovers() -> None:
    """Six EMFILE failures in a row with max_failures 3: never given up, back once the
    descriptors are (the issue: worker restarts must recover once descriptors return)."""
    _OutOfDescriptors.starts = 0
    clock = VirtualClock()
    g = GraphBuilder()
    g.add(
        "dev",
        _OutOfDescriptors,
        trigger={"timer": "10ms"},
        restart={"max_failures": 3, "backoff": "10ms", "max_backoff": "50ms"},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(3.0)
        dev = rt.stats().node("dev")
    assert dev.errors == 6
    assert dev.state != "failed"
    assert dev.completions > 100


@pytest.mark.parametrize("placement", ["inline", "process"])
async def test_a_node_that_never_starts_is_given_up_after_three_start_failures(
    placement: str,
) -> None:
    """Issue 24: a node that cannot start (its set-up raises, a worker cannot import its
    module) ends ``failed`` within about a second by default, listed by ``rt.failures()``;
    it used to restart with back-off for ever and the run exited 0."""
    g = flowrt.GraphBuilder("never")
    g.add("bad", SetupFails, trigger={"timer": 10}, placement=placement)
    rt = flowrt.Runtime(g.build(), stop_on_failure=False)
    async with rt:
        for _ in range(100):
            await asyncio.sleep(0.1)
            if any(n.state == "failed" for n in rt.failures()):  # (listed from its first
                break  # failure: in back-off, never completed)
        (failed,) = rt.failures()
    assert failed.name == "bad"
    assert failed.state == "failed"
    assert "it never started" in failed.reason
    assert failed.errors == 3
