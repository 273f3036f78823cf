"""Where a node's ``process`` runs: the kernel's one interface to it, and the inline kind.

The runner only ever talks to an :class:`Executor`: inline here, worker processes in
:mod:`flowrt.workers` (which implement this protocol directly, no adapter). Interfaces apart
from implementations, as anyio keeps its abstract classes apart from its backends.
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Callable
from typing import Any, Protocol

from ..node import Node

#: Seconds a node's ``setup()`` may take (README "Failures and exit codes"): in a worker the
#: worker is then killed (``flowrt.workers.WorkerOptions.setup_timeout``), inline an async
#: ``setup`` is cancelled; either is a failure at start-up. A synchronous inline ``setup``
#: holds the loop and cannot be cut: keep it short, or make it async or ``placement: process``.
SETUP_TIMEOUT_S = 60.0

# A direct hop's ends (kernel/hops.py): where a call's output goes (the reader's worker's
# address, the hop's tag, the output port or None for the only one), and where its input
# comes from (the input port, the hop's tag, the frame's expected size in bytes).
HopTo = tuple[str, int, str | None] | None
HopFrom = tuple[str, int, int] | None


class Executor(Protocol):
    """Runs one node instance's ``setup``/``process``/``teardown`` somewhere.

    ``sync``: ``call_sync`` may be used (an inline node whose ``process`` is a plain
    function: run straight from a loop callback, no task). ``pipelined``: ``submit`` is
    available, so calls may overlap (a worker of its own, see :mod:`flowrt.kernel.pipeline`).
    ``granted``: the OS scheduling it got, for the status table ("" inline).
    """

    @property
    def sync(self) -> bool: ...

    @property
    def pipelined(self) -> bool: ...

    @property
    def granted(self) -> str: ...

    async def start(self) -> None: ...

    def call_sync(self, inputs: dict[str, Any]) -> Any: ...

    async def call(self, inputs: dict[str, Any]) -> Any: ...

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        """Start a call now; up to ``window`` run back to back, results in order."""
        ...

    def set_priority(self, priority: int) -> None: ...

    async def stop(self, grace: float = 2.0) -> None:
        """Tear the node down; a worker that does not exit within ``grace`` s is killed."""
        ...

    # Direct hops between workers (kernel/hops.py); ``hop_address`` None: none for this node.
    @property
    def hop_address(self) -> str | None: ...

    def call_hop(
        self, inputs: dict[str, Any], to: HopTo, peer: HopFrom = None
    ) -> asyncio.Future[Any]:
        """Send a call now: its output on to another worker (``to``: its address, the hop's
        tag, the output port), its input ``peer`` = (port, tag, frame size) from one; the
        result is ``(True, result)``, or ``(False, None)`` when that input did not come."""
        ...

    def skip_hop(self, tag: int) -> None:
        """The input of the call waiting for hop ``tag`` will not come."""
        ...


class _NoHops:
    """No direct hop (kernel/hops.py never asks the rest when ``hop_address`` is None)."""

    hop_address: str | None = None

    def call_hop(
        self, inputs: dict[str, Any], to: HopTo, peer: HopFrom = None
    ) -> asyncio.Future[Any]:
        raise NotImplementedError("no direct hop to or from this node")

    def skip_hop(self, tag: int) -> None:
        pass


class NoExecutor(_NoHops):
    """The executor of a runner not started yet: every call is a programming error."""

    sync = False
    pipelined = False
    granted = ""

    async def start(self) -> None:
        raise RuntimeError("node not started")

    def call_sync(self, inputs: dict[str, Any]) -> Any:
        raise RuntimeError("node not started")

    async def call(self, inputs: dict[str, Any]) -> Any:
        raise RuntimeError("node not started")

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        raise RuntimeError("node not started")

    def set_priority(self, priority: int) -> None:
        pass

    async def stop(self, grace: float = 2.0) -> None:
        pass


class InlineExecutor(_NoHops):
    """The node runs on the event loop, in this process: ``process`` is a plain call."""

    pipelined = False
    granted = ""

    def __init__(self, factory: Callable[[], Node]) -> None:
        self._factory = factory
        self.node: Node | None = None
        self.last_node: Node | None = None  # what it reported last stays readable after stop
        self.sync = False

    async def start(self) -> None:
        node = self._factory()
        self.node = node
        self.sync = not inspect.iscoroutinefunction(node.process)
        result = node.setup()
        if inspect.isawaitable(result):
            try:
                await asyncio.wait_for(result, SETUP_TIMEOUT_S)
            except TimeoutError:
                raise TimeoutError(
                    f"setup() did not return within {SETUP_TIMEOUT_S:g} s (the limit of a "
                    "node's set-up)"
                ) from None

    def call_sync(self, inputs: dict[str, Any]) -> Any:
        assert self.node is not None
        return self.node.process(**inputs)

    async def call(self, inputs: dict[str, Any]) -> Any:
        assert self.node is not None
        result = self.node.process(**inputs)
        if inspect.isawaitable(result):
            result = await result
        return result

    def submit(self, inputs: dict[str, Any], window: int) -> asyncio.Future[Any]:
        raise NotImplementedError("an inline node is never pipelined")

    def set_priority(self, priority: int) -> None:
        pass  # the loop's own priority: nothing to change per node

    async def stop(self, grace: float = 2.0) -> None:
        node, self.node = self.node, None
        self.last_node = node
        if node is not None:
            result = node.teardown()
            if inspect.isawaitable(result):  # bounded: a teardown that hangs is its failure
                await asyncio.wait_for(result, grace)
