"""Issue 43, the command line as scripts and people use it (no process started here):

- every subcommand with ``--json`` prints exactly one JSON document on stdout, a result on
  success and ``{"error": {...}}`` on failure, with the exit code it has without ``--json``
  (the runs of ``run``/``record``/``replay``/``ctl`` are in tests/test_cli_json_runs.py);
- a bad option gets the subcommand's usage and a suggestion; a negative value is a value;
- ``check`` takes the run options (for ``--measure``), and refuses them without it;
- the small things: plurals, readable periods, ``prio`` suggesting ``priority``, kinds'
  summaries and bounds.
"""

from __future__ import annotations

import argparse
import json
import socket
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from flowrt.cli import build_parser, main

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parents[1]

TASKS = "tasks:\n  - {name: a, wcet: 1ms, period: 5ms}\n  - {name: b, wcet: 2ms, period: 10ms}\n"
GRAPH = """\
name: tiny
nodes:
  tick: {kind: counter, trigger: {timer: 66.6667ms}}
  out: {kind: sink, inputs: {input: tick.value}}
"""


@pytest.fixture
def files(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "tasks.yaml").write_text(TASKS)
    (tmp_path / "g.yaml").write_text(GRAPH)
    (tmp_path / "bad.yaml").write_text("name: x\nnodes:\n  a: {kind: capture, prio: 3}\n")
    trace = tmp_path / "t.asc"
    with can.ASCWriter(str(trace)) as w:
        for i in range(20):
            w.on_message_received(
                can.Message(timestamp=i * 0.01, arbitration_id=0x100, data=bytes(8))
            )
    return {
        "tasks": str(tmp_path / "tasks.yaml"),
        "graph": str(tmp_path / "g.yaml"),
        "bad": str(tmp_path / "bad.yaml"),
        "trace": str(trace),
        "dbc": str(REPO / "nodes" / "robot.dbc"),
        "tmp": str(tmp_path),
    }


