"""Graph-file validation, table-driven from tests/graphs/.

Each ``invalid-*.yaml`` fixture states the errors it must produce in header comments::

    # expect: LINE[:COL] substring of "file:line:col: error: key: message"

and must produce exactly those (one error per line, all in one GraphError). Each
``valid-*.yaml`` must load; ``# warn:`` lines state the warnings it must produce.
"""

from __future__ import annotations

import re
import string
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:  # for the typed test kinds, `graphkinds:FrameSource` etc.
    sys.path.insert(0, str(TESTS))

from graphkinds import FrameReader, FrameSource  # noqa: E402

from flowrt import FrameTrigger, Graph, GraphBuilder, GraphError  # noqa: E402
from flowrt.graph.diagnostics import Diagnostic, Severity  # noqa: E402

GRAPHS = TESTS / "graphs"
INVALID = sorted(GRAPHS.glob("invalid-*.yaml"))
VALID = sorted(GRAPHS.glob("valid-*.yaml"))

_EXPECT = re.compile(r"^#\s*(expect|warn):\s*(\d+)(?::(\d+))?\s+(.+?)\s*$")


@dataclass(frozen=True)
class Expected:
    severity: Severity
    line: int
    column: int | None
    text: str

    def matches(self, d: Diagnostic) -> bool:
        return (
            d.severity is self.severity
            and d.line == self.line
            and (self.column is None or d.column == self.column)
            and self.text in str(d)
        )

    def __str__(self) -> str:
        col = "" if self.column is None else f":{self.column}"
        return f"{self.severity.value} at {self.line}{col}: {self.text!r}"


def expectations(path: Path) -> list[Expected]:
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if m := _EXPECT.match(line):
            sev = Severity.error if m[1] == "expect" else Severity.warning
            out.append(Expected(sev, int(m[2]), int(m[3]) if m[3] else None, m[4]))
    return out


def assert_exactly(diags: list[Diagnostic], expected: list[Expected], path: Path) -> None:
    """Every expectation met by its own diagnostic, and no diagnostic left over."""
    left = list(diags)
    missing = []
    for exp in expected:
        hit = next((d for d in left if exp.matches(d)), None)
        if hit is None:
            missing.append(str(exp))
        else:
            left.remove(hit)
    report = "\n".join(str(d) for d in diags)
    assert not missing, f"{path.name}: not reported: {missing}\ngot:\n{report}"
    assert not left, f"{path.name}: unexpected: {[str(d) for d in left]}"
    for d in diags:
        assert d.file == str(path)
        assert d.line >= 1, d
        assert d.column >= 1, d


@pytest.mark.parametrize("path", INVALID, ids=lambda p: p.stem)
def test_invalid_graph_reports_each_error_at_its_line(path: Path) -> None:
    expected = expectations(path)
    assert expected, f"{path.name} has no '# expect:' line"
    with pytest.raises(GraphError) as info:
        Graph.from_file(path)
    assert_exactly(info.value.diagnostics, expected, path)
    assert info.value.errors


@pytest.mark.parametrize("path", VALID, ids=lambda p: p.stem)
def test_valid_graph_loads(path: Path) -> None:
    graph = Graph.from_file(path)
    assert graph.nodes
    assert_exactly(graph.warnings, expectations(path), path)


SHIPPED = sorted((TESTS.parent / "graphs").glob("*.yaml"))


@pytest.mark.parametrize("path", [*SHIPPED, *VALID], ids=lambda p: p.name)
def test_every_valid_graph_file_validates_against_the_published_schema(path: Path) -> None:
    """``flowrt schema graph`` (for editors and CI linters) refused the shipped graphs: a
    duration written ``50ms``, an input written ``cam.frame``, ``trigger: loop``."""
    import jsonschema

    from flowrt.graph.spec import GraphSpec

    schema = GraphSpec.model_json_schema(by_alias=True)
    jsonschema.Draft202012Validator.check_schema(schema)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    errors = [
        f"{'/'.join(map(str, e.absolute_path))}: {e.message}"
        for e in jsonschema.Draft202012Validator(schema).iter_errors(data)
    ]
    assert not errors, errors[:5]


