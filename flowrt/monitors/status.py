"""Monitors for the terminal: the live rich table and periodic log lines.

Both only read ``rt.stats()`` and listen to events; the runtime does not know they exist.
"""

from __future__ import annotations

import asyncio
import io
import logging
import math
import multiprocessing
import sys
import threading
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, TextIO, TypeVar, cast

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.text import Text

from .. import _startup
from ..events import DeadlineMissed, Event, HealthAlert, LoopBlocked, NodeFailed
from ..runtime._qos import QosStatus
from ..runtime._runtime import Runtime
from ..stats import EdgeStats, NodeStats, RuntimeStats
from ..system import _spawned as spawned
from ._columns import Column, fit_table

log = logging.getLogger("flowrt.monitors.status")
S = TypeVar("S")  # a row: NodeStats or EdgeStats


def _ms(x: float) -> str:
    return f"{x:.2f}" if x < 100 else f"{x:.0f}"


# --- the table's columns ------------------------------------------------------------------
#
# Each column has a drop rank: at a narrow width the columns are dropped in rank order
# (1 first) until the table fits; rank 0 is never dropped. The essentials (names, state and
# every counter of a failure) are rank 0, so an 80-column terminal still shows them in full.
# Node columns, dropped first to last: resp p99, place, trigger, prio, exec, interval,
# period, done, rst. Edge columns: age, policy, unread, deliv, pub.


def _count(n: int, style: str) -> Text:
    return Text(str(n), style=style if n else "")


def _state(n: NodeStats) -> Text:
    return Text(n.state, style=STATE_STYLE.get(n.state, "green"))


STATE_STYLE = {
    "failed": "bold red",
    "error": "bold red",
    "backoff": "yellow",
    "waiting": "cyan",
    "starting": "yellow",
    "disabled": "dim",
}

NODE_COLUMNS: tuple[Column[NodeStats], ...] = (
    Column("node", lambda n: n.name, right=False),
    Column("state", _state, right=False),
    Column("act", lambda n: str(n.activations)),
    Column("done", lambda n: str(n.completions), drop=8),
    Column("skip", lambda n: _count(n.skipped, "yellow")),
    Column("miss", lambda n: _count(n.deadline_misses, "bold red")),
    Column("drop", lambda n: _count(n.dropped, "bold red")),
    Column("err", lambda n: _count(n.errors, "bold red")),
    Column("rst", lambda n: _count(n.restarts, "yellow"), drop=9),
    Column("period", lambda n: n.period, drop=7),
    Column(
        "interval ms",
        lambda n: f"{_ms(n.interval.mean)}±{_ms(n.interval.std)}" if n.interval.count else "-",
        drop=6,
    ),
    Column(
        "exec ms p50/p99/max",
        lambda n: (
            f"{_ms(n.execution.p50)}/{_ms(n.execution.p99)}/{_ms(n.execution.max)}"
            if n.execution.count
            else "-"
        ),
        drop=5,
    ),
    Column("resp ms p99", lambda n: _ms(n.response.p99) if n.response.count else "-", drop=1),
    Column("place", lambda n: _placement(n.placement, n.granted), drop=2, right=False),
    Column("trigger", lambda n: n.trigger.replace("frame ", "⟳ "), drop=3, right=False),
    Column("prio", lambda n: str(n.priority), drop=4),
)

EDGE_COLUMNS: tuple[Column[EdgeStats], ...] = (
    Column("edge", lambda e: e.name, right=False),
    Column("policy", lambda e: e.policy, drop=2, right=False),
    Column("pub", lambda e: str(e.published), drop=5),
    Column("deliv", lambda e: str(e.delivered), drop=4),
    Column("drop", lambda e: _count(e.dropped, "bold red")),
    Column("unread", lambda e: Text(str(e.unread), style="dim"), drop=3),
    Column(
        "age ms mean/max",
        lambda e: f"{_ms(e.age.mean)}/{_ms(e.age.max)}" if e.age.count else "-",
        drop=1,
    ),
)


def _node_rank(n: NodeStats) -> int:
    """0: a failure (red), 1: a warning (yellow), 2: fine; the first to show when rows are few."""
    if n.state in ("error", "failed") or n.deadline_misses or n.dropped or n.errors:
        return 0
    if n.state in ("backoff", "starting") or n.skipped or n.restarts:
        return 1
    return 2


