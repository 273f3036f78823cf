"""Damaged rosbag2 folders as a new user meets them: one line and a nonzero exit each.

Found by the new-user audit: a truncated ``.db3`` was a traceback (``BagError``) from
``flowrt info`` and ``flowrt replay``; ``info --repair`` renamed it ``.damaged.mcap`` and put
an empty MCAP file in its place; a ``metadata.yaml`` that is not YAML printed pyyaml's five
lines with a caret. The ``replay`` node: a path that is not there was a traceback and three
restarts at run time, a damaged bag or a misspelt topic a traceback and restarts. The bags
are written by rosbags itself, then damaged.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from flowrt.nodes.replay import Replay
from ros_data import write_bag

from flowrt import FatalError
from flowrt.cli import main
from flowrt.testing import NodeHarness


@pytest.fixture
def db3_bag(tmp_path: Path) -> Path:
    frames = [np.full((24, 32, 3), i, np.uint8) for i in range(3)]
    return write_bag(tmp_path / "bag", "sqlite3", frames)


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _truncate(bag: Path) -> Path:
    (db3,) = bag.glob("*.db3")
    db3.write_bytes(db3.read_bytes()[:5000])  # the header page and a little more
    return db3


def test_info_of_a_truncated_db3_is_a_damaged_file(
    db3_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _truncate(db3_bag)
    code, out, err = _run(capsys, "info", str(db3_bag))
    assert code == 1
    assert "Traceback" not in out + err
    assert "malformed" in out
    assert "--repair" not in out  # it offered what --repair refuses (MCAP files only)
    why = "not closed cleanly (damaged or the recorder was killed)"
    assert err.strip().splitlines() == [f"flowrt info: {db3_bag}/bag.db3 {why}"]


def test_replay_of_a_truncated_db3_says_nothing_to_replay(
    db3_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _truncate(db3_bag)
    code, out, err = _run(capsys, "replay", str(db3_bag), "--no-ui", "--no-display")
    assert code == 2
    assert out == ""
    assert err.strip().splitlines() == [
        f"flowrt replay: {db3_bag}: nothing to replay (bag.db3: database disk image is malformed)"
    ]


def test_repair_refuses_a_db3_and_leaves_it_as_it_was(
    db3_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db3 = _truncate(db3_bag)
    before = db3.read_bytes()
    code, _, err = _run(capsys, "info", "--repair", str(db3_bag))
    assert code == 1
    assert "flowrt repairs MCAP files only (the original is untouched)" in err
    assert sorted(p.name for p in db3_bag.iterdir()) == ["bag.db3", "metadata.yaml"]
    assert db3.read_bytes() == before


@pytest.mark.parametrize("command", ["info", "replay"])
def test_metadata_that_is_not_yaml_is_one_line(
    db3_bag: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    (db3_bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [oops\n")
    code, out, err = _run(capsys, command, str(db3_bag))
    assert code == 2
    assert out == ""
    assert err.strip().splitlines() == [
        f"flowrt {command}: {db3_bag}/metadata.yaml: not YAML: expected ',' or ']', "
        "but got '<stream end>' (line 2, column 1)"
    ]


def test_a_replay_path_that_is_not_there_is_a_graph_error_at_its_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  cam:\n    kind: replay\n    params: {path: bags/drive}\n")
    code, _, err = _run(capsys, "validate", str(graph))
    assert code == 2
    assert err.splitlines()[0] == (
        f"{graph}:4:14: error: nodes.cam.params.path: no such file or folder: {tmp_path}/bags/drive"
    )


@pytest.mark.parametrize(
    ("damage", "said"),
    [
        ("truncate", "bag.db3: database disk image is malformed"),
        ("metadata", "metadata.yaml: not YAML"),
        ("topic", "no topic '/nope' (recorded: /camera/compressed, /camera/image_raw"),
    ],
)
def test_a_replay_node_that_cannot_start_is_given_up_in_one_line(
    db3_bag: Path, damage: str, said: str
) -> None:
    params = {"path": str(db3_bag), "topic": "/nope" if damage == "topic" else None}
    if damage == "truncate":
        _truncate(db3_bag)
    elif damage == "metadata":
        (db3_bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [oops\n")
    with pytest.raises(FatalError, match=said.replace("(", r"\(")):
        NodeHarness(Replay, params, name="cam")


@pytest.mark.parametrize(
    ("content", "said"),
    [
        # "replayed up to the damage at byte 0: truncated ..." (the command line: this)
        (b"hello\n", "x.mcap: not an MCAP file"),
        # "InvalidMagic: not a valid MCAP file, invalid magic: (35, 82, 79, ..."
        (b"#ROSBAG V2.0\n" + bytes(64), "a ROS 1 bag, not read: convert it with rosbags-convert"),
        # a folder of sessions: "no MCAP file", without naming them
        (None, "no MCAP file (it holds sessions: rec_001; give one, e.g. "),
    ],
)
def test_the_replay_node_says_what_the_command_line_says(
    tmp_path: Path, content: bytes | None, said: str
) -> None:
    if content is None:
        (tmp_path / "rec_001").mkdir()
        (tmp_path / "rec_001" / "rec_001.mcap").write_bytes(b"")
        path = tmp_path
    else:
        path = tmp_path / "x.mcap"
        path.write_bytes(content)
    with pytest.raises(FatalError, match=re.escape(said)):
        NodeHarness(Replay, {"path": str(path)}, name="cam")


@pytest.mark.parametrize("command", ["info", pytest.param("replay", marks=pytest.mark.realtime)])
def test_a_bag_named_by_its_metadata_file_is_the_bag(
    db3_bag: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """A shell completes ``bag/`` to ``bag/metadata.yaml``: that was 'not an MCAP file'."""
    argv = [command, str(db3_bag / "metadata.yaml")]
    code, out, err = _run(
        capsys, *argv, *(["--json"] if command == "info" else ["--no-ui", "--no-display"])
    )
    assert (code, err) == (0, "")
    if command == "info":
        assert json.loads(out)["messages"] == 4 * 3  # four topics of three messages


@pytest.mark.parametrize(
    ("key", "value", "said"),
    [
        ("relative_file_paths", 5, "relative_file_paths: expected a list of file names"),
        ("relative_file_paths", [None], "relative_file_paths: expected a list of file names"),
        ("compression_mode", 7, "compression_mode: expected a name"),
        ("storage_identifier", ["mcap"], "storage_identifier: expected a name"),
    ],
)
def test_metadata_with_a_field_of_the_wrong_type_is_one_line(
    db3_bag: Path, capsys: pytest.CaptureFixture[str], key: str, value: object, said: str
) -> None:
    """A hand-edited metadata.yaml was a TypeError or AttributeError traceback."""
    import yaml

    meta = db3_bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    doc["rosbag2_bagfile_information"][key] = value
    meta.write_text(yaml.safe_dump(doc))
    code, out, err = _run(capsys, "info", str(db3_bag))
    assert (code, out) == (2, "")
    assert err.splitlines() == [f"flowrt info: {meta}: {said}"]


def test_streams_whose_names_clean_to_one_get_a_node_each() -> None:
    """``/a/b`` and ``/a_b`` were both node ``_a_b``: one stream was silently not replayed."""
    from flowrt.cli.common import safe_node_names

    got = safe_node_names(["/a/b", "/a_b", "/a_b_2", "/1x", "/ü", ""])
    assert got == {
        "/a/b": "_a_b",
        "/a_b": "_a_b_2",
        "/a_b_2": "_a_b_2_2",
        "/1x": "_1x",
        "/ü": "__",
        "": "stream",
    }


def test_a_bag_whose_storage_file_is_missing_says_so(
    db3_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It said "no .mcap file in this folder" of a bag whose .db3 was not copied."""
    (db3,) = db3_bag.glob("*.db3")
    db3.unlink()
    code, _, err = _run(capsys, "info", str(db3_bag))
    assert code == 2
    assert f"{db3.name}: missing (named by metadata.yaml)" in err


def test_a_folder_of_bags_names_them(db3_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The hint listed the MCAP sessions only, not the SQLite3 bags beside them."""
    code, _, err = _run(capsys, "info", str(db3_bag.parent))
    assert code == 2
    assert f"(it holds sessions: {db3_bag.name}; give one" in err


@pytest.mark.parametrize(
    ("name", "content", "said"),
    [
        ("bag.db3", b"", "an empty file (0 bytes): no recording in it"),  # "not an MCAP file"
        ("x.mcap", b"", None),  # a recorder killed at creation: repairable
        ("x.txt", b"hello", "not an MCAP file"),
        ("x.bag", b"#ROSBAG V2.0\n", "a ROS 1 bag, not read"),
    ],
)
def test_why_a_file_is_no_recording(
    tmp_path: Path, name: str, content: bytes, said: str | None
) -> None:
    from flowrt.recording.session import not_a_recording

    path = tmp_path / name
    path.write_bytes(content)
    why = not_a_recording(path)
    assert why == said if said is None else (why or "").startswith(said)