@pytest.mark.parametrize(
    ("deadline", "valid"),
    [("10ms", True), (" 1.5 s", True), ("200us", True), (20, True), ("1e3us", True),
     ("fast", False), ("10 min", False), ("ms", False)],
)  # fmt: skip
def test_the_published_schema_refuses_a_duration_the_loader_refuses(
    deadline: object, valid: bool
) -> None:
    """The schema took any text for a duration (``deadline: fast``), which ``validate``
    refuses."""
    import jsonschema

    from flowrt.graph.spec import GraphSpec

    schema = GraphSpec.model_json_schema(by_alias=True)
    data = {"nodes": {"a": {"kind": "counter", "deadline": deadline}}}
    errors = list(jsonschema.Draft202012Validator(schema).iter_errors(data))
    assert (not errors) is valid, [e.message for e in errors]


def test_fixtures_cover_every_check() -> None:
    """The table has a case for each check the graph-file format promises."""
    stated = "\n".join(str(e) for p in INVALID for e in expectations(p))
    for fragment in [
        "YAML syntax",
        "empty graph file",
        "a graph file is a mapping",
        "duplicate key",
        "unknown field 'priorty' (did you mean 'priority'?)",
        "unknown node kind 'countr' (did you mean 'counter'?)",
        "input from unknown node 'tik' (did you mean 'tick'?)",
        "unknown frame source 'cma' (did you mean 'cam'?)",
        "has no output 'valeu' (its outputs: value) (did you mean 'value'?)",
        "has no input 'inptu' (its inputs: input) (did you mean 'input'?)",
        "incompatible port types",
        "required input 'input' of sink is not connected",
        "cycle in the graph",
        "phase 4 must be less than period 4",
        "phase 10 ms must be less than the period 10 ms",
        "period must be a positive number of frames, got 0",
        "timer period must be positive, got 0 ms",
        "deadline: must be positive, got 0 ms",
        "deadline: must be positive, got -5 ms",
        "which produces no frames",
        "must be a finite duration, got nan",
        "timer period must be at least 0.1 ms",
        "timer period must be at most 3600000 ms",
        "watchdog: must be between 1 ms and 3600000 ms",
        "cpus.0: Input should be less than or equal to 8191",
        "period must be at most 100000 frames",
        "front_cam.truth produces SceneTruth, ball.frame expects Frame",
        "host 'example.invalid' does not resolve",
        "above the 64 MiB limit of one frame: set allow_large: true",
        "YAML tag '!!python/object/apply:os.system' is not allowed",
    ]:
        assert fragment in stated, f"no invalid-*.yaml fixture expects {fragment!r}"
    warned = [e for p in VALID for e in expectations(p) if e.severity is Severity.warning]
    assert any("longer than the period" in e.text for e in warned)
    assert any("of shared memory at start" in e.text for e in warned)


def test_all_errors_reported_at_once() -> None:
    """YAML-level, schema and structural problems of different nodes come in one error."""
    path = GRAPHS / "invalid-many-errors.yaml"
    with pytest.raises(GraphError) as info:
        Graph.from_file(path)
    errors = info.value.errors
    assert len(errors) == len(expectations(path)) >= 7
    assert [(d.line, d.column) for d in errors] == sorted((d.line, d.column) for d in errors)
    text = str(info.value)
    for phase in ("duplicate key", "unknown field", "unknown node kind", "incompatible"):
        assert phase in text


def test_deadline_warning_does_not_fail() -> None:
    graph = Graph.from_file(GRAPHS / "valid-deadline-warning.yaml")
    assert [d.severity for d in graph.warnings] == [Severity.warning] * 2
    assert set(graph.nodes) == {"tick", "cam", "slow", "ok"}


