"""The ``flowrt`` command: one module per command group.

``run`` (run.py), ``validate``/``graph``/``schema`` (inspect.py), ``ctl`` (ctl.py), ``check``
(check.py). A new group is a module with an ``add_parsers(sub)`` function, listed in
``GROUPS`` below.
Exit codes: see :mod:`flowrt.cli.common`.
"""

from __future__ import annotations

import argparse
import importlib

from .common import EXIT_BAD_GRAPH as EXIT_BAD_GRAPH

GROUPS = ("run", "inspect", "kinds", "ctl", "can", "check", "record", "sync")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    p = argparse.ArgumentParser(
        prog="flowrt", description="real-time dataflow runtime for robot perception"
    )
    p.add_argument("--version", action="version", version=f"flowrt {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        importlib.import_module(f"{__name__}.{group}").add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    import signal

    from .. import _startup

    try:
        _startup.imports_done()  # from here a signal is a KeyboardInterrupt, caught below
        _startup.phase = "reading the arguments"
        args = build_parser().parse_args(argv)
        _startup.phase = f"flowrt {args.command}"
        return int(args.func(args))
    except KeyboardInterrupt as e:  # one line naming the phase, exit 128 + N (130: Ctrl-C)
        return _startup.say_interrupted(getattr(e, "signum", signal.SIGINT))
