"""The ``flowrt`` command: run, validate and inspect graphs.

Exit codes: 0 success, 2 a bad graph file or bad arguments, 1 a runtime failure.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from .diagnostics import GraphError, Severity
from .graph import Graph

EXIT_BAD_GRAPH = 2


def _print_diagnostics(console: Console, e: GraphError) -> None:
    for d in e.diagnostics:
        style = "red" if d.severity is Severity.error else "yellow"
        console.print(str(d), style=style, markup=False, highlight=False, soft_wrap=True)
    n = len(e.errors)
    console.print(f"{n} error{'s' if n != 1 else ''}", style="bold red")


def _load(path: str, console: Console) -> Graph | None:
    try:
        graph = Graph.from_file(path)
    except GraphError as e:
        _print_diagnostics(console, e)
        return None
    for w in graph.warnings:
        console.print(str(w), style="yellow", markup=False, highlight=False, soft_wrap=True)
    return graph


def cmd_validate(args: argparse.Namespace) -> int:
    err = Console(stderr=True)
    graph = _load(args.file, err)
    if graph is None:
        return EXIT_BAD_GRAPH
    Console().print(f"{args.file}: ok ({len(graph.nodes)} nodes, {len(graph.edges)} edges)")
    return 0


def cmd_graph(args: argparse.Namespace) -> int:
    from .analysis import activation_tables

    console = Console() if sys.stdout.isatty() else Console(width=200)
    graph = _load(args.file, Console(stderr=True))
    if graph is None:
        return EXIT_BAD_GRAPH
    topo = Table(title=f"graph {graph.spec.name}: nodes", title_justify="left")
    for col in ("node", "kind", "trigger", "prio", "deadline", "placement", "inputs"):
        topo.add_column(col)
    for name, n in graph.nodes.items():
        ins = ", ".join(
            f"{e.dst_port} <- {e.src}.{e.src_port} \\[{e.policy.value}]"
            for e in graph.edges
            if e.dst == name
        )
        dl = f"{n.spec.deadline:g} ms {n.spec.miss_policy.value}" if n.spec.deadline else "-"
        topo.add_row(
            name,
            n.spec.kind,
            _trigger_text(n.trigger),
            str(n.spec.priority),
            dl,
            n.spec.placement.value,
            ins,
        )
    console.print(topo)
    for tab in activation_tables(graph):
        t = Table(
            title=f"activations over one hyperperiod of {tab.clock} "
            f"({tab.ticks} ticks of {tab.unit})",
            title_justify="left",
        )
        t.add_column("node")
        t.add_column("prio", justify="right")
        for k in range(tab.ticks):
            t.add_column(str(k), justify="center")
        for name, prio, active in tab.rows:
            t.add_row(name, str(prio), *["X" if a else "." for a in active])
        t.add_row("load", "", *[str(x) for x in tab.load()], style="bold")
        console.print(t)
    return 0


def _trigger_text(trig: Any) -> str:
    from .spec import FrameTrigger, InputTrigger, TimerTrigger

    if isinstance(trig, FrameTrigger):
        return f"frame {trig.frame} every {trig.period} phase {trig.phase}"
    if isinstance(trig, TimerTrigger):
        return f"timer {trig.timer:g} ms phase {trig.phase:g} ms"
    if isinstance(trig, InputTrigger):
        return f"input {trig.input}"
    return "loop"


def cmd_schema(args: argparse.Namespace) -> int:
    from pydantic import BaseModel

    from .spec import GraphSpec
    from .stats import RuntimeStats

    model: type[BaseModel] = GraphSpec if args.what == "graph" else RuntimeStats
    print(json.dumps(model.model_json_schema(by_alias=True), indent=2))
    return 0


def new_event_loop() -> asyncio.AbstractEventLoop:
    """uvloop when installed: lower per-callback overhead than the default loop."""
    try:
        import uvloop

        return uvloop.new_event_loop()
    except ImportError:
        return asyncio.new_event_loop()


def cmd_run(args: argparse.Namespace) -> int:
    from .runtime import Runtime
    from .status import LiveTable, LogLines, render

    console = Console() if sys.stdout.isatty() else Console(width=200)
    err = Console(stderr=True)
    graph = _load(args.file, err)
    if graph is None:
        return EXIT_BAD_GRAPH
    monitor: LogLines | LiveTable
    if args.no_ui:
        monitor = LogLines(args.log_every)
        _setup_logging(_plain_handler())
    else:
        monitor = LiveTable(console, hz=args.refresh)
        _setup_logging(monitor.log_handler())
    monitors: list[Any] = [monitor]
    control = _control_config(args, err)
    rt = Runtime(
        graph, monitors=monitors, realtime=args.realtime, control=control, spin=args.spin / 1000
    )

    async def main() -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, rt.request_stop)
        try:
            async with rt:
                if rt.control is not None:
                    logging.getLogger("flowrt").info("control endpoint %s", rt.control.url)
                await rt.run(args.duration)
        finally:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)

    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        try:
            runner.run(main())
        except OSError as e:
            if rt.control_config is None or rt.control is not None:
                raise
            err.print(f"flowrt run: control endpoint: {e}", markup=False)  # e.g. port taken
            return 1
    stats = rt.stats()
    console.print(render(stats, list(rt.events)[-5:], rt.qos_status()))
    if args.stats_json:
        Path(args.stats_json).write_text(stats.model_dump_json(indent=2))
        console.print(f"statistics written to {args.stats_json}")
    return 0


def _control_config(args: argparse.Namespace, err: Console) -> Any:
    """``--control [HOST:]PORT``: a token is generated (and printed) off loopback if none given."""
    if args.control is None:
        return None
    import os
    import secrets

    from .control import ControlConfig

    try:
        config = ControlConfig.parse(args.control, args.token or os.environ.get("FLOWRT_TOKEN"))
    except ValueError as e:
        err.print(f"flowrt run: {e}", markup=False)
        raise SystemExit(2) from None
    if config.needs_token and not config.token:
        config = ControlConfig(config.host, config.port, secrets.token_urlsafe(24))
        err.print(f"control token (give it to flowrt ctl --token): {config.token}", markup=False)
    return config


def _plain_handler() -> logging.Handler:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    return handler


def _setup_logging(handler: logging.Handler) -> None:
    logging.basicConfig(level=logging.INFO, handlers=[handler], force=True)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="flowrt", description="real-time dataflow runtime for robot perception"
    )
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a graph with a live status table")
    run.add_argument("file")
    run.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    run.add_argument(
        "--no-ui", action="store_true", help="periodic log lines instead of the live table"
    )
    run.add_argument(
        "--stats-json", metavar="PATH", help="write final statistics (flowrt schema stats)"
    )
    run.add_argument(
        "--realtime", action="store_true", help="SCHED_FIFO for the loop process where permitted"
    )
    run.add_argument(
        "--spin",
        type=_spin_ms,
        default=0.0,
        metavar="DURATION",
        help="the loop busy-waits this long before each timer release (e.g. 300us; default 0)",
    )
    run.add_argument("--refresh", type=float, default=4.0, metavar="HZ", help="table refresh rate")
    run.add_argument(
        "--log-every", type=float, default=2.0, metavar="S", help="--no-ui summary period"
    )
    run.add_argument(
        "--control",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="[HOST:]PORT",
        help="serve the control endpoint (default 127.0.0.1:8765); see flowrt ctl",
    )
    run.add_argument("--token", help="bearer token of the control endpoint (default $FLOWRT_TOKEN)")
    run.set_defaults(func=cmd_run)
    val = sub.add_parser("validate", help="check a graph file; exit 2 listing every error")
    val.add_argument("file")
    val.set_defaults(func=cmd_validate)
    gr = sub.add_parser("graph", help="print the topology and one hyperperiod of activations")
    gr.add_argument("file")
    gr.set_defaults(func=cmd_graph)
    sc = sub.add_parser("schema", help="print the JSON schema of graph files or statistics")
    sc.add_argument("what", choices=["graph", "stats"])
    sc.set_defaults(func=cmd_schema)
    from .control import add_ctl_parser

    add_ctl_parser(sub)
    return p


def _spin_ms(text: str) -> float:
    from .spec import parse_duration_ms

    try:
        ms = parse_duration_ms(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if not 0 <= ms <= 10:
        raise argparse.ArgumentTypeError(f"must be between 0 and 10 ms, got {ms:g} ms")
    return ms


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
