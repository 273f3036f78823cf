"""``--zenoh-listen EP`` / ``--zenoh-connect EP`` of ``flowrt run`` and ``flowrt record``.

The same graph file runs on any machine: the robot's address belongs to the machine, not to
the graph, so the command line replaces the graph's ``zenoh:`` endpoints (each flag
repeatable; one given replaces that list, the other stays as the file says). A display's
``robots`` entry that connects where the graph itself connects is the same robot: its
``connect`` follows ``--zenoh-connect`` too, so a base station's page watches the robot its
imports come from.
"""

from __future__ import annotations

import argparse
from typing import Any

from ..graph._resolve import Graph
from ..graph.spec import ZenohSpec

__all__ = ["add_zenoh_options", "apply_zenoh_options"]


def add_zenoh_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument(
        "--zenoh-listen",
        action="append",
        metavar="EP",
        help="listen on this Zenoh endpoint instead of the graph's zenoh.listen (repeatable), "
        "e.g. tcp/10.0.0.1:7447",
    )
    parser.add_argument(
        "--zenoh-connect",
        action="append",
        metavar="EP",
        help="connect to this Zenoh endpoint instead of the graph's zenoh.connect "
        "(repeatable); display robots connecting where the graph did follow it",
    )


def apply_zenoh_options(graph: Graph, args: argparse.Namespace) -> str | None:
    """Replace the graph's endpoints by the command line's; or why not, in one line."""
    listen = getattr(args, "zenoh_listen", None)
    connect = getattr(args, "zenoh_connect", None)
    if listen is None and connect is None:
        return None
    old = graph.spec.zenoh or ZenohSpec()
    update: dict[str, Any] = {}
    if listen is not None:
        update["listen"] = listen
    if connect is not None:
        update["connect"] = connect
    try:
        new = ZenohSpec.model_validate({**old.model_dump(), **update})
    except ValueError as e:
        flags = "/".join(f"--zenoh-{k}" for k in update)
        return f"{flags}: {_one_line(e)}"
    graph.spec = graph.spec.model_copy(update={"zenoh": new})
    if connect is not None and old.connect:
        problem = _follow_robots(graph, old.connect, connect)
        if problem is not None:
            return problem
    return None


def _follow_robots(graph: Graph, old: list[str], new: list[str]) -> str | None:
    """Display ``robots`` that connected where the graph did now connect where it does."""
    for name, node in graph.nodes.items():
        robots = getattr(node.params, "robots", None)
        if not isinstance(robots, dict) or not robots:
            continue
        data = node.params.model_dump()
        changed = False
        for robot in data["robots"].values():
            if sorted(robot.get("connect", [])) == sorted(old):
                robot["connect"] = list(new)
                changed = True
        if changed:
            try:
                node.params = node.params.model_validate(data)
            except ValueError as e:
                return f"--zenoh-connect: display {name}: {_one_line(e)}"
    return None


def _one_line(e: BaseException) -> str:
    errors = getattr(e, "errors", None)
    if callable(errors):
        msgs = (str(err.get("msg", err)).removeprefix("Value error, ") for err in errors())
        return "; ".join(msgs)
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
