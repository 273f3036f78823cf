"""Every ```python block of README.md runs as written.

Each block is a complete program: it is written to a file and run with this Python from a
copy of the repository's ``graphs/`` (the live view's fixed ports replaced by 0, any free
one, so that a run does not depend on port 8750 being free). A block that truly cannot run
here (it needs a camera, say) is preceded by the line ``<!-- readme: skip REASON -->``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SKIP = re.compile(r"<!--\s*readme:\s*skip\s+(.+?)\s*-->\s*$")


def python_blocks(text: str) -> list[tuple[int, str, str | None]]:
    """(line, code, skip reason) of every fenced ```python block."""
    blocks = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() == "```python":
            start = i + 1
            j = start
            while j < len(lines) and lines[j].strip() != "```":
                j += 1
            assert j < len(lines), f"README.md:{start}: unterminated ```python block"
            k = i - 1
            while k >= 0 and not lines[k].strip():
                k -= 1
            m = SKIP.search(lines[k]) if k >= 0 else None
            blocks.append((start, "\n".join(lines[start:j]) + "\n", m.group(1) if m else None))
            i = j
        i += 1
    return blocks


BLOCKS = python_blocks(README.read_text())


def test_the_readme_has_python_blocks_and_the_extractor_finds_them() -> None:
    assert len(BLOCKS) >= 4
    sample = (
        "x\n<!-- readme: skip needs a camera -->\n```python\nprint(1)\n```\n```python\n2\n```\n"
    )
    assert python_blocks(sample) == [(3, "print(1)\n", "needs a camera"), (6, "2\n", None)]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("readme")
    shutil.copytree(ROOT / "graphs", work / "graphs")
    for graph in (work / "graphs").glob("*.yaml"):
        text = graph.read_text()
        graph.write_text(re.sub(r"\bport: \d+", "port: 0", text))
    return work


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    ("line", "code", "skip"), BLOCKS, ids=[f"README.md:{b[0]}" for b in BLOCKS]
)
def test_readme_block_runs(line: int, code: str, skip: str | None, workdir: Path) -> None:
    if skip:
        pytest.skip(skip)
    script = workdir / f"readme_{line}.py"
    script.write_text(code)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    proc = subprocess.run(
        [sys.executable, script.name],
        cwd=workdir,
        env=env,
        capture_output=True,
        text=True,
        timeout=100,
    )
    where = f"README.md:{line}"
    assert proc.returncode == 0, f"{where} exited {proc.returncode}:\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, f"{where}:\n{proc.stderr}"
    assert " ERROR " not in proc.stderr, f"{where}:\n{proc.stderr}"
    assert proc.stdout.strip(), f"{where} printed nothing: a block shows its result"
