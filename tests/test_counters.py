"""One definition of the counters, the same figures everywhere.

- ``skipped`` (node): a release not run (overrun, node down, required input missing).
- ``dropped`` (edge): a value lost that the reader wanted; (node): its input edges' dropped
  plus its results discarded by a firm deadline.
- ``unread`` (edge): a value a sampling reader (frame or timer trigger on a latest edge)
  never needed: by design, not a loss, never red.

Checked on virtual time (exact figures), on a real cambada run (the invariant, and no drop
without a skip), and across the three views: the terminal table, ``--stats-json`` and the
web view's own script run in Node.js on the same statistics.
"""

from __future__ import annotations

import asyncio
import io
import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console
from test_scheduler import Camera, Count, Gate, Recorder, cambada_like, frame, publish_frames
from test_status_table import FAILING, cambada_stats

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.monitors.status import render
from flowrt.stats import RuntimeStats

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]


def _invariant(stats: RuntimeStats) -> None:
    """Every published value is delivered, dropped, unread, or still held (at most one)."""
    for e in stats.edges:
        held = e.published - e.delivered - e.dropped - e.unread
        assert 0 <= held <= e.size, e


async def test_period_n_readers_leave_unread_samples_not_drops() -> None:
    clock = VirtualClock()
    async with Runtime(cambada_like().build(), clock=clock) as rt:
        await publish_frames(rt, clock, range(16))
        stats = rt.stats()
    _invariant(stats)
    for reader, period in (("every", 1), ("p4ph1", 4), ("p4ph3", 4), ("p8", 8)):
        edge = stats.edge(f"{reader}.frame")
        assert edge.dropped == 0, edge
        assert edge.delivered == 16 // period
        assert edge.unread == 16 - 16 // period - (edge.published - edge.delivered - edge.unread)
        assert stats.node(reader).dropped == 0
    assert stats.edge("p4ph1.frame").unread >= 11  # 3 in 4 frames, minus the one still held


async def test_a_frame_whose_release_was_skipped_is_dropped_not_unread() -> None:
    """A period-1 reader still busy on its tick loses that frame: a real, counted drop."""
    clock = VirtualClock()
    Gate.gates["slow"] = asyncio.Event()
    Gate.log.clear()
    g = GraphBuilder()
    g.add("cam", Camera, trigger={"timer": 3_600_000}, enabled=False)
    g.add("slow", Gate, trigger={"frame": "cam.frame", "period": 1},
          inputs={"value": "cam.frame"})  # fmt: skip
    g.add("every", Recorder, trigger={"frame": "cam.frame", "period": 2},
          inputs={"frame": "cam.frame"})  # fmt: skip
    async with Runtime(g.build(), clock=clock) as rt:
        for i in range(4):  # frame 0 starts "slow"; frames 1..3 arrive while it runs
            rt.publish("cam.frame", frame(i))
            await clock.advance(0.01)
        Gate.gates["slow"].set()
        await clock.advance(0.01)
        stats = rt.stats()
    _invariant(stats)
    slow = stats.node("slow")
    assert slow.skipped == 3
    edge = stats.edge("slow.value")
    assert edge.dropped == 2  # frames 1 and 2 replaced while due; frame 3 is still held
    assert edge.unread == 0
    assert slow.dropped == edge.dropped
    sampler = stats.edge("every.frame")  # the other reader, period 2: nothing lost
    assert (sampler.dropped, sampler.unread) == (0, 1)


async def test_cambada_runs_without_drops_only_unread_samples() -> None:
    """The real graph (trackers inline here): the period-4/8/16 trackers' edges are unread
    samples, never drops; a drop on a tracker's edge would need a skipped release."""
    from test_tracker_node import _cambada_spec

    rt = flowrt.Runtime(_cambada_spec("inline", display=False))
    async with rt:
        await rt.run(1.5)
        stats = rt.stats()
    _invariant(stats)
    for name in ("bgoal", "ygoal", "line", "bpost", "ypost"):
        edge = stats.edge(f"{name}.frame")
        assert edge.unread > 0, edge
        assert edge.dropped <= stats.node(name).skipped, edge
    if not any(n.skipped for n in stats.nodes):  # a healthy run: no loss anywhere
        assert sum(e.dropped for e in stats.edges) == 0
        assert sum(n.dropped for n in stats.nodes) == 0


# --- interval statistics after a timing change --------------------------------------------


async def test_interval_after_a_period_change_describes_the_new_period() -> None:
    clock = VirtualClock()
    async with Runtime(cambada_like().build(), clock=clock) as rt:
        await publish_frames(rt, clock, range(16))  # 50 ms frames: p4ph1 every 200 ms
        before = rt.stats().node("p4ph1").interval
        rt.set_timing("p4ph1", period=2, phase=0)
        await publish_frames(rt, clock, range(16, 32))
        after = rt.stats().node("p4ph1").interval
    assert before.mean == pytest.approx(200.0)
    assert before.count == 3
    # 8 activations at 100 ms since the change; the old-to-new transition is not an interval
    assert after.count == 7
    assert after.mean == pytest.approx(100.0)
    assert after.std == pytest.approx(0.0, abs=1e-6)
    assert after.max == pytest.approx(100.0)