def test_a_deadline_warning_is_said_beside_the_files_errors() -> None:
    """It appeared only once the error was fixed: every problem at once, warnings too."""
    text = (
        "nodes:\n"
        "  tick: {kind: counter, trigger: {timer: 10ms}, deadline: 20ms}\n"
        "  bad: {kind: sink, trigger: {frame: nosuch.frame}, inputs: {input: tick.value}}\n"
    )
    with pytest.raises(GraphError) as e:
        Graph.from_text(text, "g.yaml")
    said = [(d.severity, d.message) for d in e.value.diagnostics]
    assert (Severity.warning, "deadline 20 ms is longer than the period 10 ms") in said
    assert any(sev is Severity.error and "nosuch" in m for sev, m in said)


def test_unreadable_files_are_graph_errors(tmp_path: Path) -> None:
    with pytest.raises(GraphError, match="cannot read graph file"):
        Graph.from_file(tmp_path / "missing.yaml")
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(GraphError, match="not UTF-8"):
        Graph.from_file(bad)


@pytest.mark.parametrize(
    ("text", "where", "fragment"),
    [
        ("nodes:\x00\n", (1, 7), "control character U+0000"),
        ("nodes: &a\n  x: *a\n", (1, 8), "recursive alias"),
        ("? [a, b]\n: 1\n", (1, 3), "a key must be a plain name"),
        ("nodes: !foo bar\n", (1, 8), "YAML tag '!foo' is not allowed"),
        (
            "nodes:\n  t:\n    cpus: !!python/object/apply:os.system [1]\n",
            (3, 11),
            "YAML tag '!!python/object/apply:os.system' is not allowed",
        ),
        (
            "nodes: !!python/object/apply:os.system {t: {kind: counter}}\n",
            (1, 8),
            "YAML tag '!!python/object/apply:os.system' is not allowed",
        ),
        ("nodes:\n  t: {kind: !!python/name:os.system }\n", (2, 13), "YAML tag '!!python/name"),
        ("nodes:\n  !!str t: {kind: counter}\n", (2, 3), "YAML tag '!!str' is not allowed"),
        ("nodes:\n  t: {kind: counter, priority: !!int 5}\n", (2, 32), "YAML tag '!!int'"),
        ("[" + "1," * 60_000 + "1]", (1, 1), "graph file too large: more than 50000 values"),
        ("a: 1\n---\nb: 2\n", (2, 1), "expected a single document"),
        ("[" * 1000 + "]" * 1000, (1, 1), "nested too deeply"),
        ("nodes:\n  t:\n    kind: counter\n    trigger: {input: 5}\n", (4, 15), "valid list"),
    ],
    ids=[
        "nul",
        "recursive-alias",
        "list-key",
        "unknown-tag",
        "tag-on-sequence",
        "tag-on-mapping",
        "tag-on-scalar",
        "tag-on-key",
        "standard-tag",
        "too-many-values",
        "two-documents",
        "deep",
        "union",
    ],
)
def test_odd_yaml_is_a_located_error(text: str, where: tuple[int, int], fragment: str) -> None:
    with pytest.raises(GraphError) as info:
        Graph.from_text(text, "odd.yaml")
    hits = [d for d in info.value.errors if fragment in d.message]
    assert hits, str(info.value)
    assert (hits[0].line, hits[0].column) == where


# --- a node whose params fail: its params-given ports are not reported as missing -----------


def _can_graph(
    robot_dbc: str = "robot.dbc",
    chassis_dbc: str = "robot.dbc",
    robot_in: str = "WheelSpeeds",
    chassis_out: str = "Infrared",
    world_from: str = "chassis",
    exported: str = "Battery",
) -> str:
    """graphs/can.yaml's shape: a CAN node fed by another, a CAN node feeding another and
    exported; the CAN nodes' ports named after their DBC's messages."""
    return f"""\
nodes:
  wheels:
    kind: can-signals
    params: {{rate_ms: 10, signals: {{LeftSpeed: {{value: 1}}}}}}
  robot:
    kind: can
    params: {{interface: virtual, channel: r, dbc: {robot_dbc}}}
    inputs:
      {robot_in}: wheels.values
  chassis:
    kind: can
    params: {{interface: virtual, channel: r, dbc: {chassis_dbc}}}
  world:
    kind: rtdb
    inputs:
      wheels: {world_from}.WheelSpeeds
      infrared: {world_from}.{chassis_out}
export:
  robot/battery: chassis.{exported}
"""


