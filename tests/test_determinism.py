"""Deterministic replay on virtual time: each activation re-executed in the recorded order with
exactly the inputs (and the clock, and the random numbers) it had.

Each case records a run with a ``deterministic: true`` recorder, then replays it inline: the
nodes trace (node, ctx.now(), what they held, their state) in both, and the traces must be
equal, the replay identical, every activation re-executed.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel

import flowrt
from flowrt import Frame, FrameTrigger, GraphBuilder, Input, Node, Output, Runtime, VirtualClock
from flowrt.cli.record import wait_for_writers
from flowrt.determinism import canonical, digest
from flowrt.determinism.log import LogError, read_log
from flowrt.determinism.report import report_lines

TRACE: list[tuple[Any, ...]] = []


class Cam(Node):
    """A frame source the test drives by publishing."""

    frame = Output(Frame)


class Ticker(Node):
    """A timer source: 1, 2, 3 ..."""

    tick = Output(int)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> int:
        self.n += 1
        return self.n


class Acc(Node):
    """Stateful: each output depends on every value before it, on ctx.now() and ctx.random,
    so a value missed, repeated, reordered or re-timed changes everything after it."""

    class Params(BaseModel):
        factor: int = 31

    value = Input(object)
    total = Output(int)

    def setup(self) -> None:
        self.total = 0

    def process(self, value: Any) -> int:
        v = value.seq if isinstance(value, Frame) else int(value)
        noise = self.ctx.random.randrange(1000)
        ms = round(self.ctx.now() * 1000)
        self.total = (self.total * self.params.factor + v + noise + ms) % 1_000_003
        TRACE.append((self.ctx.name, round(self.ctx.now(), 9), v, noise, self.total))
        return self.total

    def get_state(self) -> int:
        return self.total

    def set_state(self, total: int) -> None:
        self.total = total


class Fragile(Acc):
    """Raises on a value that is a multiple of 7: supervision restarts it (a fresh total, a
    fresh ``ctx.random``) after its back-off, and the failed activation published nothing."""

    def process(self, value: Any) -> int:
        if int(value) % 7 == 0:
            TRACE.append((self.ctx.name, round(self.ctx.now(), 9), int(value), "raised"))
            raise ValueError(f"{value} is a multiple of 7")
        return super().process(value)


class Pair(Node):
    """Two inputs, the second optional: what it held of each, and when it was published."""

    a = Input(object)
    b = Input(object, required=False)
    out = Output(object)

    def process(self, a: Any, b: Any) -> list[Any]:
        seen = [a, b, self.ctx.input_time("a")]
        TRACE.append((self.ctx.name, round(self.ctx.now(), 9), *seen))
        return seen


def frame(seq: int) -> Frame:
    return Frame(np.full((4, 4, 3), seq % 256, np.uint8), source="cam", seq=seq)


def recorder(g: GraphBuilder, session: Path, *topics: str) -> None:
    g.add(
        "rec",
        "recorder",
        # (virtual time gives the writer thread no time: room for every frame of a case)
        params={
            "session": str(session),
            "deterministic": True,
            "log_report": False,
            "max_frames": 64,
        },
        inputs={t: {"from": t, "policy": "lossless"} for t in topics},
    )


Drive = Callable[[Runtime, VirtualClock], Awaitable[None]]


async def frames(rt: Runtime, clock: VirtualClock, n: int = 16) -> None:
    for k in range(n):
        rt.publish("cam.frame", frame(k))
        await clock.advance(0.05)


def case_timers(g: GraphBuilder) -> Drive:
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("slow", Acc, trigger={"timer": "25ms", "phase": "5ms"}, inputs={"value": "tick.tick"})
    g.add("pair", Pair, trigger={"timer": "40ms"}, inputs={"a": "tick.tick", "b": "slow.total"})

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await clock.advance(0.5)

    return drive


def case_frame_phases(g: GraphBuilder) -> Drive:
    g.add("cam", Cam, trigger={"timer": 3_600_000}, enabled=False)
    for name, period, phase in (("every", 1, 0), ("p4ph1", 4, 1), ("p4ph3", 4, 3), ("p8", 8, 0)):
        g.add(
            name,
            Acc,
            trigger=FrameTrigger(frame="cam", period=period, phase=phase),
            inputs={"value": "cam.frame"},
        )

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await frames(rt, clock, 20)

    return drive


def case_input_triggers(g: GraphBuilder) -> Drive:
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("first", Acc, inputs={"value": {"from": "tick.tick", "policy": "queue"}})
    g.add("second", Acc, inputs={"value": {"from": "first.total", "policy": "queue"}})
    g.add("pair", Pair, inputs={"a": "second.total", "b": "tick.tick"})

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await clock.advance(0.3)

    return drive


def case_lossless_and_latest(g: GraphBuilder) -> Drive:
    g.add("cam", Cam, trigger={"timer": 3_600_000}, enabled=False)
    g.add("all", Acc, inputs={"value": {"from": "cam.frame", "policy": "lossless", "size": 4}})
    g.add(
        "newest",
        Acc,
        trigger={"timer": "120ms"},
        inputs={"value": {"from": "cam.frame", "policy": "latest"}},
    )

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        for k in range(24):  # bursts of 3 frames: the latest reader samples, lossless gets all
            rt.publish("cam.frame", frame(k))
            if k % 3 == 2:
                await clock.advance(0.05)

    return drive


def case_mode_change_mid_run(g: GraphBuilder) -> Drive:
    g.add("cam", Cam, trigger={"timer": 3_600_000}, enabled=False)
    g.add("fast", Acc, trigger=FrameTrigger(frame="cam"), inputs={"value": "cam.frame"})
    g.add(
        "slow",
        Acc,
        trigger=FrameTrigger(frame="cam", period=4, phase=2),
        inputs={"value": "cam.frame"},
    )
    g.mode("sprint", slow={"period": 2, "phase": 0}, fast={"params": {"factor": 7}})

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await frames(rt, clock, 10)
        rt.set_mode("sprint", force=True)
        await frames(rt, clock, 10)

    return drive


def case_swap_mid_run(g: GraphBuilder) -> Drive:
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("acc", Acc, inputs={"value": {"from": "tick.tick", "policy": "queue"}})
    g.add("after", Acc, inputs={"value": {"from": "acc.total", "policy": "queue"}})

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await clock.advance(0.15)
        await rt.swap("acc", Acc, {"factor": 3})  # a new instance, the old one's total
        await clock.advance(0.15)

    return drive


def case_failure_and_restart(g: GraphBuilder) -> Drive:
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add(
        "fragile",
        Fragile,
        inputs={"value": {"from": "tick.tick", "policy": "queue", "size": 64}},
        restart={"backoff": "30ms"},
    )
    g.add("after", Acc, inputs={"value": {"from": "fragile.total", "policy": "queue"}})

    async def drive(rt: Runtime, clock: VirtualClock) -> None:
        await clock.advance(0.4)

    return drive


CASES = {
    "timers": case_timers,
    "frame phases": case_frame_phases,
    "input triggers": case_input_triggers,
    "lossless and latest edges": case_lossless_and_latest,
    "mode change mid-run": case_mode_change_mid_run,
    "a failure and its restart": case_failure_and_restart,
    "a swap mid-run": case_swap_mid_run,
}


async def record(
    tmp_path: Path, case: Callable[[GraphBuilder], Drive], values: bool = True
) -> tuple[Any, Path]:
    """Run the case on virtual time with a deterministic recorder: (graph, session). With
    ``values`` the recorder also records every Acc output's value (else digests only)."""
    g = GraphBuilder("det")
    drive = case(g)
    nodes = g.build().nodes
    outputs = [f"{n}.total" for n in nodes if issubclass(nodes[n].cls, Acc)] if values else []
    session = tmp_path / "session"
    recorder(g, session, *outputs)
    graph = g.build()
    clock = VirtualClock()
    async with Runtime(graph, clock=clock) as rt:
        await drive(rt, clock)
    await asyncio.to_thread(wait_for_writers)
    return graph, session


