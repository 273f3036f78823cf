"""The live status table at the widths and heights of real terminals.

The statistics are those of ``graphs/cambada.yaml`` (its nodes and edges, with large, distinct
counters so that a cut figure cannot pass for a whole one); the table is rendered by rich at
80, 120 and 200 columns and read back as plain text.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from rich.console import Console

from flowrt.events import DeadlineMissed, Event
from flowrt.graph._resolve import Graph
from flowrt.monitors.status import EDGE_COLUMNS, NODE_COLUMNS, render
from flowrt.stats import EdgeStats, FramePoolStats, LoopStats, NodeStats, RuntimeStats, Summary

pytestmark = pytest.mark.timeout(30)

ROOT = Path(__file__).resolve().parents[1]


def _summary(mean: float) -> Summary:
    return Summary(
        count=1000,
        min=mean * 0.9,
        max=mean * 3.1,
        mean=mean,
        std=mean / 40,
        p50=mean,
        p99=mean * 2.2,
    )


def cambada_stats(**overrides: dict[str, object]) -> RuntimeStats:
    """Statistics of a long cambada run: every node and edge of the graph file."""
    graph = Graph.from_file(ROOT / "graphs" / "cambada.yaml")
    nodes, edges = [], []
    for i, (name, spec) in enumerate(graph.spec.nodes.items()):
        fields: dict[str, object] = dict(
            name=name,
            kind=spec.kind,
            placement=spec.placement.value,
            trigger="frame omni_cam" if spec.trigger is not None else "input",
            priority=spec.priority,
            period="4/1",
            deadline_ms=spec.deadline,
            enabled=True,
            state="idle",
            granted="nice -14, cpus 1" if spec.placement.value == "process" else "",
            activations=123450 + i,
            completions=123440 + i,
            skipped=0,
            deadline_misses=0,
            discarded=0,
            dropped=0,
            errors=0,
            restarts=0,
            last_start=6172.5,
            last_finish=6172.51,
            interval=_summary(50.0),
            execution=_summary(1.234),
            response=_summary(2.5),
        )
        fields.update(overrides.get(name, {}))
        nodes.append(NodeStats.model_validate(fields))
        for port, inp in spec.inputs.items():
            edges.append(
                EdgeStats(
                    name=f"{inp.source}->{name}.{port}",
                    policy="latest",
                    size=1,
                    published=123456,
                    delivered=30864,
                    dropped=0,
                    unread=92592,
                    sampled=True,
                    age=_summary(0.25),
                )
            )
    return RuntimeStats(
        graph="cambada",
        uptime=6172.5,
        mode="paper_mode_change",
        loop_scheduling="nice -20",
        nodes=nodes,
        edges=edges,
        loop=LoopStats(lag=_summary(0.05), blocked_calls=0),
        events=12,
    )


# Failures to show: a miss/drop/error counter on several nodes, an error state with its reason.
FAILING = {
    "ball_fr": {"deadline_misses": 98765, "skipped": 4321},
    "ygoal": {"dropped": 55555, "errors": 77, "restarts": 3},
    "front_cam": {"state": "error", "reason": "camera:7 cannot be opened"},
    "line": {"state": "failed", "errors": 5, "reason": "gave up after 5 restarts"},
}


def show(
    stats: RuntimeStats, width: int, height: int | None = None, recent: list[Event] | None = None
) -> tuple[str, list[str]]:
    console = Console(width=width, record=True, file=io.StringIO(), color_system=None)
    console.print(render(stats, recent, width=width, height=height))
    text = console.export_text()
    return text, text.splitlines()


def row_of(lines: list[str], name: str) -> list[str]:
    rows = [ln.split() for ln in lines if not ln.startswith(" ") and ln.split()[:1] == [name]]
    assert len(rows) == 1, f"{name}: {rows}"
    return rows[0]


@pytest.mark.parametrize("width", [80, 120, 200])
def test_every_node_name_state_and_counter_in_full(width: int) -> None:
    stats = cambada_stats(**FAILING)
    text, lines = show(stats, width)
    assert max(len(ln) for ln in lines) <= width
    assert "…" not in "".join(ln for ln in lines if not ln.startswith("  "))  # nothing cut
    header = lines[1].split()
    for col in ("node", "state", "act", "skip", "miss", "drop", "err"):
        assert col in header, header
    for n in stats.nodes:
        row = row_of(lines, n.name)
        cell = dict(zip(header, row, strict=False))
        assert cell["state"] == n.state
        assert cell["act"] == str(n.activations)
        assert (cell["skip"], cell["miss"], cell["drop"], cell["err"]) == (
            str(n.skipped),
            str(n.deadline_misses),
            str(n.dropped),
            str(n.errors),
        )
    assert "front_cam error: camera:7 cannot be opened" in text
    assert "line failed: gave up after 5 restarts" in text
    for e in stats.edges:  # no height limit: every edge, its name whole
        assert re.search(rf"^{re.escape(e.name)}\s", text, re.M), e.name


@pytest.mark.slow  # a sweep of 53 widths: ~0.9 s of CPU alone, at the fast tier's 1 s limit
def test_no_width_cuts_a_cell_or_overflows() -> None:
    stats = cambada_stats(**FAILING)
    for width in range(72, 230, 3):
        _, lines = show(stats, width)
        assert max(len(ln) for ln in lines) <= width, width
        table_lines = [ln for ln in lines if not ln.startswith(" ")]
        assert not any("…" in ln for ln in table_lines), width
        header = lines[1].split()
        if width >= 80:
            assert {"node", "state", "act", "skip", "miss", "drop", "err"} <= set(header)


def test_narrow_widths_drop_the_least_important_columns_first() -> None:
    stats = cambada_stats()
    wide = show(stats, 200)[1][1].split()
    mid = show(stats, 120)[1][1].split()
    narrow = show(stats, 80)[1][1].split()
    assert len(narrow) < len(mid) <= len(wide)
    order = [c.header.split()[0] for c in sorted(NODE_COLUMNS, key=lambda c: c.drop) if c.drop]
    # the columns gone at 80 are a prefix of the documented drop order
    gone = [h for h in order if h not in narrow]
    assert gone == order[: len(gone)]
    assert "resp" not in narrow
    assert "exec" not in narrow
    essentials = [c.header for c in NODE_COLUMNS if not c.drop]
    assert set(essentials) <= set(narrow)
    assert all(c.drop for c in EDGE_COLUMNS if c.header not in ("edge", "drop"))


def test_failure_counters_are_red_and_unread_samples_are_not() -> None:
    stats = cambada_stats(**FAILING)
    console = Console(
        width=80, record=True, file=io.StringIO(), color_system="truecolor", force_terminal=True
    )
    console.print(render(stats, width=80))
    styled = console.export_text(styles=True)
    red = "\x1b[1;31m"
    for figure in ("98765", "55555", "77", "error", "failed"):
        assert re.search(rf"{re.escape(red)} *{figure}\b", styled), figure
    assert not re.search(rf"{re.escape(red)} *92592", styled)  # a sampling reader's unread


def test_80x24_keeps_failures_on_screen_and_summarises_the_rest() -> None:
    stats = cambada_stats(**FAILING)
    recent: list[Event] = [DeadlineMissed(float(i), "ball_fr", 20.0, True, False) for i in range(6)]
    text, lines = show(stats, 80, height=24, recent=recent)
    assert len(lines) <= 23
    for name in FAILING:
        row_of(lines, name)
    assert "front_cam error: camera:7 cannot be opened" in text
    # cambada has 12 nodes: with the failures' lines they all fit; the 20 edges do not
    for n in stats.nodes:
        row_of(lines, n.name)
    assert re.search(r"\+\d+ edges ok", text)


def test_more_nodes_than_rows_summarised_as_ok_never_hiding_a_failure() -> None:
    stats = cambada_stats(**FAILING)
    healthy = cambada_stats()
    many = list(stats.nodes) + [
        n.model_copy(update={"name": f"{n.name}_{k}"}) for k in range(1, 4) for n in healthy.nodes
    ]
    stats = stats.model_copy(update={"nodes": many})
    text, lines = show(stats, 80, height=24)
    assert len(lines) <= 23
    for name in FAILING:
        row_of(lines, name)
    assert "front_cam error: camera:7 cannot be opened" in text
    hidden = re.search(r"\+(\d+) nodes ok", text)
    assert hidden, text
    shown = sum(1 for n in many if any(ln.split()[:1] == [n.name] for ln in lines))
    assert shown + int(hidden.group(1)) == len(many)


def test_more_failing_nodes_than_rows_says_how_many_are_hidden() -> None:
    stats = cambada_stats(**{n.name: {"errors": 1} for n in cambada_stats().nodes})
    text, lines = show(stats, 80, height=10)
    assert len(lines) <= 9
    hidden = re.search(r"\+(\d+) nodes: (\d+) failing", text)
    assert hidden, text
    assert (
        int(hidden.group(1))
        == int(hidden.group(2))
        == len(stats.nodes)
        - sum(1 for n in stats.nodes if any(ln.split()[:1] == [n.name] for ln in lines))
    )


def test_frames_a_pool_could_not_hold_are_a_red_line() -> None:
    pool = FramePoolStats(owner="front_cam", slots=16, slots_in_use=16, max_slots=16, grown=12,
                          dropped=37)  # fmt: skip
    stats = cambada_stats().model_copy(update={"frames": [pool]})
    text, _ = show(stats, 80, height=24)
    assert "frames front_cam: 37 dropped" in text


@pytest.mark.parametrize(
    ("progress", "said"),
    [
        ({"position_s": 12.3, "duration_s": 41.0, "loops": 0},
         "replay cam " + "█" * 6 + "░" * 14 + " 12.3 / 41.0 s (30%)"),
        ({"position_s": 2.0, "duration_s": 10.0, "loops": 2}, "2.0 / 10.0 s (20%) · loop 3"),
        ({"position_s": 5.5, "duration_s": None, "loops": 0}, "replay cam 5.5 s"),  # not closed
    ],
)  # fmt: skip
def test_a_replay_shows_its_position(progress: dict[str, object], said: str) -> None:
    """The README's "a progress bar shows the position": there was none."""
    stats = cambada_stats().model_copy(update={"reports": {"cam": {"progress": progress}}})
    text, _ = show(stats, 80, height=24)
    assert said in text


def test_edge_with_drops_stays_when_edges_are_summarised() -> None:
    stats = cambada_stats()
    edges = list(stats.edges)
    edges[-1] = edges[-1].model_copy(update={"dropped": 4242})
    stats = stats.model_copy(update={"edges": edges})
    text, _ = show(stats, 80, height=24)
    assert re.search(rf"^{re.escape(edges[-1].name)}\s.*4242", text, re.M)
