"""Ctrl-C while the ``flowrt`` command is still importing: exit 130 quietly, no traceback.

The console script imports the whole package (numpy, OpenCV, pydantic: a second or more on
a busy machine) before :func:`flowrt.cli.main` can catch ``KeyboardInterrupt``; a Ctrl-C in
that time printed a traceback through numpy's import machinery. Imported first by
``flowrt/__init__.py``: only in the ``flowrt`` command (``sys.argv[0]``), and only when SIGINT
still has Python's default handler, SIGINT raises ``SystemExit(130)`` until
:func:`imports_done` (called by the CLI's ``main``) hands it back. A program that embeds
flowrt is not touched.
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Any

EXIT_INTERRUPTED = 130


def _exit_quietly(signum: int, frame: Any) -> None:
    raise SystemExit(EXIT_INTERRUPTED)


def _is_the_flowrt_command() -> bool:
    return bool(sys.argv) and os.path.basename(sys.argv[0]) in ("flowrt", "flowrt.exe")


def _install() -> None:
    if not _is_the_flowrt_command():
        return
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _exit_quietly)
    except ValueError:  # not the main thread
        pass


def imports_done() -> None:
    """SIGINT is ``KeyboardInterrupt`` again, for the command's own handling."""
    try:
        if signal.getsignal(signal.SIGINT) is _exit_quietly:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    except ValueError:
        pass


_install()
