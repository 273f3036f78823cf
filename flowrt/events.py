"""Typed runtime events: misses, failures, restarts and changes, each a frozen dataclass.

Counters say how often; events say when and why. Monitors (the status table, the web view,
the health node) and host programs subscribe to them.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Event:
    t: float  # runtime clock, seconds since start
    node: str | None

    @property
    def kind(self) -> str:
        return type(self).__name__


@dataclass(frozen=True)
class DeadlineMissed(Event):
    """Published at the deadline instant if the node is still running, else at its return."""

    deadline_ms: float
    still_running: bool
    discarded: bool


@dataclass(frozen=True)
class NodeFailed(Event):
    error: str
    traceback: str = field(repr=False)


@dataclass(frozen=True)
class NodeRestarted(Event):
    attempt: int
    backoff_ms: float


@dataclass(frozen=True)
class NodeGaveUp(Event):
    """The restart policy is exhausted (or ``never``): the node stays down."""

    reason: str


@dataclass(frozen=True)
class LoopBlocked(Event):
    """An inline call kept the event loop busy longer than the threshold."""

    duration_ms: float


@dataclass(frozen=True)
class TimingChanged(Event):
    change: str  # human-readable, e.g. "period 1 -> 2, priority 35 -> 40"
    origin: str = "api"


@dataclass(frozen=True)
class ModeChanged(Event):
    mode: str
    previous: str | None
    origin: str = "api"


@dataclass(frozen=True)
class HealthAlert(Event):
    """Raised by health monitoring or a node about a stream or the machine."""

    alert: str
    detail: str
    severity: str = "warning"


@dataclass(frozen=True)
class RealtimeStatus(Event):
    granted: str


@dataclass(frozen=True)
class NodeSwapped(Event):
    """A node's instance was replaced (swap, reload, or params for a worker node)."""

    node_kind: str
    previous_kind: str
    origin: str = "api"
