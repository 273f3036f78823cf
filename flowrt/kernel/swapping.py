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
from ..graph._resolve import ResolvedNode
from ..node import Node
from .counters import Counters
from .executor import Executor, InlineExecutor
from .ports import SchedulerPort
from .state import RunState
from .supervisor import Supervisor


class SwappedRunner(Protocol):
    """What a swap reads of its runner (read-only: mypy refuses a write through it), and
    the runner's methods that apply what it decides (the new instance, set up:
    :meth:`install`; the state: :meth:`move`)."""

    @property
    def name(self) -> str: ...
    @property
    def rnode(self) -> ResolvedNode: ...
    @property
    def inputs(self) -> dict[str, Buffer]: ...
    @property
    def outputs(self) -> dict[str, list[Buffer]]: ...
    @property
    def executor(self) -> Executor: ...
    @property
    def busy(self) -> bool: ...
    @property
    def state(self) -> RunState: ...
    @property
    def counts(self) -> Counters: ...
    @property
    def supervisor(self) -> Supervisor: ...
    @property
    def sched(self) -> SchedulerPort: ...

    def make_executor(
        self, rnode: ResolvedNode | None = None, reload: bool = False
    ) -> Executor: ...

    def idle(self) -> None: ...

    def install(self, executor: Executor, rnode: ResolvedNode | None = None) -> Executor: ...

    def move(self, to: RunState) -> None: ...

    def fail(self, exc: BaseException, starting: bool = False) -> None: ...


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
        self.swapping = False  # a swap is under way (kernel/precise.py: no call starts)

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
        r.install(r.executor, dataclasses.replace(r.rnode, params=params))
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
        # the ports its params give it too (a can node's, from its DBC: no swap of one passed)
        ins = {**cls.inputs, **cls.params_inputs(params)}
        outs = {**cls.outputs, **cls.params_outputs(params)}
        missing = [p for p in r.inputs if p not in ins and cls.any_inputs is None]
        missing += [p for p, bufs in r.outputs.items() if bufs and p not in outs]
        if missing:
            names = ", ".join(dict.fromkeys(missing))  # an input and an output of one name
            raise ValueError(f"{r.name}: kind {kind!r} has no port(s) {names}")
        unfed = [p for p, port in ins.items() if port.required and p not in r.inputs]
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
        if getattr(cls, "listens", False) or getattr(r.rnode.cls, "listens", False):
            await self._swap_in_place(rnode, reload)
            return
        new = r.make_executor(rnode, reload=reload)
        try:
            await new.start()  # raises: the old instance keeps running
        except BaseException:
            await _quietly_stopped(new)  # its worker, spawned for nothing, does not stay
            raise
        self.swapping = True  # set before busy is read: a precise thread sees one or the other
        try:
            old = await self._replace(new, rnode)
        finally:
            self.swapping = False
        try:
            await old.stop()
        except Exception as e:
            log.warning("node %s: teardown of the replaced instance failed: %s", r.name, e)

    async def _replace(self, new: Executor, rnode: ResolvedNode) -> Executor:
        """Take over now, or inside idle() when the node is busy; the old executor."""
        r = self._r
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
        return old

    async def _swap_in_place(self, rnode: ResolvedNode, reload: bool) -> None:
        """A node that owns a socket (``listens``: a display's port) cannot set its successor
        up beside it, which would find the port taken: between two activations the old one
        is torn down first (releases skipped meanwhile, as during a restart), then the new
        one starts. If it cannot, an instance as before is started again and the swap fails.
        """
        r = self._r

        def hold() -> Executor:  # synchronously: no release slips in before the teardown
            r.move(RunState.starting)
            return r.executor

        if r.busy:
            loop = asyncio.get_running_loop()
            self.waiter = loop.create_future()
            self.pending = hold
            try:
                await asyncio.wait_for(self.waiter, SWAP_WAIT)
            except TimeoutError:
                self.pending = None
                raise TimeoutError(
                    f"{r.name}: still running after {SWAP_WAIT:g} s; not swapped"
                ) from None
        old = hold()
        getter = getattr(getattr(old, "node", None), "get_state", None)
        state = getter() if getter is not None else None
        try:
            await old.stop()
        except Exception as e:
            log.warning("node %s: teardown of the replaced instance failed: %s", r.name, e)
        new = r.make_executor(rnode, reload=reload)
        try:
            await new.start()
        except Exception:
            again = r.make_executor()  # the old class and params: rnode not replaced yet
            try:
                await again.start()
            except Exception as e:
                r.install(again)
                r.fail(e, starting=True)
                raise
            r.install(again)
            r.move(RunState.idle)
            self._give_state(again, state, getter is not None)
            r.idle()
            raise
        r.install(new, rnode)
        r.move(RunState.idle)
        self._give_state(new, state, getter is not None)
        r.supervisor.succeeded()
        r.idle()

    @staticmethod
    def _give_state(executor: Executor, state: object, has_state: bool) -> None:
        setter = getattr(getattr(executor, "node", None), "set_state", None)
        if has_state and setter is not None:
            setter(state)

    def _take_over(self, new: Executor, rnode: ResolvedNode) -> Executor:
        """The new instance replaces the old one (synchronously: between two activations)."""
        r = self._r
        old_node, new_node = getattr(r.executor, "node", None), getattr(new, "node", None)
        getter, setter = getattr(old_node, "get_state", None), getattr(new_node, "set_state", None)
        if getter is not None and setter is not None:
            setter(getter())
        old = r.install(new, rnode)
        if r.state in (RunState.failed, RunState.backoff):
            r.move(RunState.idle)
        r.supervisor.succeeded()
        return old


def _log_swap_failure(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("params change by swap failed: %s", task.exception())


async def _quietly_stopped(executor: Executor) -> None:
    """Stop an executor whose start failed (its worker process, if one was spawned); what
    that stop raises is not the news: the failed start is."""
    try:
        await asyncio.shield(executor.stop())
    except Exception as e:  # the start's error is what the caller sees
        log.debug("an executor whose start failed did not stop cleanly: %r", e)