_NO_DBC = "nosuch.dbc: no such file"


@pytest.mark.parametrize(
    ("graph", "errors"),
    [
        # the DBC's messages are the CAN nodes' ports: without it none of them can be checked
        (
            _can_graph(robot_dbc="nosuch.dbc", chassis_dbc="nosuch.dbc"),
            [("nodes.robot.params.dbc", _NO_DBC), ("nodes.chassis.params.dbc", _NO_DBC)],
        ),
        (
            _can_graph(chassis_dbc="nosuch.dbc", chassis_out="Infrred", exported="Batery"),
            [("nodes.chassis.params.dbc", _NO_DBC)],
        ),
        # with the DBC read, a misspelt port is an error of its own, at each side
        (
            _can_graph(robot_in="WheelSpeed"),
            [
                (
                    "nodes.robot.inputs.WheelSpeed",
                    "can has no input 'WheelSpeed' (its inputs: ",
                ),
            ],
        ),
        (
            _can_graph(chassis_out="Infrred"),
            [("nodes.world.inputs.infrared", "node 'chassis' (can) has no output 'Infrred'")],
        ),
        (
            _can_graph(exported="Batery"),
            [("export.robot/battery", "node 'chassis' has no output 'Batery'")],
        ),
        # an error that does not follow from the params is still told
        (
            _can_graph(robot_dbc="nosuch.dbc", world_from="chasis"),
            [
                ("nodes.robot.params.dbc", _NO_DBC),
                ("nodes.world.inputs.wheels", "input from unknown node 'chasis'"),
                ("nodes.world.inputs.infrared", "input from unknown node 'chasis'"),
            ],
        ),
    ],
    ids=[
        "no-dbc",
        "no-dbc-and-its-ports",
        "misspelt-input",
        "misspelt-output",
        "misspelt-export",
        "no-dbc-and-unknown-node",
    ],
)
def test_ports_of_a_node_with_invalid_params_are_not_reported(
    tmp_path: Path, graph: str, errors: list[tuple[str, str]]
) -> None:
    path = tmp_path / "can.yaml"  # robot.dbc is not beside it: the one in flowrt.nodes
    path.write_text(graph, encoding="utf-8")
    with pytest.raises(GraphError) as info:
        Graph.from_file(path)
    got = [(d.key, d.message) for d in info.value.errors]
    assert len(got) == len(errors), str(info.value)
    for (key, message), (want_key, fragment) in zip(got, errors, strict=True):
        assert key == want_key, str(info.value)
        assert fragment in message, str(info.value)


# --- GraphBuilder: the same model as YAML ---------------------------------------------------


def test_builder_gives_the_same_model_as_yaml() -> None:
    from_yaml = Graph.from_file(GRAPHS / "valid-frames.yaml")
    g = GraphBuilder("frames")
    g.add("cam", FrameSource, params={"period_ms": 10})
    g.add(
        "every",
        "graphkinds:FrameReader",
        trigger={"frame": "cam"},
        priority=40,
        inputs={"frame": "cam.frame"},
    )
    g.add(
        "fourth",
        FrameReader,
        trigger=FrameTrigger(frame="cam", period=4, phase=1),
        priority=30,
        inputs={"frame": {"from": "cam.frame"}},
    )
    g.add(
        "eighth",
        FrameReader,
        trigger={"frame": "cam.frame", "period": 8, "phase": 3},
        priority=20,
        inputs={"frame": "cam.frame"},
    )
    built = g.build()
    assert built.spec == from_yaml.spec
    assert list(built.nodes) == list(from_yaml.nodes)
    for name, node in built.nodes.items():
        other = from_yaml.nodes[name]
        assert (node.cls, node.trigger, node.params) == (other.cls, other.trigger, other.params)
    assert built.edges == from_yaml.edges


