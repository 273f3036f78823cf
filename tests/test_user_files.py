"""What users bring (issue 24): their own node modules beside the graph, run from anywhere.

- ``kind: mynodes:Motion`` with ``mynodes.py`` beside the graph file imports without
  ``PYTHONPATH``, in the main process and in worker processes (placement: process);
- an import that fails says where it looked;
- the folder that holds a clone named ``flowrt/`` (a namespace package there) does not
  shadow the installed flowrt in the workers.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

MODULE = """
from flowrt import Input, Node, Output


class Motion(Node):
    out = Output(object)

    def process(self):
        return {"v": 1.0}


class Heavy(Node):
    x = Input(object)
    out = Output(object)

    def process(self, x):
        return x
"""

GRAPH = """\
name: user
nodes:
  m: {kind: "mynodes:Motion", trigger: {timer: 50ms}}
  h: {kind: "mynodes:Heavy", placement: process, inputs: {x: m.out}}
"""


def flowrt(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(
        [str(Path(sys.executable).with_name("flowrt")), *args],  # the console script users type
        cwd=cwd,
        env=dict(env, COLUMNS="200"),
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.fixture
def project(tmp_path: Path) -> Path:
    d = tmp_path / "robot"
    d.mkdir()
    (d / "mynodes.py").write_text(MODULE)
    (d / "graph.yaml").write_text(GRAPH)
    return d


def test_a_kind_beside_the_graph_runs_inline_and_in_a_worker_from_another_folder(
    project: Path, tmp_path: Path
) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "flowrt").mkdir()  # the parent folder of a clone named flowrt/
    stats = tmp_path / "stats.json"
    r = flowrt(
        "run", str(project / "graph.yaml"), "--duration", "1", "--no-ui", "--no-display",
        "--stats-json", str(stats), cwd=elsewhere,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "cannot import" not in r.stderr
    import json

    nodes = {n["name"]: n for n in json.loads(stats.read_text())["nodes"]}
    # of 20 in the fixed 1 s (50 ms): room for a loaded machine's late ticks
    assert nodes["m"]["completions"] >= 10
    assert nodes["h"]["completions"] >= 10  # in a worker process
    assert nodes["h"]["state"] == "idle"


def test_an_import_that_fails_says_where_it_looked(project: Path) -> None:
    (project / "graph.yaml").write_text(GRAPH.replace("mynodes:Motion", "nomodule:Motion"))
    r = flowrt("validate", str(project / "graph.yaml"), cwd=project.parent)
    assert r.returncode == 2
    assert "nomodule" in r.stdout + r.stderr
    assert f"beside the graph file ({project})" in r.stdout + r.stderr


def test_a_recorder_path_resolves_beside_the_graph(tmp_path: Path) -> None:
    d = tmp_path / "robot"
    d.mkdir()
    (d / "rec.yaml").write_text(
        "nodes:\n"
        "  tick: {kind: counter, trigger: {timer: 50ms}}\n"
        "  rec: {kind: recorder, params: {path: recs, name: run}, inputs: {tick: tick.value}}\n"
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = flowrt("run", str(d / "rec.yaml"), "--duration", "0.5", "--no-ui", cwd=elsewhere)
    assert r.returncode == 0, r.stderr
    assert list((d / "recs").glob("run_*/*.mcap"))
    assert not (elsewhere / "recs").exists()
