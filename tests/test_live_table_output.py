"""Lines printed while the live table is on a terminal stay on screen, above the table.

rich redraws the table by moving the cursor up over the table's own height; a line written
to the terminal by anyone else (the display node's ``display: URL``) shifts the table down
a row, so the next redraw erased that line and left the table's old title behind. The run's
``sys.stdout`` is forwarded to the table's process while the table is up, which prints it
above the table. The screens are read back through a small terminal model of the few
control sequences rich's Live writes.
"""

from __future__ import annotations

import fcntl
import io
import os
import re
import select
import struct
import subprocess
import sys
import termios
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from rich.console import Console

from flowrt.monitors.status import _Forward, _Screen
from flowrt.stats import LoopStats, NodeStats, RuntimeStats, Summary

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parents[1]
URL = "display: http://127.0.0.1:8750"
_CONTROL = re.compile(r"\x1b\[([0-9;?]*)([A-Za-z])|\r|\n|\x1b")


def screen(output: str, width: int = 80) -> list[str]:
    """The lines a terminal shows after ``output`` (scrolled-off lines included), for the
    sequences rich's Live writes: CR, LF (as a tty's CR LF), erase line, cursor up, cursor
    shown/hidden and colours; any other control sequence fails the test rather than being
    misread."""
    rows: list[list[str]] = [[]]
    r = c = 0

    def put(text: str) -> None:
        nonlocal r, c
        for ch in text:
            if c >= width:  # autowrap
                r, c = r + 1, 0
            rows.extend([] for _ in range(r + 1 - len(rows)))
            row = rows[r]
            row.extend(" " * (c + 1 - len(row)))
            row[c] = ch
            c += 1

    pos = 0
    for m in _CONTROL.finditer(output):
        put(output[pos : m.start()])
        pos = m.end()
        token, (args, final) = m.group(0), m.groups()
        if token == "\r":
            c = 0
        elif token == "\n":
            r, c = r + 1, 0
            rows.extend([] for _ in range(r + 1 - len(rows)))
        elif final == "K" and args == "2":
            rows[r] = []
        elif final == "A":
            r = max(0, r - int(args or 1))
        elif final == "m" or (final in "hl" and args == "?25"):
            pass  # colours; the cursor hidden or shown
        else:
            raise AssertionError(f"a control sequence the model does not know: {token!r}")
    put(output[pos:])
    return ["".join(row).rstrip() for row in rows]


def stats(uptime: float) -> tuple[RuntimeStats]:
    node = NodeStats(
        name="tick", kind="counter", placement="inline", trigger="timer", priority=0,
        period="20ms", deadline_ms=None, enabled=True, state="idle", reason="",
        activations=int(uptime * 50), completions=int(uptime * 50), skipped=0,
        deadline_misses=0, discarded=0, aborted=0, dropped=0, errors=0, restarts=0,
        paced_lead_max=0, last_start=None, last_finish=None, interval=Summary(),
        execution=Summary(), response=Summary(),
    )  # fmt: skip
    loop = LoopStats(lag=Summary(), blocked_calls=0)
    return (RuntimeStats(graph="g", uptime=uptime, nodes=[node], edges=[], loop=loop, events=0),)


def terminal() -> tuple[io.StringIO, _Screen]:
    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=80, height=24, color_system=None)
    return out, _Screen(console)


def titles(lines: list[str]) -> list[str]:
    return [ln for ln in lines if ln.startswith("flowrt · g ·")]


def test_a_line_written_past_the_table_is_erased_and_leaves_a_stale_title() -> None:
    """The defect itself, as the model shows it: what the forwarding exists to avoid."""
    out, table = terminal()
    table.show("stats", stats(0.6))
    out.write(URL + "\n")  # the display node's print, straight to the terminal
    table.show("stats", stats(1.2))
    lines = screen(out.getvalue())
    assert not any(URL in ln for ln in lines)
    assert titles(lines) == ["flowrt · g · 0.6 s", "flowrt · g · 1.2 s"]


def test_a_line_printed_while_the_table_is_up_stays_above_it() -> None:
    out, table = terminal()

    def send(msg: object) -> bool:
        assert isinstance(msg, tuple)
        table.show(*msg)
        return True

    stdout = _Forward(send, io.StringIO())
    table.show("stats", stats(0.6))
    print(URL, file=stdout, flush=True)
    table.show("stats", stats(1.2))
    print("two", "lines\nin one write", file=stdout, end="", flush=False)
    table.show("stats", stats(1.8))
    stdout.flush()  # the line without its newline: not held back
    table.show("stats", stats(2.4))
    lines = screen(out.getvalue())
    assert [ln for ln in lines if not ln.startswith(("flowrt", "node", "tick", "─", "loop"))] == [
        URL,
        "two lines",
        "in one write",
    ]
    assert lines[0] == URL
    assert titles(lines) == ["flowrt · g · 2.4 s"]


