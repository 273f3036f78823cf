"""``flowrt record --deterministic`` and ``flowrt replay --deterministic`` as a user runs them,
on the CAMBADA graph: identical against the same graph, a divergence at ``ball_fr`` (the same
on every run) against a copy whose ``ball_fr`` looks for another object."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO, FlowrtCli

pytestmark = [pytest.mark.subprocess, pytest.mark.slow]


async def test_nodes_in_workers_replay_what_they_computed_inline(tmp_path: Path) -> None:
    """ctx.now(), ctx.random and ctx.input_time reach a worker process as recorded: the
    outputs of nodes recorded inline (each depends on all three) replay identical in workers."""
    from test_determinism import Acc, Pair, Ticker, case_timers, record

    import flowrt
    from flowrt.graph._resolve import resolve
    from flowrt.graph.spec import Placement

    graph, session = await record(tmp_path, case_timers)
    spec = graph.spec
    placed = {
        name: n.model_copy(update={"placement": Placement.process})
        if name in ("slow", "pair")
        else n
        for name, n in spec.nodes.items()
    }
    kinds = {f"test_determinism:{c.__name__}": c for c in (Acc, Pair, Ticker)}
    workers = resolve(spec.model_copy(update={"nodes": placed}), kinds=kinds)
    async with flowrt.replay(session, workers) as rp:
        report = await rp.run()
    assert report.identical, report.first_divergence
    assert report.compared == report.activations > 20


KEYS = {
    "identical", "activations", "compared", "first_divergence", "wall_s", "recorded_s", "log_cut"
}  # fmt: skip


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """cambada.yaml recorded 1.5 s with --deterministic (once for the module)."""
    out = tmp_path_factory.mktemp("det")
    r = subprocess.run(
        [
            *(sys.executable, "-m", "flowrt.cli", "record", str(REPO / "graphs/cambada.yaml")),
            *("-o", str(out), "--deterministic", "--duration", "1.5", "--no-ui", "--no-display"),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    return out / "rec_001"


def other_object(repo: Path, tmp_path: Path) -> Path:
    """A copy of cambada.yaml whose ball_fr looks for the yellow goal instead."""
    spec = yaml.safe_load((repo / "graphs/cambada.yaml").read_text())
    spec["nodes"]["ball_fr"]["params"]["object"] = "yellow_goal"
    path = tmp_path / "cambada-other.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def test_identical_against_the_recorded_graph(session: Path, flowrt_cli: FlowrtCli) -> None:
    r = flowrt_cli(
        "replay", str(session), "--graph", "graphs/cambada.yaml", "--deterministic", "--check",
        "--json",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert set(result) == KEYS
    assert result["identical"] is True
    assert result["first_divergence"] is None
    assert result["compared"] == result["activations"] > 50
    assert result["recorded_s"] > 1.0
    r = flowrt_cli("replay", str(session), "--graph", "graphs/cambada.yaml", "--deterministic")
    assert r.returncode == 0, r.stderr
    assert "identical" in r.stdout
    assert "ball_fr" in r.stdout


def test_another_object_diverges_at_ball_fr_the_same_way_every_time(
    session: Path, flowrt_cli: FlowrtCli, repo: Path, tmp_path: Path
) -> None:
    graph = other_object(repo, tmp_path)
    runs = [
        flowrt_cli(
            "replay", str(session), "--graph", str(graph), "--deterministic", "--check", "--json"
        )
        for _ in range(2)
    ]
    for r in runs:
        assert r.returncode == 1, r.stderr
    first = [json.loads(r.stdout)["first_divergence"] for r in runs]
    assert first[0] == first[1]
    # exit 1 with "error", as every --json failure (it had the verdict alone)
    error = json.loads(runs[0].stdout)["error"]
    assert error["message"].startswith("flowrt replay: diverged at ball_fr.detection seq 1")
    assert first[0]["node"] == "ball_fr"
    assert first[0]["port"] == "detection"
    assert first[0]["seq"] == 1
    r = flowrt_cli("replay", str(session), "--graph", str(graph), "--deterministic", "--check")
    assert r.returncode == 1
    assert "diverged at ball_fr.detection seq 1" in r.stdout
    assert "recorded: " in r.stdout  # the recording holds ball_fr's detections
    assert '"object": "yellow_goal"' in r.stdout


def test_a_cut_log_is_not_identical_and_says_how_much_was_compared(
    session: Path, flowrt_cli: FlowrtCli, tmp_path: Path
) -> None:
    """A recording cut short (a killed run, a full disk) replayed with exit 0 and
    "identical": what it lost was never compared (issue 37 item 10)."""
    cut = tmp_path / session.name
    shutil.copytree(session, cut)
    mcap = next(cut.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) * 2 // 3])
    args = ("replay", str(cut), "--graph", "graphs/cambada.yaml", "--deterministic", "--check")
    r = flowrt_cli(*args, "--json")
    assert r.returncode == 1, r.stderr
    result = json.loads(r.stdout)
    assert result["identical"] is False
    assert result["first_divergence"] is None
    assert result["log_cut"]
    assert result["compared"] > 0
    r = flowrt_cli(*args)
    assert r.returncode == 1
    assert "not identical: the log was cut" in r.stdout
    assert f"{result['compared']} outputs compared over the" in r.stdout
    assert "identical: every" not in r.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--deterministic"], "needs --graph"),
        (["--deterministic", "--graph", "graphs/cambada.yaml", "--rate", "2"], "--rate"),
        (["--inline"], "goes with --deterministic"),  # --json: any replay (issue 43)
        (["--deterministic", "--graph", "nothere.yaml"], "nothere.yaml"),
    ],
)
def test_bad_arguments_are_one_line_exit_2(
    session: Path, flowrt_cli: FlowrtCli, args: list[str], message: str
) -> None:
    r = flowrt_cli("replay", str(session), *args)
    assert r.returncode == 2
    assert message in r.stderr
    assert "Traceback" not in r.stderr


def test_a_plain_recording_is_refused_in_one_line(flowrt_cli: FlowrtCli, tmp_path: Path) -> None:
    r = flowrt_cli(
        "record", "graphs/cambada.yaml", "-o", str(tmp_path), "--duration", "0.5", "--no-ui",
        "--no-display", "--topics", "front_cam.*",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = flowrt_cli(
        "replay", str(tmp_path / "rec_001"), "--graph", "graphs/cambada.yaml", "--deterministic"
    )
    assert r.returncode == 2
    assert "not a deterministic recording" in r.stderr
    assert "Traceback" not in r.stderr
