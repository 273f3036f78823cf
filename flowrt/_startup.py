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
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from typing import Any

EXIT_INTERRUPTED = 130

#: What the command is doing, for the line a signal prints ("importing", "loading the graph").
phase = "importing"
#: SIGHUP was ignored when the command started (``nohup``): every phase leaves it so.
hup_ignored = False
_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(KeyboardInterrupt):
    """A signal while the command starts; ``signum`` says which (exit 128 + signum)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def say_interrupted(signum: int, prog: str = "flowrt") -> int:
    """The one line for a signal at start-up; returns the exit code."""
    code = 128 + signum
    with contextlib.suppress(OSError):  # a terminal that hung up
        os.write(2, f"{prog}: {signal.Signals(signum).name} while {phase}: exit {code}\n".encode())
    return code


def _exit_quietly(signum: int, frame: Any) -> None:
    raise SystemExit(say_interrupted(signum))


def _raise_interrupted(signum: int, frame: Any) -> None:
    raise Interrupted(signum)


def _is_the_flowrt_command() -> bool:
    return bool(sys.argv) and os.path.basename(sys.argv[0]) in ("flowrt", "flowrt.exe")


def _install() -> None:
    global hup_ignored
    if not _is_the_flowrt_command():
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


def imports_done() -> None:
    """From here a signal is an :class:`Interrupted` (a ``KeyboardInterrupt``), for the
    command's own handling."""
    try:
        for sig in _SIGNALS:
            if signal.getsignal(sig) is _exit_quietly:
                signal.signal(sig, _raise_interrupted)
    except ValueError:
        pass


_install()
