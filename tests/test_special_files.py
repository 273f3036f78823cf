"""Only regular files are read, sizes checked first (issue 32 item 5): ``/dev/zero``, a FIFO
or an oversized file given to any command or graph param ends at once with exit 2 (or a
located validation error), never a hang or gigabytes read."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from flowrt.files import NotARegularFile, read_bytes

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    p = tmp_path / "graph.yaml"
    os.mkfifo(p)
    return p


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,  # a hang fails here
    )


@pytest.mark.parametrize(
    "command",
    [
        ["validate", "{path}"],
        ["run", "{path}", "--no-ui", "--duration", "1"],
        ["graph", "{path}"],
        ["check", "graphs/cambada.yaml", "--wcet-from", "{path}"],
    ],
)
@pytest.mark.parametrize("which", ["/dev/zero", "fifo"])
def test_special_files_end_at_once_with_exit_2(command: list[str], which: str, fifo: Path) -> None:
    path = "/dev/zero" if which == "/dev/zero" else str(fifo)
    r = cli(*[a.replace("{path}", path) for a in command])
    assert r.returncode == 2, r.stdout + r.stderr
    assert "not a regular file" in r.stdout + r.stderr
    assert "Traceback" not in r.stderr


def test_a_large_graph_file_is_refused_before_it_is_read(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(1 << 30)  # 1 GiB, sparse: costs nothing unless read
    r = cli("run", str(big), "--no-ui", "--duration", "1")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize(
    ("source", "message"),
    [
        ("script:/dev/zero", "a device"),
        ("script:{fifo}", "a FIFO"),
        ("script:missing.csv", "not found"),
    ],
)
def test_a_joystick_script_must_be_a_regular_file(
    tmp_path: Path, fifo: Path, source: str, message: str
) -> None:
    g = tmp_path / "joy.yaml"
    g.write_text(
        "nodes:\n  joy:\n    kind: joystick\n"
        f'    params: {{source: "{source.replace("{fifo}", str(fifo))}"}}\n'
    )
    r = cli("validate", str(g))
    assert r.returncode == 2, r.stdout
    assert message in r.stdout + r.stderr
    assert "joy.yaml:4:" in r.stdout + r.stderr  # located at the param


def test_a_joystick_script_resolves_beside_the_graph(tmp_path: Path) -> None:
    (tmp_path / "drive.csv").write_text("time,x,button:a\n0,0,0\n1,0.5,1\n")
    g = tmp_path / "joy.yaml"
    g.write_text('nodes:\n  joy: {kind: joystick, params: {source: "script:drive.csv"}}\n')
    r = cli("validate", str(g))
    assert r.returncode == 0, r.stdout + r.stderr


def test_read_bytes_refuses_what_is_over_its_limit(tmp_path: Path) -> None:
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert read_bytes(p, 100) == b"x" * 100
    with pytest.raises(NotARegularFile, match="more than the 99"):
        read_bytes(p, 99)
