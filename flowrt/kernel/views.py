"""What a node looks like from outside the kernel: the scheduler's read API.

The overload controller, the timing checks and monitors read a node through a
:class:`NodeView` (a snapshot taken at the call) or :meth:`Scheduler.timing_of` (a copy),
never through its runner: the runner's fields stay the kernel's to change, and what a
reader holds cannot change under it or change the node.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from ..graph._resolve import ResolvedNode
from .runner import NodeRunner
from .timing import Timing

log = logging.getLogger("flowrt")


@dataclass(frozen=True, slots=True)
class NodeView:
    """One node as of the read: its place in the graph, its timing, its two load counters."""

    name: str
    node: ResolvedNode  # the graph's node (trigger, kind, declared priority, order)
    timing: Timing  # a copy: changing it changes nothing (``Runtime.apply_timing`` does)
    activations: int  # since the start
    misses: int  # deadline misses since the start


def view_of(r: NodeRunner) -> NodeView:
    return NodeView(r.name, r.rnode, r.timing.copy(), r.counts.activations, r.counts.misses)


def reports_of(runners: Iterable[NodeRunner]) -> dict[str, Any]:
    """Each inline node's optional ``report()`` (also after stop: its last instance's)."""
    out: dict[str, Any] = {}
    for r in runners:
        name = r.name
        ex = r.executor
        node = getattr(ex, "node", None) or getattr(ex, "last_node", None)
        hook = getattr(node, "report", None)
        if not callable(hook):
            continue
        try:
            value = hook()
        except Exception as e:  # a report must never break the statistics
            log.warning("node %s: report() failed: %s", name, e)
            continue
        if value is not None:
            out[name] = value
    return out