@pytest.mark.parametrize(
    ("add", "message"),
    [
        (
            {"name": "tick", "kind": "countr", "trigger": {"timer": "10ms"}},
            "nodes.tick.kind: unknown node kind 'countr' (did you mean 'counter'?)",
        ),
        (
            {"name": "tick", "kind": "counter", "trigger": {"timer": "10ms"}, "priorty": 3},
            "nodes.tick.priorty: unknown field 'priorty' (did you mean 'priority'?)",
        ),
        (
            {"name": "tick", "kind": "counter", "trigger": {"timer": "10ms", "phase": "10ms"}},
            "nodes.tick.trigger.phase: phase 10 ms must be less than the period 10 ms",
        ),
        (  # a tuple given too few items: said of the list, not of an item the file lacks
            {"name": "cam", "kind": "capture", "params": {"size": [320]}},
            "nodes.cam.params.size: too few items: none at position 1 (from 0)",
        ),
    ],
    ids=["kind", "field", "phase", "short tuple"],
)
def test_builder_reports_the_same_errors(add: dict[str, object], message: str) -> None:
    g = GraphBuilder("typos")
    g.add(**add)  # type: ignore[arg-type]
    with pytest.raises(GraphError) as info:
        g.build()
    assert [d.message for d in info.value.errors] == [message.split(": ", 1)[1]]
    assert info.value.errors[0].key == message.split(": ", 1)[0]
    # No file, so no invented line number: the key says where.
    assert str(info.value).startswith(f"<python>: error: {message}")


# --- never a crash, always a located error -------------------------------------------------

_WORDS = [
    "nodes", "name", "kind", "params", "trigger", "timer", "frame", "period", "phase",
    "input", "inputs", "loop", "deadline", "priority", "placement", "process", "from",
    "policy", "latest", "queue", "size", "modes", "initial_mode", "restart", "watchdog",
    "counter", "sink", "relay", "burn", "graphkinds:FrameSource", "graphkinds:FrameReader",
    "tick", "out", "cam", "tick.value", "cam.frame", "10ms", "0", "-1", "4", "1.5s",
    "true", "null", "~", "&a", "*a", "!!int", "!tag", "<<",
]  # fmt: skip
_PUNCT = [": ", ":", "- ", "-", "{", "}", "[", "]", ", ", "#", "'", '"', "|", ">", "?", "\t"]
_SPACE = ["\n", "\n  ", "\n    ", "\n      ", " ", "  "]
_TOKENS = st.sampled_from(_WORDS + _PUNCT + _SPACE) | st.text(
    alphabet=string.printable + "\x00\x85é", max_size=4
)

_SEEDS = [p.read_text(encoding="utf-8") for p in VALID]


def assert_graph_or_located_error(text: str) -> None:
    """Any text gives a Graph, or a GraphError whose every diagnostic has a place."""
    error: GraphError | None = None
    try:
        diags = Graph.from_text(text, "g.yaml").warnings
    except GraphError as e:
        error, diags = e, e.diagnostics
    assert error is None or error.errors, "a GraphError without errors"
    for d in diags:
        assert d.file == "g.yaml"
        assert d.line >= 1, str(d)
        assert d.column >= 1, str(d)
        assert d.message


_FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_FAST
@given(st.lists(_TOKENS, max_size=60).map("".join))
def test_random_text_never_crashes(text: str) -> None:
    assert_graph_or_located_error(text)


