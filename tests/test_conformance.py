"""The conformance matrix (issue 38): every built-in stream crossed with every consumer.

Rows: the streams of a graph per group of built-in kinds (:data:`MATRIX`), generated from the
registry: every kind of the ``flowrt.nodes`` entry points must have a row (a graph that runs
it with example params) or a written reason (:data:`NOT_A_SOURCE`), so a new kind without one
fails here. Dynamic outputs (a ``can`` node's messages, a ``sync`` node's set) are rows too.

Cells, each a test over every stream of a graph, with outside tools (tests/_conformance.py):

- ``recorded``: ``flowrt record`` (one recording per graph, shared by the cells), read back
  with the ``mcap`` reader; every JSON message valid against its own schema (``jsonschema``),
  every JSON schema within the apps' ``parseJsonSchema`` rules, every protobuf message decoded
  with the descriptors in the file; every output of the graph present.
- ``live``: the graph served by ``FoxgloveLive`` (``raw`` images: the recording's channels)
  and read by a ``foxglove.websocket.v1`` client: every recorded topic advertised with the
  same schema name, encodings and schema; every live JSON message valid; audio as
  ``foxglove.RawAudio`` with >= 95 % of its blocks.
- ``replay``: the recording replayed into the same graph (``flowrt replay --graph``).
- ``zenoh``: every output exported over Zenoh and imported back (two runtimes in this process,
  127.0.0.1, no scouting) and read by a plain Zenoh subscriber: every imported value one the
  exporter published, in order (tuples, typed values, frames, audio); every plain payload the
  recording's message (the recorded schema's name, valid against it). See :func:`zenoh_cell`.
- ``ajv``: the JavaScript side, in tests/js/mcap_validate.mjs (``@mcap/core`` + ``ajv``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from _conformance import Channel, LiveClient, audio_times, blocks_delivered, read_recording

ROOT = Path(__file__).resolve().parents[1]

# graph -> the built-in kinds it is the example of (with their params in the file)
MATRIX: dict[str, tuple[str, ...]] = {
    "graphs/cambada.yaml": ("capture", "tracker"),
    "graphs/can.yaml": ("can", "can-signals", "rtdb"),
    "graphs/avsync.yaml": ("audio", "sync"),
    "graphs/agent.yaml": (
        "robot_sim",
        "track_target",
        "avoid_obstacles",
        "follow_wall",
        "arbiter",
        "decision",
    ),
    "tests/graphs/matrix/basics.yaml": (
        "counter",
        "relay",
        "burn",
        "health",
        "joystick",
        "teleop",
        "estop",
    ),
    "graphs/haptic.yaml": ("haptic", "vision_force", "haptic_view"),
}
# kinds that publish no stream of their own: the reason each is no row
NOT_A_SOURCE: dict[str, str] = {
    "sink": "no outputs (it is in tests/graphs/matrix/basics.yaml)",
    "display": "no outputs: a web view (in graphs/cambada.yaml; --no-display in the cells)",
    "recorder": "no outputs: it is the recorded cell itself",
    "replay": "its outputs are recorded streams: it is the replay cell itself",
}
GRAPHS = list(MATRIX)
RECORD_SECONDS = "2"
LIVE_SECONDS = 3.0
AUDIO_BLOCK = 1024 / 48000  # graphs/avsync.yaml's mic


def test_every_builtin_kind_has_a_row() -> None:
    """A new kind fails here until it has a graph in MATRIX (or a reason)."""
    from flowrt.graph._registry import available_kinds

    covered = {k for kinds in MATRIX.values() for k in kinds} | set(NOT_A_SOURCE)
    missing = sorted(set(available_kinds()) - covered)
    assert missing == [], f"built-in kinds without a conformance row: {missing}"
    for graph, kinds in MATRIX.items():
        text = (ROOT / graph).read_text()
        for kind in kinds:
            assert re.search(rf"kind: {re.escape(kind)}\b", text), (graph, kind)


# --- one recording per graph ------------------------------------------------------------------

_recordings: dict[str, Path] = {}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _recordings


def record(graph: str, recordings: dict[str, Path], tmp: Path) -> Path:
    """The session folder of ``graph`` recorded for ``RECORD_SECONDS`` (once per module)."""
    if graph not in recordings:
        out = tmp / re.sub(r"\W", "_", graph)
        stats = str(out) + ".stats.json"
        r = _flowrt(
            "record", graph, "-o", str(out), "--duration", RECORD_SECONDS, "--stats-json", stats
        )
        assert r.returncode == 0, r.stderr[-2000:]
        (session,) = out.glob("rec_*")
        recordings[graph] = session
    return recordings[graph]


def _flowrt(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args, "--no-ui", "--no-display"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=180,
        env={**os.environ, "COLUMNS": "200"},
    )


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("matrix")


def recorded(graph: str, recordings: dict[str, Path], scratch: Path) -> dict[str, Channel]:
    session = record(graph, recordings, scratch)
    (path,) = session.glob("*.mcap")
    return read_recording(path)


def _outputs(graph: str) -> list[str]:
    """Every output of ``graph`` (declared and made by params), as ``node.port``."""
    from flowrt.graph._resolve import Graph

    g = Graph.from_file(ROOT / graph)
    return [
        f"{name}.{port}"
        for name, n in g.nodes.items()
        for port in {**n.cls.outputs, **n.cls.params_outputs(n.params)}
    ]


# --- the cells ---------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("graph", GRAPHS)
def test_recorded(graph: str, recordings: dict[str, Path], scratch: Path) -> None:
    channels = recorded(graph, recordings, scratch)
    bad = {t: c.invalid for t, c in channels.items() if c.invalid}
    assert bad == {}, bad
    rules = {t: c.problems for t, c in channels.items() if c.problems}
    assert rules == {}, rules
    # every output that published is a stream of the recording (a set: its members too)
    session = recordings[graph]
    edges = json.loads(Path(str(session.parent) + ".stats.json").read_text())["edges"]
    published = {
        e["name"].split("->")[0]: e["published"] for e in edges if "->recorder." in e["name"]
    }
    assert set(published) >= set(_outputs(graph)) - {"recorder"}, "an output not recorded"
    for out, n in published.items():
        if n:
            assert out in channels, f"{out} published {n} but is not in the recording"


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.parametrize("graph", GRAPHS)
async def test_live(graph: str, recordings: dict[str, Path], scratch: Path) -> None:
    import flowrt
    from flowrt.graph._resolve import Graph
    from flowrt.recording.live import FoxgloveLive

    channels = recorded(graph, recordings, scratch)
    g = Graph.from_file(ROOT / graph)
    for n in g.nodes.values():  # the web views on any free port
        if getattr(n.cls, "listens", False):
            n.params = n.params.model_validate({**n.params.model_dump(), "port": 0})
    live = FoxgloveLive(port=0, image_format="raw")  # the recording's image channels
    client = LiveClient("")
    async with flowrt.Runtime(g, monitors=[live]):
        client.url = f"ws://127.0.0.1:{live.port}/"
        await client.run(LIVE_SECONDS)
    assert client.subprotocol == "foxglove.websocket.v1"
    seen = client.channels
    missing = sorted(t for t in channels if t not in seen)
    assert missing == [], f"recorded but not served live: {missing}"
    for topic, rec in channels.items():
        got = seen[topic]
        same = (got.schema_name, got.schema_encoding, got.message_encoding)
        assert same == (rec.schema_name, rec.schema_encoding, rec.message_encoding), topic
        if rec.schema_encoding == "jsonschema":
            assert json.loads(got.schema) == json.loads(rec.schema), topic
        else:
            assert got.schema == rec.schema, topic
    bad = {t: c.invalid for t, c in seen.items() if c.invalid}
    assert bad == {}, bad
    rules = {t: c.problems for t, c in seen.items() if c.problems}
    assert rules == {}, rules
    for topic, ch in seen.items():
        if ch.schema_name == "foxglove.RawAudio":
            share = blocks_delivered(audio_times(ch.schema, client.arrivals[topic]), AUDIO_BLOCK)
            assert share >= 0.95, f"{topic}: {share:.0%} of the audio blocks live"
            assert len(client.arrivals[topic]) >= 0.5 * LIVE_SECONDS / AUDIO_BLOCK


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("graph", GRAPHS)
def test_replay(graph: str, recordings: dict[str, Path], scratch: Path) -> None:
    session = record(graph, recordings, scratch)
    stats = scratch / ("replay_" + re.sub(r"\W", "_", graph) + ".json")
    r = _flowrt(
        "replay", str(session), "--graph", graph, "--duration", "2", "--stats-json", str(stats)
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "replaying" in r.stdout
    nodes = {n["name"]: n for n in json.loads(stats.read_text())["nodes"]}
    stood_in = [n for n, s in nodes.items() if s["kind"].startswith("replay-as-")]
    assert stood_in, f"no source node replayed: {sorted(nodes)}"
    for name in stood_in:
        assert nodes[name]["completions"] > 0, name
    failing = {n: s["reason"] for n, s in nodes.items() if s["state"] in ("error", "failed")}
    assert failing == {}, failing


ZENOH_SECONDS = 3.0


async def zenoh_cell(graph: str, channels: dict[str, Channel]) -> None:
    """One exporting runtime (every output under ``m/NODE/PORT``, listening on a free
    127.0.0.1 port, no scouting), one importing runtime (an import per output) and a plain
    Zenoh subscriber, for ``ZENOH_SECONDS``. Equal values: every imported value is one the
    exporter published, in order (tuples as tuples, a typed value's fields by name, frames
    pixel for pixel, audio sample for sample, a ``timestamp`` rebased within 0.25 s); every
    JSON payload the plain subscriber reads is the recording's message: its schema named in
    the Zenoh encoding as the recorded channel's, valid against that channel's schema."""
    import asyncio
    import socket

    import yaml
    import zenoh

    import flowrt
    from flowrt.graph._resolve import Graph

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    outputs = [o for o in _outputs(graph) if not o.startswith("recorder.")]
    base = Graph.from_file(ROOT / graph)
    frames = {o for o in outputs if getattr(_output(base, o), "type", None) is flowrt.Frame}
    doc = yaml.safe_load((ROOT / graph).read_text())
    doc["zenoh"] = {"listen": [endpoint]}
    doc["export"] = {_key(o): {"from": o, "size": 1024} for o in outputs}
    ex = _with_free_ports(
        Graph.from_text(yaml.safe_dump(doc), graph, base_dir=(ROOT / graph).parent)
    )
    names = {o: f"zi{i}" for i, o in enumerate(outputs)}
    im_doc = {
        "name": "zenoh-cell",
        "nodes": {},
        "zenoh": {"listen": [], "connect": [endpoint]},
        "import": {
            names[o]: {"key": _key(o), "stale_after": "never", "size": 1024, "frames": o in frames}
            for o in outputs
        },
    }
    im = Graph.from_text(yaml.safe_dump(im_doc), "zenoh-cell.yaml")

    plain: dict[str, list[tuple[str, bytes]]] = {o: [] for o in outputs}
    by_key = {_key(o): o for o in outputs}

    def on_sample(sample: Any) -> None:  # a plain program: docs/zenoh.md alone
        out = by_key.get(str(sample.key_expr))
        if out is not None and out not in frames:
            plain[out].append((str(sample.encoding), sample.payload.to_bytes()))

    published: dict[str, list[Any]] = {o: [] for o in outputs}
    imported: dict[str, list[Any]] = {o: [] for o in outputs}
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    subs: list[tuple[Any, list[Any], str]] = []

    async def keep() -> None:  # frames copied and released at once: no pool slot pinned
        while True:
            await asyncio.sleep(0.02)
            for sub, into, topic in subs:
                while (v := sub.take_held()) is not flowrt.edges.EMPTY:
                    into.append(_kept(v, topic))

    keeper = asyncio.create_task(keep())
    try:
        async with flowrt.Runtime(ex) as ex_rt:
            subs += [(ex_rt.subscribe(o, size=4096), published[o], o) for o in outputs]
            session = await asyncio.to_thread(zenoh.open, conf)
            try:
                session.declare_subscriber("m/**", on_sample)
                async with flowrt.Runtime(im) as im_rt:
                    subs += [
                        (im_rt.subscribe(f"{names[o]}.output", size=4096), imported[o], o)
                        for o in outputs
                    ]
                    await asyncio.sleep(ZENOH_SECONDS)
            finally:
                await asyncio.to_thread(session.close)
    finally:
        keeper.cancel()
    problems: list[str] = []
    for o in outputs:
        if not published[o]:
            continue  # an output that did not publish in the time (a CAN status: 1 s)
        if not imported[o]:
            problems.append(f"{o}: published {len(published[o])}, none imported")
            continue
        if why := _subsequence(imported[o], published[o]):
            problems.append(f"{o}: {why}")
        if o not in frames:
            problems += _plain_is_recorded(o, plain[o], channels.get(o))
    assert problems == [], problems


def _key(output: str) -> str:
    return "m/" + output.replace(".", "/")


def _output(g: Any, output: str) -> Any:
    node, port = output.split(".")
    return g.nodes[node].cls.outputs.get(port)


def _with_free_ports(g: Any) -> Any:
    for n in g.nodes.values():  # the web views on any free port
        if getattr(n.cls, "listens", False):
            n.params = n.params.model_validate({**n.params.model_dump(), "port": 0})
    return g


def _kept(v: Any, topic: str) -> Any:
    """A received value kept for the comparison: a frame as (seq, pixels), its slot freed; a
    set as its index (what goes over Zenoh, as in a recording: its frames are streams)."""
    import flowrt
    from flowrt.recording.streams import is_set, split_set

    if is_set(v):
        for m in v.values():
            if isinstance(m, flowrt.Frame):
                m.release()
        return split_set(topic, v)[0]
    if isinstance(v, flowrt.Frame):
        kept = ("frame", int(v.seq), v.pixel_format, v.data.copy())
        v.release()
        return kept
    return v


def _subsequence(got: list[Any], sent: list[Any]) -> str:
    """'' when ``got`` is, in order, a subsequence of ``sent`` (equal values), else why not."""
    i = 0
    for n, g in enumerate(got):
        start = i
        while i < len(sent) and not _same(g, sent[i]):
            i += 1
        if i == len(sent):
            near = [w for s in sent[start:] if not (w := _why(g, s)).startswith(("index:", "t:"))]
            near = near[:3] or [_why(g, s) for s in sent[start : start + 3]]
            return f"imported value {n} of {len(got)} was never published: {near}"
        i += 1
    return ""


def _same(a: Any, b: Any) -> bool:
    return _why(a, b) == ""


def _why(a: Any, b: Any, path: str = "") -> str:
    """'' when the imported ``a`` equals the published ``b`` (see :func:`zenoh_cell`)."""
    import dataclasses
    import math
    import types

    import numpy as np

    import flowrt

    at = path or "<value>"
    if isinstance(b, flowrt.AudioBlock):
        if not isinstance(a, flowrt.AudioBlock) or a.rate != b.rate:
            return f"{at}: {a!r:.60} is not the audio block"
        ok = np.allclose(a.samples, np.asarray(b.samples, np.float32).reshape(a.samples.shape),
                         atol=2 / 32768)  # fmt: skip
        return "" if ok and abs(a.timestamp - b.timestamp) < 0.25 else f"{at}: other samples"
    if isinstance(b, tuple) and b[:1] == ("frame",):
        same = a[:3] == b[:3] and np.array_equal(a[3], b[3])
        return "" if same else f"{at}: frame {a[:3]} is not {b[:3]}"
    if (dataclasses.is_dataclass(b) and not isinstance(b, type)) or hasattr(b, "model_dump"):
        name = f"{type(b).__module__}.{type(b).__qualname__}"
        if not isinstance(a, types.SimpleNamespace) or getattr(a, "_type", "") != name:
            return f"{at}: {type(a).__name__} {getattr(a, '_type', '')!r}, sent a {name}"
        fields = (
            {f.name: getattr(b, f.name) for f in dataclasses.fields(b)}
            if dataclasses.is_dataclass(b)
            else dict(b)
        )
        got = {k: v for k, v in vars(a).items() if not k.startswith("_")}
        return _why(got, fields, path)
    if isinstance(b, dict):  # a None field may be left out
        return _why_dict(a, b, path)
    if isinstance(b, float) and not math.isfinite(b):
        return "" if a is None else f"{at}: {a!r} for {b!r}"
    if isinstance(b, np.ndarray | np.generic):
        b = b.tolist()
    if isinstance(b, bytes):
        return "" if a == b else f"{at}: {a!r:.60} for bytes"
    if isinstance(b, tuple | list):
        return _why_sequence(a, b, at)
    if isinstance(b, float) and isinstance(a, int | float):
        return "" if math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-12) else f"{at}: {a} for {b}"
    if a != b or type(a) is not type(b):
        return f"{at}: {type(a).__name__} {a!r:.60} for {type(b).__name__} {b!r:.60}"
    return ""


def _why_dict(a: Any, b: dict[Any, Any], path: str) -> str:
    """:func:`_why` of a mapping: the same keys (a None field may be left out), each value
    the same, timestamps within the clocks' rebasing."""
    at = path or "<value>"
    keys, valued = {str(k) for k in b}, {str(k) for k in b if _value(b[k])}
    if not isinstance(a, dict) or set(a) - keys or valued - set(a):
        return f"{at}: {a!r:.80}, sent keys {sorted(keys)}"
    for k, v in b.items():
        if k == "timestamp" and isinstance(v, float):  # rebased on the importer's clock
            if not isinstance(a.get(k), float) or abs(a[k] - v) > 0.25:
                return f"{at}.timestamp: {a.get(k)!r} for {v!r}"
            continue
        if why := _why(a.get(str(k)), v, f"{path}.{k}" if path else str(k)):
            return why
    return ""


