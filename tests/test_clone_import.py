"""Issue 43: ``import flowrt`` in the folder that holds a clone named ``flowrt/`` found the
clone's folder, an empty namespace package without ``Runtime``. The clone's root
``__init__.py`` loads the installed flowrt in its place, or says what to do."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.subprocess

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def holder(tmp_path: Path) -> Path:
    (tmp_path / "flowrt").symlink_to(REPO, target_is_directory=True)
    return tmp_path


def test_the_installed_flowrt_is_imported_not_the_clone_folder(holder: Path) -> None:
    code = "import flowrt, flowrt.cli; print(flowrt.Runtime.__name__, flowrt.__file__)"
    r = subprocess.run([sys.executable, "-c", code], cwd=holder, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    name, where = r.stdout.split()
    assert name == "Runtime"
    assert Path(where).name == "__init__.py"
    assert Path(where).parent.name == "flowrt"
    assert Path(where).resolve() != (REPO / "__init__.py").resolve()


def test_without_flowrt_installed_the_import_says_what_to_do(holder: Path) -> None:
    # -S: no site-packages, so no installed flowrt (as a system Python without it)
    r = subprocess.run(
        [sys.executable, "-S", "-c", "import flowrt"], cwd=holder, capture_output=True, text=True
    )
    assert r.returncode == 1
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: 'import flowrt' found ")
    assert "a flowrt source checkout, and flowrt is not installed in this Python" in last
