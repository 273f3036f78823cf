"""Execution-time budgets from measurements: a run's statistics, per node.

A declared ``wcet:`` is a contract; a measured budget is evidence, and only as good as the
run it came from: p99 ignores the rare long activation (a page fault, a preempted worker),
max keeps it. Both come from the runtime's execution-time statistics (start to finish of
``process``), so a budget measured under contention already includes some of it — which is
why the validation benchmark compares the bounds with the same run's response times.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Literal

from ..stats import NodeStats
from .timing import Budget

Stat = Literal["p99", "max"]


def budgets_from_stats(nodes: Iterable[NodeStats], stat: Stat, label: str) -> dict[str, Budget]:
    """``stat`` of each node's execution time (ms), for nodes that completed at least once."""
    out = {}
    for n in nodes:
        if n.execution.count > 0:
            ms = n.execution.p99 if stat == "p99" else n.execution.max
            out[n.name] = Budget(max(ms, 1e-6), f"{label} {stat}")
    return out
