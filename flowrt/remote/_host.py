"""The runtime as the Zenoh bridge sees it: :class:`BridgeHost`, and :class:`RemoteHost`."""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Protocol

from ..clock import Clock
from ..edges import Buffer
from ..events import Event
from ..frames import Frame
from ..graph._resolve import Graph
from ..kernel import Scheduler


class BridgeHost(Protocol):
    """What the bridge needs from the runtime (kept narrow: the runtime owns it)."""

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    def now_mono(self) -> float: ...

    def runner_output(self, node: str, port: str) -> list[Buffer]: ...

    def add_buffer(self, buf: Buffer) -> None: ...

    def publish(self, node: str, port: str, value: Any) -> None: ...

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pf: str) -> Frame: ...

    def import_node(self, name: str) -> Any: ...

    def is_frame_port(self, node: str, port: str) -> bool: ...

    def emit(self, event: Event) -> None: ...

    def record(self, name: str, value: Any, validity_ms: float | None) -> None: ...


class BridgedRuntime(Protocol):
    """What the bridge's host reads of the runtime (this module does not import it)."""

    @property
    def graph(self) -> Graph: ...

    @property
    def scheduler(self) -> Scheduler: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def rtdb(self) -> Any: ...

    def emit(self, event: Event) -> None: ...


log = logging.getLogger("flowrt")


class RemoteHost:
    """The runtime as the Zenoh bridge sees it (a :class:`BridgeHost`)."""

    def __init__(self, rt: BridgedRuntime) -> None:
        self.rt = rt

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        return self.rt.scheduler.loop

    def now_mono(self) -> float:
        return self.rt.clock.now()

    def runner_output(self, node: str, port: str) -> list[Buffer]:
        return self.rt.scheduler.runners[node].outputs[port]

    def add_buffer(self, buf: Buffer) -> None:
        self.rt.scheduler.buffers.append(buf)

    def publish(self, node: str, port: str, value: Any) -> None:
        self.rt.scheduler.runners[node].publish(port, value, self.rt.clock.now())

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pf: str) -> Frame:
        return self.rt.scheduler.new_frame(owner, shape, dtype, pf)

    def import_node(self, name: str) -> Any:
        return getattr(self.rt.scheduler.runners[name].executor, "node", None)

    def emit(self, event: Event) -> None:
        self.rt.emit(event)

    def record(self, name: str, value: Any, validity_ms: float | None) -> None:
        try:
            self.rt.rtdb.write(name, value, validity_ms=validity_ms)
        except Exception as e:  # a value the RTDB cannot hold: the edge still has it
            log.debug("RTDB record %s: %s", name, e)

    def is_frame_port(self, node: str, port: str) -> bool:
        return port in self.rt.graph.nodes[node].cls.frame_ports()