def _pick(items: Sequence[S], rank: Callable[[S], int], rows: int) -> list[S]:
    """At most ``rows`` items, the lowest ranks first, shown in their original order."""
    if len(items) <= rows:
        return list(items)
    order = sorted(range(len(items)), key=lambda i: (rank(items[i]), i))
    keep = sorted(order[: max(rows, 0)])
    return [items[i] for i in keep]


def _line(text: str, style: str = "") -> Text:
    return Text(text, style=style, no_wrap=True, overflow="ellipsis")


def render(
    stats: RuntimeStats,
    recent: list[Event] | None = None,
    qos: QosStatus | None = None,
    alerts: list[HealthAlert] | None = None,
    *,
    width: int | None = None,
    height: int | None = None,
) -> Group:
    """The process-manager table: one row per node, one per edge, the loop and recent events.

    ``qos`` adds the QoS line (mode, overload, shed nodes); ``alerts`` the latest health alerts,
    which stay on screen even when other events scroll them out of ``recent``.

    ``width`` drops the least important columns first (see ``NODE_COLUMNS``) so that names
    and failure counters are never cut; ``height`` (a terminal's rows) makes the nodes with
    failures and warnings the rows that stay, the others summarised as ``+N ok``, then the
    edges with drops, then recent events. ``None``: everything.
    """
    title = f"flowrt · {stats.graph} · {stats.uptime:.1f} s"
    if stats.mode:
        title += f" · mode {stats.mode}"
    if stats.cpu_latency:  # asked for (--cpu-latency): held, or the operator is told it is not
        title += f" · wake-up {_bound(stats.cpu_latency)}"  # (before the loop's longer words)
    if stats.loop_scheduling:
        title += f" · loop {stats.loop_scheduling}"
    elif stats.realtime:
        title += f" · {stats.realtime}"

    lag = stats.loop.lag
    footer = _line(
        f"loop lag ms p50 {lag.p50:.2f} p99 {lag.p99:.2f} max {lag.max:.2f} · "
        f"blocking calls {stats.loop.blocked_calls} · events {stats.events}"
    )
    extra: list[Text] = [
        _line(f"  frames {p.owner}: {p.dropped} dropped, every one of its slots held", "bold red")
        for p in stats.frames
        if p.dropped
    ]
    extra.extend(_progress(name, r) for name, r in stats.reports.items() if _has_progress(r))
    if qos is not None and (qos.overload_control or qos.mode is not None):
        extra.append(_line(qos.describe(), "bold red" if qos.overloaded else "magenta"))
    for a in alerts or []:
        line = f"  alert {a.t:8.3f}s {a.alert} {a.node or ''} {a.detail}"
        extra.append(_line(line, _alert_style(a)))

    # rows: 1 title, 2 node header, the nodes, their reasons, footer, qos/alerts, the rest
    room = math.inf if height is None else height - 1  # the cursor's line
    room -= 1 + 2 + 1 + len(extra)
    nodes = list(stats.nodes)
    shown = _fit_nodes(nodes, room)
    reasons = [
        _line(f"  {n.name} {n.state}: {n.reason}", "bold red") for n in shown if _has_reason(n)
    ]
    room -= len(shown) + len(reasons)
    parts: list[RenderableType] = [_line(title, "bold"), fit_table(NODE_COLUMNS, shown, width)]
    if len(shown) < len(nodes):
        parts.append(_hidden(nodes, shown, _node_rank, "nodes"))
        room -= 1
    parts.extend(reasons)
    parts.append(footer)
    parts.extend(extra)

    edges = list(stats.edges)
    if edges and room >= 3:
        fit = room - 2
        shown_e = edges if fit >= len(edges) else _pick(edges, _edge_rank, int(fit) - 1)
        parts.append(fit_table(EDGE_COLUMNS, shown_e, width))
        room -= 2 + len(shown_e)
        if len(shown_e) < len(edges):
            parts.append(_hidden(edges, shown_e, _edge_rank, "edges"))
            room -= 1
    elif edges and room >= 1:
        parts.append(_hidden(edges, [], _edge_rank, "edges"))
        room -= 1

    events = list(recent or [])
    if room < len(events):
        events = events[len(events) - max(int(room), 0) :]
    for ev in events:
        style = "red" if isinstance(ev, DeadlineMissed | NodeFailed) else "cyan"
        if isinstance(ev, HealthAlert):
            style = _alert_style(ev)
        parts.append(_line(f"  {ev.t:8.3f}s {ev.kind} {ev.node or ''} {_describe(ev)}", style))
    return Group(*parts)


