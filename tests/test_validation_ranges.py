"""'validate OK' means 'runs': ranges of durations, rates, sizes and ids; port types at run time.

The located-error side is table-driven in tests/graphs/invalid-ranges.yaml (and the other
fixtures run by test_validation.py); here: the ranges are the ones run-time changes use, a
wrong-typed value at run time is one counted error, and generated graph values either fail
validation with a located error or run without a traceback or a node error.
"""

from __future__ import annotations

import logging
import math

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from flowrt import Frame, Graph, GraphBuilder, GraphError, Input, Node, Output, Runtime
from flowrt.graph import spec as S
from flowrt.graph.spec import TimingOverride


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"timer": math.nan}, "timer"),
        ({"timer": math.inf}, "timer"),
        ({"timer": 1e-9}, "timer"),
        ({"timer": 1e300}, "timer"),
        ({"timer": 10**400}, "timer"),
        ({"deadline": math.nan}, "deadline"),
        ({"deadline": -1}, "deadline"),
        ({"period": 10**18}, "period"),
        ({"period": 0}, "period"),
        ({"phase": -1}, "phase"),
        ({"priority": 100}, "priority"),
        ({"timer": "1e999ms"}, "timer"),
    ],
)
def test_timing_override_refuses_what_a_graph_file_refuses(change: dict, field: str) -> None:
    """The control endpoint and modes validate changes with the graph files' ranges."""
    with pytest.raises(ValidationError) as info:
        TimingOverride.model_validate(change)
    assert [e["loc"][0] for e in info.value.errors()] == [field]


def test_timing_override_accepts_the_range_limits() -> None:
    o = TimingOverride.model_validate(
        {"timer": S.MIN_TIMER_MS, "deadline": S.MAX_DURATION_MS, "period": S.MAX_FRAME_PERIOD}
    )
    assert (o.timer, o.deadline, o.period) == (0.1, 3_600_000.0, 100_000)
    assert TimingOverride.model_validate({"timer": "100us"}).timer == pytest.approx(0.1)


# --- a wrong type at run time: one counted error, one message --------------------------------


class Anything(Node):
    """An untyped source: what a relay or Runtime.publish lets through."""

    out = Output(object)


class FrameUser(Node):
    frame = Input(Frame)
    mean = Output(float)

    def setup(self) -> None:
        self.calls = 0

    def process(self, frame: Frame) -> float:
        self.calls += 1
        return float(frame.data.mean())


async def test_a_wrong_type_is_one_counted_error(caplog: pytest.LogCaptureFixture) -> None:
    g = GraphBuilder("types")
    g.add("src", Anything, trigger={"timer": S.MAX_DURATION_MS}, enabled=False)
    g.add("user", FrameUser, inputs={"frame": "src.out"})
    async with Runtime(g.build()) as rt:
        with caplog.at_level(logging.ERROR):
            for i in range(5):
                rt.publish("src.out", f"not a frame {i}")
                await rt.run(0.01)
            rt.publish("src.out", 42)
            await rt.run(0.01)
        stats = rt.stats().node("user")
        node = rt.scheduler.runners["user"].executor.node  # type: ignore[attr-defined]
    assert node.calls == 0  # never called with a value it cannot take
    assert stats.errors == 6
    lines = [r.getMessage() for r in caplog.records if "expects Frame" in r.getMessage()]
    assert len(lines) == 2, lines  # one per wrong type (str, int), not one per value
    assert "got str" in lines[0]
    assert "got int" in lines[1]
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


def test_a_float_input_takes_ints_and_numpy_numbers() -> None:
    import numpy as np

    from flowrt.graph._resolve import checked_type

    real = checked_type(float)
    assert real is not None
    assert all(isinstance(v, real) for v in (1, 1.5, np.float32(2), np.int64(3), True))
    assert not isinstance("1.0", real)
    assert checked_type(object) is None
    assert checked_type(list[int]) is None


# --- hypothesis: every generated graph fails with a located error, or runs cleanly ----------

_GOOD_DURATIONS = st.one_of(
    st.sampled_from(["100us", "1ms", "20ms", "0.5s", 0.1, 3_600_000]),
    st.floats(min_value=0.1, max_value=200, allow_nan=False),
)
_BAD_DURATIONS = st.sampled_from(
    [math.nan, math.inf, -math.inf, 0, -1, 1e-9, 1e300, 10**30, 10**400, "1e-9ms", "1e999s"]
)
_GOOD_INTS = st.integers(0, 8)
_BAD_INTS = st.sampled_from([-1, 100, 10**18, 10**40, math.nan])
_GOOD_SIZES = st.sampled_from([[32, 24], [64, 48], [320, 240]])
_BAD_SIZES = st.sampled_from([[16384, 16384], [0, 10], [10**12, 10], [31, 24], [-2, 5]])