def test_forwarded_stdout_falls_back_to_the_stream_once_the_table_is_gone() -> None:
    stream = io.StringIO()
    sent: list[object] = []

    def send(msg: object) -> bool:
        sent.append(msg)
        return len(sent) < 2  # the table's process is gone after the first line

    stdout = _Forward(send, stream)
    stdout.write("a\nb")
    stdout.write("c\n")
    assert sent == [("out", "a"), ("out", "bc")]
    assert stream.getvalue() == "bc\n"  # not lost: written where it was going
    assert stdout.isatty() is False  # the stream's answer, not a guess
    with pytest.raises(TypeError):
        stdout.write(b"bytes")  # type: ignore[arg-type]


PRINTER = '''
from flowrt import Node

class Printer(Node):
    """Prints a line every tenth tick, as the display node prints its URL; ends the run after
    its 52nd tick (2.6 s on an idle machine, later on a loaded one that skips ticks)."""

    def setup(self) -> None:
        self.n = 0

    def process(self) -> None:
        self.n += 1
        if self.n % 10 == 0:
            print(f"printed {self.n // 10}", flush=True)
        if self.n == 52:
            self.ctx.request_stop()
'''


def on_a_pty(
    args: list[str],
    cwd: Path,
    react: Callable[[bytes, subprocess.Popen[bytes]], None] | None = None,
) -> tuple[int, str]:
    """``python -m flowrt.cli ARGS`` on an 80x24 pty until it ends (50 s at most): its exit
    code and everything it wrote; ``react(output so far, process)`` after each read."""
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=cwd,
        env={**env, "TERM": "xterm-256color"},
        stdin=subprocess.DEVNULL,
        stdout=slave,
        stderr=slave,
    )
    os.close(slave)
    raw = bytearray()
    deadline = time.monotonic() + 50
    try:
        while time.monotonic() < deadline:
            if react is not None:
                react(bytes(raw), proc)
            if select.select([master], [], [], 0.2)[0]:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: every end of the pty's slave is closed
                    break
                if not chunk:
                    break
                raw += chunk
        return proc.wait(timeout=10), raw.decode(errors="replace")
    finally:
        os.close(master)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_run_on_a_terminal_keeps_what_a_node_prints(tmp_path: Path) -> None:
    """``flowrt run`` on an 80x24 pty: every line a node printed, once, above the final
    table, and no title of an earlier table left on screen."""
    (tmp_path / "printer.py").write_text(PRINTER)
    graph = tmp_path / "g.yaml"
    graph.write_text("name: g\nnodes:\n  p: {kind: 'printer:Printer', trigger: {timer: 50ms}}\n")
    # the node ends the run after 5 lines: not a window a loaded machine's late or skipped
    # ticks would leave fewer in (the duration is a bound)
    code, out = on_a_pty(["run", str(graph), "--duration", "30"], tmp_path)
    assert code == 0, out
    lines = screen(out)
    printed = [ln for ln in lines if ln.startswith("printed")]
    assert printed == [f"printed {i}" for i in range(1, len(printed) + 1)], lines
    assert len(printed) >= 4, lines
    assert len([ln for ln in lines if ln.startswith("flowrt · g ·")]) == 1, lines


def test_the_stopping_line_of_a_signal_stays_above_the_table(tmp_path: Path) -> None:
    """Ctrl-C while the table is up: the line saying what the signal does is printed above
    the table by the table's process (written to the terminal by the handler, the table's
    next redraw erased it), once, and the run still ends as a stopped run does."""
    import signal

    graph = tmp_path / "g.yaml"
    graph.write_text("name: g\nnodes:\n  c: {kind: counter, trigger: {timer: 20ms}}\n")
    sent: list[bool] = []

    def interrupt(out: bytes, proc: subprocess.Popen[bytes]) -> None:
        if not sent and out.count("flowrt · g ·".encode()) >= 3:  # the table, redrawn
            proc.send_signal(signal.SIGINT)
            sent.append(True)

    code, out = on_a_pty(["run", str(graph), "--duration", "60"], tmp_path, interrupt)
    assert sent, out
    assert code == 0, out  # stopped, not failed
    said = [ln for ln in screen(out) if "stopping the run" in ln]
    assert said == ["flowrt run: SIGINT: stopping the run (drain, then teardown)"], screen(out)