def _has_progress(report: Any) -> bool:
    return isinstance(report, dict) and isinstance(report.get("progress"), dict)


def _progress(name: str, report: dict[str, Any], bar: int = 20) -> Text:
    """A replay node's position in its recording (its ``report()``'s ``progress``)."""
    p = report["progress"]
    pos, span = float(p.get("position_s") or 0.0), p.get("duration_s")
    loops = f" · loop {p['loops'] + 1}" if p.get("loops") else ""
    if not span:  # a file not closed cleanly: its length is not known
        return _line(f"  replay {name} {pos:.1f} s{loops}", "cyan")
    done = min(1.0, pos / float(span))
    filled = round(done * bar)
    line = f"  replay {name} {'█' * filled}{'░' * (bar - filled)} {pos:.1f} / {span:.1f} s"
    return _line(f"{line} ({done:.0%}){loops}", "cyan")


def _has_reason(n: NodeStats) -> bool:
    return bool(n.reason) and n.state in ("error", "failed", "waiting")


def _fit_nodes(nodes: list[NodeStats], room: float) -> list[NodeStats]:
    """As many nodes as fit ``room`` rows with their reason lines (failures first), leaving a
    row for the ``+N`` summary when some are left out."""
    if len(nodes) + sum(map(_has_reason, nodes)) <= room:
        return nodes
    order = sorted(nodes, key=_node_rank)  # stable: graph order within a rank
    used, k = 1, 0  # the summary's row
    for n in order:
        cost = 1 + _has_reason(n)
        if used + cost > room:
            break
        used += cost
        k += 1
    return _pick(nodes, _node_rank, k)


def _edge_rank(e: EdgeStats) -> int:
    return 0 if e.dropped else 2


def _hidden(items: Sequence[S], shown: Sequence[S], rank: Callable[[S], int], what: str) -> Text:
    """``+12 ok`` for rows left out; those with failures or warnings said apart, in colour."""
    rest = [x for x in items if x not in shown]
    bad = sum(1 for x in rest if rank(x) == 0)
    warn = sum(1 for x in rest if rank(x) == 1)
    if not bad and not warn:
        return _line(f"  +{len(rest)} {what} ok", "green")
    text = f"  +{len(rest)} {what}: {bad} failing, {warn} warning, {len(rest) - bad - warn} ok"
    return _line(text, "bold red" if bad else "yellow")


def _alert_style(a: HealthAlert) -> str:
    return "bold red" if a.severity in ("error", "critical") else "yellow"


def _placement(placement: str, granted: str) -> str:
    """``process FIFO 45`` / ``pool nice 3``: where a node runs and what the OS granted."""
    if not granted:
        return placement
    short = granted.replace("SCHED_", "").split(" (")[0]
    return f"{placement} {short}"


def _describe(ev: Event) -> str:
    if isinstance(ev, NodeFailed):
        return ev.error
    if isinstance(ev, DeadlineMissed):
        return f"deadline {ev.deadline_ms:g} ms" + (" (still running)" if ev.still_running else "")
    if isinstance(ev, LoopBlocked):
        return f"blocked the loop {ev.duration_ms:.1f} ms"
    for attr in ("change", "mode", "alert", "granted", "detail", "reason"):
        if hasattr(ev, attr):
            return str(getattr(ev, attr))
    return ""


def _renderer(conn: Connection) -> None:
    """The table's own process: it renders what the runtime sends, newest first.

    Rendering a table of a dozen nodes and twenty edges takes ~10 ms of pure Python; on the
    event loop that would delay ticks, in a thread it would still hold the GIL. Here it costs
    the runtime one ``stats()`` and one pickle (~1.5 ms) per refresh, in a gap between ticks.
    The table is fitted to the terminal's size at every refresh (a resized pane just works).
    """
    spawned.ignore_interrupts()  # Ctrl-C is the runtime's to handle (started with it blocked)
    screen = _Screen(Console())
    try:
        while True:
            try:
                msg = conn.recv()
                while msg is not None and msg[0] == "stats" and conn.poll():
                    msg = conn.recv()  # only the newest table is worth drawing
            except (EOFError, OSError):
                break
            if msg is None:
                break
            screen.show(*msg)
    finally:
        screen.close()


