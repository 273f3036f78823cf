"""Issue 43: ``--json`` on the commands that run a graph (``run``, ``record``, ``replay``,
``info``/``sync`` of what was recorded) and on every ``ctl`` subcommand against a running
graph: exactly one JSON document on stdout each time, a result on success and an ``error``
on failure, with the exit code of the run. (The failure paths that start nothing, and the
commands that run nothing, are in tests/test_cli_paths.py.)"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from conftest import flowrt_running

from flowrt.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.timeout(300)]

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"

GRAPH = """\
name: jsonruns
nodes:
  cam: {kind: capture, params: {source: "synthetic:soccer", fps: 10, size: [32, 24]}}
  tick: {kind: counter, trigger: {timer: 50ms}}
  out: {kind: sink, inputs: {input: tick.value}}
modes:
  fast:
    nodes:
      tick: {timer: 20ms}
"""


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env={**os.environ, "COLUMNS": "80", "PYTHONPATH": str(TESTS)},
        capture_output=True,
        text=True,
        timeout=240,
    )


def one_document(r: subprocess.CompletedProcess[str]) -> Any:
    return json.loads(r.stdout)  # the whole of stdout, nothing before or after


@pytest.fixture(scope="module")
def graph(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("g") / "g.yaml"
    path.write_text(GRAPH)
    return path


def test_run_record_replay_info_sync_print_one_document(graph: Path, tmp_path: Path) -> None:
    r = cli("run", str(graph), "--duration", "1", "--json")
    doc = one_document(r)
    assert r.returncode == 0, r.stderr
    assert doc["exit_code"] == 0
    assert {n["name"] for n in doc["stats"]["nodes"]} == {"cam", "tick", "out"}
    assert "error" not in doc

    r = cli("record", str(graph), "-o", str(tmp_path), "--duration", "1", "--json")
    doc = one_document(r)
    assert r.returncode == 0, r.stderr
    session = doc["session"]
    assert Path(session).is_dir()
    assert {s["topic"] for s in doc["recording"]["streams"]} >= {"cam.frame", "tick.value"}
    assert "recording" in r.stderr  # what is said besides the result goes to stderr

    r = cli("info", session, "--json")
    assert r.returncode == 0, r.stderr
    assert one_document(r)["messages"] > 0

    r = cli("replay", session, "--duration", "0.5", "--json")
    doc = one_document(r)
    assert r.returncode == 0, r.stderr
    assert "cam.frame" in doc["streams"]
    assert doc["stats"]["nodes"]

    # no LED in the synthetic scene: nothing paired is exit 1 with the result, not an error
    r = cli("sync", "measure", session, "--video", "cam.frame", "--video", "cam.frame", "--json")
    doc = one_document(r)
    assert r.returncode in (0, 1), r.stderr
    assert "error" not in doc
    r = cli("sync", "measure", session, "--video", "nope", "--audio", "tick.value", "--json")
    assert r.returncode == 2
    assert "nope" in one_document(r)["error"]["message"]


def test_a_run_that_fails_has_its_statistics_and_the_error(tmp_path: Path) -> None:
    path = tmp_path / "f.yaml"
    path.write_text(
        "nodes:\n  bad: {kind: 'failkinds:GivesUp', trigger: {timer: 20ms}}\n"
        "  t: {kind: counter, trigger: {timer: 20ms}}\n"
    )
    r = cli("run", str(path), "--duration", "2", "--json")
    doc = one_document(r)
    assert r.returncode == 1
    assert doc["exit_code"] == 1
    assert "node bad failed" in doc["error"]["message"]
    assert {n["name"] for n in doc["stats"]["nodes"]} == {"bad", "t"}


async def test_every_ctl_subcommand_prints_one_document(
    graph: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ("run", str(graph), "--control", "127.0.0.1:0", "--no-ui")
    async with flowrt_running(*args, "--recordings", str(tmp_path)) as run:
        found = await run.addresses(url=r"control endpoint (http://\S+)")

        async def ctl(*argv: str) -> tuple[int, Any]:
            code = await asyncio.to_thread(main, ["ctl", "--url", found["url"], *argv, "--json"])
            return code, json.loads(capsys.readouterr().out)

        for argv in (
            ["stats"],
            ["modes"],
            ["events", "-n", "5"],
            ["qos"],
            ["rtdb"],
            ["timing", "tick", "--timer", "40ms"],
            ["mode", "fast"],
            ["record", "start"],
            ["record", "stop"],
            ["swap", "out", "sink"],
            ["reload", "out"],
        ):
            code, doc = await ctl(*argv)
            assert code == 0, (argv, doc)
            assert "error" not in doc, argv
        code, doc = await ctl("mode", "nosuchmode")
        assert code == 1
        assert "nosuchmode" in doc["error"]["message"]
        code, doc = await ctl("timing", "nosuchnode", "--period", "2")
        assert code == 1
        assert "nosuchnode" in doc["error"]["message"]
        await run.stop()


def test_check_measure_takes_the_run_options(tmp_path: Path) -> None:
    """Issue 43: `check --measure ... --display-port` was refused, and the measuring run bound
    the live view's port anyway; now it runs as `flowrt run` would, with the options given."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = tmp_path / "d.yaml"
        path.write_text(
            GRAPH.split("modes:")[0]
            + f"  view: {{kind: display, params: {{port: {port}}}, inputs: {{cam: cam.frame}}}}\n"
        )
        stats = tmp_path / "stats.json"
        r = cli("check", str(path), "--measure", "1s", "--no-display", "--stats-json", str(stats),
                "--cpus", "2", "--json")  # fmt: skip
        doc = one_document(r)
        assert r.returncode in (0, 1), r.stderr  # 1: a node without a deadline has no bound
        assert "error" not in doc
        assert {t["name"] for t in doc["tasks"]} >= {"cam", "tick"}
        assert "view" not in {t["name"] for t in doc["tasks"]}  # the analysis of the run
        assert "display:" not in r.stderr
        assert stats.exists()  # --stats-json of the measuring run

        r = cli("check", str(path), "--measure", "1s", "--json")  # the view's port is taken
        assert r.returncode == 1
        assert "display 'view'" in one_document(r)["error"]["message"]
