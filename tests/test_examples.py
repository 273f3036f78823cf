"""``flowrt examples``: the example graphs a wheel's user has without a clone."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import pytest
from rich.console import Console

from flowrt.cli import main
from flowrt.cli.common import load

GRAPHS = Path(__file__).resolve().parent.parent / "graphs"


def test_every_graph_of_the_repository_ships(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["examples", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [g["name"] for g in listed] == sorted(p.name for p in GRAPHS.glob("*.yaml"))
    assert all(g["summary"] for g in listed)


def test_copy_writes_the_clone_layout_and_refuses_to_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["examples", "--copy", str(tmp_path)]) == 0
    written = sorted(p.name for p in (tmp_path / "graphs").iterdir())
    assert {"cambada.yaml", "video.yaml", "sample.avi"} <= set(written)
    assert (tmp_path / "graphs/sample.avi").read_bytes() == (GRAPHS / "sample.avi").read_bytes()
    # again, unchanged: the README's one-liner run twice (it failed: "exists, add --force")
    assert main(["examples", "--copy", str(tmp_path)]) == 0
    capsys.readouterr()

    (tmp_path / "graphs/cambada.yaml").write_text("# mine\n")
    assert main(["examples", "--copy", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "--force" in err
    assert (tmp_path / "graphs/cambada.yaml").read_text() == "# mine\n"  # untouched

    assert main(["examples", "--copy", str(tmp_path), "--force"]) == 0
    assert (tmp_path / "graphs/cambada.yaml").read_text().startswith("# The CAMBADA")


@pytest.mark.parametrize(
    ("path", "hinted"),
    [
        ("graphs/cambada.yaml", True),  # the README's command, where there is no clone
        ("cambada.yaml", True),
        ("graphs/mine.yaml", False),  # not an example: the plain error
        ("graphs/make_sample_video.py", False),
    ],
)
def test_a_missing_example_says_where_the_examples_are(
    tmp_path: Path, path: str, hinted: bool
) -> None:
    out = io.StringIO()
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert load(path, Console(file=out, width=300)) is None
    finally:
        os.chdir(here)
    text = out.getvalue()
    assert "cannot read graph file" in text
    assert ("flowrt examples --copy ." in text) is hinted
