"""A run's verdict: which nodes failed it (``Runtime.failures()``, ``flowrt run``'s exit 1)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from ..events import Event, NodeFailed
from ..stats import NodeStats
from ..supervision import failure_kind


def failures(nodes: Iterable[NodeStats], events: Sequence[Event]) -> list[NodeStats]:
    """Nodes given up (``failed``), in an error state they reported, or waiting to restart
    without one completed activation (every call failed: a run shorter than the give-up
    takes is no success either), the last with their last error as the reason."""
    found = [n for n in nodes if n.state in ("failed", "error") or never_ran(n)]
    return [_with_last_error(n, events) if never_ran(n) else n for n in found]


def never_ran(n: NodeStats) -> bool:
    """Waiting to restart, and no activation of it has completed: every call failed."""
    return n.state == "backoff" and n.completions == 0 and n.errors > 0


def _with_last_error(n: NodeStats, events: Sequence[Event]) -> NodeStats:
    """``n`` with the last failure it had as its reason (a node in back-off has none)."""
    for e in reversed(events):
        if isinstance(e, NodeFailed) and e.node == n.name:
            return n.model_copy(update={"reason": f"last error: {failure_kind(e.error)}"})
    return n
