"""The graph's exports (``export:``) against the nodes they publish from."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

from pydantic import BaseModel

from ..frames import Frame
from ..node import Node
from ._ports import is_compatible, node_ports, ports_unknown
from .diagnostics import did_you_mean
from .spec import GraphSpec

__all__ = ["check_exports"]


def check_exports(
    spec: GraphSpec,
    at: Any,
    classes: Mapping[str, type[Node]],
    params: Mapping[str, BaseModel],
    names: Collection[str],
    invalid_nodes: Collection[str],
) -> None:
    """Exports name outputs that exist; an image encoding (``jpeg``, ``png``) names a frame
    output (on a counter's ``int`` it was accepted, and the value went out as JSON)."""
    for key, ex in spec.exports.items():
        src_cls = classes.get(ex.node)
        if ex.node not in spec.nodes and ex.node not in invalid_nodes:
            at(
                ("export", key),
                f"export from unknown node {ex.node!r}" + did_you_mean(ex.node, names),
            )
        elif src_cls is not None and not ports_unknown(src_cls, params, ex.node, False):
            src_outs = node_ports(src_cls, params, ex.node, False)
            if ex.port not in src_outs:
                at(
                    ("export", key),
                    f"node {ex.node!r} has no output {ex.port!r}" + did_you_mean(ex.port, src_outs),
                )
            elif ex.encoding != "raw" and not is_compatible(src_outs[ex.port].type, Frame):
                at(
                    ("export", key, "encoding"),
                    f"encoding {ex.encoding} is for frames: {ex.source} is not a Frame output "
                    "(leave encoding out: a message goes out as JSON)",
                )
