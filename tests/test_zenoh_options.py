"""``--zenoh-listen`` / ``--zenoh-connect`` replace a graph's endpoints (issue 40 item 1)."""

from __future__ import annotations

import argparse
from pathlib import Path

from flowrt.cli.zenoh_options import add_zenoh_options, apply_zenoh_options
from flowrt.graph._resolve import Graph


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_zenoh_options(parser)
    return parser.parse_args(list(argv))


def test_connect_replaces_the_graph_and_the_same_robot_on_the_page(repo: Path) -> None:
    graph = Graph.from_file(repo / "graphs" / "zenoh_base.yaml")
    args = _args("--zenoh-connect", "tcp/10.203.0.1:7447", "--zenoh-connect", "tcp/10.9.0.1:7447")
    assert apply_zenoh_options(graph, args) is None
    assert graph.spec.zenoh is not None
    assert graph.spec.zenoh.connect == ["tcp/10.203.0.1:7447", "tcp/10.9.0.1:7447"]
    assert graph.spec.zenoh.listen == []  # the other list stays as the file says
    robot = graph.nodes["display"].params.robots["robot1"]  # type: ignore[attr-defined]
    assert robot.connect == ["tcp/10.203.0.1:7447", "tcp/10.9.0.1:7447"]


def test_listen_replaces_the_graph_listen(repo: Path) -> None:
    graph = Graph.from_file(repo / "graphs" / "zenoh_robot.yaml")
    assert apply_zenoh_options(graph, _args("--zenoh-listen", "tcp/10.203.0.1:7447")) is None
    assert graph.spec.zenoh is not None
    assert graph.spec.zenoh.listen == ["tcp/10.203.0.1:7447"]


def test_a_bad_endpoint_is_one_line(repo: Path) -> None:
    graph = Graph.from_file(repo / "graphs" / "zenoh_robot.yaml")
    problem = apply_zenoh_options(graph, _args("--zenoh-listen", "10.203.0.1:7447"))
    assert problem is not None
    assert problem.startswith("--zenoh-listen: ")
    assert "\n" not in problem


def test_no_flag_leaves_the_graph_alone(repo: Path) -> None:
    graph = Graph.from_file(repo / "graphs" / "zenoh_base.yaml")
    before = graph.spec
    assert apply_zenoh_options(graph, _args()) is None
    assert graph.spec is before
