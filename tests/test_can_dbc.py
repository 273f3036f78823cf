"""Databases as vehicles have them, and arguments as people type them, for ``flowrt can``.

The corpus: every DBC of the installed ``opendbc`` package that cantools loads non-strictly
(94 of its 115 files with cantools 45) gets an answer from ``flowrt can analyse``: exit 0
or 1, never a refusal or a traceback.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import cantools
import pytest
from _can_dbcs import FD_DBC, OVERLAP_DBC, write
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt import cli
from flowrt.analysis.can_database import CanDatabaseError, load_database

pytestmark = pytest.mark.timeout(60)


def _opendbc_files() -> list[Path]:
    try:
        import opendbc
    except ImportError:
        return []
    return sorted((Path(opendbc.__file__).parent / "dbc").rglob("*.dbc"))


def _run(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return rc, out.getvalue(), err.getvalue()


@pytest.mark.slow
def test_every_opendbc_file_cantools_loads_is_analysed() -> None:
    files = _opendbc_files()
    if not files:
        pytest.skip("opendbc is not installed")
    loadable, answered, fd_files = 0, 0, 0
    for path in files:
        try:
            db = cantools.database.load_file(str(path), strict=False)
        except Exception:  # cantools refuses it too (syntax, 29-bit ids marked standard...)
            rc, _, err = _run("can", "analyse", str(path))
            assert rc == 2, path
            assert len(err.strip().splitlines()) == 1, (path, err)
            continue
        loadable += 1
        rc, out, err = _run("can", "analyse", str(path), "--json")
        assert rc in (0, 1), (path.name, err)
        doc = json.loads(out)
        assert "Traceback" not in err
        answered += 1
        by = {m["name"]: m for m in doc["messages"]}
        assert set(by) == {m.name for m in db.messages}
        for m in db.messages:
            row = by[m.name]
            if m.cycle_time and not row["fd"]:  # Davis 2007 bits for every periodic classic one
                g = 54 if m.is_extended_frame else 34
                assert row["frame_bits"] == g + 8 * m.length + 13 + (g + 8 * m.length - 1) // 4
        fd_files += any(r["fd"] for r in doc["messages"])
        periodic = [r for r in doc["messages"] if r["period_ms"]]
        expected = sum(r["c_ms"] / r["period_ms"] for r in periodic)
        assert doc["utilisation"] == pytest.approx(expected)
    assert loadable == answered
    assert loadable >= 90
    assert fd_files >= 3  # Ford's and Hyundai's FD databases among them


def test_strict_refusals_are_named_warnings_once(tmp_path: Path) -> None:
    path = write(tmp_path, OVERLAP_DBC)
    rc, out, err = _run("can", "analyse", path)
    assert rc == 0
    warnings = err.strip().splitlines()
    assert warnings == [
        f"warning: {path}: Over.B: overlaps signal A",
        f"warning: {path}: Over.C: does not fit in the message's 2 bytes",
    ]
    assert "Over" in out
    rc, out, _ = _run("can", "analyse", path, "--json")
    assert json.loads(out)["warnings"][0] == {
        "message": "Over",
        "signal": "B",
        "reason": "overlaps signal A",
    }
    rc, out, err = _run("can", "analyse", path, "--strict")
    assert rc == 2
    assert err.strip().splitlines() == [
        f"flowrt can analyse: {path}: refused by strict loading: Over.B: overlaps signal A"
    ]


@pytest.mark.parametrize(
    ("name", "text", "said"),
    [
        ("g.yaml", "nodes: {}\n", "but got 'yaml'"),  # the closing quote was cut
        ("k.dbc", 'VERSION ""\nBO_ 4000 X: 8 E\n', 'more than 11 bits in message X."'),
    ],
)
def test_a_quoted_word_at_the_end_of_a_reason_keeps_its_quote(
    tmp_path: Path, name: str, text: str, said: str
) -> None:
    path = tmp_path / name
    path.write_text(text)
    rc, _, err = _run("can", "analyse", str(path))
    assert rc == 2
    (line,) = err.strip().splitlines()
    assert line.endswith(said)


def test_unparsable_database_is_one_line_with_its_line_number(tmp_path: Path) -> None:
    path = write(tmp_path, FD_DBC.replace("BO_ 257 Fd12: 12 ECU", "BO_ 257 12Fd: 12 ECU"))
    rc, _, err = _run("can", "analyse", path)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1
    line = FD_DBC.splitlines().index("BO_ 257 Fd12: 12 ECU") + 1
    assert err.startswith(f"flowrt can analyse: {path}:{line}: not a valid CAN database")
    with pytest.raises(CanDatabaseError, match="no such file"):
        load_database(tmp_path / "missing.dbc")


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--jitter", "Classic=inf"], "--jitter 'Classic=inf'"),
        (["--jitter", "Classic=nan"], "--jitter 'Classic=nan'"),
        (["--jitter", "Classic=1e9"], "at most 1 h"),
        (["--jitter", "Classic=-1"], "--jitter"),
        (["--period", "Classic=0"], "more than 0"),
        (["--deadline", "Classic=1e400"], "--deadline"),
        (["--sporadic", "Event"], "NAME=MS"),
        (["--period", "Nope=10"], "not a message of the DBC"),
        (["--bitrate", "fast"], "--bitrate 'fast'"),
        (["--bitrate", "0"], "between 1k and 20M"),
        (["--bitrate", "1e12"], "between 1k and 20M"),
        (["--bitrate", "inf"], "--bitrate"),
        (["--data-bitrate", "2.5"], "--data-bitrate"),
    ],
)
def test_every_value_is_range_checked(tmp_path: Path, args: list[str], needle: str) -> None:
    rc, _out, err = _run("can", "analyse", write(tmp_path, FD_DBC), *args)
    assert rc == 2
    assert needle in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_big_jitter_within_range_ends_unbounded_not_hanging(tmp_path: Path) -> None:
    rc, out, _ = _run(
        "can", "analyse", write(tmp_path, FD_DBC), "--jitter", "Classic=3600s", "--json"
    )
    classic = next(m for m in json.loads(out)["messages"] if m["name"] == "Classic")
    assert classic["wcrt_ms"] is None
    assert rc == 1


@pytest.mark.parametrize(
    ("text", "rate"),
    [
        ("500k", 500_000),
        ("1e6", 1_000_000),
        ("1M", 1_000_000),
        ("250000", 250_000),
        ("2Mbit/s", 2_000_000),
    ],
)
def test_bitrate_units(tmp_path: Path, text: str, rate: int) -> None:
    rc, out, _ = _run("can", "analyse", write(tmp_path, FD_DBC), "--bitrate", text, "--json")
    assert rc == 0
    assert json.loads(out)["bitrate"] == rate


def test_aperiodic_listed_and_sporadic_included(tmp_path: Path) -> None:
    path = write(tmp_path, FD_DBC)
    rc, out, _ = _run("can", "analyse", path)
    assert rc == 0
    assert "not analysed (no cycle time" in out
    assert "Event" in out.split("not analysed (no cycle time")[1]
    assert "without bound" in out  # how it can still delay the others
    rc, out, _ = _run("can", "analyse", path, "--json")
    doc = json.loads(out)
    assert [m["name"] for m in doc["not_analysed"]] == ["Event"]
    assert doc["not_analysed"][0]["delays"] == []  # 0x400 is the lowest priority here
    before = {m["name"]: m for m in doc["messages"]}
    rc, out, _ = _run("can", "analyse", path, "--sporadic", "Event=2ms", "--json")
    doc = json.loads(out)
    assert doc["not_analysed"] == []
    by = {m["name"]: m for m in doc["messages"]}
    assert by["Event"]["sporadic"] is True
    assert by["Event"]["period_ms"] == 2.0
    assert by["Event"]["wcrt_ms"] is not None
    assert doc["utilisation"] == pytest.approx(
        before["Classic"]["c_ms"] * 0 + sum(m["c_ms"] / m["period_ms"] for m in by.values())
    )


def test_sporadic_from_the_dbc_attribute(tmp_path: Path) -> None:
    text = (
        FD_DBC.replace(
            'BA_DEF_DEF_  "GenMsgCycleTime" 0;',
            'BA_DEF_DEF_  "GenMsgCycleTime" 0;\nBA_DEF_ BO_  "GenMsgDelayTime" INT 0 65535;\n'
            'BA_DEF_DEF_  "GenMsgDelayTime" 0;',
        )
        + 'BA_ "GenMsgDelayTime" BO_ 1024 5;\n'
    )
    _rc, out, _ = _run("can", "analyse", write(tmp_path, text), "--json")
    by = {m["name"]: m for m in json.loads(out)["messages"]}
    assert by["Event"]["sporadic"] is True
    assert by["Event"]["period_ms"] == 5.0


@pytest.mark.parametrize("command", ["analyse", "stats"])
def test_special_files_end_at_once(tmp_path: Path, command: str) -> None:
    import os

    fifo = tmp_path / "pipe.dbc"
    os.mkfifo(fifo)
    for path, kind in ((str(fifo), "a FIFO (named pipe)"), ("/dev/zero", "a device")):
        rc, _, err = _run("can", command, path)
        assert rc == 2
        assert err.strip() == f"flowrt can {command}: {path} is {kind}, not a regular file"


def test_the_node_loads_what_cantools_loads_and_strict_refuses(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from flowrt import GraphBuilder, GraphError

    path = write(tmp_path, OVERLAP_DBC, "node.dbc")
    g = GraphBuilder()
    g.add("bus", "can", params={"interface": "virtual", "channel": "x", "dbc": path})
    g.build()  # loads: the overlapping message does not stop the others
    assert caplog.text.count("Over.B: overlaps signal A") == 1
    g.build()
    assert caplog.text.count("Over.B: overlaps signal A") == 1  # once, not per load
    g = GraphBuilder()
    g.add("bus", "can", params={"interface": "virtual", "dbc": path, "strict": True})
    with pytest.raises(GraphError, match=r"refused by strict loading: Over\.B: overlaps signal A"):
        g.build()


@pytest.mark.slow  # over 1 s of CPU (hypothesis)
@settings(max_examples=60, deadline=None)
@given(
    flag=st.sampled_from(["--jitter", "--period", "--deadline", "--sporadic"]),
    value=st.one_of(
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.integers(-(10**20), 10**20).map(str),
        st.text(max_size=8),
    ),
)
def test_any_typed_value_is_an_answer_or_one_line(flag: str, value: str) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        name = "Event" if flag == "--sporadic" else "Classic"
        rc, out, err = _run("can", "analyse", write(Path(tmp), FD_DBC), flag, f"{name}={value}")
    assert "Traceback" not in err
    if rc == 2:
        assert len(err.strip().splitlines()) == 1
    else:
        assert rc in (0, 1)
        assert out


def test_paths_resolve_beside_the_graph_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from flowrt import Graph

    robot = tmp_path / "robot"
    robot.mkdir()
    write(robot, FD_DBC, "mine.dbc")
    (robot / "g.yaml").write_text(
        "name: g\nnodes:\n  bus:\n    kind: can\n    params:\n      interface: virtual\n"
        "      dbc: mine.dbc\n      trace: logs/bus.blf\n"
        "  ship:\n    kind: can\n    params: {interface: virtual, dbc: robot.dbc}\n"
    )
    monkeypatch.chdir(tmp_path)  # not the graph's directory
    graph = Graph.from_file(robot / "g.yaml")
    params = graph.nodes["bus"].params
    assert params.dbc == str(robot / "mine.dbc")
    assert params.trace == str(robot / "logs" / "bus.blf")
    assert graph.nodes["ship"].params.dbc == "robot.dbc"  # shipped with flowrt.nodes
    (robot / "bad.yaml").write_text(
        "name: g\nnodes:\n  bus:\n    kind: can\n    params: {dbc: nope.dbc}\n"
    )
    rc, _, err = _run("validate", str(robot / "bad.yaml"))
    assert rc == 2
    assert f"nope.dbc: no such file (looked for {robot / 'nope.dbc'} and in flowrt.nodes)" in err


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("250k", 250_000),
        ("1e6", 1_000_000),
        (500000, 500_000),
        ("2M", 2_000_000),
        ("inf", None),
        (0, None),
        ("1.5", None),
        (True, None),
    ],
)
def test_node_bit_rates_take_units(value: Any, expected: int | None) -> None:
    from flowrt import GraphBuilder, GraphError

    g = GraphBuilder()
    g.add("bus", "can", params={"dbc": "robot.dbc", "bitrate": value, "data_bitrate": "2M"})
    if expected is None:
        with pytest.raises(GraphError, match="bitrate"):
            g.build()
    else:
        params = g.build().nodes["bus"].params
        assert params.bitrate == expected
        assert params.data_bitrate == 2_000_000


def test_an_error_naming_a_message_is_located_at_it(tmp_path: Path) -> None:
    """cantools gives no line for a frame id out of range (opendbc's vw_meb.dbc): the line
    of the message it names (the README promises FILE:LINE)."""
    path = tmp_path / "k.dbc"
    path.write_text('VERSION ""\n\nBU_: E\n\nBO_ 4000 X: 8 E\n')
    rc, _, err = _run("can", "analyse", str(path))
    assert rc == 2
    assert err.startswith(f"flowrt can analyse: {path}:5: not a valid CAN database")