@pytest.mark.parametrize("name", list(CASES))
async def test_replay_re_executes_every_activation_with_its_inputs(
    name: str, tmp_path: Path
) -> None:
    TRACE.clear()
    graph, session = await record(tmp_path, CASES[name])
    live = list(TRACE)
    assert live, "the case ran nothing"
    TRACE.clear()
    async with flowrt.replay(session, graph, inline=True) as rp:
        report = await rp.run()
    replayed = list(TRACE)
    assert replayed == live  # the same activations, in order, each with its inputs and time
    assert report.identical, report.first_divergence
    assert report.activations == len(live)
    failed = sum(1 for entry in live if entry[-1] == "raised")
    assert report.compared == len(live) - failed  # a failed activation published nothing
    log = read_log(session)
    assert len(log.activations) == len(live)
    assert len(log.completions) == len(live) - failed
    if name == "a swap mid-run":
        assert [(a.node, a.swap, a.params) for a in log.activations if a.swap] == [
            ("acc", True, {"factor": 3})
        ]
    restarts = [c for c in log.changes if c.what == "restart"]
    assert (failed >= 3, len(restarts) == failed) == (name == "a failure and its restart", True)


async def test_mode_change_is_recorded_and_its_params_applied(tmp_path: Path) -> None:
    TRACE.clear()
    graph, session = await record(tmp_path, case_mode_change_mid_run)
    log = read_log(session)
    assert any(c.what == "timing" and "mode sprint" in c.origin for c in log.changes)
    changed = [a for a in log.activations if a.params is not None]
    assert [(a.node, a.params) for a in changed] == [("fast", {"factor": 7})]
    async with flowrt.replay(session, graph, inline=True) as rp:
        fast = rp.subscribe("fast.total")
        report = await rp.run()
    assert report.identical
    assert len(fast.drain()) == 20
    assert any("mode sprint" in c for c in report.changes)


