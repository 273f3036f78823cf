"""``flowrt check``: will the timing hold? Load per tick, response times, phase advice.

Works on a graph file (budgets from ``wcet:``, a previous run's ``--stats-json``, or a short
measuring run) or on a task-set file (``tasks:``). Exit 0 when every node/task is shown to
meet its deadline, 1 when not (or when a node has no budget, so nothing can be shown), 2 for
a bad file or bad arguments. The analyses are in :mod:`flowrt.analysis`.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from typing import Any

from rich.console import Console
from rich.table import Table

from ..graph.diagnostics import GraphError
from .common import (
    EXIT_BAD_GRAPH,
    EXIT_FAILED,
    EXIT_OK,
    _with_examples_hint,
    load,
    print_diagnostics,
    stdout_console,
)
from .json_output import emit
from .run import add_run_options


def _ms(x: float | None) -> str:
    if x is None:
        return "-"
    return "inf" if not math.isfinite(x) else f"{x:.3f}".rstrip("0").rstrip(".")


def _json_ms(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def cmd_check(args: argparse.Namespace) -> int:
    from ..analysis.taskset import is_task_set
    from ..graph._loading import parse_yaml, read_graph_file

    err = Console(stderr=True, soft_wrap=True)
    given = _run_option_given(args)
    if given and args.measure is None:
        err.print(
            f"flowrt check: {given} is an option of the measuring run (give --measure DURATION)",
            markup=False,
            soft_wrap=True,
        )
        return EXIT_BAD_GRAPH
    try:
        text = read_graph_file(args.file)
    except GraphError as e:  # a missing shipped example: the hint run and validate give
        print_diagnostics(err, _with_examples_hint(e, args.file))
        return EXIT_BAD_GRAPH
    data, _, _ = parse_yaml(text, args.file)
    if is_task_set(data):
        return _check_tasks(args, text, err)
    return _check_graph(args, err)


# --- task-set files ----------------------------------------------------------------------------


def _check_tasks(args: argparse.Namespace, text: str, err: Console) -> int:
    from ..analysis.rta import response_times, utilisation
    from ..analysis.taskset import parse_task_set

    if args.wcet_from or args.measure:
        err.print("flowrt check: --wcet-from and --measure apply to graphs, not task sets")
        return EXIT_BAD_GRAPH
    if args.plot:
        err.print(
            "flowrt check: --plot draws a graph's load per frame tick; a task set has no "
            "frame ticks (its response times are in the table)",
            markup=False,
        )
        return EXIT_BAD_GRAPH
    try:
        tasks, preemptive = parse_task_set(text, args.file)
    except GraphError as e:
        print_diagnostics(err, e)
        return EXIT_BAD_GRAPH
    res = response_times(tasks, preemptive=preemptive)
    ok = all(r.schedulable for r in res)
    util = utilisation(tasks)
    if args.json:
        emit(
            {
                "schedulable": ok,
                "utilisation": util,
                "tasks": [
                    {
                        "name": r.task.name,
                        "wcet_ms": r.task.wcet,
                        "period_ms": r.task.period,
                        "deadline_ms": r.task.effective_deadline,
                        "blocking_ms": r.blocking,
                        "response_ms": _json_ms(r.response),
                        "schedulable": r.schedulable,
                    }
                    for r in res
                ],
            },
        )
    else:
        console = stdout_console()
        kind = "preemptive" if preemptive else "non-preemptive"
        console.print(f"{args.file}: {kind} fixed priority, response R = J + w (ms)")
        t = Table()
        for col in ("task", "prio", "C", "T", "D", "J", "B", "R", ""):
            t.add_column(col, justify="left" if col in ("task", "") else "right")
        for r in sorted(res, key=lambda r: -r.task.priority):
            k = r.task
            t.add_row(
                k.name,
                f"{k.priority:g}",
                _ms(k.wcet),
                _ms(k.period),
                _ms(k.effective_deadline),
                _ms(k.jitter),
                _ms(r.blocking),  # the B used: non-preemptive, the longest lower job too
                _ms(r.response),
                "[green]ok[/]" if r.schedulable else "[red]MISS[/]",
            )
        console.print(t)
        misses = [r.task.name for r in res if not r.schedulable]
        console.print(_verdict_line(ok, util, misses, []))
    return EXIT_OK if ok else EXIT_FAILED


def _verdict_line(ok: bool, util: float, misses: list[str], unknown: list[str]) -> str:
    """The last line: the verdict, who may miss, who has no budget; utilisation is summed
    over every resource (so above 100 % is possible on several CPUs)."""
    if ok:
        return f"[green]schedulable[/]: every deadline holds (utilisation {util:.1%})"
    parts = []
    if misses:
        parts.append(f"may miss: {', '.join(misses)}")
    if unknown:
        parts.append(
            f"no budget for {', '.join(unknown)} (declare wcet:, or use --wcet-from / --measure)"
        )
    return f"[red]NOT shown schedulable[/]: {'; '.join(parts)} (utilisation {util:.1%})"


# --- graphs ------------------------------------------------------------------------------------


def _check_graph(args: argparse.Namespace, err: Console) -> int:
    from ..analysis.load import load_tables
    from ..analysis.phases import advise, snippet
    from ..analysis.schedulability import analyse
    from ..analysis.timing import graph_timing, with_mode

    graph = load(args.file, err)
    if graph is None:
        return EXIT_BAD_GRAPH
    cpus = args.cpus or os.cpu_count() or 1
    for name, n in graph.nodes.items():
        if n.spec.cpus and max(n.spec.cpus) >= cpus:
            err.print(
                f"flowrt check: {name} is pinned to CPU {max(n.spec.cpus)}, "
                f"but --cpus says the machine has {cpus}",
                markup=False,
            )
            return EXIT_BAD_GRAPH
    budgets = _budgets(graph, args, err)
    if isinstance(budgets, int):  # an exit code: said why
        return budgets
    timing = graph_timing(graph, budgets)
    mode = args.mode if args.mode is not None else graph.spec.initial_mode
    if mode:
        if mode not in graph.spec.modes:
            from ..graph.diagnostics import did_you_mean

            err.print(
                f"flowrt check: unknown mode {mode!r}" + did_you_mean(mode, graph.spec.modes),
                markup=False,
            )
            return EXIT_BAD_GRAPH
        timing = with_mode(timing, graph, mode)
        if not args.json:
            stdout_console().print(f"timing of mode {mode}", markup=False)
    verdict = analyse(timing, cpus)
    tables = load_tables(timing)
    advice = advise(timing)
    paste = snippet(advice, timing)
    if args.json:
        extra = {"cpus": cpus, "mode": mode}
        emit({**_graph_json(verdict, tables, advice, paste), **extra})
    else:
        _print_graph(args.file, cpus, verdict, tables, advice, paste)
    if args.plot:
        problem = _plot(tables, args.plot)
        if problem:
            err.print(f"flowrt check: {problem}", markup=False)
            return EXIT_BAD_GRAPH
        if not args.json:
            stdout_console().print(f"load per tick plotted to {args.plot}")
    return EXIT_OK if verdict.schedulable else EXIT_FAILED


def _budgets(graph: Any, args: argparse.Namespace, err: Console) -> dict[str, Any] | int:
    """The execution budgets the analysis uses: declared (none here), from a statistics file
    (--wcet-from) or from a measuring run (--measure); an exit code when they cannot be had."""
    budgets: dict[str, Any] = {}
    if args.wcet_from:
        got = _stats_budgets(args, err)
        if got is None:
            return EXIT_BAD_GRAPH
        budgets = got
    elif args.measure is not None:
        if args.plot and _plot_unavailable():  # said before a measuring run, not after it
            err.print(f"flowrt check: --plot: {_plot_unavailable()}", markup=False)
            return EXIT_BAD_GRAPH
        try:
            measured = _measure(graph, args, err)
        except Exception as e:  # a node that cannot start, a port taken: one line, exit 1
            err.print(f"flowrt check: the measuring run failed: {e}", markup=False)
            return EXIT_FAILED
        if measured is None:  # the run said why
            return EXIT_FAILED
        if isinstance(measured, int):  # cut by a signal: its exit code
            return measured
        budgets = measured
    return budgets


def _run_option_given(args: argparse.Namespace) -> str | None:
    """The first run option given on the command line (not left at its default)."""
    import argparse as ap

    parser = ap.ArgumentParser(add_help=False)
    add_run_options(parser, measuring=True)
    for action in parser._actions:
        if getattr(args, action.dest, action.default) != action.default:
            return action.option_strings[0]
    return None


MAX_STATS_BYTES = 64 << 20  # a --stats-json of thousands of nodes is a few MB


def _stats_budgets(args: argparse.Namespace, err: Console) -> dict[str, Any] | None:
    from pydantic import ValidationError

    from ..analysis.budgets import budgets_from_stats
    from ..files import read_bytes
    from ..stats import RuntimeStats

    try:
        stats = RuntimeStats.model_validate_json(read_bytes(args.wcet_from, MAX_STATS_BYTES))
    except OSError as e:
        err.print(f"flowrt check: cannot read {args.wcet_from}: {e.strerror}", markup=False)
        return None
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        err.print(
            f"flowrt check: {args.wcet_from} is not a flowrt --stats-json file "
            f"({where}: {first['msg']})",
            markup=False,
        )
        return None
    return budgets_from_stats(stats.nodes, args.wcet_stat, "stats")


def _plot_unavailable() -> str | None:
    """Why ``--plot`` cannot work here (matplotlib missing), or None."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        return "needs matplotlib (pip install matplotlib, or flowrt[dev])"
    return None