class _Screen:
    """The terminal as the table's process draws it: the table, and lines printed above it.

    Only this process may write to the terminal while the table is up: rich's redraw moves
    the cursor up by the table's own height, so a line written by anyone else shifts the
    table down one row, the redraw starts one row too low, and it erases that line and
    leaves the table's old first line behind. Lines of the run's process (log records,
    ``print``) are sent here instead and printed through the same Live.
    """

    def __init__(self, console: Console) -> None:
        self.console = console
        self.live: Live | None = None

    def show(self, kind: str, payload: Any) -> None:
        """``("log", text)``, ``("out", text)`` (the run's stdout) or ``("stats", args)``."""
        if kind == "log":
            self.console.print(payload, markup=False, highlight=False, soft_wrap=True)
            return
        if kind == "out":  # a rich console's colours in it stay colours, not escape codes
            self.console.print(Text.from_ansi(payload), soft_wrap=True)
            return
        if self.live is None:
            self.live = Live(console=self.console, auto_refresh=False, transient=True)
            self.live.start()
        width, height = self.console.size
        self.live.update(render(*payload, width=width, height=height), refresh=True)

    def close(self) -> None:
        """Remove the table (transient): the run's final table is printed in its place."""
        if self.live is not None:
            self.live.stop()
            self.live = None


class LiveTable:
    """Refreshes the table ``hz`` times a second while the runtime runs, from its own process.

    Log records are forwarded to that process too (``log_handler``), and so is what this
    process prints to ``sys.stdout`` while the table is on a terminal (a node's ``print``,
    the display's URL), so that they print above the table instead of tearing it (see
    :class:`_Screen`). What other processes (workers) write to the terminal is not.
    """

    def __init__(self, console: Console | None = None, hz: float = 4.0) -> None:
        self.console = console or Console()
        self.hz = hz
        self.recent: deque[Event] = deque(maxlen=6)
        self.alerts: deque[HealthAlert] = deque(maxlen=3)
        self._task: asyncio.Task[None] | None = None
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._lock = threading.Lock()  # log records come from any thread
        self._proc = ctx.Process(target=_renderer, args=(child,), name="flowrt-table", daemon=True)
        spawned.start(self._proc)
        child.close()
        self._stdout: _Forward | None = None  # sys.stdout while the table is up

    def log_handler(self) -> logging.Handler:
        return _PipeHandler(self)

    def send(self, msg: object) -> bool:
        with self._lock:
            if self._conn.closed:
                return False
            try:
                self._conn.send(msg)
            except (OSError, ValueError):
                return False
            return True

    def started(self, rt: Runtime) -> None:
        self._task = asyncio.get_running_loop().create_task(self._refresh(rt))
        # Before the nodes' setup: what they print from then on goes above the table. Only
        # on a terminal: elsewhere there is no table to tear, and the output stays as it is.
        if self.console.is_terminal and self._stdout is None:
            self._stdout = _Forward(self.send, sys.stdout)
            sys.stdout = cast(TextIO, self._stdout)
            _startup.screen = self._say_above  # a signal's line too (``stopping the run``)

    def _say_above(self, text: str) -> bool:
        """A signal handler's line, printed above the table. Called between two bytecodes
        of the main thread, maybe inside :meth:`send`: never waits for its lock (False:
        the caller writes the line itself)."""
        if not self._lock.acquire(blocking=False):
            return False
        try:
            if self._conn.closed:
                return False
            self._conn.send(("log", text))
            return True
        except (OSError, ValueError):
            return False
        finally:
            self._lock.release()

    async def _refresh(self, rt: Runtime) -> None:
        while True:
            # Even a snapshot holds the loop a little: take it between ticks.
            await asyncio.sleep(rt.quiet_delay(1 / self.hz))
            if rt.started:
                payload = (rt.stats(), list(self.recent), rt.qos_status(), list(self.alerts))
                self.send(("stats", payload))

    def event(self, event: Event) -> None:
        self.recent.append(event)
        if isinstance(event, HealthAlert):
            self.alerts.append(event)

    def stopped(self, rt: Runtime) -> None:
        if self._task is not None:
            self._task.cancel()
        self.close()

    def close(self) -> None:
        """Stop the renderer (it removes its table) and wait for it, briefly."""
        if _startup.screen == self._say_above:
            _startup.screen = None
        forward, self._stdout = self._stdout, None
        if forward is not None:
            forward.flush()  # a line without its newline yet: printed before the table goes
            if sys.stdout is forward:  # else someone replaced it since: theirs to restore
                sys.stdout = forward.stream
        self.send(None)
        with self._lock:
            self._conn.close()
        self._proc.join(timeout=2.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=1.0)


