"""Graph files from someone else: no code runs with --no-import, no tag, no oversize file.

A graph file is code (a dotted-path kind imports its module); ``flowrt validate --no-import``
checks one without importing anything it names. Tags are refused in tests/graphs/
invalid-yaml-tags.yaml and test_validation.py's odd-YAML table.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from flowrt import Graph, GraphError
from flowrt.cli import main
from flowrt.graph._loading import MAX_FILE_BYTES, parse_yaml, read_graph_file

_MODULE = """
from pathlib import Path
Path({marker!r}).write_text("imported")

from flowrt import Node, Output

class Source(Node):
    value = Output(int)

    def process(self) -> int:
        return 1
"""


@pytest.fixture
def marker_kind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    """A graph whose dotted-path kind's module writes a marker file when imported."""
    name = f"flowrt_marker_{tmp_path.name.replace('-', '_')}"
    marker = tmp_path / "imported.txt"
    (tmp_path / f"{name}.py").write_text(_MODULE.format(marker=str(marker)))
    monkeypatch.syspath_prepend(str(tmp_path))
    graph = tmp_path / "g.yaml"
    graph.write_text(
        textwrap.dedent(f"""\
            nodes:
              src:
                kind: {name}:Source
                trigger: {{timer: 10ms}}
              sink:
                kind: sink
                inputs: {{input: src.value}}
              tick:
                kind: counter
                trigger: {{timer: 0ms}}
            """)
    )
    yield graph, marker
    sys.modules.pop(name, None)


def test_no_import_checks_without_running_the_kinds_module(
    marker_kind: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    graph, marker = marker_kind
    assert main(["validate", "--no-import", str(graph)]) == 2  # the rest is still checked
    err = capsys.readouterr().err
    assert "g.yaml:10:15: error: nodes.tick.trigger.timer: timer period must be positive" in err
    assert not marker.exists()

    graph.write_text(graph.read_text().replace("timer: 0ms", "timer: 5ms"))
    assert main(["validate", "--no-import", str(graph)]) == 0
    out = capsys.readouterr().out
    assert "g.yaml: ok (3 nodes, 1 edge)" in out  # the file's (it said "2 nodes, 0 edges")
    assert "not imported (--no-import): src (flowrt_marker_" in out
    assert "their params, ports and triggers are not checked" in out
    assert not marker.exists()

    assert main(["validate", str(graph)]) == 0  # without the flag the module is imported
    assert marker.read_text() == "imported"


def test_no_import_still_resolves_installed_kinds(marker_kind: tuple[Path, Path]) -> None:
    graph, _ = marker_kind
    with pytest.raises(GraphError, match="timer period must be positive"):
        Graph.from_file(graph, import_kinds=False)
    graph.write_text(graph.read_text().replace("timer: 0ms", "timer: 5ms"))
    g = Graph.from_file(graph, import_kinds=False)
    assert set(g.nodes) == {"sink", "tick"}  # built-in kinds resolved and checked
    assert list(g.not_imported) == ["src"]


def test_an_oversize_file_is_refused_before_it_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The 6 MB / 100 000-node file of the audit: refused by its size, never parsed."""
    big = tmp_path / "big.yaml"
    with big.open("w") as f:
        f.write("nodes:\n")
        for i in range(100_000):
            f.write(f"  n{i}:\n    kind: counter\n    trigger: {{timer: 10ms}}\n")
    assert big.stat().st_size > 5_000_000

    def no_reading(*args: object, **kwargs: object) -> str:
        raise AssertionError("an oversize file was read")

    monkeypatch.setattr(Path, "read_text", no_reading)
    with pytest.raises(GraphError) as info:
        read_graph_file(big)
    size = big.stat().st_size / 2**20
    assert str(info.value) == (
        f"{big}: error: graph file too large: {size:.1f} MiB, the limit is 256 KiB "
        "(a graph of hundreds of nodes is tens of kB)"
    )


def test_oversize_text_is_refused_without_parsing() -> None:
    data, _, errors = parse_yaml("nodes:\n" + "#" * MAX_FILE_BYTES, "t.yaml")
    assert data is None
    assert [e.message.split(":")[0] for e in errors] == ["graph file too large"]
    # At the limit a file is read as usual.
    data, _, errors = parse_yaml("nodes: {}\n" + "#" * (MAX_FILE_BYTES - 20), "t.yaml")
    assert data == {"nodes": {}}
    assert not errors