def _measure(graph: Any, args: argparse.Namespace, err: Console) -> dict[str, Any] | int | None:
    """Run the graph for ``--measure`` and take each node's execution-time statistic; None
    when the run failed (said on ``err``); 128 + N when a signal cut it (no verdict).

    The run is :func:`flowrt.cli.run.run_graph` with the run options given to ``check``
    (``--no-display``, ``--display-port``, ``--control``, ``--stats-json`` ...), as ``flowrt
    run`` would run it.
    """
    from ..analysis.budgets import budgets_from_stats
    from .run import run_graph

    err.print(f"measuring: running {graph.spec.name} for {args.measure:g} s ...", markup=False)
    run_args = argparse.Namespace(**vars(args))
    run_args.duration, run_args.check = args.measure, False
    run_args.json = False  # the check's own --json follows
    # the live table (on stderr: stdout is the check's) in a terminal; else log lines
    run_args.no_ui = args.no_ui or args.json or not sys.stderr.isatty()
    ran: list[Any] = []

    def keep(rt: Any) -> int:
        ran.append(rt)
        return EXIT_OK

    # What the graph's nodes print (a display's address) is not the check's output: a script
    # reading --json gets one JSON document on stdout and nothing else.
    with contextlib.redirect_stdout(sys.stderr):
        code = run_graph(graph, run_args, err, prog="flowrt check", after=keep, measuring=True)
    if code > 128:  # interrupted: the run said so
        return code
    if code != EXIT_OK or not ran:  # the run said why, as "flowrt check: ..."
        return None
    stats = ran[0].stats()
    loop = f"loop {stats.loop_scheduling}" if stats.loop_scheduling else stats.realtime
    # the times depend on it: a bound held wakes every node faster
    bound = f"CPU wake-up bound {stats.cpu_latency}" if stats.cpu_latency else ""
    if said := "; ".join(u for u in (loop, bound) if u):
        err.print(f"measured under: {said}", markup=False)
    return budgets_from_stats(stats.nodes, args.wcet_stat, "measured")


