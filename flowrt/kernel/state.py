"""The states of a node's runner (what the status table's ``state`` column shows)."""

from __future__ import annotations

import enum


class RunState(enum.StrEnum):
    """``starting``: setup running (at start, or a restart); ``idle``: ready for a release;
    ``running``: an activation took its inputs and runs; ``backoff``: failed, waiting to
    restart; ``failed``: given up by supervision (final until a swap)."""

    starting = "starting"
    idle = "idle"
    running = "running"
    backoff = "backoff"
    failed = "failed"
