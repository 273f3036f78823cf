"""``flowrt validate``, ``graph`` and ``schema``: look at a graph without running it."""

from __future__ import annotations

import argparse
import json
from typing import Any

from rich.console import Console
from rich.table import Table

from .common import EXIT_BAD_GRAPH, diagnostic_json, load, plural, stdout_console
from .json_output import emit


def cmd_validate(args: argparse.Namespace) -> int:
    err = Console(stderr=True, soft_wrap=True)
    graph = load(args.file, err, import_kinds=not args.no_import)
    if graph is None:
        return EXIT_BAD_GRAPH
    # every node and edge of the file, those of kinds not imported too (it said "1 node,
    # 0 edges" of three nodes and two edges under --no-import)
    nodes = len(graph.spec.nodes)
    declared = sum(len(ns.inputs) for ns in graph.spec.nodes.values())
    edges = declared if graph.not_imported else len(graph.edges)
    if args.json:
        emit(
            {
                "file": args.file,
                "ok": True,
                "nodes": nodes,
                "edges": edges,
                "warnings": [diagnostic_json(w) for w in graph.warnings],
                "not_imported": graph.not_imported,
            }
        )
        return 0
    out = Console(soft_wrap=True, highlight=False)
    counts = f"{plural(nodes, 'node')}, {plural(edges, 'edge')}"
    out.print(f"{args.file}: ok ({counts})", markup=False)
    if graph.not_imported:
        listed = ", ".join(f"{n} ({k})" for n, k in graph.not_imported.items())
        out.print(
            f"not imported (--no-import): {listed}; their params, ports and triggers "
            "are not checked",
            markup=False,
        )
    return 0


def cmd_graph(args: argparse.Namespace) -> int:
    """The nodes (one line each), the edges (one line each), then which node runs on which
    tick of one hyperperiod: compact, so that it reads at 80 columns and pipes well."""
    from ..analysis import activation_tables

    console = stdout_console()
    graph = load(args.file, Console(stderr=True, soft_wrap=True))
    if graph is None:
        return EXIT_BAD_GRAPH
    if args.json:
        emit(_graph_json(graph))
        return 0
    topo = Table(
        title=f"graph {graph.spec.name}: {len(graph.nodes)} nodes",
        title_justify="left",
        box=None,
        header_style="bold",
        pad_edge=False,
    )
    for col, right in (
        ("node", False),
        ("kind", False),
        ("trigger", False),
        ("prio", True),
        ("deadline", True),
        ("placement", False),
    ):
        topo.add_column(col, justify="right" if right else "left", overflow="fold")
    for name, n in graph.nodes.items():
        dl = f"{_ms(n.spec.deadline)}ms" if n.spec.deadline else "-"
        if n.spec.deadline and n.spec.miss_policy.value != "continue":
            dl += f" {n.spec.miss_policy.value}"
        topo.add_row(
            name,
            _kind(graph, name),
            _trigger_text(n.trigger),
            str(n.spec.priority),
            dl,
            n.spec.placement.value,
        )
    console.print(topo)
    if graph.edges:
        console.print()
        edges = Table(
            title=f"edges: {len(graph.edges)}",
            title_justify="left",
            box=None,
            header_style="bold",
            pad_edge=False,
        )
        edges.add_column("from", overflow="fold")
        edges.add_column("to", overflow="fold")
        edges.add_column("policy")
        for e in graph.edges:
            edges.add_row(f"{e.src}.{e.src_port}", f"{e.dst}.{e.dst_port}", e.policy.value)
        console.print(edges)
    for tab in activation_tables(graph):
        _print_ticks(console, tab)
    return 0


def _kind(graph: Any, name: str) -> str:
    """A node's kind as the file says it: an ``import:`` entry is ``import KEY`` (it showed
    the class that implements it, ``flowrt.remote._bridge:RemoteSource``)."""
    imported = graph.spec.imports.get(name)
    return f"import {imported.key}" if imported is not None else str(graph.nodes[name].spec.kind)