async def test_a_changed_param_diverges_at_that_node_the_same_way_every_time(
    tmp_path: Path,
) -> None:
    TRACE.clear()
    graph, session = await record(tmp_path, case_frame_phases)
    node = graph.spec.nodes["p4ph3"].model_copy(update={"params": {"factor": 5}})
    spec = graph.spec.model_copy(update={"nodes": {**graph.spec.nodes, "p4ph3": node}})
    changed = flowrt.graph._resolve.resolve(spec, kinds={"Acc": Acc, "Cam": Cam})  # the same wiring
    firsts = []
    for _ in range(2):
        async with flowrt.replay(session, changed, inline=True, stop_at_divergence=True) as rp:
            report = await rp.run()
        firsts.append(report.first_divergence)
    d = firsts[0]
    assert d is not None
    # its first total does not depend on the factor (0 * factor + ...): the second does
    assert (d.node, d.port, d.seq) == ("p4ph3", "total", 2)
    assert d.recorded is not None  # the recorder has the values
    assert d.replayed is not None
    assert firsts[1] == d
    assert report.stopped_early


async def test_removed_nodes_are_not_run_and_a_new_node_runs(tmp_path: Path) -> None:
    TRACE.clear()
    _, session = await record(tmp_path, case_input_triggers)
    ticks = [v for name, _, v, *_ in TRACE if name == "first"]
    g = GraphBuilder("det")
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("first", Acc, inputs={"value": {"from": "tick.tick", "policy": "queue"}})
    g.add("third", Acc, inputs={"value": "tick.tick"})  # new: nothing recorded of it
    TRACE.clear()
    async with flowrt.replay(session, g.build(), inline=True) as rp:
        third = rp.subscribe("third.total")
        report = await rp.run()
    status = {n.node: (n.status, n.reason) for n in report.nodes}
    assert status["first"][0] == "compared"
    assert status["third"][0] == "new"  # run on its input trigger over the recorded ticks
    assert [v for name, _, v, *_ in TRACE if name == "third"] == ticks
    assert len(third.drain()) == len(ticks)
    assert status["second"][0] == "not run"  # removed
    assert status["pair"][0] == "not run"
    assert report.identical