@st.composite
def generated_graphs(draw: st.DrawFn) -> str:
    """A capture + tracker + timer graph with generated durations, rates, sizes and ids.

    Half of the graphs draw only in-range values (so that some run), the others mix in
    hostile ones (NaN, inf, huge ints, tiny durations): each value is hostile with p = 1/4.
    """
    hostile = draw(st.booleans())

    def pick(good: st.SearchStrategy, bad: st.SearchStrategy) -> object:
        if hostile and draw(st.integers(0, 3)) == 0:
            return draw(bad)
        return draw(good)

    def duration() -> object:
        return pick(_GOOD_DURATIONS, _BAD_DURATIONS)

    def integer(lo: int = 0) -> object:
        return pick(st.integers(lo, 8), _BAD_INTS)

    period = integer(1)
    good_phase = (
        st.integers(0, period - 1) if isinstance(period, int) and period >= 1 else st.just(0)
    )
    phase = pick(good_phase, _BAD_INTS)
    cam: dict = {
        "kind": "capture",
        "params": {
            "size": pick(_GOOD_SIZES, _BAD_SIZES),
            "fps": pick(st.integers(5, 50), _BAD_DURATIONS),
        },
    }
    tracker: dict = {
        "kind": "tracker",
        "placement": "process",
        "trigger": {"frame": "cam", "period": period, "phase": phase},
        "inputs": {"frame": {"from": "cam.frame", "size": integer(1)}},
        "deadline": duration(),
        "watchdog": pick(st.sampled_from(["500ms", "1s", 1000]), _BAD_DURATIONS),
        "priority": pick(st.integers(1, 99), _BAD_INTS),
        "cpus": [pick(st.integers(0, 3), st.sampled_from([-1, 10**20, 8192]))],
    }
    tick: dict = {
        "kind": "counter",
        "trigger": {
            "timer": duration(),
            "phase": pick(st.sampled_from([0, "50us"]), _BAD_DURATIONS),
        },
        "restart": {"backoff": duration()},
    }
    nodes = {"cam": cam, "ball": tracker, "tick": tick}
    for node in nodes.values():  # leave some keys out: defaults must be in range too
        for key in [k for k in node if k not in ("kind", "inputs")]:
            if key not in ("trigger", "placement") and draw(st.integers(0, 3)) == 0:
                del node[key]
    return yaml.safe_dump({"nodes": nodes}, sort_keys=False)


_OUTCOMES = {"refused": 0, "ran": 0}


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _run_briefly(graph: Graph, text: str) -> None:
    """Run 0.6 s: no exception, no traceback logged, no node error or failure."""
    import asyncio

    from flowrt.system._eventloop import new_event_loop

    async def main() -> None:
        async with Runtime(graph) as rt:
            await rt.run(0.6)
            stats = rt.stats()
        for node in stats.nodes:
            assert node.errors == 0, (node.name, text)
            assert node.state not in ("failed", "error"), (node.name, node.state, text)

    handler = _Records()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            runner.run(main())
    finally:
        root.removeHandler(handler)
    tracebacks = [r for r in handler.records if r.exc_info or "Traceback" in r.getMessage()]
    assert not tracebacks, [r.getMessage() for r in tracebacks]


@pytest.mark.subprocess  # runs graphs placing nodes in workers
@pytest.mark.timeout(240)
@settings(
    max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(generated_graphs())
def test_generated_values_fail_located_or_run(text: str) -> None:
    """Every generated file fails validation with located errors, or runs cleanly."""
    try:
        graph = Graph.from_text(text, "gen.yaml")
    except GraphError as e:
        errors = e.errors
        diagnostics = e.diagnostics
    else:
        _OUTCOMES["ran"] += 1
        _run_briefly(graph, text)
        return
    assert errors
    for d in diagnostics:
        assert d.line >= 1, str(d)
        assert d.column >= 1, str(d)
    _OUTCOMES["refused"] += 1


def test_generated_graphs_both_ran_and_were_refused() -> None:
    """The generator reaches both sides (runs after the test above, in file order)."""
    if sum(_OUTCOMES.values()) == 0:
        pytest.skip("the generated-graph test did not run in this session")
    assert _OUTCOMES["ran"] >= 2, _OUTCOMES
    assert _OUTCOMES["refused"] >= 2, _OUTCOMES


class FloatUser(Node):
    x = Input(float)

    def process(self, x: float) -> None:
        pass


class TextUser(Node):
    x = Input(str)

    def process(self, x: str) -> None:
        pass


@pytest.mark.parametrize(("reader", "ok"), [(FloatUser, True), (TextUser, False)])
def test_declared_port_types_are_checked_like_at_run_time(reader: type[Node], ok: bool) -> None:
    """An int output feeds a float input (as a value would pass at run time), not a str one."""
    g = GraphBuilder("types")
    g.add("count", "counter", trigger={"timer": "10ms"})
    g.add("user", reader, inputs={"x": "count.value"})
    if ok:
        assert [e.name for e in g.build().edges] == ["count.value->user.x"]
    else:
        with pytest.raises(GraphError, match=r"count\.value produces int, user\.x expects str"):
            g.build()