async def test_interval_after_a_timer_change_and_a_re_enable() -> None:
    clock = VirtualClock()
    g = GraphBuilder()
    g.add("t", Count, trigger={"timer": "50ms"})
    async with Runtime(g.build(), clock=clock) as rt:
        await clock.advance(0.5)
        rt.set_timing("t", timer=20)  # ms
        await clock.advance(0.2)
        changed = rt.stats().node("t").interval
        rt.set_timing("t", enabled=False)
        await clock.advance(1.0)
        rt.set_timing("t", enabled=True)
        await clock.advance(0.1)
        enabled = rt.stats().node("t").interval
    assert changed.mean == pytest.approx(20.0)
    assert changed.max == pytest.approx(20.0)
    assert enabled.max == pytest.approx(20.0)  # the second spent disabled is no interval
    assert enabled.count >= 4


# --- the three views -------------------------------------------------------------------------

DOM_STUB = r"""
const node = (tag) => ({
  tag, children: [], attrs: {}, className: "", textContent: "", dataset: {}, title: "", style: {},
  append(...c) { this.children.push(...c); },
  replaceChildren(...c) { this.children = c; },
  setAttribute(k, v) { this.attrs[k] = v; },
  remove() {},
  querySelector() { return null; },
});
const nodes = {};
globalThis.document = {
  title: "",
  createElement: node,
  querySelector: (sel) => (nodes[sel] ??= node(sel)),
};
globalThis.window = {};
globalThis.location = { protocol: "http:", host: "127.0.0.1" };
globalThis.WebSocket = class { constructor() {} };
globalThis.fetch = () => new Promise(() => {});
globalThis.setTimeout = () => 0;
"""

DUMP = r"""
const text = (c) => typeof c === "string" ? c : c.children.map(text).join("");
const cells = (tr) => tr.children.map((td) => [text(td), td.className]);
const rows = (sel) => nodes[sel].children.map(cells);
renderStats({ runtime: STATS, display: { clients: 0, sources: [] } });
console.log(JSON.stringify({ nodes: rows("#stats tbody"), edges: rows("#edges tbody") }));
"""


def web_view(stats: RuntimeStats) -> dict[str, Any]:
    """The page's tables as the page's own script renders them from ``/stats.json``."""
    html = (ROOT / "nodes" / "station" / "display.html").read_text()
    script = html[html.index("<script>") + len("<script>") : html.index("</script>")]
    script = script.replace("__REFRESH_MS__", "500").replace("__FLOWRT_STATS__", "null")
    # the page's start-up (joystick, first statistics, WebSocket, polling) is not run here
    script = re.sub(r"^setupJoystick\(\);.*?^poll\(\);\s*$", "", script, flags=re.M | re.S)
    program = DOM_STUB + script + f"\nconst STATS = {stats.model_dump_json()};\n" + DUMP
    node = shutil.which("node") or shutil.which("nodejs")
    assert node is not None
    out = subprocess.run([node, "-"], input=program, capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def headers(html_table: str) -> list[str]:
    html = (ROOT / "nodes" / "station" / "display.html").read_text()
    part = html[html.index(f'id="{html_table}"') :]
    part = part[: part.index("</thead>")]
    return [re.sub(r"<[^>]+>", "", h).strip() for h in re.findall(r"<th[^>]*>.*?</th>", part)]


def terminal(stats: RuntimeStats) -> tuple[list[str], dict[str, list[str]]]:
    console = Console(width=200, file=io.StringIO(), record=True, color_system=None)
    console.print(render(stats))
    lines = console.export_text().splitlines()
    rows = {ln.split()[0]: ln.split() for ln in lines if ln and not ln.startswith(" ")}
    return lines[1].split(), rows


@pytest.mark.skipif(not (shutil.which("node") or shutil.which("nodejs")), reason="no Node.js")
def test_terminal_json_and_web_view_show_the_same_figures() -> None:
    stats = cambada_stats(**FAILING)
    edges = list(stats.edges)
    edges[3] = edges[3].model_copy(update={"dropped": 4242, "unread": 0})
    stats = stats.model_copy(update={"edges": edges})
    as_json = RuntimeStats.model_validate_json(stats.model_dump_json())  # --stats-json
    assert as_json == stats
    web = web_view(as_json)
    head, term = terminal(stats)
    web_nodes = {row[0][0]: row for row in web["nodes"]}
    node_head = headers("stats")
    counters = {
        "act": "activations",
        "done": "completions",
        "skip": "skipped",
        "miss": "deadline_misses",
        "drop": "dropped",
        "err": "errors",
        "rst": "restarts",
    }
    for n in stats.nodes:
        for col, field in counters.items():
            want = str(getattr(n, field))
            assert term[n.name][head.index(col)] == want, (n.name, col)
            text, cls = web_nodes[n.name][node_head.index(col)]
            assert text == want, (n.name, col, text)
            red = col in ("miss", "drop", "err") and getattr(n, field) > 0
            assert ("bad" in cls) == red, (n.name, col, cls)
        state_text, state_cls = web_nodes[n.name][node_head.index("state")]
        assert state_text.split(":")[0] == n.state == term[n.name][head.index("state")]
        assert ("bad" in state_cls) == (n.state in ("error", "failed"))
        if n.state in ("error", "failed") and n.reason:
            assert state_text == f"{n.state}: {n.reason}"
    edge_head = headers("edges")
    web_edges = {row[0][0]: row for row in web["edges"]}
    for e in stats.edges:
        text, cls = web_edges[e.name][edge_head.index("dropped")]
        assert text == str(e.dropped) == term[e.name][4]
        assert ("bad" in cls) == (e.dropped > 0)
        text, cls = web_edges[e.name][edge_head.index("unread")]
        assert text == str(e.unread)
        assert "bad" not in cls
        assert "warn" not in cls
