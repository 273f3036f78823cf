"""A node that raised: count, log (rate-limited), and decide: restart after a back-off, or give up.

The one supervision rule of :mod:`flowrt.supervision` (Erlang/OTP's restart intensity, in
the words of a graph file's ``restart:``), for one runner. The supervisor never changes its
runner: it returns a :data:`Decision` that the runner applies (:meth:`NodeRunner.fail`), as
copper-rs's monitors return a ``Decision`` for its runtime to apply, so that the runner's
state has one writer.
"""

from __future__ import annotations

import logging
import traceback
from dataclasses import dataclass
from typing import Protocol

from ..events import NodeFailed, NodeGaveUp, NodeRestarted
from ..graph._resolve import ResolvedNode
from ..supervision import FailureLog, backoff_s, failure_kind, give_up_reason, out_of_resources
from .counters import Counters
from .executor import Executor
from .ports import SchedulerPort
from .state import RunState


class SupervisedRunner(Protocol):
    """What supervision reads of its runner (read-only: mypy refuses a write through it)."""

    @property
    def name(self) -> str: ...
    @property
    def rnode(self) -> ResolvedNode: ...
    @property
    def counts(self) -> Counters: ...
    @property
    def state(self) -> RunState: ...
    @property
    def stopping(self) -> bool: ...
    @property
    def sched(self) -> SchedulerPort: ...


@dataclass(frozen=True, slots=True)
class Restart:
    """Restart the node after ``backoff`` seconds (state ``backoff`` meanwhile)."""

    backoff: float


@dataclass(frozen=True, slots=True)
class GiveUp:
    """Give the node up (state ``failed``, final until a swap), for ``reason``."""

    reason: str


Decision = Restart | GiveUp


log = logging.getLogger("flowrt.scheduler")


class Supervisor:
    """Restarts one runner's node after failures, or gives it up (state ``failed``)."""

    def __init__(self, runner: SupervisedRunner) -> None:
        self._r = runner
        self.consecutive = 0  # failures since the last completion (or swap)
        self.log = FailureLog(runner.name)
        self.failed_reason = ""  # why the node was given up (state "failed")

    def succeeded(self) -> None:
        self.consecutive = 0

    def failed(self, exc: BaseException, starting: bool = False) -> Decision:
        """Count, log and report ``exc``; what the runner is to do about it."""
        r = self._r
        sched = r.sched
        r.counts.errors += 1
        self.consecutive += 1
        # A worker's error brings its own one-line summary and the worker's traceback (none
        # for a dead worker): the main side's stack would only show the transport.
        tb = getattr(exc, "traceback", None)
        if not isinstance(tb, str):
            tb = "".join(traceback.format_exception(exc))
        error = getattr(exc, "summary", None) or f"{type(exc).__name__}: {exc}"
        now = sched.clock.now()
        fatal = bool(getattr(exc, "fatal", False))
        if not fatal:  # a fatal error is said once, below
            self.log.failed(now, error, tb)
        sched.emit(NodeFailed(sched.rel(now), r.name, error, tb))
        policy = r.rnode.spec.restart
        # Out of descriptors/processes/memory: the machine's failure, retried without a bound.
        counted = 0 if out_of_resources(exc) else self.consecutive
        never_started = starting and r.counts.completions == 0
        why = give_up_reason(policy, counted, r.counts.restarts, fatal, never_started)
        if why is not None:
            last = failure_kind(error)
            self.failed_reason = last if fatal else f"{why}; last error: {last}"
            return GiveUp(self.failed_reason)
        return Restart(backoff_s(policy, self.consecutive))

    def gave_up(self, decision: GiveUp) -> None:
        """Say it, once the runner is ``failed``: whoever hears ``NodeGaveUp`` (a run that
        stops on a failure, a monitor) sees the node failed."""
        r = self._r
        now = r.sched.clock.now()
        self.log.flush(now)
        log.error("node %s given up: %s", r.name, decision.reason)
        r.sched.emit(NodeGaveUp(r.sched.rel(now), r.name, decision.reason))

    async def stop_executor(self, executor: Executor) -> None:
        """Tear the failed instance down; a teardown that fails is counted and logged."""
        try:
            await executor.stop()
        except Exception as e:
            self.teardown_failed(e, final=False)

    def teardown_failed(self, exc: BaseException, final: bool = True) -> GiveUp | None:
        """``teardown`` raised (or did not return): the node's error, counted and logged with
        its traceback. At the run's end (``final``) the node ends ``failed`` with that reason,
        so the run exits 1: a device left unreleased is not a clean end."""
        r = self._r
        sched = r.sched
        r.counts.errors += 1
        tb = getattr(exc, "traceback", None)
        if isinstance(exc, TimeoutError) and not str(exc):
            error = "teardown did not return in time"
            tb = ""  # the wait's own frames (flowrt's), nothing of the node's
        else:
            error = getattr(exc, "summary", None) or f"{type(exc).__name__}: {exc}"
        if not isinstance(tb, str):
            tb = "".join(traceback.format_exception(exc))
        now = sched.clock.now()
        sched.emit(NodeFailed(sched.rel(now), r.name, f"teardown: {error}", tb))
        log.error("node %s: teardown failed: %s%s", r.name, error, f"\n{tb.rstrip()}" * bool(tb))
        if final and r.state is not RunState.failed:
            self.failed_reason = f"teardown failed: {failure_kind(error)}"
            return GiveUp(self.failed_reason)
        return None

    async def backoff(self, restart: Restart, executor: Executor) -> bool:
        """Tear the failed instance down and wait out the back-off; False: the run stops
        meanwhile (no restart). True: the restart is counted, the runner starts a new one."""
        r = self._r
        sched = r.sched
        await self.stop_executor(executor)
        await sched.sleep(restart.backoff)
        if r.stopping:
            return False
        r.counts.restarts += 1
        ms = restart.backoff * 1000
        sched.emit(NodeRestarted(sched.rel(sched.clock.now()), r.name, r.counts.restarts, ms))
        return True