def _why_sequence(a: Any, b: tuple[Any, ...] | list[Any], at: str) -> str:
    """:func:`_why` of a tuple or list: the same type and length, each item the same."""
    if type(a) is not type(b) or len(a) != len(b):
        return f"{at}: {type(a).__name__} {a!r:.60} for {type(b).__name__} {b!r:.60}"
    for n, (x, y) in enumerate(zip(a, b, strict=True)):
        if why := _why(x, y, f"{at}[{n}]"):
            return why
    return ""


def _value(v: Any) -> bool:
    import math

    return not (v is None or (isinstance(v, float) and not math.isfinite(v)))


def _plain_is_recorded(out: str, got: list[tuple[str, bytes]], rec: Channel | None) -> list[str]:
    """What a plain subscriber read of ``out`` is the recording's message (see above)."""
    import jsonschema

    if not got:
        return [f"{out}: no sample for the plain subscriber"]
    if rec is None:
        return []  # not in the 2 s recording (a slow output): its schema is not known here
    problems = []
    names = {enc.partition(";")[2] for enc, _ in got}
    if names != {rec.schema_name}:
        problems.append(f"{out}: Zenoh encoding names {names}, recorded {rec.schema_name!r}")
    if rec.schema_encoding == "protobuf":  # audio: decoded with the recording's descriptors
        times = audio_times(rec.schema, [p for _, p in got])
        return problems + ([] if all(t > 1e9 for t in times) else [f"{out}: not Unix times"])
    validator = jsonschema.Draft202012Validator(json.loads(rec.schema))
    for _, payload in got[:200]:
        for err in validator.iter_errors(json.loads(payload)):
            problems.append(f"{out}: {err.message[:120]}")
            return problems
    return problems


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.subprocess
@pytest.mark.parametrize("graph", GRAPHS)
async def test_zenoh(graph: str, recordings: dict[str, Path], scratch: Path) -> None:
    await zenoh_cell(graph, recorded(graph, recordings, scratch))


