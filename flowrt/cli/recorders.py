"""A recorder node added to a graph: what ``flowrt record`` and ``flowrt run --recordings`` do.

Both record the outputs of a graph that does not say so itself: a ``recorder`` node (the
first free name from ``recorder``) reading the chosen outputs over lossless edges, so the
producers are never dropped on.
"""

from __future__ import annotations

import fnmatch
from typing import Any

RECORDER = "recorder"


def graph_outputs(graph: Any) -> list[str]:
    """Every output, those a node declares from its params too (a CAN node's messages)."""
    return [
        f"{name}.{port}"
        for name, n in graph.nodes.items()
        for port in {**n.cls.outputs, **n.cls.params_outputs(n.params)}
    ]


def with_recorder(spec: Any, topics: list[str], params: dict[str, Any], size: int = 16) -> Any:
    """``spec`` plus a recorder node reading ``topics`` over lossless edges."""
    from ..graph.spec import NodeSpec

    name = RECORDER
    while name in spec.nodes:
        name += "_"
    node = NodeSpec.model_validate(
        {
            "kind": "recorder",
            "params": params,
            "priority": 5,
            "inputs": {t: {"from": t, "policy": "lossless", "size": size} for t in topics},
        }
    )
    return spec.model_copy(update={"nodes": {**spec.nodes, name: node}})


def split_patterns(text: str | None) -> list[str]:
    return [p.strip() for p in (text or "").split(",") if p.strip()]


def select_outputs(outputs: list[str], patterns: list[str]) -> tuple[list[str], list[str]]:
    """(outputs matching any pattern, in graph order; the patterns that matched nothing)."""
    if not patterns:
        return outputs, []
    chosen = [o for o in outputs if any(fnmatch.fnmatchcase(o, p) for p in patterns)]
    unmatched = [p for p in patterns if not any(fnmatch.fnmatchcase(o, p) for o in outputs)]
    return chosen, unmatched
