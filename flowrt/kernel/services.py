"""What the kernel needs from the runtime that hosts it, handed over at construction.

The scheduler never imports the runtime (nor workers, frames pools or monitors): the
composition root (:class:`flowrt.Runtime`) builds these ports and passes them in, as
copper-rs builds its runtime from its parts. A kernel built without a port refuses what needs
it with one clear error (a worker node without worker support) or falls back to plain memory
(frames without a shared-memory store).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from ..events import Event
from ..frames import Frame
from ..graph._resolve import ResolvedNode
from ..node import NodeFactory
from .executor import Executor


class FramePort(Protocol):
    """Where the kernel allocates the frames a node makes (``ctx.new_frame``)."""

    def new_frame(
        self, owner: str, shape: tuple[int, ...], dtype: Any, pixel_format: str
    ) -> Frame: ...


class WorkerPort(Protocol):
    """Builds the executor of a node placed in a worker process (``process``/``pool``)."""

    def executor_for(
        self, rnode: ResolvedNode, priority: int, factory: NodeFactory
    ) -> Executor: ...


@dataclass(frozen=True)
class Services:
    """The runtime's services, as the kernel sees them (each optional outside a Runtime)."""

    emit: Callable[[Event], None]
    workers: WorkerPort | None = None
    frames: FramePort | None = None
    stats: Callable[[], Any] | None = None  # ctx.stats(): the runtime's statistics
    rtdb: Callable[[], Any] | None = None  # ctx.rtdb: the real-time database
    set_mode: Callable[[str, str], None] | None = None  # ctx.set_mode(mode) (mode, origin)
    request_stop: Callable[[], None] | None = None  # ctx.request_stop()
    drain_timeout: float = 5.0  # seconds the drain at stop may take (then reported)
    real_time: bool = True  # a system clock: inline calls that block the loop are reported