def _graph_json(verdict: Any, tables: Any, advice: Any, paste: str) -> dict[str, Any]:
    return {
        "schedulable": verdict.schedulable,
        "utilisation": verdict.utilisation,
        "tasks": [
            {
                "name": v.name,
                "wcet_ms": v.budget.ms if v.budget else None,
                "period_ms": v.period_ms,
                "deadline_ms": v.deadline_ms,
                "blocking_ms": v.blocking_ms,
                "response_ms": _json_ms(v.response_ms),
                "schedulable": v.schedulable is True,
            }
            for v in verdict.nodes
        ],
        "analysis": [
            {
                "name": v.name,
                "resource": v.resource,
                "priority": v.priority,
                "budget_source": v.budget.source if v.budget else None,
                "jitter_ms": _json_ms(v.jitter_ms),
                "blocking_ms": v.blocking_ms,
                "note": v.note,
            }
            for v in verdict.nodes
        ],
        "ticks": [
            {
                "source": t.source,
                "frame_ms": t.frame_ms,
                "heaviest": t.heaviest,
                "truncated": t.truncated,
                "ticks": [
                    {
                        "tick": k.tick,
                        "nodes": k.nodes,
                        "total_ms": k.total_ms,
                        "loop_ms": k.loop_ms,
                        "workers_ms": k.workers_ms,
                        "pool_ms": k.pool_ms,
                        "per_cpu_ms": k.per_cpu_ms,
                        "per_worker_ms": k.per_worker_ms,
                        "unbudgeted": k.unbudgeted,
                    }
                    for k in t.ticks
                ],
            }
            for t in tables
        ],
        "phase_advice": [
            {
                "clock": a.clock,
                "unit": a.unit,
                "measure": a.measure,
                "before": a.before,
                "after": a.after,
                "peak_before": a.peak_before,
                "peak_after": a.peak_after,
            }
            for a in advice
        ],
        "phase_snippet": paste,
    }