async def test_a_graph_with_none_of_the_recordings_nodes_is_never_identical(
    tmp_path: Path,
) -> None:
    """Another graph (graphs/agent.yaml against a cambada recording): nothing re-executed,
    nothing compared, and the report said "identical" (exit 0)."""
    TRACE.clear()
    _, session = await record(tmp_path, case_input_triggers)
    g = GraphBuilder("other")
    g.add("other_tick", Ticker, trigger={"timer": "10ms"})
    g.add("other_acc", Acc, inputs={"value": "other_tick.tick"})
    async with flowrt.replay(session, g.build(), inline=True) as rp:
        report = await rp.run()
    assert (report.compared, report.identical) == (0, False)
    reasons = {n.node: n.reason for n in report.nodes}
    assert "does not hold" in reasons["other_tick"]  # not "its values are the recording's"
    text = "\n".join(report_lines(report))
    assert "no node of this graph re-executes what the recording holds" in text


async def test_a_new_frame_reader_runs_on_its_period_and_phase(tmp_path: Path) -> None:
    TRACE.clear()
    _, session = await record(tmp_path, case_frame_phases)
    g = GraphBuilder("det")
    case_frame_phases(g)
    g.add(
        "p2ph1",
        Acc,
        trigger=FrameTrigger(frame="cam", period=2, phase=1),
        inputs={"value": "cam.frame"},
    )
    TRACE.clear()
    async with flowrt.replay(session, g.build(), inline=True) as rp:
        report = await rp.run()
    assert [v for name, _, v, *_ in TRACE if name == "p2ph1"] == list(range(1, 20, 2))
    assert report.identical
    assert {n.node: n.status for n in report.nodes}["p2ph1"] == "new"


async def test_a_reader_whose_input_is_gone_is_not_comparable(tmp_path: Path) -> None:
    TRACE.clear()
    _, session = await record(tmp_path, case_input_triggers, values=False)
    g = GraphBuilder("det")
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("second", Acc, inputs={"value": {"from": "tick.tick", "policy": "queue"}})
    async with flowrt.replay(session, g.build(), inline=True) as rp:
        report = await rp.run()
    status = {n.node: (n.status, n.reason) for n in report.nodes}
    # second read first.total, which neither runs nor was recorded by value
    assert status["second"][0] == "not comparable"
    assert "first.total #1 is not recorded" in status["second"][1]
    assert status["first"] == (
        "not run",
        "not in this graph (its recorded outputs stand in for it)",
    )
    assert report.activations == 0


async def test_not_a_deterministic_recording_is_one_clear_error(tmp_path: Path) -> None:
    g = GraphBuilder("plain")
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add(
        "rec",
        "recorder",
        params={"session": str(tmp_path / "s"), "log_report": False},
        inputs={"tick.tick": {"from": "tick.tick", "policy": "lossless"}},
    )
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock):
        await clock.advance(0.1)
    await asyncio.to_thread(wait_for_writers)
    with pytest.raises(LogError, match="not a deterministic recording"):
        read_log(tmp_path / "s")
    with pytest.raises(LogError, match="no such file"):
        read_log(tmp_path / "nothing")


@dataclass(frozen=True)
class _Det:
    x: float
    tags: tuple[str, ...]


class _Model(BaseModel):
    b: int
    a: float


