"""A node disabled while it runs leaves what it drives safe (``Node.on_disable``).

Disabling a node (``Runtime.set_timing(node, enabled=False)``, a mode that disables it) stops
its releases; nothing more happens to it. For a node that commands a device every tick (a
haptic handle, a motor's set-point) the device then keeps the last command: a haptic handle
went on pushing with its last force (1.5 N for as long as the node stayed disabled). The
node's optional ``on_disable()`` is where it zeroes that command, or returns what to publish
as ``process`` does (the arbiter's zero command, for the actuator's driver downstream, which
otherwise went on sending the last one it had); the runtime calls it once
per disabling, between two calls of ``process``, never beside one: now when no call runs,
else when the running call ends (a precise node's thread included: it starts no call once
the node is disabled, see :meth:`DisableHook.disabled`).

Enabled again before the running call ended, the hook is not called (the node never stopped
running). A node in a worker process runs it there (a request after its calls,
``OP_DISABLE``, flowrt/workers/wire.py). A hook that raises, or returns what the node's
outputs cannot carry, fails the node for good (its device may not be safe): given up, torn
down, and the run exits 1.
"""

from __future__ import annotations

import asyncio
import inspect
from typing import Any, Protocol

from ..node import FatalError


class _Runner(Protocol):
    """What the hook reads of a node's runner (kernel/runner.py)."""

    @property
    def busy(self) -> bool: ...

    executor: Any
    timing: Any
    out_check: Any  # OutputCheck: what the node's outputs can carry

    sched: Any  # SchedulerPort: its clock

    def publish_result(self, result: Any, t: float) -> None: ...

    def fail(self, exc: BaseException, starting: bool = False) -> None: ...


class DisableHook:
    """One node's pending ``on_disable`` call."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.due = False  # disabled while a call ran: run the hook when that call ends

    def disabled(self, runner: _Runner) -> None:
        """The node was just disabled: its hook now, or when its running call ends."""
        self.due = True
        precise = getattr(runner, "precise", None)
        if precise is not None:
            # its thread tests ``enabled`` and counts its call in under this lock: past it, a
            # call the thread began is in ``busy`` (the hook waits for it), none begins
            with precise.lock:
                pass
        if not runner.busy:
            self._run(runner)

    def idle(self, runner: _Runner) -> None:
        """A call of the node ended (``NodeRunner.idle``): the hook, if a disabling waits."""
        if self.due and not runner.busy:
            self._run(runner)

    def _run(self, runner: _Runner) -> None:
        """No call of the node runs: its hook, unless it was enabled again meanwhile."""
        self.due = False
        if runner.timing.enabled:
            return  # enabled again before its call ended: it never stopped
        executor = runner.executor
        remote = getattr(executor, "on_disable", None)  # a worker's: a request to it
        if remote is not None:
            fut = remote()
            if fut is not None:
                fut.add_done_callback(lambda f: self._done(runner, f))
            return
        node = getattr(executor, "node", None)  # an inline node's instance (None: stopped)
        hook = getattr(node, "on_disable", None)
        if not callable(hook):
            return
        try:
            result = hook()
        except Exception as e:
            self._failed(runner, e)
            return
        if inspect.isawaitable(result):
            task = asyncio.ensure_future(result)
            task.add_done_callback(lambda f: self._done(runner, f))
            return
        self._publish(runner, result)

    def _done(self, runner: _Runner, fut: asyncio.Future[Any]) -> None:
        """A coroutine's or a worker's hook ended: what it returned, published."""
        if fut.cancelled():
            return
        if (e := fut.exception()) is not None:
            self._failed(runner, e)
            return
        self._publish(runner, fut.result())

    def _publish(self, runner: _Runner, result: Any) -> None:
        """What the hook returned, as ``process`` returns it (the arbiter's zero command),
        checked against the node's outputs; None: nothing."""
        if result is None:
            return
        problem = runner.out_check.problem(result)
        if problem is not None:
            self._failed(runner, problem)
            return
        runner.publish_result(result, runner.sched.clock.now())

    @staticmethod
    def _failed(runner: _Runner, e: BaseException) -> None:
        """What leaves the node's device safe failed: the node fails for good (a fatal error:
        given up, torn down, the run exits 1), as a teardown that fails does. Logged only,
        the run exited 0 with a device perhaps left pushing."""
        summary = getattr(e, "summary", None) or f"{type(e).__name__}: {e}"
        fatal = FatalError(f"on_disable() failed: {summary}")
        fatal.__cause__ = e  # its traceback, as the supervisor formats one
        tb = getattr(e, "traceback", None)
        if isinstance(tb, str):  # a worker's: its own frames (as a worker call's failure)
            fatal.traceback = tb  # type: ignore[attr-defined]
        runner.fail(fatal)
