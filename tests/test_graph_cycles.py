"""Cycle detection of graph validation (issue 31): the report is the shortest way back from
the first node of each cycle, as before, and no longer a search from every node (quadratic:
a chain of 2000 nodes took a second to validate)."""

from __future__ import annotations

from collections import deque
from types import SimpleNamespace
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt.graph._resolve import Edge, _check_cycles, _components
from flowrt.graph.spec import EdgePolicy


def _edges(pairs: list[tuple[int, int]]) -> list[Edge]:
    return [
        Edge(f"n{a}", "out", f"n{b}", f"in{i}", EdgePolicy.queue, 8)
        for i, (a, b) in enumerate(pairs)
    ]


def _reference(names: list[str], edges: list[Edge]) -> list[tuple[Any, str]]:
    """The search from every node that validation did before issue 31."""
    succ: dict[str, list[Edge]] = {n: [] for n in names}
    for e in edges:
        succ[e.src].append(e)
    out = []
    reported: set[str] = set()
    for start in names:
        if start in reported:
            continue
        came_by: dict[str, Edge] = {}
        todo = deque([start])
        closing = None
        while todo and closing is None:
            for e in succ[todo.popleft()]:
                if e.dst == start:
                    closing = e
                    break
                if e.dst not in came_by:
                    came_by[e.dst] = e
                    todo.append(e.dst)
        if closing is None:
            continue
        path = [closing]
        while path[0].src != start:
            path.insert(0, came_by[path[0].src])
        cycle = [start, *(e.dst for e in path)]
        reported.update(cycle)
        where = ("nodes", closing.dst, "inputs", closing.dst_port)
        out.append((where, "cycle in the graph: " + " -> ".join(cycle)))
    return out


def _reported(names: list[str], edges: list[Edge]) -> list[tuple[Any, str]]:
    got: list[tuple[Any, str]] = []
    spec = SimpleNamespace(nodes={n: None for n in names})
    _check_cycles(spec, edges, lambda where, text: got.append((where, text)))  # type: ignore[arg-type]
    return got


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 9).flatmap(
        lambda n: st.tuples(
            st.just(n), st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)))
        )
    )
)
def test_cycles_are_reported_as_before(graph: tuple[int, list[tuple[int, int]]]) -> None:
    n, pairs = graph
    names = [f"n{i}" for i in range(n)]
    edges = _edges(pairs)
    assert _reported(names, edges) == _reference(names, edges)


def test_a_long_chain_has_no_cycle_and_a_closed_one_has_one() -> None:
    names = [f"n{i}" for i in range(3000)]
    chain = _edges([(i, i + 1) for i in range(2999)])
    assert _components({n: [e for e in chain if e.src == n] for n in names}) == {}
    assert _reported(names, chain) == []
    closed = [*chain, *_edges([(2999, 0)])]
    (only,) = _reported(names, closed)
    assert only[1].startswith("cycle in the graph: n0 -> n1 -> ")
