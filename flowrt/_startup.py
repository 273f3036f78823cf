"""A signal while the ``flowrt`` command is still starting: one line, exit 128 + N, no traceback.

The console script imports the whole package (numpy, OpenCV, pydantic: a second or more on
a busy machine) before :func:`flowrt.cli.main` can catch anything; a Ctrl-C in that time
printed a traceback through numpy's import machinery, SIGTERM and SIGHUP killed the process
by the signal, and a SIGINT that a non-interactive shell had set to be ignored (``flowrt run
... &`` in a script) was lost until the run's own handlers came, so that ``kill -INT`` 0.8 s
after the start let the run go on to its end with exit 0.

Imported first by ``flowrt/__init__.py``, and only in the ``flowrt`` command
(``sys.argv[0]``): SIGINT, SIGTERM and SIGHUP raise ``SystemExit(128 + N)`` after one line
naming the :data:`phase`, until :func:`imports_done` (called by the CLI's ``main``) makes
them raise :class:`Interrupted`, a ``KeyboardInterrupt`` that ``main`` turns into the same
line and exit code; a command that runs a graph then installs its own handlers
(:mod:`flowrt.cli.signals`). SIGHUP ignored at the start (``nohup``) stays ignored, and a
program that embeds flowrt is not touched.

While importing, the exit is ``os._exit`` after the line (and, with ``--json``, the error
document on stdout), not an exception: a ``SystemExit`` raised inside a class body's
``__set_name__`` (pydantic's models) came out of Python 3.11 as a ``RuntimeError``, a
traceback and exit 1; nothing is started yet that an exit would leave behind.

The processes the command spawns (the table, the live view's and the control endpoint's
servers) re-import it with the same ``sys.argv``: they ignore SIGINT instead (a Ctrl-C
reaches the whole process group; the main process stops them in order) and print nothing.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Callable
from typing import Any, NoReturn

EXIT_INTERRUPTED = 130

#: What the command is doing, for the line a signal prints ("importing", "loading the graph").
phase = "importing"
#: SIGHUP was ignored when the command started (``nohup``): every phase leaves it so.
hup_ignored = False
#: The signal :func:`_raise_interrupted` last raised (None: none). Raised where exceptions are
#: ignored (a weakref callback of the import machinery, a ``__del__``), it never reached the
#: command: the run went on as if no Ctrl-C had come (CI: 60 s, then killed). A command that
#: runs a graph takes it when it installs its own handlers (flowrt.cli.signals).
received: int | None = None
_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(KeyboardInterrupt):
    """A signal while the command starts; ``signum`` says which (exit 128 + signum)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: Called with every line :func:`say` writes (``--json`` keeps them for its error document:
#: they bypass ``sys.stderr``, which a signal handler must not write to).
listeners: list[Callable[[str], None]] = []

#: Who owns the terminal while a live table is up (:class:`flowrt.monitors.status.LiveTable`):
#: a line :func:`say` writes is handed to it, to be printed above the table (written to the
#: terminal directly, the table's next redraw erased it). Returns False when it could not
#: take the line (its process gone, or busy in this very thread): then it is written here.
screen: Callable[[str], bool] | None = None


def interrupted_by(e: BaseException) -> int | None:
    """The signal behind ``e``, when an :class:`Interrupted` is in its chain: raised inside
    code that wraps what it catches (Python 3.11's ``__set_name__`` makes a ``RuntimeError``
    of it), it is still a signal, not a bug."""
    seen: set[int] = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return cur.signum if isinstance(cur, Interrupted) else int(signal.SIGINT)
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None


def say(text: str) -> None:
    """One line on stderr from a signal handler (``os.write``: the handler may run while the
    main thread is inside a write to ``sys.stderr``, which is not reentrant)."""
    taker = screen
    if taker is None or not taker(text):
        with contextlib.suppress(OSError):  # a terminal that hung up
            os.write(2, (text + "\n").encode())
    for listener in listeners:
        listener(text)


def say_interrupted(signum: int, prog: str = "flowrt") -> int:
    """The one line for a signal at start-up; returns the exit code."""
    say(_line(signum, prog))
    return 128 + signum


def _line(signum: int, prog: str = "flowrt") -> str:
    return f"{prog}: {signal.Signals(signum).name} while {phase}: exit {128 + signum}"


def _exit_quietly(signum: int, frame: Any) -> None:
    exit_now(say_interrupted(signum), _line(signum))


def exit_now(code: int, line: str) -> NoReturn:
    """``os._exit(code)`` from a signal handler, with, under ``--json``, the error document
    (``line`` its message) on stdout first: exactly one document, whatever happens (a
    forced exit printed none)."""
    given = sys.argv[1:]
    given = given[: given.index("--")] if "--" in given else given  # as flowrt.cli.main reads
    if "--json" in given:  # exactly one document on stdout (cli/json_output.py's form)
        command = next((w for w in given if not w.startswith("-")), "")
        text = _quoted(line)
        doc = (
            f'{{"error": {{"message": {text}, "exit_code": {code}, '
            f'"command": {_quoted(command)}, "lines": [{text}]}}}}\n'
        )
        with contextlib.suppress(OSError):
            os.write(1, doc.encode())
    _unlink_own_segments()
    os._exit(code)


def _unlink_own_segments() -> None:
    """This process's shared-memory segments (frames, the RTDB: ``flowrt_{pid}_...``, see
    flowrt.frames.pool), unlinked before a forced exit: they waited in /dev/shm for the next
    start to reclaim them. Processes that still map one keep their mapping."""
    prefix = f"flowrt_{os.getpid()}_"
    try:
        names = os.listdir("/dev/shm")
    except OSError:
        return
    for name in names:
        if name.startswith(prefix):
            with contextlib.suppress(OSError):
                os.unlink(os.path.join("/dev/shm", name))


def _quoted(text: str) -> str:
    """A JSON string (no ``json`` import in a signal handler that may run inside an import)."""
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + "".join(c if " " <= c < "\x7f" else f"\\u{ord(c):04x}" for c in escaped) + '"'


def _raise_interrupted(signum: int, frame: Any) -> None:
    global received
    received = signum
    raise Interrupted(signum)


def _is_the_flowrt_command() -> bool:
    return bool(sys.argv) and os.path.basename(sys.argv[0]) in ("flowrt", "flowrt.exe")


def _is_spawned_child() -> bool:
    """A process multiprocessing spawned (its ``sys.argv`` is the parent's)."""
    return "--multiprocessing-fork" in getattr(sys, "orig_argv", ())


def _install() -> None:
    global hup_ignored
    if not _is_the_flowrt_command():
        return
    if _is_spawned_child():  # see the module: Ctrl-C is the main process's to handle
        with contextlib.suppress(ValueError):
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        return
    try:
        for sig in _SIGNALS:
            current = signal.getsignal(sig)
            if sig == signal.SIGHUP and current is signal.SIG_IGN:
                hup_ignored = True
            elif sig == signal.SIGINT or current is signal.SIG_DFL:
                signal.signal(sig, _exit_quietly)
    except ValueError:  # not the main thread
        pass


def _unraisable(hook: Any) -> Callable[[Any], None]:
    """``sys.unraisablehook`` that says nothing of an :class:`Interrupted` raised where it is
    ignored (``Exception ignored in: <function _get_module_lock.<locals>.cb>`` and a
    traceback): :data:`received` keeps it for the command; anything else as before."""

    def unraisable(info: Any) -> None:
        if not isinstance(info.exc_value, Interrupted):
            hook(info)

    return unraisable


def imports_done() -> None:
    """From here a signal is an :class:`Interrupted` (a ``KeyboardInterrupt``), for the
    command's own handling."""
    if _is_the_flowrt_command() and not _is_spawned_child():
        sys.unraisablehook = _unraisable(sys.unraisablehook)
    try:
        for sig in _SIGNALS:
            if signal.getsignal(sig) is _exit_quietly:
                signal.signal(sig, _raise_interrupted)
    except ValueError:
        pass


_install()
