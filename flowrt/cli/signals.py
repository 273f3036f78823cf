"""SIGINT, SIGTERM and SIGHUP at every phase of a command that runs a graph.

One rule per phase, each ending the run within about 2 s with its documented exit code and
one line on stderr naming what was interrupted (README "Signals"):

- importing, reading the arguments, loading the graph (:mod:`flowrt._startup`, then
  :func:`flowrt.cli.main`): exit 128 + the signal's number (130 for Ctrl-C), nothing started;
- set-up (workers starting, nodes' ``setup()``): the start is cancelled and undone (nodes
  torn down, workers killed after a short grace, shared memory freed), exit 128 + N;
- the run: an orderly stop (the drain, then teardown), the run's own verdict (0, or 1 when a
  node ended failed);
- the drain: cut short, what it holds counted as dropped (reason ``interrupted``);
- teardown: noted (``still stopping``), teardown goes on (bounded by each node's grace);
- a third signal in all forces the exit at once (128 + N); /dev/shm is reclaimed at the
  next start.

SIGHUP ignored when the command started (``nohup flowrt run ...``) stays ignored.
"""

from __future__ import annotations

import asyncio
import atexit
import signal
from collections.abc import Callable
from typing import Any

from .. import _startup

NO_VERDICT = ("set-up", "the start", "the re-execution")
"""Phases a signal ends with 128 + N and nothing else: what ran so far proves nothing (a
deterministic replay's re-execution cut short is no verdict on the recording)."""


class StopSignals:
    """The handlers of a command that runs a graph, from before its loop until it exits."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(
        self,
        phase: Callable[[], str],
        interrupt: Callable[[], str],
        prog: str = "flowrt run",
        stop_now: Callable[[], None] | None = None,
    ) -> None:
        self.phase = phase  # Runtime.interruption: what a signal cuts now (reads only)
        self.interrupt = interrupt  # Runtime.interrupt: acts by phase, on the loop
        # Runtime.mark_stop: from the handler, no source released from now on (the loop,
        # held by a slow call, runs its expired timers before the interrupt it is handed)
        self.stop_now = stop_now
        self.prog = prog
        self.received: list[int] = []
        self.loop: asyncio.AbstractEventLoop | None = None  # the run's loop, while it runs
        self.before_start: int | None = None  # a signal before the loop ran: do not start
        self.in_setup: int | None = None  # a signal that cancelled the set-up
        self.ran = False  # the loop has run (a signal after it is a stop in progress)
        self.stop_asked = False  # a signal asked the run to stop (the loop may not know yet)

    def install(self) -> None:
        """Plain ``signal.signal`` handlers, not the loop's: they also run while the loop is
        blocked (an inline node's teardown that hangs), so a third signal can always force
        the exit; and they stay until the process exits (the final table and the
        interpreter's own clean-up come after the loop: a signal then killed it, rc -15)."""
        for sig in self.SIGNALS:
            if sig == signal.SIGHUP and _startup.hup_ignored:
                continue  # nohup: the user asked for the run to outlive the terminal
            signal.signal(sig, self._handler)
        atexit.register(self._ignore_from_now)
        swallowed, _startup.received = _startup.received, None
        if swallowed is not None:  # raised where it was ignored (see _startup.received)
            self(swallowed)

    def _ignore_from_now(self) -> None:
        """At exit, after the final output: a signal now is ignored. The interpreter's
        finalization puts a Python handler back to the default action (an ignored one it
        leaves), and a second Ctrl-C in its 0.2-0.5 s killed the process (exit 130) after
        the run had reported exit 0."""
        for sig in self.SIGNALS:
            if signal.getsignal(sig) == self._handler:
                signal.signal(sig, signal.SIG_IGN)

    def _handler(self, signum: int, frame: Any) -> None:
        self(signum)

    def __call__(self, sig: int) -> None:
        """Said at once, from the handler (the loop may be held by an inline teardown);
        done on the loop (``call_soon_threadsafe`` is safe in a handler)."""
        self.received.append(sig)
        name = signal.Signals(sig).name
        if len(self.received) >= 3:
            line = f"{self.prog}: {name}: forced exit"
            _say(line)
            _startup.exit_now(128 + sig, line)
        loop = self.loop
        if self.in_setup is not None:  # the set-up is being undone: not a run to drain
            _say(f"{self.prog}: {name}: still stopping; a third signal forces the exit")
        elif loop is not None and not loop.is_closed():
            what = self.phase()
            if what == "the run" and self.stop_asked:
                # a second signal while a slow call holds the loop: the stop the first asked
                # for has not begun yet, but it is the drain this one cuts
                what = "the drain"
            self._say_phase(name, sig, what)
            if what == "the run":
                self.stop_asked = True
                if self.stop_now is not None:
                    self.stop_now()
            if what != "teardown":
                loop.call_soon_threadsafe(self.interrupt)
        elif not self.ran and self.before_start is None:
            self.before_start = sig  # the loop has not started: nothing will
            _say(f"{self.prog}: {name} before the start: exit {128 + sig}")
        else:
            _say(f"{self.prog}: {name}: still stopping; a third signal forces the exit")

    def _say_phase(self, name: str, sig: int, what: str) -> None:
        if what.startswith(NO_VERDICT):
            self.in_setup = sig
            _say(f"{self.prog}: {name} during {what}: stopping, exit {128 + sig}")
        elif what == "the run":
            _say(f"{self.prog}: {name}: stopping the run (drain, then teardown)")
        elif what == "the drain":
            _say(
                f"{self.prog}: {name} during the drain: cut short, what it held is counted "
                "as dropped (interrupted)"
            )
        else:
            _say(
                f"{self.prog}: {name}: still stopping (tearing the nodes down); a third "
                "signal forces the exit"
            )

    @property
    def exit_code(self) -> int | None:
        """128 + N when the signal came before the run started (then nothing ran)."""
        sig = self.before_start if self.before_start is not None else self.in_setup
        return None if sig is None else 128 + sig


def _say(text: str) -> None:
    """One line on stderr from a signal handler (``--json`` keeps it too, see _startup.say)."""
    _startup.say(text)
