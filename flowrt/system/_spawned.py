"""The processes the runtime spawns beside its loop (the table, the live view's and the
control endpoint's servers): Ctrl-C is the main process's to handle.

A Ctrl-C in a terminal reaches the whole process group. Such a child ignores SIGINT once its
body runs (the main process stops it in order, by ending its channel), but a spawned child
first starts an interpreter and unpickles its target, tens of milliseconds in which a
Ctrl-C printed a traceback from inside its imports (or "Fatal Python error:
init_import_site"). So the child starts with SIGINT blocked (a thread's signal mask is
inherited through fork and exec), and its body ignores it, then unblocks it: one sent in
between was pending, and is dropped.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Collection, Iterator
from multiprocessing import resource_tracker
from typing import Any

_INT = {signal.SIGINT}


@contextlib.contextmanager
def blocked(signals: Collection[int] = _INT) -> Iterator[None]:
    """``signals`` blocked in this thread meanwhile: a child started here inherits the mask
    (through fork and exec) and holds them pending until it unblocks them (:func:`ignore`)."""
    # The resource tracker first: its own start unblocks SIGINT and SIGTERM in this thread.
    resource_tracker.ensure_running()
    masked = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, masked)


def start(proc: Any) -> None:
    """``proc.start()`` (a ``multiprocessing`` process) with SIGINT blocked: its body calls
    :func:`ignore_interrupts`."""
    with blocked():
        proc.start()


def ignore(signals: Collection[int]) -> None:
    """In a child started under :func:`blocked`: ``signals`` ignored (a pending one dropped),
    then unblocked."""
    for sig in signals:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, signals)


def ignore_interrupts() -> None:
    """First thing in a spawned child's body: SIGINT ignored, then unblocked."""
    ignore(_INT)
