"""The states of a node's runner (what the status table's ``state`` column shows), and the
moves between them that the runner may make (:meth:`NodeRunner.move`, the one place the
state changes: a move not in :data:`MOVES` is a bug in the kernel, raised at once)."""

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


_S = RunState
MOVES: dict[RunState, frozenset[RunState]] = {
    # set up: ready, or failed at once (restarted, or given up)
    _S.starting: frozenset((_S.idle, _S.backoff, _S.failed)),
    # released; a swap in place (teardown first); failed between calls (a worker lost, a
    # teardown at the end)
    _S.idle: frozenset((_S.running, _S.starting, _S.backoff, _S.failed)),
    # returned; raised (restart or give up)
    _S.running: frozenset((_S.idle, _S.backoff, _S.failed)),
    # restarted; a swap took over; gave up (the restart's setup failed); a swap in place
    _S.backoff: frozenset((_S.idle, _S.failed, _S.starting)),
    # only a swap brings a failed node back (taken over, or in place)
    _S.failed: frozenset((_S.idle, _S.starting)),
}
"""Allowed moves, from each state. Staying in a state is not a move (always allowed)."""
STAY_OR_MOVE: dict[RunState, frozenset[RunState]] = {s: MOVES[s] | {s} for s in MOVES}
"""What :meth:`NodeRunner.move` checks: one lookup, as it runs twice per activation."""


class StateError(RuntimeError):
    """A move the table refuses: the kernel's own bug, never the node's."""