def _one_pixel(shape: tuple[int, ...]) -> np.ndarray:
    a = np.zeros(shape, np.uint8)
    a[shape[0] // 2, shape[1] // 2, 1] = 1
    return a


@pytest.mark.parametrize(
    ("left", "right", "same"),
    [
        ({"b": 1, "a": 2}, {"a": 2, "b": 1}, True),  # key order does not matter
        ((1, 2.5), [1, 2.5], True),  # tuples are lists
        (0.1 + 0.2, 0.3, False),  # floats to the bit
        (_Det(1.0, ("a",)), _Det(1.0, ("a",)), True),
        (_Det(1.0, ("a",)), _Det(1.0, ("b",)), False),
        (_Model(b=1, a=2.0), _Model(a=2.0, b=1), True),
        (np.arange(6, dtype=np.uint8), np.arange(6, dtype=np.uint8), True),
        (np.arange(6, dtype=np.uint8), np.arange(6, dtype=np.int16), False),  # dtype counts
        (np.zeros((2, 3)), np.zeros((3, 2)), False),  # shape counts
        (frame(3), frame(3), True),
        (frame(3), frame(4), False),  # pixels differ
        (np.zeros((300, 300, 3), np.uint8), _one_pixel((300, 300, 3)), False),  # large arrays
        (np.zeros((300, 300, 3), np.uint8), np.zeros((300, 300, 3), np.uint8), True),
        (np.zeros((300, 300, 3), np.uint8), np.zeros((300, 900), np.uint8), False),
        (float("nan"), float("nan"), True),
        (1, 1.0, False),
        (b"\x00\x01", b"\x00\x01", True),
    ],
)
def test_digest_is_canonical(left: Any, right: Any, same: bool) -> None:
    assert (digest(left) == digest(right)) is same
    assert len(digest(left)) == 32
    assert canonical(left) == canonical(left)


def test_ctx_random_is_seeded_by_node_and_run(monkeypatch: pytest.MonkeyPatch) -> None:
    from flowrt.node import NodeContext, node_seed

    a = [NodeContext("a").random.random() for _ in range(2)]
    assert a[0] == a[1]  # a fresh context draws the same first number
    assert NodeContext("a").random.random() != NodeContext("b").random.random()
    monkeypatch.setenv("FLOWRT_SEED", "7")
    assert NodeContext("a").random.random() != a[0]
    assert node_seed("a") == node_seed("a", "7")


class Stamped(Node):
    """A value with its own time, as a detection carries its frame's capture time."""

    class Params(BaseModel):
        factor: int = 3

    value = Input(int)
    out = Output(object)

    def process(self, value: int) -> dict[str, Any]:
        return {"timestamp": self.ctx.now() - 0.001, "v": value * self.params.factor}


async def test_a_divergence_shows_both_values_on_one_clock(tmp_path: Path) -> None:
    """The recording holds a value's own timestamp in Unix nanoseconds, the replay has it on
    the runtime clock in seconds: shown side by side they must read the same (before, they
    read as a mismatch where there was none: 1.7e18 against 0.039)."""
    g = GraphBuilder("det")
    g.add("tick", Ticker, trigger={"timer": "10ms"})
    g.add("stamped", Stamped, inputs={"value": "tick.tick"})
    recorder(g, tmp_path / "session", "stamped.out")
    graph = g.build()
    clock = VirtualClock()
    async with Runtime(graph, clock=clock):
        await clock.advance(0.1)
    await asyncio.to_thread(wait_for_writers)
    node = graph.spec.nodes["stamped"].model_copy(update={"params": {"factor": 5}})
    spec = graph.spec.model_copy(update={"nodes": {**graph.spec.nodes, "stamped": node}})
    changed = flowrt.graph._resolve.resolve(spec, kinds={"Ticker": Ticker, "Stamped": Stamped})
    async with flowrt.replay(tmp_path / "session", changed, inline=True) as rp:
        d = (await rp.run()).first_divergence
    assert d is not None
    assert (d.node, d.seq) == ("stamped", 1)
    assert d.recorded is not None
    assert d.replayed is not None
    recorded, replayed = json.loads(d.recorded), json.loads(d.replayed)
    assert (recorded["v"], replayed["v"]) == (3, 5)
    assert recorded["timestamp"] == replayed["timestamp"]


def _cut_after(session: Path, last: Callable[[str, dict[str, Any]], bool]) -> Path:
    """A copy of ``session`` whose file ends right after the first log record ``last``
    accepts (topic, record), as a killed recorder's does: no summary, not closed."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    src = next(session.glob("*.mcap"))
    cut = session.parent / "cut"
    cut.mkdir()
    with open(src, "rb") as fh, open(cut / src.name, "wb") as out:
        reader = make_reader(fh)
        writer = Writer(out, use_chunking=False)
        writer.start(profile="", library="test")
        for m in reader.iter_metadata():
            writer.add_metadata(m.name, dict(m.metadata))
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas.get(channel.schema_id, 0)
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
            if channel.topic.startswith("/flowrt/det/") and last(
                channel.topic, json.loads(message.data)
            ):
                return cut
    raise AssertionError("no such record")


@pytest.mark.parametrize("k", [1, 5, 12])
async def test_a_log_cut_between_a_completion_and_its_outputs_does_not_diverge(
    k: int, tmp_path: Path
) -> None:
    """A completion is written before its results publish: a log cut between the two has
    the activation's completion and not its output. That output is not compared, and is no
    divergence (it made a cut recording of cambada.yaml "diverge" on a loaded machine)."""
    graph, session = await record(tmp_path, case_timers)
    seen = 0

    def kth_completion(topic: str, r: dict[str, Any]) -> bool:
        nonlocal seen
        seen += topic.endswith("completion") and r["node"] == "slow"
        return seen == k

    cut = _cut_after(session, kth_completion)
    log = read_log(cut)
    assert not log.closed_cleanly
    assert ("slow", k) in log.completions
    assert ("slow", k) not in log.outputs
    async with flowrt.replay(cut, graph, inline=True) as rp:
        report = await rp.run()
    assert report.first_divergence is None
    assert report.log_cut
    assert not report.identical
    assert report.compared == sum(len(v) for v in log.outputs.values()) > 0


async def test_a_repaired_log_is_never_identical(tmp_path: Path) -> None:
    """``flowrt info --repair`` makes a cut file whole, not what the cut lost: its log still
    says so (it replayed "identical", log_cut null, exit 0)."""
    from flowrt.recording.repair import repair

    graph, session = await record(tmp_path, case_timers)
    seen = [0]

    def twentieth(topic: str, r: dict[str, Any]) -> bool:
        seen[0] += 1
        return seen[0] == 20

    session = _cut_after(session, twentieth)
    repair(next(session.glob("*.mcap")))
    log = read_log(session)
    assert not log.closed_cleanly
    assert log.damage is not None
    assert log.damage.startswith("repaired after ")
    async with flowrt.replay(session, graph, inline=True) as rp:
        report = await rp.run()
    assert report.first_divergence is None
    assert not report.identical
    assert report.log_cut == log.damage


async def test_a_deterministic_recorder_swapped_while_recording_logs_both_sessions(
    tmp_path: Path,
) -> None:
    """Swapped (``ctl swap rec recorder --params '{"compression": "zstd"}'``), the new
    instance installed its observer before its file was open: what ran meanwhile was logged
    by neither instance, and its numbers began at 0 in the middle of the run. Every
    activation is now in one of the two logs, numbered as the run did; the first session
    replays identical; the second, begun mid-run (its nodes' inputs and state from before
    it unrecorded), is not comparable, and never called identical."""
    import os

    TRACE.clear()
    g = GraphBuilder("det")
    drive = case_timers(g)
    g.add(
        "rec",
        "recorder",
        params={
            "path": str(tmp_path),
            "name": "s",
            "deterministic": True,
            "log_report": False,
            "writer": "thread",
        },
        inputs={"slow.total": {"from": "slow.total", "policy": "lossless"}},
    )
    graph = g.build()
    clock = VirtualClock()
    async with Runtime(graph, clock=clock) as rt:
        await drive(rt, clock)
        await rt.swap("rec", "recorder", {"compression": "zstd"})
        await drive(rt, clock)
    await asyncio.to_thread(wait_for_writers)
    live = list(TRACE)
    sessions = sorted(tmp_path / n for n in os.listdir(tmp_path))
    assert [s.name for s in sessions] == ["s_001", "s_002"]
    first, second = (read_log(s) for s in sessions)
    numbers = [(a.node, a.n) for a in first.activations + second.activations]
    assert len(numbers) == len(set(numbers)) == len(live)  # each once, none lost
    assert min(a.n for a in second.activations if a.node == "slow") > 1  # the run's numbers
    async with flowrt.replay(sessions[0], graph, inline=True) as rp:
        report = await rp.run()
    assert report.identical, report.first_divergence
    assert report.activations == len(first.activations)
    async with flowrt.replay(sessions[1], graph, inline=True) as rp:
        report = await rp.run()
    assert not report.identical
    assert report.first_divergence is None
    assert {n.node: n.status for n in report.nodes}["slow"] == "not comparable"
