"""The node an ``import:`` entry of a graph becomes: a source whose output is a remote stream.

The graph names it by kind path (``flowrt.remote._bridge:RemoteSource``, re-exported there); the
bridge binds its :class:`~flowrt.remote._importer.ImportLink` once the runtime runs. Values
arrive on Zenoh's thread and are published by the loop as they come; the node's own
activations only check the stream is alive.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ..frames import Frame
from ..graph.spec import TimerTrigger
from ..node import Node, Output
from ._importer import ImportLink

__all__ = ["RemoteFrameSource", "RemoteSource", "RemoteSourceParams"]


class RemoteSourceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    key: str
    period_ms: float | None = Field(default=None, gt=0)
    stale_after: float | None = Field(default=5.0, gt=0, description="None: never stale")
    stale: Literal["error", "state"] = "error"
    size: int = Field(default=16, ge=1)


class RemoteSource(Node):
    """What an ``import:`` entry becomes: a node whose ``output`` is the remote stream.

    Its activations are liveness checks (every 50 ms); values are published when they
    arrive, not on the checks.
    """

    Params = RemoteSourceParams
    # rate_hz=None: at the remote producer's rate / on a change, not at this node's tick
    output: Output[Any] = Output(
        object, doc="the remote stream's values (frames: local pool)", rate_hz=None
    )
    state: Output[dict[str, Any]] = Output(
        dict,
        doc="the link's state at each change: {key, stale, silent_s, last_contact, outages}",
        rate_hz=None,
    )

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=50.0)

    def setup(self) -> None:
        self.link: ImportLink | None = None  # bound by the bridge once the runtime runs

    def process(self) -> None:
        if self.link is not None:
            self.link.check_liveness(self.ctx)

    def report(self) -> Any:
        """The link's liveness (stale, outages, time down, last contact) for ``reports``."""
        return None if self.link is None else self.link.report()


class RemoteFrameSource(RemoteSource):
    """An import with ``frames: true``: its ``output`` is a frame source (every frame a tick)."""

    output: Output[Any] = Output(Frame, doc="the remote frames, in the local frame pool")
