"""Every exception a node can cause is that node's error (issue 37 item 9, issue 43 item 2).

Table-driven: each kind of tests/failkinds.py makes one mistake (``setup``, ``process``,
``teardown`` raising; a returned port it does not have; a value of another type than its
output declares; a bare value from a node with two outputs; ``ctx.publish`` on a missing
port), inline on virtual time and in a worker process. Each must be counted on the node,
its restart policy applied (``never`` here: given up at once), and listed by
``Runtime.failures()`` so that ``flowrt run`` exits 1. Before, a returned port it does not
have was an exception in a loop callback: the node stayed ``running`` with 0 errors.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock

TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

import failkinds  # noqa: E402

pytestmark = pytest.mark.timeout(60)

# kind, what the node's reason says, placements it can make the mistake in
MISTAKES = [
    ("SetupFails", "RuntimeError: cannot open the device", ("inline", "process")),
    ("AlwaysFails", "ValueError: boom", ("inline", "process")),
    ("WrongOutputName", "no output port 'scor' (its outputs: score, level)", ("inline", "process")),
    ("WrongOutputType", "output 'score' expects float, got str", ("inline", "process", "pool")),
    ("NotAMapping", "must return a mapping of them, not float", ("inline", "process")),
    ("PublishesWrongPort", "no output port 'nope'", ("inline",)),
    (
        "TeardownFails",
        "teardown failed: OSError: cannot release the device",
        ("inline", "process", "pool"),
    ),
    # (a worker's: the run's end waits for it only so long, then kills its worker; it was
    # killed without a word and the run exited 0)
    ("TeardownHangs", "teardown failed: teardown did not return in time", ("process", "pool")),
]

CASES = [
    pytest.param(
        kind,
        reason,
        placement,
        id=f"{kind}-{placement}",
        marks=[pytest.mark.subprocess] if placement != "inline" else [],
    )
    for kind, reason, placements in MISTAKES
    for placement in placements
]


def _graph(kind: str, placement: str) -> flowrt.Graph:
    g = GraphBuilder()
    g.add(
        "bad",
        getattr(failkinds, kind),
        trigger={"timer": "20ms"},
        placement=placement,
        restart={"policy": "never"},
    )
    g.add("ok", "counter", trigger={"timer": "20ms"})
    return g.build()


@pytest.mark.parametrize(("kind", "reason", "placement"), CASES)
async def test_every_mistake_of_a_node_is_its_error(kind: str, reason: str, placement: str) -> None:
    if placement == "inline":
        clock = VirtualClock()
        async with Runtime(_graph(kind, placement), clock=clock) as rt:
            await clock.advance(1.0)
    else:
        async with Runtime(_graph(kind, placement)) as rt:
            await rt.run(1.5)
    bad = rt.stats().node("bad")
    assert bad.errors == 1, bad
    assert bad.state == "failed", bad
    assert reason in bad.reason
    assert [n.name for n in rt.failures()] == ["bad"]
    assert rt.stats().node("ok").errors == 0


async def test_a_value_of_the_declared_type_is_published() -> None:
    """The check refuses only what the declaration refuses: an int on ``Output(float)`` (a
    real number, as on the reader's side), None on any port (nothing published)."""

    class Fine(flowrt.Node):
        score = Output(float)
        level = Output(int)

        def process(self) -> dict[str, object]:
            return {"score": 3, "level": None}

    clock = VirtualClock()
    g = GraphBuilder()
    g.add("fine", Fine, trigger={"timer": "20ms"}, restart={"policy": "never"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.5)
    fine = rt.stats().node("fine")
    assert (fine.state != "failed", fine.errors) == (True, 0)
    assert fine.completions >= 20


Output = flowrt.Output


@pytest.mark.subprocess
def test_flowrt_run_exits_1_on_a_value_of_the_wrong_type(tmp_path: Path) -> None:
    graph = tmp_path / "g.yaml"
    graph.write_text(
        textwrap.dedent("""\
            nodes:
              level:
                kind: failkinds:WrongOutputType
                trigger: {timer: 20ms}
                restart: {policy: never}
            """)
    )
    r = subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "run", str(graph), "--no-ui", "--duration", "5"],
        cwd=TESTS,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1, r.stderr
    assert "node level failed" in r.stderr
    assert "output 'score' expects float, got str" in r.stderr
    assert "Traceback" not in r.stderr.split("given up")[-1]


async def test_the_drain_does_not_wait_for_a_reader_that_failed() -> None:
    """A producer held on a full lossless edge whose reader failed waited out the whole
    drain (5 s of every ``flowrt record`` whose recorder could not start)."""
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("src", "counter", trigger={"timer": "10ms"})
    g.add(
        "sink",
        failkinds.FailingSink,
        inputs={"value": {"from": "src.value", "policy": "lossless", "size": 4}},
        restart={"policy": "never"},
    )
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(1.0)
        assert rt.stats().node("sink").state == "failed"
    alerts = [e for e in rt.events if isinstance(e, flowrt.HealthAlert)]
    assert not [a for a in alerts if a.alert == "drain-timeout"], alerts
    edge = next(e for e in rt.stats().edges if e.name.endswith("sink.value"))
    assert edge.published == edge.delivered + edge.dropped


@pytest.mark.parametrize(
    ("kind", "reason"),
    [(k, r) for k, r, _ in MISTAKES if k in ("WrongOutputName", "WrongOutputType", "NotAMapping")],
)
def test_the_harness_refuses_what_the_runtime_refuses(kind: str, reason: str) -> None:
    """``NodeHarness`` returned ``{'scor': 1.0}`` without a word; the run failed on it."""
    from flowrt.kernel.outputs import OutputError
    from flowrt.testing import NodeHarness

    with pytest.raises(OutputError, match=re.escape(reason)):
        NodeHarness(getattr(failkinds, kind)).process()