@pytest.mark.slow
@pytest.mark.node
@pytest.mark.subprocess
@pytest.mark.parametrize("graph", GRAPHS)
def test_ajv(graph: str, recordings: dict[str, Path], scratch: Path) -> None:
    """The apps' own libraries: @mcap/core reads the file, ajv validates every JSON message."""
    modules = os.environ.get("FLOWRT_NODE_MODULES")
    node = shutil.which("node")
    if not modules or node is None:
        pytest.skip("needs Node.js and FLOWRT_NODE_MODULES with @mcap/core and ajv")
    session = record(graph, recordings, scratch)
    (path,) = session.glob("*.mcap")
    script = Path(modules).parent / "mcap_validate.mjs"  # ES modules resolve beside them
    shutil.copyfile(ROOT / "tests" / "js" / "mcap_validate.mjs", script)
    r = subprocess.run([node, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout)
    assert got["json_messages"] > 0
    assert got["invalid"] == {}, got["invalid"]


@pytest.mark.slow
@pytest.mark.subprocess
async def test_a_replayed_sync_set_holds_its_frames(
    recordings: dict[str, Path], scratch: Path
) -> None:
    """Issue 38 item 6: a set was recorded as repr strings; now its frames are streams of
    their own and a replay of the set alone gives frames back, stamped on the replay's clock."""
    import asyncio

    import flowrt

    session = record("graphs/avsync.yaml", recordings, scratch)
    g = flowrt.GraphBuilder("sets")
    g.add("rp", "replay", params={"path": str(session), "topics": ["pair.set"]})
    async with flowrt.Runtime(g.build()) as rt:
        value = await asyncio.wait_for(rt.subscribe("rp.message").get(), 20)
        now = rt.clock.now()
    assert isinstance(value["a"], flowrt.Frame)
    assert isinstance(value["b"], flowrt.Frame)
    assert value["a"].data.shape == (120, 160, 3)
    assert 0 <= now - value["stamp"] < 5  # the replay's clock, not epoch nanoseconds
    assert value["spread_ms"] <= 10


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("topic", ["pair.set", "/pair/set"])
async def test_a_ros2_recordings_sync_set_is_joined_again(scratch: Path, topic: str) -> None:
    """In the ``ros2`` profile the set's index names its members by their flowrt streams
    (``pair.set/a``) and the channels are ROS topics (``/pair/set/a``): a replay gave the
    references back instead of the frames. Joined now, the set asked for by either name."""
    import asyncio

    import flowrt

    out = scratch / f"ros2_sets_{topic.strip('/').replace('/', '_')}"
    r = _flowrt(
        "record", "graphs/avsync.yaml", "--profile", "ros2", "-o", str(out), "--duration", "3"
    )
    assert r.returncode == 0, r.stderr[-2000:]
    (session,) = out.glob("rec_*")
    g = flowrt.GraphBuilder("sets")
    g.add("rp", "replay", params={"path": str(session), "topics": [topic]})
    async with flowrt.Runtime(g.build()) as rt:
        value = await asyncio.wait_for(rt.subscribe("rp.message").get(), 20)
        now = rt.clock.now()
    assert isinstance(value["a"], flowrt.Frame), value
    assert isinstance(value["b"], flowrt.Frame), value
    assert value["a"].data.shape == (120, 160, 3)
    assert 0 <= now - value["stamp"] < 5
    r = _flowrt("replay", str(session), "--topics", topic)  # the command line takes both too
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_deterministic_log_validates_too(scratch: Path) -> None:
    """Issue 38 item 5: ``/flowrt/det/activation`` held mixed tuples its schema refused."""
    out = scratch / "deterministic"
    r = _flowrt(
        "record", "tests/graphs/matrix/basics.yaml", "--deterministic", "-o", str(out),
        "--duration", "2",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    (path,) = out.glob("*/*.mcap")
    channels = read_recording(path)
    assert {"/flowrt/det/activation", "/flowrt/det/output"} <= set(channels)
    bad = {t: c.invalid for t, c in channels.items() if c.invalid}
    assert bad == {}, bad
    rules = {t: c.problems for t, c in channels.items() if c.problems}
    assert rules == {}, rules
