"""Every command's ``--json`` prints exactly one JSON document on stdout and nothing else
(issue 24: ``flowrt check G --measure 5s --json`` printed ``display: http://...`` first), and
``flowrt kinds`` lists and describes the node kinds."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

REPO = Path(__file__).resolve().parents[1]


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env=dict(os.environ, COLUMNS="80"),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("json")
    r = cli("record", "graphs/cambada.yaml", "-o", str(out), "--duration", "1", "--no-ui",
            "--no-display", "--topics", "front_cam.frame", "--deterministic")  # fmt: skip
    assert r.returncode == 0, r.stderr
    (s,) = out.glob("rec_*")
    return s


@pytest.mark.parametrize(
    "args",
    [
        ["kinds", "--json"],
        ["kinds", "arbiter", "--json"],
        ["check", "graphs/cambada.yaml", "--json"],
        ["check", "graphs/cambada.yaml", "--measure", "1s", "--json"],
        ["can", "analyse", "nodes/robot.dbc", "--bitrate", "250000", "--json"],
        ["info", "{session}", "--json"],
        ["replay", "{session}", "--graph", "graphs/cambada.yaml", "--deterministic", "--json"],
        ["schema", "stats"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_json_output_is_exactly_one_document(args: list[str], session: Path) -> None:
    r = cli(*[a.replace("{session}", str(session)) for a in args])
    assert r.returncode in (0, 1), r.stderr
    json.loads(r.stdout)  # the whole of stdout, nothing before or after


def test_every_command_with_json_is_covered() -> None:
    """A new --json option needs its case above."""
    from flowrt.cli import build_parser

    # ctl stats --json: tests/test_control.py; can stats --json: tests/test_can_*.py;
    # sync measure --json: tests/test_avsync.py; every subcommand's success and failure:
    # tests/test_cli_paths.py and tests/test_cli_json_runs.py (issue 43)
    ctl = {"stats", "timing", "mode", "modes", "events", "qos", "rtdb", "record", "swap", "reload"}
    covered = {
        "kinds", "examples", "check", "can analyse", "can analyze", "can stats", "info",
        "sync measure", "replay", "run", "record", "validate", "graph", "schema",
        "ctl",  # before its command (ctl --json stats): tests/test_cli_paths.py
        *(f"ctl {c}" for c in ctl),
    }  # fmt: skip
    parser = build_parser()
    found = set()
    for action in parser._subparsers._group_actions:  # type: ignore[union-attr]
        for name, sub in action.choices.items():
            opts = {o for a in sub._actions for o in a.option_strings}
            if "--json" in opts:
                found.add(name)
            for inner in sub._subparsers._group_actions if sub._subparsers else []:
                for sname, ssub in inner.choices.items():
                    if "--json" in {o for a in ssub._actions for o in a.option_strings}:
                        found.add(f"{name} {sname}")
    assert found <= covered, f"--json without a test: {found - covered}"


def test_kinds_lists_every_kind_in_one_line_each_at_80_columns() -> None:
    r = cli("kinds")
    assert r.returncode == 0
    lines = r.stdout.splitlines()
    assert all(len(line) <= 80 for line in lines)
    for kind in ("capture", "tracker", "arbiter", "recorder", "can"):
        assert any(line.split()[:1] == [kind] for line in lines), kind


def test_kinds_describes_ports_and_params() -> None:
    info = json.loads(cli("kinds", "capture", "--json").stdout)
    assert {o["name"] for o in info["outputs"]} == {"frame", "truth"}
    fps = next(p for p in info["params"] if p["name"] == "fps")
    assert fps["default"] == 20.0
    assert ">= 0.001" in fps["range"]
    rec = json.loads(cli("kinds", "recorder", "--json").stdout)
    assert rec["inputs"][0]["policy"] == "lossless"  # as the README's table says
    r = cli("kinds", "nosuchkind")
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1


def test_every_argument_has_help() -> None:
    """Issue 24: help text on every argument of every command."""
    import argparse

    from flowrt.cli import build_parser

    missing: list[str] = []

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    walk(sub, f"{prefix} {name}".strip())
            elif not isinstance(a, argparse._HelpAction | argparse._VersionAction) and not a.help:
                missing.append(f"{prefix}: {a.option_strings or a.dest}")

    walk(build_parser(), "")
    assert not missing, missing


@pytest.mark.parametrize(
    "args",
    [["kinds", "--json"], ["schema", "stats"], ["validate", "graphs/cambada.yaml", "--json"]],
)
def test_a_reader_that_closed_the_pipe_ends_the_command_quietly(args: list[str]) -> None:
    """``flowrt ... --json | head -c 50``: a BrokenPipeError traceback (3 runs of 6). The
    pipe's reading end is closed before the command writes: the first write fails."""
    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "flowrt.cli", *args],
            cwd=REPO,
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
        )
    finally:
        os.close(write)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 1
