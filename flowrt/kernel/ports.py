"""What a runner and its collaborators use of their scheduler (so that none imports it).

The scheduler builds the runners and calls them; they call back through this port only:
the kernel's modules stay without an import circle, as the runtime's do (``tests/test_imports``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any, Protocol

from ..clock import Clock
from ..events import Event
from ..frames import Frame
from ..graph._resolve import Graph, ResolvedNode
from ..node import NodeFactory
from .executor import Executor
from .services import Services


class SchedulerPort(Protocol):
    clock: Clock
    loop: asyncio.AbstractEventLoop
    services: Services
    real_time: bool
    blocked_calls: int
    paced: set[str]
    emit: Callable[[Event], None]
    graph: Graph
    # A run's observer (flowrt.determinism), set by ``ctx.observe``: told of every activation,
    # completion and publication, in order, to record what makes the run reproducible.
    observer: Any
    stop_at: float | None  # no source is released from then on (None: no stop due)

    def rel(self, t: float) -> float: ...

    def drain_over(self) -> bool: ...

    def tick(self, key: str, t: float) -> None: ...

    def new_frame(
        self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str
    ) -> Frame: ...

    def worker_executor(
        self, rnode: ResolvedNode, priority: int, factory: NodeFactory
    ) -> Executor: ...

    async def wait_readers(self, runner: Any) -> None: ...

    async def sleep(self, seconds: float) -> None: ...
