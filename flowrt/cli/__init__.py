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

GROUPS = ("run", "inspect", "kinds", "examples", "ctl", "can", "check", "record", "sync")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from .parser import Parser

    p = Parser(prog="flowrt", description="real-time dataflow runtime for robot perception")
    p.add_argument("--version", action="version", version=f"flowrt {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        importlib.import_module(f"{__name__}.{group}").add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    """Exit codes: see :mod:`flowrt.cli.common`; ``--json``: see :mod:`flowrt.cli.json_output`.

    A reader that closes the pipe early (``| head -c 50``) ends the command quietly, exit 1:
    what it read is all it wanted, and a traceback would be noise on the terminal."""
    try:
        return _documented(argv)
    except BrokenPipeError:
        _quiet_stdout()
        return 1


def _quiet_stdout() -> None:
    """Standard output pointed at /dev/null: the interpreter's last flush cannot fail again."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)


def _documented(argv: list[str] | None) -> int:
    import sys

    given = list(sys.argv[1:] if argv is None else argv)
    words = given[: given.index("--")] if "--" in given else given
    if "--json" not in words:
        return _main(given)
    from .json_output import finish, json_mode

    command = next((w for w in words if not w.startswith("-")), "")
    bug: BaseException | None = None
    with json_mode(command) as out:
        try:
            code = _main(given)
        except SystemExit as e:  # argparse, --help, a refused option
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        except BaseException as e:  # a bug: the document says so, the traceback follows
            print(f"flowrt {command}: {type(e).__name__}: {e}", file=sys.stderr)
            code, bug = 1, e
    finish(out, code)
    if bug is not None:
        raise bug
    return code


def _name_command(args: argparse.Namespace) -> None:
    """``ctl modes``, ``can stats``: the name an ``--json`` error document gives."""
    from . import json_output

    words = [args.command]
    sub = getattr(args, f"{args.command}_command", None)
    if isinstance(sub, str):
        words.append(sub)
    json_output.name_command(" ".join(words))


def _main(argv: list[str]) -> int:
    import signal

    from .. import _startup

    try:
        _startup.imports_done()  # from here a signal is a KeyboardInterrupt, caught below
        _startup.phase = "reading the arguments"
        args = build_parser().parse_args(argv)
        _name_command(args)
        _startup.phase = f"starting {args.command}"  # "SIGINT while starting run"
        return int(args.func(args))
    except KeyboardInterrupt as e:  # one line naming the phase, exit 128 + N (130: Ctrl-C)
        return _startup.say_interrupted(getattr(e, "signum", signal.SIGINT))
    except Exception as e:  # an Interrupted that a library wrapped is still the signal
        signum = _startup.interrupted_by(e)
        if signum is None:
            raise
        return _startup.say_interrupted(signum)