@st.composite
def mutated_graphs(draw: st.DrawFn) -> str:
    text = draw(st.sampled_from(_SEEDS))
    for _ in range(draw(st.integers(1, 4))):
        lines = text.split("\n")
        op = draw(st.sampled_from(["insert", "delete", "dup-line", "drop-line", "swap-lines"]))
        if op == "insert":
            at = draw(st.integers(0, len(text)))
            text = text[:at] + draw(_TOKENS) + text[at:]
        elif op == "delete":
            at = draw(st.integers(0, len(text)))
            text = text[:at] + text[at + draw(st.integers(1, 12)) :]
        else:
            i = draw(st.integers(0, len(lines) - 1))
            j = draw(st.integers(0, len(lines) - 1))
            if op == "dup-line":
                lines.insert(j, lines[i])
            elif op == "drop-line":
                del lines[i]
            else:
                lines[i], lines[j] = lines[j], lines[i]
            text = "\n".join(lines)
    return text


@_FAST
@given(mutated_graphs())
def test_mutated_graphs_never_crash(text: str) -> None:
    assert_graph_or_located_error(text)


_SCALARS = st.sampled_from(_WORDS) | st.integers(-3, 100) | st.floats(allow_nan=False) | st.none()
_KEYS = st.sampled_from(_WORDS) | st.text(max_size=5)
_DATA = st.recursive(
    _SCALARS,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(_KEYS, inner, max_size=4),
    max_leaves=20,
)


@_FAST
@given(st.dictionaries(st.sampled_from(["nodes", "name", "modes", "initial_mode"]), _DATA))
def test_random_structures_never_crash(data: dict[str, object]) -> None:
    assert_graph_or_located_error(yaml.safe_dump(data))


_NODE_KEYS = ["kind", "params", "trigger", "deadline", "priority", "placement", "inputs", "x"]


@st.composite
def graphs_with_a_bad_value(draw: st.DrawFn) -> str:
    """A valid graph with one node field, trigger field or input replaced by anything."""
    data = yaml.safe_load(draw(st.sampled_from(_SEEDS)))
    for _ in range(draw(st.integers(1, 3))):
        node = data["nodes"][draw(st.sampled_from(sorted(data["nodes"])))]
        key = draw(st.sampled_from(_NODE_KEYS))
        inner = node.get(key)
        if isinstance(inner, dict) and inner and draw(st.booleans()):
            inner[draw(st.sampled_from(sorted(inner)))] = draw(_DATA)
        else:
            node[key] = draw(_DATA)
    return yaml.safe_dump(data, sort_keys=False)


@pytest.mark.slow  # over 1 s of CPU (hypothesis)
@_FAST
@given(graphs_with_a_bad_value())
def test_graphs_with_a_bad_value_never_crash(text: str) -> None:
    assert_graph_or_located_error(text)


# --- every built-in kind's params (issue 32 item 6) ---------------------------------------

_BAD_PARAM_VALUES = [None, [1, 2], {"a": 1}, 10**400, "x", -1, 1e308, float("nan"), True, ""]


def _kind_fields() -> list[tuple[str, str]]:
    from flowrt.graph._registry import available_kinds, resolve_kind

    out = []
    for kind in available_kinds():
        cls = resolve_kind(kind)
        for name in getattr(cls.Params, "model_fields", {}):
            out.append((kind, name))
    return out


@pytest.mark.parametrize(("kind", "field"), _kind_fields())
def test_every_built_in_kind_refuses_bad_params_with_a_location(kind: str, field: str) -> None:
    """Each param of each built-in kind, given each odd value: a Graph or a located error,
    never a traceback (arbiter's timeout given as null, a list, a mapping or 10**400 was)."""
    import math

    for bad in _BAD_PARAM_VALUES:
        value = ".nan" if isinstance(bad, float) and math.isnan(bad) else bad
        text = yaml.safe_dump({"nodes": {"n": {"kind": kind, "params": {field: value}}}})
        if value == ".nan":
            text = text.replace("'.nan'", ".nan")
        assert_graph_or_located_error(text)
