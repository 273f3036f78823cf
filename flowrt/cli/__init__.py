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
    from .._startup import imports_done

    try:
        imports_done()  # from here Ctrl-C is a KeyboardInterrupt, caught below
        args = build_parser().parse_args(argv)
        return int(args.func(args))
    except KeyboardInterrupt:
        return 130