def _print_graph(file: str, cpus: int, verdict: Any, tables: Any, advice: Any, paste: str) -> None:
    console = stdout_console()
    console.print(f"{file}: worst-case response times on {cpus} CPUs (from release, ms)")
    console.print(_verdict_table(verdict.nodes, console.width))
    notes: dict[str, list[str]] = {}  # said once per note, not once per node: at 80 columns
    for v in verdict.nodes:  # a note in every row squeezes the names out
        if v.note and not v.note.startswith("no budget"):  # those: in the verdict line
            notes.setdefault(v.note, []).append(v.name)
    for note, names in notes.items():
        if note.startswith("MISS"):  # one line per node: the figures are its own
            console.print(f"  {names[0]}: {note}", markup=False, style="red")
        else:
            console.print(f"  {note}: {', '.join(names)}", markup=False)
    console.print(
        "  block: the longest lower-priority call that cannot be preempted (an inline call "
        "holding the loop) when the node is released; response includes it, and jitter "
        "(release delay) comes on top",
        markup=False,
        style="dim",
    )
    if any(v.resource == "precise thread" for v in verdict.nodes):
        console.print(  # else "where" looks like a resource with nothing else on it
            "  precise thread: timing: precise, called in its own release thread; the loop "
            "neither delays nor blocks it, its calls count against the loop and the workers",
            markup=False,
            style="dim",
        )
    for tab in tables:
        cpu_cols = sorted({c for k in tab.ticks for c in k.per_cpu_ms})
        frame = f"{tab.frame_ms:g} ms" if tab.frame_ms else "unknown interval"
        console.print(
            f"load per tick of {tab.source} (frame {frame}; summed budgets, ms)"
            + (" - first ticks only" if tab.truncated else "")
        )
        lt = Table(box=None, header_style="bold", pad_edge=False)
        for col in ("tick", "nodes", "loop", "workers", "pool", *cpu_cols, "total", "of frame"):
            lt.add_column(
                col, justify="left" if col == "nodes" else "right", overflow="fold", no_wrap=False
            )
        heavy = tab.heaviest
        for k in tab.ticks:
            share = f"{k.total_ms / tab.frame_ms:.0%}" if tab.frame_ms else "-"
            listed = ", ".join(n + ("?" if n in k.unbudgeted else "") for n in k.nodes)
            lt.add_row(
                str(k.tick),
                listed,
                _ms(k.loop_ms),
                _ms(k.workers_ms),
                _ms(k.pool_ms),
                *[_ms(k.per_cpu_ms.get(c, 0.0)) for c in cpu_cols],
                _ms(k.total_ms),
                share,
                style="bold red" if k.tick == heavy else None,
            )
        console.print(lt)
    for a in advice:
        unit = "ms" if a.measure == "ms" else " nodes"
        what = f"{a.clock} ({'frames' if a.unit == 'frame' else 'ms'})"
        if a.changed:
            console.print(
                f"phase advice for {what}: heaviest tick {a.peak_before:.4g}{unit} -> "
                f"{a.peak_after:.4g}{unit}; "
                + ", ".join(f"{n} {a.before[n]:g} -> {p:g}" for n, p in a.changed.items()),
                markup=False,
            )
        else:
            console.print(
                f"phase advice for {what}: the current phases are already best "
                f"(heaviest tick {a.peak_before:.4g}{unit})",
                markup=False,
            )
    if paste:
        console.print("paste into the graph file (replaces these nodes' triggers):")
        console.print(paste, markup=False, highlight=False)
    misses = [v.name for v in verdict.nodes if v.schedulable is False]
    unknown = [v.name for v in verdict.nodes if v.schedulable is None]
    console.print(_verdict_line(verdict.schedulable, verdict.utilisation, misses, unknown))