@pytest.fixture
def closed_port() -> Iterator[int]:
    """A loopback port nobody listens on (bound, not listening: connections are refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def _json_run(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, object, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, json.loads(out), err  # the whole of stdout: one document, nothing else


# (subcommand, argv of a success, argv of a failure and its exit code); {x}: from `files`
CASES: dict[str, tuple[list[str] | None, list[str], int]] = {
    "kinds": (["kinds", "capture"], ["kinds", "nope"], 2),
    "examples": (["examples"], ["examples", "--copy", "{graph}"], 2),  # a file, not a folder
    "validate": (["validate", "{graph}"], ["validate", "{bad}"], 2),
    "graph": (["graph", "{graph}"], ["graph", "{tmp}/missing.yaml"], 2),
    "schema": (["schema", "stats"], ["schema", "nope"], 2),
    "check": (["check", "{tasks}"], ["check", "{bad}"], 2),
    "can analyse": (["can", "analyse", "{dbc}"], ["can", "analyse", "{tmp}/nope.dbc"], 2),
    "can analyze": (["can", "analyze", "{dbc}"], ["can", "analyze", "{graph}"], 2),
    "can stats": (["can", "stats", "{trace}"], ["can", "stats", "{graph}"], 2),
    "info": (None, ["info", "{tmp}/nothing"], 2),
    "sync measure": (None, ["sync", "measure", "{tmp}/no", "--video", "a", "--audio", "b"], 2),
    "run": (None, ["run", "{bad}"], 2),
    "record": (None, ["record", "{graph}", "--split-duration", "-3s"], 2),
    "replay": (None, ["replay", "{tmp}/nothing"], 2),
    **{
        f"ctl {q}": (None, ["ctl", "--url", "http://127.0.0.1:{port}", *rest], 1)
        for q, rest in {
            "stats": ["stats"],
            "timing": ["timing", "tick", "--timer", "50ms"],
            "mode": ["mode", "fast"],
            "modes": ["modes"],
            "events": ["events"],
            "qos": ["qos"],
            "rtdb": ["rtdb"],
            "record": ["record", "start"],
            "swap": ["swap", "tick", "counter"],
            "reload": ["reload", "tick"],
        }.items()
    },
}
# Those with None: their success needs a run or a recording (test_cli_json_runs.py).


def test_every_subcommand_has_json_and_a_case() -> None:
    """A new subcommand needs --json and its cases here (and a run's in the slow file)."""
    commands: dict[str, argparse.ArgumentParser] = {}

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs and prefix:
            commands[prefix] = parser
        for action in subs:
            for name, sub in action.choices.items():
                walk(sub, f"{prefix} {name}".strip())

    walk(build_parser(), "")
    assert set(commands) == set(CASES)
    assert all("--json" in p._option_string_actions for p in commands.values())


@pytest.mark.parametrize("command", sorted(CASES))
def test_json_success_and_failure_are_one_document(
    command: str,
    files: dict[str, str],
    closed_port: int,
    capsys: pytest.CaptureFixture[str],
) -> None:
    success, failure, failure_code = CASES[command]
    values = {**files, "port": str(closed_port)}
    if success is not None:
        code, doc, err = _json_run(capsys, [a.format(**values) for a in success] + ["--json"])
        assert code == 0, err
        assert doc
        assert "error" not in doc
    code, doc, err = _json_run(capsys, [a.format(**values) for a in failure] + ["--json"])
    assert code == failure_code
    assert isinstance(doc, dict)
    error = doc["error"]
    assert error["exit_code"] == failure_code
    assert error["command"] == command
    assert error["message"]
    assert error["message"] in err  # what a person saw on stderr, the same words


def test_a_graph_error_in_json_has_its_diagnostics(
    files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    code, doc, _ = _json_run(capsys, ["validate", files["bad"], "--json"])
    assert code == 2
    assert isinstance(doc, dict)
    (d,) = doc["error"]["diagnostics"]
    assert (d["line"], d["key"]) == (3, "nodes.a.prio")
    assert "did you mean 'priority'" in d["message"]


def test_a_bad_option_in_json_is_an_error_document(
    files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    code, doc, err = _json_run(capsys, ["run", files["graph"], "--duraton", "3", "--json"])
    assert code == 2
    assert isinstance(doc, dict)
    assert "did you mean --duration?" in doc["error"]["message"]
    assert "usage: flowrt run" in err


# --- option errors --------------------------------------------------------------------------


def _refused(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "usage", "hint"),
    [
        (["run", "g.yaml", "--duraton", "3"], "usage: flowrt run ", "did you mean --duration?"),
        (["record", "g.yaml", "--split-durration=3s"], "usage: flowrt record ", "--split-duration"),
        (["ctl", "events", "--jsn"], "usage: flowrt ctl events", "did you mean --json?"),
        (["check", "g.yaml", "--no-displya"], "usage: flowrt check ", "did you mean --no-display?"),
        (["rnu", "g.yaml"], "usage: flowrt [-h]", "did you mean run?"),
        (["ctl", "evnts"], "usage: flowrt ctl ", "did you mean events?"),
        (["run", "--duraton", "3"], "usage: flowrt run ", "did you mean --duration?"),
    ],
)
def test_a_bad_option_gets_the_subcommand_usage_and_a_suggestion(
    capsys: pytest.CaptureFixture[str], argv: list[str], usage: str, hint: str
) -> None:
    err = _refused(capsys, argv)
    assert err.startswith(usage)
    if usage != "usage: flowrt [-h]":  # a subcommand's own usage, not flowrt's
        assert "usage: flowrt [-h]" not in err
    assert hint in err.splitlines()[-1]


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "g.yaml", "--duration", "-3s"],
        ["run", "g.yaml", "--duration", "-3"],
        ["run", "g.yaml", "--refresh", "-1"],
        ["replay", "s", "--rate", "-2"],
        ["replay", "s", "--rate", "0"],
        ["check", "g.yaml", "--measure", "-3s"],
        ["ctl", "events", "-n", "-5"],
    ],
)
def test_a_negative_value_is_a_value_that_must_be_more_than_0(
    capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    err = _refused(capsys, argv)
    assert "expected one argument" not in err
    assert "must be more than 0" in err


def test_split_duration_negative_says_more_than_0(
    files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["record", files["graph"], "-o", files["tmp"], "--split-duration", "-3s"]) == 2
    err = capsys.readouterr().err
    assert "--split-duration '-3s': must be more than 0" in err
    assert not list(Path(files["tmp"]).glob("rec_*"))  # nothing left behind


# --- the same run options ------------------------------------------------------------------


def test_run_record_replay_and_check_share_the_run_options() -> None:
    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    def options(name: str) -> set[str]:
        p = subs.choices[name]
        group = next(g for g in p._action_groups if g.title == "run options")
        return {o for a in group._group_actions for o in a.option_strings}

    run = options("run")
    for option in ("--no-display", "--display-port", "--control", "--foxglove", "--realtime"):
        assert option in run
    assert options("record") == run
    assert options("replay") == run
    assert options("check") == run - {"--duration", "--check", "--json"}


def test_check_refuses_a_run_option_without_measure(
    files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check", files["graph"], "--display-port", "0"]) == 2
    err = capsys.readouterr().err
    assert "--display-port is an option of the measuring run (give --measure DURATION)" in err


@pytest.mark.parametrize("command", ["check", "validate", "graph", "run", "record"])
def test_a_missing_example_graph_gets_the_examples_hint_from_every_command(
    command: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """From an empty folder ``check`` said only ``No such file or directory``; the others
    said where the shipped examples are."""
    monkeypatch.chdir(tmp_path)
    assert main([command, "graphs/cambada.yaml"]) == 2
    err = capsys.readouterr().err
    assert "No such file or directory" in err
    assert "`flowrt examples --copy .` writes ./graphs" in err


# --- small things ---------------------------------------------------------------------------


def test_validate_counts_in_the_singular_and_plural(
    files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["validate", files["graph"]]) == 0
    assert "ok (2 nodes, 1 edge)" in capsys.readouterr().out


def test_a_mode_override_misspelt_prio_suggests_priority(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(GRAPH + "modes:\n  m:\n    nodes:\n      tick: {prio: 3}\n")
    assert main(["validate", str(path)]) == 2
    assert "unknown field 'prio' (did you mean 'priority'?)" in capsys.readouterr().err


async def test_periods_read_as_people_write_them_and_rates_stay_exact() -> None:
    from flowrt import GraphBuilder, Runtime, VirtualClock
    from flowrt.recording.report import nominal_rates

    g = GraphBuilder("p")
    g.add("tick", "counter", trigger={"timer": "66.6667ms"})
    g.add("late", "counter", trigger={"timer": "100ms", "phase": "5ms"})
    async with Runtime(g.build(), clock=VirtualClock()) as rt:
        stats = rt.stats()
    assert stats.node("tick").period == "66.67ms"
    assert stats.node("late").period == "100ms +5ms"
    assert nominal_rates(stats)["tick"] == pytest.approx(1000 / 66.6667, rel=1e-9)


def test_kinds_summaries_stand_alone_and_bounds_are_said_once(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["kinds", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    for r in rows:
        assert "see the module" not in r["summary"]
        assert "see above" not in r["summary"]
    assert main(["kinds", "capture", "--json"]) == 0
    params = {p["name"]: p for p in json.loads(capsys.readouterr().out)["params"]}
    assert params["flash_on"]["range"] == "> 0, <= 3600000.0"


def test_kinds_at_80_columns_and_nested_defaults(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A nested params model's default is its fields (it was a Python repr in a JSON string),
    and a wrapped line continues indented under its own: at column 0 it read as a new row."""
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["kinds", "haptic", "--json"]) == 0
    params = {p["name"]: p for p in json.loads(capsys.readouterr().out)["params"]}
    assert params["sim"]["default"]["hand"]["target"] == [60.0, 0.0, 0.0]
    assert main(["kinds", "haptic"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert max(len(x) for x in lines) <= 80
    assert not [x for x in lines if x != x.rstrip()]
    sim = next(i for i, x in enumerate(lines) if x.startswith("  sim: SimParams = {"))
    assert lines[sim + 1].startswith("    [-100.0, 100.0]")  # the default, continued
    rows = [x for x in lines[sim + 1 :] if x.startswith("  ") and not x.startswith("   ")]
    assert rows[0].startswith("  evdev: EvdevParams = {")  # the next param, nothing between


@pytest.mark.parametrize("where", ["before", "after"])
def test_ctl_takes_url_before_or_after_its_command(
    where: str, closed_port: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README lists ``flowrt ctl stats ... --url``: after the command it was refused."""
    url = ["--url", f"http://127.0.0.1:{closed_port}"]
    argv = ["ctl", *url, "stats"] if where == "before" else ["ctl", "stats", *url]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(
        f"flowrt ctl: cannot reach the runtime at http://127.0.0.1:{closed_port} "
    )


@pytest.mark.parametrize("argv", [["ctl"], ["ctl", "--json"], ["ctl", "--url", "http://x:1"]])
def test_ctl_without_a_command_says_what_to_do_in_one_line(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """``flowrt ctl --json`` said ``the following arguments are required: ctl_command
    (--json: did you mean --token?)``: argparse's name for the command, and a valid option
    taken for a typo."""
    line = (
        "flowrt ctl: say what to do: stats, timing, mode, modes, events, qos, rtdb, record, "
        "swap, reload (flowrt ctl --help)"
    )
    if "--json" in argv:  # the error document's exit code
        assert main(argv) == 2
    else:  # argparse's
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
    out, err = capsys.readouterr()
    assert err.splitlines() == [line]
    if "--json" in argv:
        error = json.loads(out)["error"]
        assert (error["message"], error["exit_code"], error["command"]) == (line, 2, "ctl")
    else:
        assert out == ""


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["can"], "flowrt can: say what to do: analyse, analyze, stats (flowrt can --help)"),
        (["sync"], "flowrt sync: say what to do: measure (flowrt sync --help)"),
        ([], "flowrt: say what to do: run, validate, graph, schema, kinds, examples, ctl, can, "
             "check, record, info, replay, sync (flowrt --help)"),
        (["ctl", "--tokn"], None),  # a typo before the command still gets its hint
    ],
)  # fmt: skip
def test_every_missing_command_is_said_the_same_way(
    argv: list[str], line: str | None, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    if line is not None:
        assert err.splitlines() == [line]
    else:
        assert "did you mean --token?" in err
    assert "_command" not in err


def test_ctl_takes_json_before_its_command(
    closed_port: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """As --url: ``ctl --json stats`` was refused (``unrecognized arguments: --json``)."""
    url = f"http://127.0.0.1:{closed_port}"
    assert build_parser().parse_args(["ctl", "--json", "stats"]).json is True
    assert build_parser().parse_args(["ctl", "stats", "--json"]).json is True
    assert build_parser().parse_args(["ctl", "stats"]).json is False
    assert main(["ctl", "--json", "stats", "--url", url]) == 1
    error = json.loads(capsys.readouterr().out)["error"]
    assert error["message"].startswith(f"flowrt ctl: cannot reach the runtime at {url}")


def test_ctl_at_something_else_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """Not a URL, or a server whose reply is not JSON (the live view's port): were tracebacks."""
    import http.server
    import threading

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.end_headers()
            self.wfile.write(b"<html>the live view</html>")

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Page)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        assert main(["ctl", "stats", "--url", url]) == 1
        got = capsys.readouterr().err.splitlines()
        assert got == [f"flowrt ctl: {url}: not a flowrt control endpoint (its reply is not JSON)"]
    finally:
        server.shutdown()
        server.server_close()
    assert main(["ctl", "stats", "--url", "nonsense"]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "flowrt ctl: nonsense: not a URL (http://HOST:PORT)"
    ]


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_stats_json_that_cannot_be_written_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """It was written after the run: a traceback, and the run's statistics lost."""
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    for path, said in ((tmp_path / "no" / "s.json", f"no folder {tmp_path}/no"),
                       (tmp_path, f"{tmp_path} is a folder"),
                       # a folder that takes no file: said after the whole run, stats lost
                       ("/proc/flowrt-stats.json", "cannot be written (No such file or directory)"),
                       # it wrote a file named '-', and the script's parser read nothing
                       ("-", "--json prints the statistics on stdout")):  # fmt: skip
        with pytest.raises(SystemExit) as exited:
            main([command, str(graph), "--duration", "1", "--stats-json", str(path)])
        assert exited.value.code == 2
        err = capsys.readouterr().err
        assert err.splitlines()[-1].startswith(f"flowrt {command}: error: argument --stats-json")
        assert err.rstrip().endswith(said)


def test_an_images_glob_matching_nothing_fails_validation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "i.yaml"
    path.write_text("nodes:\n  cam: {kind: capture, params: {source: 'images:shots/*.png'}}\n")
    assert main(["validate", str(path)]) == 2
    assert f"no image file matches {tmp_path}/shots/*.png" in capsys.readouterr().err
    (tmp_path / "shots").mkdir()
    (tmp_path / "shots" / "a.png").write_bytes(b"")
    assert main(["validate", str(path)]) == 0


def test_a_session_has_one_length_first_message_to_last() -> None:
    """Issue 43: POST /api/record/stop said 6.0 s (start to stop) for a session the sessions
    API and the player give as 4.95 s (first message to last): both read the report's span."""
    from flowrt.nodes.station.sessions import session_length

    from flowrt.recording import RecordingReport

    report = RecordingReport(
        session="s", files=[], start_time="t", duration=6.0, span=4.95, error=None, streams=[]
    )
    assert session_length(report.model_dump(mode="json")) == 4.95
    assert session_length({"duration": 6.0}) == 6.0  # a report from before the span


def test_a_verdict_is_a_result_not_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """check exits 1 when the timing does not hold: its document is the result, no error."""
    path = tmp_path / "t.yaml"
    path.write_text("tasks:\n  - {name: a, wcet: 3ms, period: 2ms}\n")
    code, doc, _ = _json_run(capsys, ["check", str(path), "--json"])
    assert code == 1
    assert isinstance(doc, dict)
    assert doc["schedulable"] is False
    assert "error" not in doc


@pytest.mark.parametrize("command", ["info", "replay"])
def test_a_folder_of_sessions_names_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """``flowrt info recordings/`` (the folder ``-o`` was given): which session to give."""
    for name in ("rec_001", "rec_002"):
        (tmp_path / "recordings" / name).mkdir(parents=True)
        (tmp_path / "recordings" / name / f"{name}.mcap").write_bytes(b"")
    (tmp_path / "recordings" / "notes").mkdir()  # a folder without a recording: not named
    assert main([command, str(tmp_path / "recordings")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "no .mcap file in this folder (it holds sessions: rec_001, rec_002; give one, "
        f"e.g. {tmp_path / 'recordings' / 'rec_002'})"
    )
    assert "notes" not in err
    (tmp_path / "empty").mkdir()
    assert main([command, str(tmp_path / "empty")]) == 2
    assert capsys.readouterr().err.strip().endswith("no .mcap file in this folder")


def test_can_analyse_finds_the_shipped_database_as_the_node_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``dbc: robot.dbc`` in a graph finds the database shipped with the node kinds; so does
    ``flowrt can analyse robot.dbc`` from any folder (an installed wheel has no nodes/)."""
    monkeypatch.chdir(tmp_path)
    assert main(["can", "analyse", "robot.dbc", "--bitrate", "250000"]) == 0
    assert capsys.readouterr().out.startswith("robot.dbc: 5 messages at 250000 bit/s")
    # the README's command, from a folder with the examples copied out but no nodes/
    assert main(["can", "analyse", "nodes/robot.dbc", "--bitrate", "250000"]) == 0
    assert capsys.readouterr().out.startswith("nodes/robot.dbc: 5 messages at 250000 bit/s")
    assert main(["can", "analyse", "nodes/nosuch.dbc"]) == 2
    assert capsys.readouterr().err.strip() == "flowrt can analyse: nodes/nosuch.dbc: no such file"
    (tmp_path / "robot.dbc").write_text("not a database\n")  # the user's own file comes first
    assert main(["can", "analyse", "robot.dbc"]) == 2
    assert "robot.dbc:1: not a valid CAN database" in capsys.readouterr().err
    assert main(["can", "analyse", "nosuch.dbc"]) == 2
    assert capsys.readouterr().err.strip() == "flowrt can analyse: nosuch.dbc: no such file"


@pytest.mark.parametrize(
    ("host", "refused", "token_said"),
    [("1.2.3.4.5", True, False), ("0.0.0.0", False, True), ("127.0.0.1", False, False)],
)
def test_a_view_token_is_said_only_for_an_address_taken(
    capsys: pytest.CaptureFixture[str], host: str, refused: bool, token_said: bool
) -> None:
    """--display-host 1.2.3.4.5 printed a freshly made token before refusing the address."""
    import argparse

    from flowrt import Graph
    from flowrt.cli.run import _display_options

    graph = Graph.from_file(REPO / "graphs" / "cambada.yaml")
    args = argparse.Namespace(
        no_display=False, display_token=None, display_host=host, display_port=None
    )
    problem = _display_options(graph, args)
    assert (problem is not None) == refused
    assert ("live view token" in capsys.readouterr().out) == token_said


@pytest.mark.parametrize("command", ["run", "record", "replay"])
@pytest.mark.parametrize(("port", "said"), [("99999", "port out of range: 99999 (0-65535)"),
                                            ("-1", "port out of range: -1"),
                                            ("x", "not a port number: 'x'")])  # fmt: skip
def test_a_foxglove_port_out_of_range_is_refused_as_an_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, port: str, said: str
) -> None:
    """It was a traceback from the socket's bind (OverflowError), exit 1."""
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    with pytest.raises(SystemExit) as exited:
        main([command, str(graph), "--duration", "1", "--foxglove", port])
    assert exited.value.code == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith(f"flowrt {command}: error: argument --foxglove")
    assert said in last
