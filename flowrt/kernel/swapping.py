"""Replacing a node's instance or params while the rest of the graph runs.

A new instance is set up beside the old one, takes over between two activations, gets the
old one's state (``get_state``/``set_state``), and the old one is torn down after: other
nodes are not touched (the hot swap of Erlang's code server, one node at a time).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable
from typing import Protocol

from pydantic import BaseModel

from ..edges import Buffer
from ..graph import ResolvedNode
from ..node import Node
from .counters import Counters
from .executor import Executor, InlineExecutor
from .ports import SchedulerPort
from .state import RunState
from .supervisor import Supervisor


class SwappedRunner(Protocol):
    """What a swap reads and changes of its runner."""

    name: str
    rnode: ResolvedNode
    inputs: dict[str, Buffer]
    outputs: dict[str, list[Buffer]]
    executor: Executor
    busy: bool
    state: RunState
    counts: Counters
    supervisor: Supervisor
    sched: SchedulerPort

    def make_executor(
        self, rnode: ResolvedNode | None = None, reload: bool = False
    ) -> Executor: ...


log = logging.getLogger("flowrt.scheduler")

SWAP_WAIT = 5.0  # seconds a swap waits for the running activation to end


class Swapper:
    """Swaps one runner's node instance (or params) between two activations."""

    def __init__(self, runner: SwappedRunner) -> None:
        self._r = runner
        # Invariant: ``pending`` is set only while a swap waits for a running activation to
        # end (``waiter`` then receives the old executor from :meth:`take_pending`).
        self.pending: Callable[[], Executor] | None = None
        self.waiter: asyncio.Future[Executor] | None = None

    def take_pending(self) -> None:
        """The runner is idle: a swap that waited for this moment takes over now."""
        if self.pending is None:
            return
        take_over, self.pending = self.pending, None
        old = take_over()
        if self.waiter is not None and not self.waiter.done():
            self.waiter.set_result(old)

    def set_params(self, params: BaseModel) -> None:
        """New params between two activations (a mode's weights, a tuning change).

        An inline node gets them at once (``process`` reads ``self.params``; an optional
        ``params_changed(old)`` hook recomputes what ``setup`` derived from them); a worker
        node is swapped for a new instance with them (``swap``), in the background.
        """
        r = self._r
        r.rnode = dataclasses.replace(r.rnode, params=params)
        ex = r.executor
        if isinstance(ex, InlineExecutor) and ex.node is not None:
            node = ex.node
            old, node.params = node.params, params
            hook = getattr(node, "params_changed", None)
            if hook is not None:
                hook(old)
            return
        task = r.sched.loop.create_task(self.swap(r.rnode.cls, params, r.rnode.spec.kind))
        task.add_done_callback(_log_swap_failure)

    async def swap(
        self, cls: type[Node], params: BaseModel, kind: str, *, reload: bool = False
    ) -> None:
        """Replace the node's instance by a new one of ``cls``, between two activations.

        A failure to set the new one up leaves the old one running and raises.
        """
        r = self._r
        missing = [p for p in r.inputs if p not in cls.inputs and cls.any_inputs is None]
        missing += [p for p, bufs in r.outputs.items() if bufs and p not in cls.outputs]
        if missing:
            raise ValueError(f"{r.name}: kind {kind!r} has no port(s) {', '.join(missing)}")
        unfed = [p for p, port in cls.inputs.items() if port.required and p not in r.inputs]
        if unfed:
            raise ValueError(
                f"{r.name}: kind {kind!r} needs input(s) {', '.join(unfed)}, "
                "which nothing feeds in this graph"
            )
        rnode = dataclasses.replace(
            r.rnode,
            cls=cls,
            params=params,
            spec=r.rnode.spec.model_copy(update={"kind": kind}),
        )
        new = r.make_executor(rnode, reload=reload)
        await new.start()  # raises: the old instance keeps running
        if r.busy:
            # Take over inside idle(), before a loop or input trigger can release again.
            loop = asyncio.get_running_loop()
            self.waiter = loop.create_future()
            self.pending = lambda: self._take_over(new, rnode)
            try:  # real time: a virtual clock may stand still
                old = await asyncio.wait_for(self.waiter, SWAP_WAIT)
            except TimeoutError:
                self.pending = None
                await new.stop()
                raise TimeoutError(
                    f"{r.name}: still running after {SWAP_WAIT:g} s; not swapped"
                ) from None
        else:
            old = self._take_over(new, rnode)
        try:
            await old.stop()
        except Exception as e:
            log.warning("node %s: teardown of the replaced instance failed: %s", r.name, e)

    def _take_over(self, new: Executor, rnode: ResolvedNode) -> Executor:
        """The new instance replaces the old one (synchronously: between two activations)."""
        r = self._r
        old_node, new_node = getattr(r.executor, "node", None), getattr(new, "node", None)
        getter, setter = getattr(old_node, "get_state", None), getattr(new_node, "set_state", None)
        if getter is not None and setter is not None:
            setter(getter())
        old, r.executor, r.rnode = r.executor, new, rnode
        if r.state in (RunState.failed, RunState.backoff):
            r.state = RunState.idle
        r.supervisor.succeeded()
        return old


def _log_swap_failure(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("params change by swap failed: %s", task.exception())
