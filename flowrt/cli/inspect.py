"""``flowrt validate``, ``graph`` and ``schema``: look at a graph without running it."""

from __future__ import annotations

import argparse
import json
from typing import Any

from rich.console import Console
from rich.table import Table

from .common import EXIT_BAD_GRAPH, load, stdout_console


def cmd_validate(args: argparse.Namespace) -> int:
    err = Console(stderr=True)
    graph = load(args.file, err, import_kinds=not args.no_import)
    if graph is None:
        return EXIT_BAD_GRAPH
    out = Console(soft_wrap=True, highlight=False)
    out.print(f"{args.file}: ok ({len(graph.nodes)} nodes, {len(graph.edges)} edges)", markup=False)
    if graph.not_imported:
        listed = ", ".join(f"{n} ({k})" for n, k in graph.not_imported.items())
        out.print(
            f"not imported (--no-import): {listed}; their params, ports and triggers "
            "are not checked",
            markup=False,
        )
    return 0


def cmd_graph(args: argparse.Namespace) -> int:
    from ..analysis import activation_tables

    console = stdout_console()
    graph = load(args.file, Console(stderr=True))
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
    from ..spec import FrameTrigger, InputTrigger, TimerTrigger

    if isinstance(trig, FrameTrigger):
        return f"frame {trig.frame} every {trig.period} phase {trig.phase}"
    if isinstance(trig, TimerTrigger):
        return f"timer {trig.timer:g} ms phase {trig.phase:g} ms"
    if isinstance(trig, InputTrigger):
        return f"input {trig.input}"
    return "loop"


def cmd_schema(args: argparse.Namespace) -> int:
    from pydantic import BaseModel

    from ..spec import GraphSpec
    from ..stats import RuntimeStats

    model: type[BaseModel] = GraphSpec if args.what == "graph" else RuntimeStats
    print(json.dumps(model.model_json_schema(by_alias=True), indent=2))
    return 0


def add_parsers(sub: Any) -> None:
    val = sub.add_parser("validate", help="check a graph file; exit 2 listing every error")
    val.add_argument("file")
    val.add_argument(
        "--no-import",
        action="store_true",
        help="do not import dotted-path kinds (package.module:Class): checking a graph file "
        "from someone else runs none of its code",
    )
    val.set_defaults(func=cmd_validate)
    gr = sub.add_parser("graph", help="print the topology and one hyperperiod of activations")
    gr.add_argument("file")
    gr.set_defaults(func=cmd_graph)
    sc = sub.add_parser("schema", help="print the JSON schema of graph files or statistics")
    sc.add_argument("what", choices=["graph", "stats"])
    sc.set_defaults(func=cmd_schema)
