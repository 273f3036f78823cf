"""The ``flowrt`` command: validate, graph and run, as a user types them.

Most tests start the real command (``python -m flowrt.cli``) in a subprocess, to see its exit
code and its output exactly as a shell would; the per-fixture exit-code table runs
``flowrt.cli.main`` in-process to stay fast.
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
if str(TESTS) not in sys.path:  # for the typed test kinds, `graphkinds:FrameSource` etc.
    sys.path.insert(0, str(TESTS))

from flowrt import cli  # noqa: E402

GRAPHS = Path("tests/graphs")  # relative to REPO: short paths in the output
_EXPECT = re.compile(r"^#\s*expect:\s*(\d+)(?::(\d+))?\s+(.+?)\s*$", re.MULTILINE)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), env.get("PYTHONPATH")) if p)
    env["COLUMNS"] = "200"
    return env


def flowrt(
    *args: str, timeout: float = 30, env_columns: str | None = None
) -> subprocess.CompletedProcess[str]:
    env = _env()
    if env_columns is not None:
        env["COLUMNS"] = env_columns
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _flat(text: str) -> str:
    """Output with line wrapping undone, so a message is found whatever the terminal width."""
    return " ".join(text.split())


# --- validate --------------------------------------------------------------------------------


def test_validate_bad_file_exits_2_listing_every_error() -> None:
    path = GRAPHS / "invalid-many-errors.yaml"
    proc = flowrt("validate", str(path))
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    expected = _EXPECT.findall((REPO / path).read_text())
    starts = [line for line in proc.stderr.splitlines() if line.startswith(f"{path}:")]
    assert len(starts) == len(expected)
    for line, col, text in expected:
        assert f"{path}:{line}:{col}: error:" in proc.stderr
        assert _flat(text) in _flat(proc.stderr)
    assert f"{len(expected)} errors" in proc.stderr


def test_validate_yaml_syntax_error_exits_2_without_traceback() -> None:
    proc = flowrt("validate", str(GRAPHS / "invalid-yaml-syntax.yaml"))
    assert proc.returncode == 2
    assert "Traceback" not in proc.stdout + proc.stderr
    assert f"{GRAPHS / 'invalid-yaml-syntax.yaml'}:7:6: error: YAML syntax" in proc.stderr


def test_validate_good_file_exits_0() -> None:
    proc = flowrt("validate", str(GRAPHS / "valid-frames.yaml"))
    assert proc.returncode == 0, proc.stderr
    assert "ok (4 nodes, 3 edges)" in proc.stdout
    assert proc.stderr == ""


def test_validate_warning_is_printed_and_passes() -> None:
    path = GRAPHS / "valid-deadline-warning.yaml"
    proc = flowrt("validate", str(path))
    assert proc.returncode == 0, proc.stderr
    assert f"{path}:10:5: warning:" in proc.stderr
    assert "deadline 25 ms is longer than the period 20 ms" in _flat(proc.stderr)


@pytest.mark.parametrize("command", ["validate", "graph", "run"])
def test_missing_file_exits_2_with_a_clear_message(command: str) -> None:
    proc = flowrt(command, "no/such/graph.yaml")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stdout + proc.stderr
    assert "no/such/graph.yaml" in proc.stderr
    assert "cannot read graph file: No such file or directory" in _flat(proc.stderr)


@pytest.mark.parametrize(
    "path", sorted((REPO / GRAPHS).glob("invalid-*.yaml")), ids=lambda p: p.stem
)
def test_every_invalid_fixture_exits_2_with_its_locations(
    path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    for line, col, _ in _EXPECT.findall(path.read_text()):
        assert f"{path}:{line}:{col}: error:" in err


# --- graph -----------------------------------------------------------------------------------


def _cells(line: str, sep: str = "│") -> list[str]:
    return [c.strip() for c in line.strip().strip(sep).split(sep)]


def _table_row(output: str, name: str) -> list[str]:
    """The cells after the node name and priority of ``name``'s row in a rich table."""
    for line in output.splitlines():
        cells = _cells(line)
        if cells and cells[0] == name and len(cells) > 2:
            return cells[2:]
    raise AssertionError(f"no row {name!r} in:\n{output}")


def _stat(output: str, node: str, column: str) -> str:
    """One cell of the final statistics table, found by its (one-word, leading) column header."""
    lines = output.splitlines()
    header = next(line.split() for line in lines if line.split()[:1] == ["node"])
    row = next(c for line in lines if (c := line.split()) and c[0] == node)
    return row[header.index(column)]


def test_graph_prints_topology_and_hyperperiod_activation_table() -> None:
    proc = flowrt("graph", str(GRAPHS / "valid-frames.yaml"))
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "graph frames:" in out
    assert any(line.split() == ["cam.frame", "every.frame", "latest"] for line in out.splitlines())
    assert "hyperperiod of cam.frame (8 ticks of frame (10 ms))" in _flat(out)
    table = out[out.index("activations over one hyperperiod of cam.frame") :]
    table = table[: table.index("activations over", 1)]  # the timers' table follows
    rows = {c[0]: c[1:] for line in table.splitlines() if (c := line.split())}
    # Readers of cam at (period, phase) = (1, 0), (4, 1), (8, 3), in priority order.
    assert rows["every"][1:] == ["X"] * 8
    assert rows["fourth"][1:] == [".", "X", ".", ".", ".", "X", ".", "."]
    assert rows["eighth"][1:] == [".", ".", ".", "X", ".", ".", ".", "."]
    assert rows["load"] == ["1", "2", "1", "2", "1", "2", "1", "1"]
    order = [c[0] for line in table.splitlines() if (c := line.split())]
    assert order.index("every") < order.index("fourth") < order.index("eighth")
    assert "cam" not in order  # the source is not its own reader


