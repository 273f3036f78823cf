"""What every command shares: loading a graph with its diagnostics, exit codes, logging.

Exit codes (documented in the README): 0 success, 1 a runtime failure (a node ended failed,
the timing does not hold), 2 a bad graph file or bad arguments, 128 + N interrupted by signal N
before the run ran (130 for Ctrl-C; :mod:`flowrt.cli.signals`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import re
import sys
from collections.abc import Iterable
from pathlib import Path

from rich.console import Console

from ..graph._resolve import Graph
from ..graph.diagnostics import Diagnostic, GraphError, Severity

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_GRAPH = 2


def plural(n: int, word: str) -> str:
    """``1 edge``, ``2 nodes``, ``0 errors``."""
    return f"{n} {word}{'' if n == 1 else 's'}"


def diagnostic_json(d: Diagnostic) -> dict[str, object]:
    return {
        "file": d.file,
        "line": d.line,
        "column": d.column,
        "severity": str(d.severity),
        "key": d.key,
        "message": d.message,
    }


def _with_examples_hint(e: GraphError, path: str) -> GraphError:
    """A missing ``graphs/cambada.yaml``: a wheel's user has the examples in the package."""
    from .example_files import is_example

    if Path(path).exists() or len(e.diagnostics) != 1 or not is_example(path):
        return e
    (d,) = e.diagnostics
    hint = "; the example graphs ship with flowrt: `flowrt examples --copy .` writes ./graphs"
    return GraphError([dataclasses.replace(d, message=d.message + hint)])


def print_diagnostics(console: Console, e: GraphError) -> None:
    from .json_output import note

    errors = e.errors or e.diagnostics
    more = f" (and {plural(len(errors) - 1, 'more error')})" if len(errors) > 1 else ""
    note(message=f"{errors[0]}{more}" if errors else str(e))
    note(diagnostics=[diagnostic_json(d) for d in e.diagnostics])
    for d in e.diagnostics:
        style = "red" if d.severity is Severity.error else "yellow"
        console.print(str(d), style=style, markup=False, highlight=False, soft_wrap=True)
    console.print(plural(len(e.errors), "error"), style="bold red")


def load(path: str, console: Console, *, import_kinds: bool = True) -> Graph | None:
    try:
        graph = Graph.from_file(path, import_kinds=import_kinds)
    except GraphError as e:
        print_diagnostics(console, _with_examples_hint(e, path))
        return None
    for w in graph.warnings:
        console.print(str(w), style="yellow", markup=False, highlight=False, soft_wrap=True)
    return graph


_CONTROL = {c: f"\\x{c:02x}" for c in (*range(0x00, 0x20), 0x7F, *range(0x80, 0xA0)) if c != 0x0A}


def printable(text: str) -> str:
    """``text`` from data (a recording's topic names, metadata, a file name) made safe to
    print: control characters (terminal escape sequences among them) shown as ``\\xNN``.

    Print it with ``markup=False`` too, so ``[/bold]`` in a name is text, not rich markup.
    """
    return text.translate(_CONTROL)


def stdout_console() -> Console:
    """A terminal's own width, or a wide console when the output goes to a file or pipe."""
    if sys.stdout.isatty():
        return Console()
    columns = os.environ.get("COLUMNS", "")  # what a script piping the output asks for
    return Console(width=int(columns) if columns.isdigit() and int(columns) >= 40 else 200)


def plain_handler() -> logging.Handler:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    return handler


def setup_logging(handler: logging.Handler) -> None:
    logging.basicConfig(level=logging.INFO, handlers=[handler], force=True)


def seconds_arg(text: str) -> float:
    """A command-line duration: ``60``, ``90s``, ``2m``, ``500ms`` (:func:`parse_seconds`);
    0 or more (``--start``)."""
    from ..graph.spec import parse_seconds

    try:
        s = parse_seconds(text.removeprefix("-"))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if text.startswith("-") and s:
        raise argparse.ArgumentTypeError("must be 0 or more")
    return s


def positive_seconds_arg(text: str) -> float:
    """A length of time that must be more than 0 (``--duration``)."""
    s = seconds_arg(text.removeprefix("-"))
    if s <= 0 or text.startswith("-"):
        raise argparse.ArgumentTypeError("must be more than 0")
    return s


def positive_float_arg(text: str) -> float:
    """A rate or period that must be more than 0 (``--refresh``, ``--rate``)."""
    import math

    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise argparse.ArgumentTypeError("must be more than 0")
    return x


def output_file_arg(text: str) -> str:
    """A file written when the command ends (``--stats-json``): refused before the run when
    it cannot be written, not after it with a traceback and the statistics lost."""
    from pathlib import Path

    if text == "-":  # the final statistics on stdout are --json's document
        raise argparse.ArgumentTypeError("- is not a file: --json prints the statistics on stdout")
    p = Path(text).expanduser()
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text or '.'} is a folder")
    if not p.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no folder {p.parent}")
    if not os.access(p if p.exists() else p.parent, os.W_OK):  # (/dev/stdout: /dev is not)
        raise argparse.ArgumentTypeError(f"{text}: not writable")
    if not p.exists():  # made and removed now: a folder that takes no file (/proc) said so
        try:  # after the whole run, its statistics lost
            with open(p, "x"):
                pass
            p.unlink()
        except OSError as e:
            why = e.strerror or e
            raise argparse.ArgumentTypeError(f"{text}: cannot be written ({why})") from None
    return str(p)


def port_arg(text: str) -> int:
    """A TCP port (0: any free one), refused as the option is parsed: ``--foxglove 99999``
    was a traceback from the socket's bind."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port out of range: {port} (0-65535)")
    return port


def safe_node_names(names: Iterable[str]) -> dict[str, str]:
    """Node names for the sources a recording names (data, not code): identifier-like and
    distinct. ``/a/b`` and ``/a_b`` were one node, and one of the streams was not replayed."""
    out: dict[str, str] = {}
    for name in names:
        clean = re.sub(r"[^A-Za-z0-9_]", "_", name)[:64] or "stream"
        clean = clean if not clean[0].isdigit() else f"n{clean}"
        unique, n = clean, 1
        while unique in out.values():
            n += 1
            unique = f"{clean}_{n}"
        out[name] = unique
    return out
