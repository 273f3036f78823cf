"""``flowrt.replay``: a deterministic replay embedded in a program or a test.

    async with flowrt.replay("recordings/drive_001", "graph.yaml") as rp:
        ball = rp.subscribe("ball_fr.detection")
        report = await rp.run()
    assert report.identical
    assert sum(d.found for d in ball.drain()) > 100

Record once on the robot, check every change in CI: the replay re-executes the processing
nodes of ``graph`` on exactly what each activation saw in the recording, as fast as the CPU
allows, and ``report`` says whether every output is what the robot computed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

from ..graph._resolve import Graph
from ..graph.spec import Placement
from ..runtime._subscription import Subscription
from .report import ReplayReport

if TYPE_CHECKING:
    from .engine import ReplayEngine
    from .log import DeterminismLog

__all__ = ["Replay", "replay"]


class Replay:
    """A deterministic replay of ``session`` into ``graph`` (see :func:`replay`)."""

    def __init__(
        self,
        session: str | Path,
        graph: str | Path | Graph,
        *,
        inline: bool = False,
        stop_at_divergence: bool = False,
    ) -> None:
        self.session = Path(session)
        self.graph_arg = graph
        self.inline = inline
        self.stop_at_divergence = stop_at_divergence
        self.engine: ReplayEngine | None = None
        self.report: ReplayReport | None = None
        self.preloaded: DeterminismLog | None = None  # the log, when the caller read it already
        self.began: float | None = None  # perf_counter when the caller began (reading the log)
        self._t0 = 0.0

    async def start(self) -> None:
        """Read the log, load the graph, set the nodes up; raises LogError or GraphError."""
        from .engine import ReplayEngine  # (the recording's readers: imported when used)
        from .log import read_log

        self._t0 = self.began if self.began is not None else time.perf_counter()
        g = self.graph_arg
        graph = g if isinstance(g, Graph) else Graph.from_file(g)
        reading = self._read_log(read_log)
        if not self.inline and any(
            n.spec.placement is not Placement.inline and not n.cls.inline_only
            for n in graph.nodes.values()
        ):  # the worker processes' forkserver (~0.5 s, importing OpenCV) meanwhile
            from ..workers import start_forkserver

            log, _ = await asyncio.gather(reading, asyncio.to_thread(start_forkserver))
        else:
            log = await reading
        self.engine = ReplayEngine(
            log, graph, inline=self.inline, stop_at_divergence=self.stop_at_divergence
        )
        await self.engine.start()

    async def _read_log(self, read_log: Callable[[Path], DeterminismLog]) -> DeterminismLog:
        if self.preloaded is not None:
            return self.preloaded
        return await asyncio.to_thread(read_log, self.session)

    def subscribe(self, target: str, size: int | None = None) -> Subscription:
        """Every value ``node.port`` publishes during the replay, in order (all of them unless
        ``size`` bounds the buffer: then the oldest are dropped, counted)."""
        if self.engine is None:
            raise RuntimeError("subscribe inside `async with flowrt.replay(...)`")
        return Subscription(self.engine.subscribe(target, size))

    async def run(self) -> ReplayReport:
        """Re-execute the whole recording; the report (``identical``, ``compared`` ...)."""
        if self.engine is None:
            await self.start()
        assert self.engine is not None
        await self.engine.run()
        self.report = self.engine.report(time.perf_counter() - self._t0)
        return self.report

    async def stop(self) -> None:
        if self.engine is not None:
            await self.engine.stop()

    async def __aenter__(self) -> Replay:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()


def replay(
    session: str | Path,
    graph: str | Path | Graph,
    deterministic: bool = True,
    *,
    inline: bool = False,
    stop_at_divergence: bool = False,
) -> Replay:
    """A deterministic replay of a ``--deterministic`` recording into ``graph``, as an async
    context manager with ``subscribe`` and ``run`` (see the module docstring).

    ``inline``: every node on the event loop, whatever its placement (else workers as placed).
    ``stop_at_divergence``: stop at the first output that differs (``flowrt replay --check``).
    A timed replay (``deterministic=False``) is ``flowrt replay`` / the ``replay`` node kind.
    """
    if not deterministic:
        raise ValueError(
            "flowrt.replay re-executes a deterministic recording; for a timed replay use "
            "`flowrt replay --graph` or the replay node kind"
        )
    return Replay(session, graph, inline=inline, stop_at_divergence=stop_at_divergence)
