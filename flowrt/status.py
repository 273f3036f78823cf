"""Monitors for the terminal: the live rich table and periodic log lines.

Both only read ``rt.stats()`` and listen to events; the runtime does not know they exist.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import signal
import sys
import threading
from collections import deque
from multiprocessing.connection import Connection

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from .events import DeadlineMissed, Event, HealthAlert, LoopBlocked, NodeFailed
from .qos import QosStatus
from .runtime import Runtime
from .stats import RuntimeStats

log = logging.getLogger("flowrt.status")


def _ms(x: float) -> str:
    return f"{x:.2f}" if x < 100 else f"{x:.0f}"


def render(
    stats: RuntimeStats,
    recent: list[Event] | None = None,
    qos: QosStatus | None = None,
    alerts: list[HealthAlert] | None = None,
) -> Group:
    """The process-manager table: one row per node, one per edge, the loop and recent events.

    ``qos`` adds the QoS line (mode, overload, shed nodes); ``alerts`` the latest health alerts,
    which stay on screen even when other events scroll them out of ``recent``.
    """
    title = f"flowrt · {stats.graph} · {stats.uptime:.1f} s"
    if stats.mode:
        title += f" · mode {stats.mode}"
    if stats.loop_scheduling:
        title += f" · loop {stats.loop_scheduling}"
    elif stats.realtime:
        title += f" · {stats.realtime}"
    t = Table(title=title, title_justify="left", expand=False, pad_edge=False)
    for col, justify in [
        ("node", "left"),
        ("place", "left"),
        ("trigger", "left"),
        ("prio", "right"),
        ("period", "right"),
        ("act", "right"),
        ("done", "right"),
        ("skip", "right"),
        ("miss", "right"),
        ("err", "right"),
        ("rst", "right"),
        ("interval ms\nmean±std", "right"),
        ("exec ms\np50/p99/max", "right"),
        ("resp ms\np99", "right"),
        ("state", "left"),
    ]:
        t.add_column(col, justify=justify, no_wrap=True)  # type: ignore[arg-type]
    for n in stats.nodes:
        miss = Text(str(n.deadline_misses), style="bold red" if n.deadline_misses else "")
        skip = Text(str(n.skipped), style="yellow" if n.skipped else "")
        err = Text(str(n.errors), style="bold red" if n.errors else "")
        state_style = {"failed": "bold red", "backoff": "yellow", "disabled": "dim"}.get(
            n.state, "green"
        )
        trig = n.trigger.replace("frame ", "⟳ ")
        t.add_row(
            n.name,
            _placement(n.placement, n.granted),
            trig,
            str(n.priority),
            n.period,
            str(n.activations),
            str(n.completions),
            skip,
            miss,
            err,
            str(n.restarts),
            f"{_ms(n.interval.mean)}±{_ms(n.interval.std)}" if n.interval.count else "-",
            f"{_ms(n.execution.p50)}/{_ms(n.execution.p99)}/{_ms(n.execution.max)}"
            if n.execution.count
            else "-",
            _ms(n.response.p99) if n.response.count else "-",
            Text(n.state, style=state_style),
        )
    e = Table(expand=False, pad_edge=False, show_edge=True)
    for col in ("edge", "policy", "published", "delivered", "dropped", "age ms mean/max"):
        e.add_column(col, justify="left" if col in ("edge", "policy") else "right", no_wrap=True)
    for edge in stats.edges:
        style = "dim" if edge.sampled else "bold red"
        drop = Text(str(edge.dropped), style=style if edge.dropped else "")
        age = f"{_ms(edge.age.mean)}/{_ms(edge.age.max)}" if edge.age.count else "-"
        e.add_row(edge.name, edge.policy, str(edge.published), str(edge.delivered), drop, age)
    lag = stats.loop.lag
    footer = Text(
        f"loop lag ms p50 {lag.p50:.2f}  p99 {lag.p99:.2f}  max {lag.max:.2f}   "
        f"blocking calls {stats.loop.blocked_calls}   events {stats.events}"
    )
    parts: list[Table | Text] = [t, e, footer]
    if qos is not None and (qos.overload_control or qos.mode is not None):
        parts.append(Text(qos.describe(), style="bold red" if qos.overloaded else "magenta"))
    for a in alerts or []:
        line = f"  alert {a.t:8.3f}s {a.alert} {a.node or ''} {a.detail}"
        parts.append(Text(line, style=_alert_style(a)))
    for ev in recent or []:
        style = "red" if isinstance(ev, DeadlineMissed | NodeFailed) else "cyan"
        if isinstance(ev, HealthAlert):
            style = _alert_style(ev)
        parts.append(Text(f"  {ev.t:8.3f}s {ev.kind} {ev.node or ''} {_describe(ev)}", style=style))
    return Group(*parts)


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
    for attr in ("change", "mode", "alert", "granted", "detail"):
        if hasattr(ev, attr):
            return str(getattr(ev, attr))
    return ""


def _renderer(conn: Connection) -> None:
    """The table's own process: it renders what the runtime sends, newest first.

    Rendering a table of a dozen nodes and twenty edges takes 20-50 ms of pure Python; on the
    event loop that would delay ticks, in a thread it would still hold the GIL. Here it costs
    the runtime one ``stats()`` and one pickle (~1.5 ms) per refresh, in a gap between ticks.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the runtime's to handle
    console = Console()
    live: Live | None = None
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
            kind, payload = msg
            if kind == "log":
                console.print(payload, markup=False, highlight=False, soft_wrap=True)
                continue
            if live is None:
                live = Live(console=console, auto_refresh=False, transient=True)
                live.start()
            live.update(render(*payload), refresh=True)
    finally:
        if live is not None:
            live.stop()


class LiveTable:
    """Refreshes the table ``hz`` times a second while the runtime runs, from its own process.

    Log records are forwarded to that process too (``log_handler``), so that they print
    above the table instead of tearing it.
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
        self._proc.start()
        child.close()

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
        self.send(None)
        with self._lock:
            self._conn.close()
        self._proc.join(timeout=2.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=1.0)


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
            f"{n.name}: act={n.activations} done={n.completions} skip={n.skipped} "
            f"miss={n.deadline_misses} err={n.errors} rst={n.restarts} "
            f"interval={n.interval.mean:.2f}±{n.interval.std:.3f}ms "
            f"exec_p99={n.execution.p99:.2f}ms"
        )
    dropped = sum(e.dropped for e in stats.edges if not e.sampled)
    out.append(f"loop lag p99={stats.loop.lag.p99:.2f}ms dropped={dropped} events={stats.events}")
    return out