def test_graph_reads_at_80_columns_and_piped() -> None:
    """Issue 24: 'flowrt graph' was truncated at 80 columns (a…) and 600 columns wide piped."""
    for columns in ("80", "200"):
        proc = flowrt("graph", str(REPO / "graphs" / "cambada.yaml"), env_columns=columns)
        assert proc.returncode == 0
        assert "…" not in proc.stdout
        assert max(len(line) for line in proc.stdout.splitlines()) <= int(columns)


def test_graph_shows_an_import_as_its_key() -> None:
    """(the class behind it: ``flowrt.remote._bridge:RemoteSource``)"""
    proc = flowrt("graph", str(REPO / "graphs" / "zenoh_base.yaml"), env_columns="200")
    assert proc.returncode == 0, proc.stderr
    (row,) = [
        c
        for line in proc.stdout.splitlines()
        if (c := line.split())[:2] == ["remote_ball", "import"]
    ]
    assert row[2] == "robot1/front/ball"
    assert "_bridge" not in proc.stdout


def test_activation_table_of_timers_uses_their_common_tick() -> None:
    from flowrt import Graph
    from flowrt.analysis import activation_tables

    graph = Graph.from_text(
        "nodes:\n"
        "  fast: {kind: counter, trigger: {timer: 10ms}, priority: 30}\n"
        "  slow: {kind: counter, trigger: {timer: 20ms, phase: 5ms}, priority: 20}\n"
        "  slowest: {kind: counter, trigger: {timer: 40ms, phase: 15ms}, priority: 10}\n"
    )
    (table,) = activation_tables(graph)
    assert (table.clock, table.unit, table.ticks) == ("timers", "5 ms", 8)
    marks = {name: "".join("X" if a else "." for a in active) for name, _, active in table.rows}
    assert marks == {"fast": "X.X.X.X.", "slow": ".X...X..", "slowest": "...X...."}
    assert table.load() == [1, 1, 1, 1, 1, 1, 1, 0]


# --- run -------------------------------------------------------------------------------------


def test_run_for_a_duration_writes_statistics_json(tmp_path: Path) -> None:
    out = tmp_path / "stats.json"
    proc = flowrt(
        "run", str(GRAPHS / "valid-frames.yaml"), "--duration", "1", "--no-ui",
        "--stats-json", str(out),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    stats = json.loads(out.read_text())
    assert stats["graph"] == "frames"
    counts = {n["name"]: n["activations"] for n in stats["nodes"]}
    assert set(counts) == {"cam", "every", "fourth", "eighth"}
    assert all(c > 0 for c in counts.values()), counts
    # Every frame reaches `every`; `eighth` runs on one frame in eight.
    assert counts["every"] > counts["fourth"] > counts["eighth"]
    assert all(n["errors"] == 0 for n in stats["nodes"])


def test_run_stops_cleanly_on_sigint() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "flowrt.cli", "run", str(GRAPHS / "valid-minimal.yaml"),
         "--no-ui", "--log-every", "0.25"],
        cwd=REPO,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    err: list[str] = []

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            err.append(line)
            lines.put(line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    started = time.monotonic()
    try:
        # The first periodic summary means the runtime is up and its signal handlers are set.
        try:
            while "act=" not in lines.get(timeout=20):
                pass
        except queue.Empty:
            pytest.fail("no summary line from flowrt run --no-ui:\n" + "".join(err))
        time.sleep(max(0.0, 1.5 - (time.monotonic() - started)))
        proc.send_signal(signal.SIGINT)
        stdout, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(timeout=5)
    stderr = "".join(err)
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stdout + stderr
    # The final table: both nodes, with their activation counts.
    assert "flowrt · minimal" in stdout
    assert int(_stat(stdout, "tick", "act")) > 0
    assert int(_stat(stdout, "out", "act")) > 0


def test_run_spin_and_fair_share_scheduling(tmp_path: Path) -> None:
    """--spin is accepted; the loop and the pinned, spinning worker report what they got."""
    out = tmp_path / "stats.json"
    proc = flowrt(
        "run", str(GRAPHS / "valid-worker-options.yaml"), "--duration", "1", "--no-ui",
        "--spin", "200us", "--stats-json", str(out),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    stats = json.loads(out.read_text())
    assert stats["loop_scheduling"].startswith("nice ")
    loop_nice = int(stats["loop_scheduling"].split()[1].rstrip(","))
    node = {n["name"]: n for n in stats["nodes"]}["out"]
    assert node["activations"] > 20  # of 50 in the fixed 1 s: room for a loaded machine
    assert node["errors"] == 0
    # the only worker: the top rank, 3 nice levels above the loop (or 0), whatever the
    # priority of the inline node (it runs in the loop)
    assert node["granted"] == f"nice {max(loop_nice, min(loop_nice + 3, 0))}, cpus 0"


@pytest.mark.parametrize("value", ["fast", "20ms", "-1ms"])
def test_run_rejects_a_bad_spin(value: str) -> None:
    proc = flowrt("run", str(GRAPHS / "valid-minimal.yaml"), "--spin", value)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stdout + proc.stderr
    assert "--spin" in proc.stderr