def _graph_json(graph: Any) -> dict[str, Any]:
    """``flowrt graph --json``: what the tables show, as data."""
    from ..analysis import activation_tables

    return {
        "name": graph.spec.name,
        "nodes": [
            {
                "name": name,
                "kind": _kind(graph, name),
                "trigger": _trigger_text(n.trigger),
                "priority": n.spec.priority,
                "deadline_ms": n.spec.deadline,
                "miss_policy": n.spec.miss_policy.value,
                "placement": n.spec.placement.value,
            }
            for name, n in graph.nodes.items()
        ],
        "edges": [
            {
                "from": f"{e.src}.{e.src_port}",
                "to": f"{e.dst}.{e.dst_port}",
                "policy": e.policy.value,
            }
            for e in graph.edges
        ],
        "activations": [
            {
                "clock": tab.clock,
                "unit": tab.unit,
                "ticks": tab.ticks,
                "nodes": {
                    name: [i for i, a in enumerate(active) if a] for name, _, active in tab.rows
                },
                "load": list(tab.load()),
            }
            for tab in activation_tables(graph)
        ],
    }


def _print_ticks(console: Console, tab: Any) -> None:
    """One hyperperiod's activations, in pages of ticks that fit the console's width."""
    name_w = max([4, *(len(name) for name, _, _ in tab.rows)])
    per_page = max(8, (console.width - name_w - 6) // 3)
    for first in range(0, tab.ticks, per_page):
        last = min(tab.ticks, first + per_page)
        part = f", ticks {first}-{last - 1}" if tab.ticks > per_page else ""
        console.print()
        console.print(
            f"activations over one hyperperiod of {tab.clock} ({tab.ticks} ticks of "
            f"{tab.unit}{part})",
            markup=False,
            highlight=False,
            style="bold",
        )
        t = Table(
            box=None,
            header_style="bold",
            pad_edge=False,
            collapse_padding=True,
        )
        t.add_column("node", no_wrap=True)
        t.add_column("prio", justify="right")
        for k in range(first, last):
            t.add_column(str(k), justify="center", no_wrap=True)
        for name, prio, active in tab.rows:
            t.add_row(name, str(prio), *["X" if a else "." for a in active[first:last]])
        loads = [str(x) for x in tab.load()]
        t.add_row("load", "", *loads[first:last], style="bold")
        console.print(t)


def _ms(ms: float) -> str:
    return f"{ms:.2f}".rstrip("0").rstrip(".") if ms >= 0.01 else f"{ms:.3g}"


def _trigger_text(trig: Any) -> str:
    from ..graph.spec import FrameTrigger, InputTrigger, TimerTrigger

    if isinstance(trig, FrameTrigger):
        phase = f" +{trig.phase}" if trig.phase else ""
        every = f"1/{trig.period}" if trig.period != 1 else "each"
        return f"{every} {trig.frame}{phase}"
    if isinstance(trig, TimerTrigger):
        phase = f" +{_ms(trig.phase)}ms" if trig.phase else ""
        return f"{_ms(trig.timer)}ms{phase}"
    if isinstance(trig, InputTrigger):
        return f"input {trig.input}"
    return "loop"


def cmd_schema(args: argparse.Namespace) -> int:
    from pydantic import BaseModel

    from ..graph.spec import GraphSpec
    from ..stats import RuntimeStats

    model: type[BaseModel] = GraphSpec if args.what == "graph" else RuntimeStats
    schema = model.model_json_schema(by_alias=True)
    if args.json:
        emit(schema)
    else:
        print(json.dumps(schema, indent=2))
    return 0


def add_parsers(sub: Any) -> None:
    val = sub.add_parser("validate", help="check a graph file; exit 2 listing every error")
    val.add_argument("file", help="graph file")
    val.add_argument(
        "--no-import",
        action="store_true",
        help="do not import dotted-path kinds (package.module:Class): checking a graph file "
        "from someone else runs none of its code",
    )
    val.add_argument(
        "--json", action="store_true", help="one JSON document: counts, warnings or errors"
    )
    val.set_defaults(func=cmd_validate)
    gr = sub.add_parser("graph", help="print the topology and one hyperperiod of activations")
    gr.add_argument("file", help="graph file")
    gr.add_argument("--json", action="store_true", help="nodes, edges and activations as JSON")
    gr.set_defaults(func=cmd_graph)
    sc = sub.add_parser("schema", help="print the JSON schema of graph files or statistics")
    sc.add_argument("what", choices=["graph", "stats"], help="graph files, or --stats-json output")
    sc.add_argument(
        "--json", action="store_true", help="the same (the schema is JSON): for scripts' sake"
    )
    sc.set_defaults(func=cmd_schema)