def _verdict_table(nodes: Any, width: int) -> Any:
    """One row per node; at a narrow width the less telling columns go first."""
    from rich.text import Text

    from ..monitors._columns import Column, fit_table

    def mark(v: Any) -> Text:
        if v.schedulable is None:
            return Text("?", style="yellow")
        return Text("ok", style="green") if v.schedulable else Text("MISS", style="red")

    cols: tuple[Column[Any], ...] = (
        Column("node", lambda v: v.name, right=False),
        Column("where", lambda v: v.resource, drop=4, right=False),
        Column("prio", lambda v: str(v.priority), drop=5),
        Column("budget", lambda v: _ms(v.budget.ms) if v.budget else "-"),
        Column("from", lambda v: v.budget.source if v.budget else "-", drop=1, right=False),
        Column("period", lambda v: _ms(v.period_ms), drop=6),
        Column("deadline", lambda v: _ms(v.deadline_ms) + ("" if v.has_deadline else " (T)")),
        Column("jitter", lambda v: _ms(v.jitter_ms), drop=2),
        Column("block", lambda v: _ms(v.blocking_ms), drop=3),
        Column("response", lambda v: _ms(v.response_ms)),
        Column("", mark, right=False),
    )
    return fit_table(cols, nodes, width)


def _plot(tables: Any, path: str) -> str | None:
    """A PNG of the load per tick, one panel per frame source; an error text or None."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "--plot needs matplotlib (pip install matplotlib, or flowrt[dev])"
    if not tables:
        return "--plot: the graph has no frame-triggered nodes, so no per-tick load"
    fig, axes = plt.subplots(len(tables), 1, figsize=(9, 2.6 * len(tables)), squeeze=False)
    for ax, tab in zip(axes[:, 0], tables, strict=True):
        xs = [k.tick for k in tab.ticks]
        bottom = [0.0] * len(xs)
        for label, attr, colour in (
            ("loop", "loop_ms", "#4c72b0"),
            ("workers", "workers_ms", "#55a868"),
            ("pool", "pool_ms", "#8172b2"),
        ):
            ys = [getattr(k, attr) for k in tab.ticks]
            if any(ys):
                ax.bar(xs, ys, bottom=bottom, label=label, color=colour)
                bottom = [b + y for b, y in zip(bottom, ys, strict=True)]
        heavy = tab.heaviest
        ax.bar(
            [heavy],
            [bottom[heavy]],
            fill=False,
            edgecolor="red",
            linewidth=2,
            label="heaviest tick",
        )
        if tab.frame_ms:
            ax.axhline(tab.frame_ms, color="grey", linestyle="--", label="frame interval")
        ax.set_xlim(-0.6, len(xs) - 0.4)
        if len(xs) <= 32:
            ax.set_xticks(xs)
        ax.set_ylim(0, 1.4 * max(tab.frame_ms or 0.0, max(bottom, default=0.0), 1e-3))
        ax.set_title(f"{tab.source}: summed budget per tick")
        ax.set_xlabel("tick (frame)")
        ax.set_ylabel("ms")
        ax.legend(fontsize="small", loc="upper right")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=100)
    except OSError as e:
        return f"cannot write {path}: {e.strerror}"
    finally:
        plt.close(fig)
    return None


def _duration_s(text: str) -> float:
    from ..graph.spec import parse_duration_ms

    if text.startswith("-"):
        raise argparse.ArgumentTypeError("must be more than 0")
    try:
        ms = parse_duration_ms(text if any(c.isalpha() for c in text) else f"{text}s")
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if not 0 < ms <= 3_600_000:
        raise argparse.ArgumentTypeError("must be more than 0 and at most 1 h")
    return ms / 1000


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError("must be at least 1")
    return n


def add_parsers(sub: Any) -> None:
    ck = sub.add_parser(
        "check",
        help="schedulability: load per tick, worst-case response times, phase advice",
    )
    ck.add_argument("file", help="a graph file, or a task-set file (tasks: [...])")
    src = ck.add_mutually_exclusive_group()
    src.add_argument("--wcet-from", metavar="STATS.json", help="budgets from a run's --stats-json")
    src.add_argument(
        "--measure",
        type=_duration_s,
        metavar="DURATION",
        help="budgets from a measuring run of this long first (e.g. 20s)",
    )
    ck.add_argument(
        "--wcet-stat",
        choices=["p99", "max"],
        default="p99",
        help="which execution-time statistic is the budget (default p99)",
    )
    ck.add_argument(
        "--cpus",
        type=_positive_int,
        metavar="N",
        help="CPUs of the target machine (default: this one's)",
    )
    ck.add_argument(
        "--mode", metavar="NAME", help="analyse the timing of this mode (default: initial_mode)"
    )
    ck.add_argument("--json", action="store_true", help="machine-readable result")
    ck.add_argument("--plot", metavar="PNG", help="plot the load per tick (needs matplotlib)")
    add_run_options(ck, measuring=True)  # for the measuring run: see _measure
    ck.set_defaults(func=cmd_check)
