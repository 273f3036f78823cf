"""``flowrt replay SESSION --graph G --deterministic [--check] [--json] [--inline]``.

Re-executes the recorded activations of ``G``'s processing nodes on recorded time
(:mod:`flowrt.determinism`): no clock, no sleeping, no live view, nothing real-time. Exit 0
when every compared output has its recorded digest; with ``--check``, exit 1 at the first that
does not, saying node, port, sequence number and time (and both values when the recording has
the value), or when the log was cut (what it lost was never compared). A session that is not
a deterministic recording, a bad graph: one line, exit 2.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path
from typing import Any

from rich.console import Console

from .common import EXIT_BAD_GRAPH, EXIT_FAILED, EXIT_OK, load, printable, stdout_console
from .json_output import emit
from .signals import StopSignals

__all__ = ["cmd_replay_deterministic"]


def _refused_options(args: argparse.Namespace) -> str | None:
    """Options of the timed replay that mean nothing on recorded time."""
    if args.rate != 1.0:
        return "--rate"
    if args.loop:
        return "--loop"
    if args.start:
        return "--start"
    if args.topics:
        return "--topics"
    if args.duration is not None:
        return "--duration"
    return None


def _graph(args: argparse.Namespace, log: Any, err: Console) -> Any:
    """The recorded graph with --trust-graph, else None after one line on ``err``."""
    from ..graph._resolve import Graph

    if not args.trust_graph:
        err.print(
            "flowrt replay: --deterministic needs --graph FILE (or --trust-graph to run the "
            "graph stored in the recording)",
            markup=False,
        )
        return None
    if not log.graph:
        err.print(f"flowrt replay: {args.path}: --trust-graph: no graph is recorded", markup=False)
        return None
    try:
        return Graph.from_text(log.graph, f"{args.path} (recorded graph)")
    except Exception as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        err.print(
            f"flowrt replay: the recorded graph is not valid: {printable(first)}", markup=False
        )
        return None


def cmd_replay_deterministic(args: argparse.Namespace) -> int:
    from ..determinism.log import LogError, read_log
    from ..determinism.report import report_lines, verdict_line

    err = Console(stderr=True, highlight=False, soft_wrap=True)
    bad = _refused_options(args)
    if bad is not None:
        err.print(f"flowrt replay: {bad} has no meaning with --deterministic", markup=False)
        return EXIT_BAD_GRAPH
    began = time.perf_counter()  # wall_s counts reading the log and the graph, as the API's
    log: Any = None
    if args.graph:  # its errors first; the log is read while the workers' forkserver starts
        graph = load(args.graph, err)
    else:
        try:
            log = read_log(args.path)
        except LogError as e:
            err.print(f"flowrt replay: {printable(str(e))}", markup=False)
            return EXIT_BAD_GRAPH
        graph = _graph(args, log, err)
    if graph is None:
        return EXIT_BAD_GRAPH

    report = _re_execute(args, graph, log, began, err)
    if isinstance(report, int):
        return report
    if args.json:
        emit(report.summary())
        if not report.identical and args.check:  # the verdict's line: the document's "error"
            err.print(f"flowrt replay: {printable(verdict_line(report))}", markup=False)
    else:
        console = stdout_console()
        for line in report_lines(report):
            console.print(printable(line), markup=False, highlight=False, soft_wrap=True)
    if not report.identical and args.check:
        return EXIT_FAILED  # a divergence; a cut log, or nothing compared, proves nothing
    return EXIT_OK


def _re_execute(args: argparse.Namespace, graph: Any, log: Any, began: float, err: Console) -> Any:
    """The replay's report, or an exit code when it gave none (a signal, a failed start).

    A signal: the start or the re-execution cancelled and undone (workers stopped), one line,
    128 + N, no verdict. Without these handlers the start-up's raised its KeyboardInterrupt
    inside a worker's socket callback: a traceback, the worker taken for crashed, a
    divergence that was not one (exit 1), once a hang."""
    from ..determinism.api import Replay
    from ..determinism.log import LogError
    from ..system._eventloop import run

    phase = ["the start"]
    main_task: list[asyncio.Task[Any]] = []

    def interrupt() -> str:
        for t in main_task:
            t.cancel()
        return phase[0]

    signals = StopSignals(lambda: phase[0], interrupt, "flowrt replay")
    signals.install()

    async def main() -> Any:
        signals.loop = asyncio.get_running_loop()
        signals.ran = True
        if signals.before_start is not None:
            raise asyncio.CancelledError  # a signal while loading: nothing starts
        task = asyncio.current_task()
        assert task is not None
        main_task.append(task)
        rp = Replay(Path(args.path), graph, inline=args.inline, stop_at_divergence=args.check)
        rp.preloaded, rp.began = log, began
        try:
            await rp.start()
            phase[0] = "the re-execution"
            if rp.engine is not None and not rp.engine.log.closed_cleanly:
                err.print(
                    f"flowrt replay: {args.path} was not closed cleanly "
                    f"({rp.engine.log.damage}): replaying what was recorded before the damage",
                    markup=False,
                )
            return await rp.run()
        finally:
            phase[0] = "teardown"
            await rp.stop()
            signals.loop = None

    try:
        return run(main())
    except asyncio.CancelledError:
        if signals.exit_code is None:
            raise
        return signals.exit_code
    except LogError as e:
        err.print(f"flowrt replay: {printable(str(e))}", markup=False)
        return EXIT_BAD_GRAPH
    except Exception as e:  # a node whose setup fails, a worker that cannot start: one line
        summary = getattr(e, "summary", None) or f"{type(e).__name__}: {e}"
        err.print(f"flowrt replay: {printable(str(summary))}", markup=False)
        return EXIT_FAILED
