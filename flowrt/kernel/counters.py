"""What a node's runner counts, and the statistics it reports from them.

Every activation that does not complete is counted with its reason (skipped, discarded,
aborted, failed): nothing is lost silently, and the same figures reach the status table,
``--stats-json``, the web view and recordings through :class:`flowrt.stats.NodeStats`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..stats import Running


@dataclass
class Counters:
    """Invariant: ``activations >= completions + skipped`` (a release is counted once, and
    ends completed, skipped, or still running / failed / discarded / aborted)."""

    activations: int = 0  # releases, including the skipped ones
    completions: int = 0
    skipped: int = 0  # overruns, missing required inputs, the node down
    misses: int = 0  # deadline misses (flowrt.kernel.deadlines)
    discarded: int = 0  # late results dropped by miss_policy: discard
    aborted: int = 0  # activations in flight lost with their worker (or its instance)
    errors: int = 0  # exceptions, and values of a refused type
    restarts: int = 0
    swaps: int = 0
    lead_max: int = 0  # most frames of a paced source published and not yet processed
    error_reports: int = 0  # ctx.set_error() calls that changed the reason
    last_start: float | None = None
    last_finish: float | None = None
    interval_from: float | None = None  # None after a timing change: a new series
    interval: Running = field(default_factory=Running)
    execution: Running = field(default_factory=Running)
    response: Running = field(default_factory=Running)

    def new_interval_series(self) -> None:
        """The interval statistics describe the new timing, not a mean of old and new."""
        self.interval = Running()
        self.interval_from = None
