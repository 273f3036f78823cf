"""A recording is data (issue 32): replaying or inspecting one never runs what it names.

- ``flowrt replay REC`` without ``--graph`` imports no module the recorded graph names and
  plays the recorded streams; ``--trust-graph`` is needed to run the recorded graph; a
  malformed stored graph is one line.
- ``flowrt info`` prints terminal escape sequences and rich markup from a file as text.
- ``flowrt info --repair`` on a read-only folder is one line and exit 1; a second repair never
  overwrites the original kept by the first.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

REPO = Path(__file__).resolve().parents[1]

EVIL_MODULE = """
import os
from pathlib import Path

from flowrt import Node, Output

marker = os.environ.get("FLOWRT_TEST_MARKER")
if marker:
    Path(marker).write_text("imported")


class Evil(Node):
    out = Output(object)

    def process(self):
        return {"n": 1}
"""

GRAPH = """\
name: evil
nodes:
  cam:
    kind: capture
    params: {source: "synthetic:soccer", fps: 20, size: [64, 48]}
  evil:
    kind: evilkind:Evil
    trigger: {timer: 100ms}
"""


def cli(*args: str, env: dict[str, str] | None = None, timeout: float = 90) -> Any:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        env=dict(os.environ, COLUMNS="200", **(env or {})),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def evil_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("evil")
    (tmp / "evilkind.py").write_text(EVIL_MODULE)
    graph = tmp / "evil.yaml"
    graph.write_text(GRAPH)
    r = cli(
        "record", str(graph), "-o", str(tmp / "recs"), "--duration", "1", "--no-ui",
        env={"PYTHONPATH": str(tmp)},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    (session,) = (tmp / "recs").glob("rec_*")
    return tmp, session


def test_replay_without_graph_imports_nothing_the_recording_names(
    evil_session: tuple[Path, Path], tmp_path: Path
) -> None:
    mod_dir, session = evil_session
    marker = tmp_path / "imported"
    env = {"PYTHONPATH": str(mod_dir), "FLOWRT_TEST_MARKER": str(marker)}
    r = cli("replay", str(session), "--rate", "4", "--no-ui", "--no-display", env=env)
    assert r.returncode == 0, r.stderr
    assert not marker.exists()
    assert "--trust-graph" in r.stderr  # says how to run the recorded graph
    assert "replay nodes publishing the recorded streams" in r.stdout
    # with --trust-graph the recorded graph runs: the same module is imported (the test
    # above can fail)
    r = cli(
        "replay", str(session), "--trust-graph", "--rate", "4", "--no-ui", "--no-display",
        "--duration", "0.5", env=env,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert marker.exists()
    assert "replacing its source node(s) cam" in r.stdout


def test_replay_takes_the_run_options_and_prints_the_final_table(
    evil_session: tuple[Path, Path], tmp_path: Path
) -> None:
    _, session = evil_session
    stats = tmp_path / "stats.json"
    r = cli(
        "replay", str(session), "--no-ui", "--no-display", "--duration", "0.5",
        "--stats-json", str(stats),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert stats.exists()
    assert "activations" in r.stdout or "node" in r.stdout  # the final table


def test_a_malformed_recorded_graph_is_one_line(tmp_path: Path) -> None:
    from mcap.writer import Writer

    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start(profile="flowrt", library="test")
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("cam.frame", "json", sid)
        for k in range(3):
            w.add_message(cid, k * 10**8, b"{}", k * 10**8, k)
        w.add_attachment(0, 0, "graph.yaml", "application/yaml", b"nodes: [unclosed")
        w.add_metadata("flowrt", {"graph": "nodes: [unclosed"})
        w.finish()
    r = cli("replay", str(bad), "--trust-graph", "--no-ui", "--no-display", "--duration", "0.2")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
    assert len(lines) == 1, r.stderr


def test_info_escapes_what_comes_from_the_file(tmp_path: Path) -> None:
    from mcap.writer import Writer

    f_path = tmp_path / "[bold]x[" / "bold].mcap"  # the path reads "...[bold]x[/bold].mcap"
    f_path.parent.mkdir()
    with open(f_path, "wb") as f:
        w = Writer(f)
        w.start(profile="flowrt", library="test")
        sid = w.register_schema("evil\x1b[2J", "jsonschema", b"{}")
        cid = w.register_channel("cam\x1b]0;pwned\x07.frame[/red]", "json", sid)
        for k in range(3):
            w.add_message(cid, k * 10**8, b"{}", k * 10**8, k)
        w.add_metadata("meta\x1b[31m", {"k": "v\x1b[0m"})
        w.finish()
    r = cli("info", str(f_path))
    assert r.returncode == 0, r.stderr
    assert "\x1b" not in r.stdout
    assert "\\x1b" in r.stdout
    assert "Traceback" not in r.stderr
    assert "[/red]" in r.stdout


def _damaged_copy(tmp_path: Path, session: Path) -> Path:
    (src,) = session.glob("*.mcap")
    data = src.read_bytes()
    bad = tmp_path / "cut" / "rec.mcap"
    bad.parent.mkdir()
    bad.write_bytes(data[: len(data) * 2 // 3])  # the summary and footer gone
    return bad


def test_repair_on_a_read_only_folder_is_one_line_and_keeps_the_original(
    evil_session: tuple[Path, Path], tmp_path: Path
) -> None:
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders; the full-disk path is the same code")
    _, session = evil_session
    bad = _damaged_copy(tmp_path, session)
    before = bad.read_bytes()
    bad.parent.chmod(0o555)
    try:
        r = cli("info", str(bad), "--repair")
    finally:
        bad.parent.chmod(0o755)
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    assert "cannot repair" in r.stderr
    assert bad.read_bytes() == before


def test_repair_failing_to_write_keeps_the_original(
    evil_session: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk, simulated in-process: the original is untouched and no part is left."""
    from flowrt.recording import repair as reader

    _, session = evil_session
    bad = _damaged_copy(tmp_path, session)
    before = bad.read_bytes()

    def full_disk(*args: Any, **kw: Any) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(reader, "_write_repaired", full_disk)
    with pytest.raises(OSError, match="No space"):
        reader.repair(bad)
    assert bad.read_bytes() == before
    assert sorted(p.name for p in bad.parent.iterdir()) == ["rec.mcap"]


def test_a_second_repair_never_overwrites_the_kept_original(
    evil_session: tuple[Path, Path], tmp_path: Path
) -> None:
    from flowrt.recording import repair as reader

    _, session = evil_session
    bad = _damaged_copy(tmp_path, session)
    first_original = bad.read_bytes()
    reader.repair(bad)
    kept = bad.with_name("rec.damaged.mcap")
    assert kept.read_bytes() == first_original
    bad.write_bytes(first_original[: len(first_original) // 2])  # damaged again
    second_original = bad.read_bytes()
    reader.repair(bad)
    assert kept.read_bytes() == first_original
    assert bad.with_name("rec.damaged-2.mcap").read_bytes() == second_original