class _Forward(io.TextIOBase):
    """``sys.stdout`` while the table is up: each whole line is sent to the table's process,
    which prints it above the table; written to ``stream`` itself once that process is gone.

    Whole lines, because the table is redrawn after each message: half a line would end
    up on a line of its own anyway. ``flush`` sends what is buffered, so a line written
    without its newline (a prompt, a progress dot) is not held back until the run's end.
    """

    def __init__(self, send: Callable[[object], bool], stream: TextIO) -> None:
        super().__init__()
        self.send = send
        self.stream = stream
        self._partial = ""
        self._lock = threading.Lock()  # print() from any thread

    def write(self, text: str) -> int:
        if not isinstance(text, str):  # as a real text stream says it
            raise TypeError(f"write() argument must be str, not {type(text).__name__}")
        with self._lock:
            head, newline, tail = (self._partial + text).rpartition("\n")
            self._partial = tail
            if newline:
                self._out(head)
        return len(text)

    def flush(self) -> None:
        with self._lock:
            partial, self._partial = self._partial, ""
            if partial:
                self._out(partial)
        self.stream.flush()

    def _out(self, text: str) -> None:
        if not self.send(("out", text)):
            self.stream.write(text + "\n")
            self.stream.flush()

    # What callers ask of sys.stdout besides writing: the terminal's answers. Anything else
    # (``buffer``, ``reconfigure``) is the stream's: bytes written there bypass the table, as
    # they did before, rather than fail.
    def __getattr__(self, name: str) -> Any:
        if name == "stream":  # not set yet (a copy being made): no endless recursion
            raise AttributeError(name)
        return getattr(self.stream, name)

    def isatty(self) -> bool:
        return self.stream.isatty()

    def fileno(self) -> int:
        return self.stream.fileno()

    def writable(self) -> bool:
        return True

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return self.stream.encoding

    @property
    def errors(self) -> str | None:  # type: ignore[override]
        return self.stream.errors


class _PipeHandler(logging.Handler):
    """Formats a record here and prints it in the table's process (stderr once it is gone)."""

    def __init__(self, table: LiveTable) -> None:
        super().__init__()
        self.table = table
        self.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
        )

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:
            self.handleError(record)
            return
        if not self.table.send(("log", text)):
            print(text, file=sys.stderr)


class LogLines:
    """``--no-ui``: one summary line per node every ``every`` seconds, events as they happen."""

    def __init__(self, every: float = 2.0) -> None:
        self.every = every
        self._task: asyncio.Task[None] | None = None

    def started(self, rt: Runtime) -> None:
        self._task = asyncio.get_running_loop().create_task(self._loop(rt))

    async def _loop(self, rt: Runtime) -> None:
        while True:
            await asyncio.sleep(rt.quiet_delay(self.every))
            if rt.started:
                for line in summary_lines(rt.stats()):
                    log.info("%s", line)

    def event(self, event: Event) -> None:
        if not isinstance(event, NodeFailed):  # failures are logged with their traceback
            log.info("event %s %s %s", event.kind, event.node or "", _describe(event))

    def stopped(self, rt: Runtime) -> None:
        if self._task is not None:
            self._task.cancel()


def summary_lines(stats: RuntimeStats) -> list[str]:
    out = []
    for n in stats.nodes:
        out.append(
            f"{n.name}: {n.state}{f' ({n.reason})' if n.reason else ''} "
            f"act={n.activations} done={n.completions} skip={n.skipped} "
            f"miss={n.deadline_misses} drop={n.dropped} err={n.errors} rst={n.restarts} "
            f"interval={n.interval.mean:.2f}±{n.interval.std:.3f}ms "
            f"exec_p99={n.execution.p99:.2f}ms"
        )
    dropped = sum(e.dropped for e in stats.edges)
    unread = sum(e.unread for e in stats.edges)
    out.append(
        f"loop lag p99={stats.loop.lag.p99:.2f}ms dropped={dropped} unread={unread} "
        f"events={stats.events}"
    )
    return out


def _bound(granted: str) -> str:
    """``held at 10000 us`` -> ``≤ 10 ms``; a refusal -> ``bound not held``."""
    us = granted.removeprefix("held at ").removesuffix(" us")
    if not us.isdigit():
        return "bound not held"
    n = int(us)
    return f"≤ {n / 1000:g} ms" if n >= 1000 else f"≤ {n} us"
