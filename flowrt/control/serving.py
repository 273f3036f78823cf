"""Serving HTTP from a process of its own, beside a runtime: what every such server shares.

The control endpoint (:mod:`flowrt.control.server`) and the live view (the ``display`` node) serve
their clients from a child process, so that a flood of clients costs the event loop neither
time nor the GIL. Both talk to their side in the runtime over a socket pair with the same
framing, guard their ``Host`` the same way, run at the same low priority and count and time
out their connections the same way; this public module is that common part, for them and for
a third-party node that serves HTTP the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import os
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from ..system._spawned import ignore_interrupts

FRAME = struct.Struct(">II")  # header length, body length
NICE = 19  # a server's nice level: it gets the CPU the graph leaves


def pack(header: dict[str, Any], body: bytes = b"") -> bytes:
    """One message on the channel: a JSON header and an opaque body, both length-prefixed."""
    head = json.dumps(header).encode()
    return FRAME.pack(len(head), len(body)) + head + body


async def unpack(reader: asyncio.StreamReader) -> tuple[dict[str, Any], bytes]:
    """The next message :func:`pack` wrote (IncompleteReadError when the other side is gone)."""
    hlen, blen = FRAME.unpack(await reader.readexactly(FRAME.size))
    header = json.loads(await reader.readexactly(hlen))
    return header, (await reader.readexactly(blen) if blen else b"")


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses; any other name counts as exposed."""
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def hostname(host: str) -> str:
    """The name in a Host header, without its port."""
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def lower_priority(pid: int) -> None:
    """SCHED_OTHER at nice :data:`NICE` (``0``: this process). Called by the parent right after
    the start too: the child's own imports would otherwise run at the loop's priority."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))  # never the loop's FIFO
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, pid, NICE)


class ServerSide(Protocol):
    """What :func:`serve_in_process` runs: serves ``sock`` until ``channel`` ends."""

    async def run(self, sock: socket.socket, channel: socket.socket) -> None: ...


def serve_in_process(
    make: Callable[[dict[str, Any]], ServerSide],
    sock: socket.socket,
    channel: socket.socket,
    settings: dict[str, Any],
) -> None:
    """The body of a server's process: below the runtime's priority, Ctrl-C left to the
    runtime (which stops it by ending the channel), ``make(settings)`` served until then."""
    ignore_interrupts()  # started with SIGINT blocked (flowrt/system/_spawned.py)
    lower_priority(0)

    async def main() -> None:
        await make(settings).run(sock, channel)

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())


async def stop_server(
    writer: asyncio.StreamWriter | None,
    task: asyncio.Task[Any] | None,
    proc: Any,
    grace: float,
) -> None:
    """End a server process: close its channel (it closes its clients and exits), stop the
    task answering it, give the process ``grace`` seconds, then kill it."""
    if writer is not None:
        writer.close()
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
    if proc is not None:
        await asyncio.to_thread(proc.join, grace)
        if proc.is_alive():
            proc.kill()
            await asyncio.to_thread(proc.join, 0.5)


@dataclass
class Conn:
    """An open connection: when it must have sent its next request, and if one is running."""

    transport: asyncio.BaseTransport
    deadline: float
    busy: int = 0
    next_read: float = 0.0  # for servers that pace reads: none answered before this
    requests: int = 0  # requests answered on it: 0 = it has not earned its slot yet
    reserve: bool = False  # taken over the cap: only a request with the token may keep it
    # A request's headers are all in (their blank line seen): it is answered, however late
    # this low-priority process gets to it; only a client still sending headers times out.
    headers_in: bool = False
    tail: bytes = b""  # the last bytes received: a blank line split across two reads

    def received(self, data: bytes) -> None:
        if not self.headers_in:
            seen = self.tail + data
            self.headers_in = b"\r\n\r\n" in seen
            self.tail = seen[-3:]

    def answered(self, timeout: float) -> None:
        """A request done: the next one has ``timeout`` for its headers."""
        self.headers_in, self.tail = False, b""
        self.deadline = time.monotonic() + timeout

    def late(self, now: float) -> bool:
        """Past its deadline with no request under way: the sweeper closes it."""
        return not self.busy and not self.headers_in and now > self.deadline


class Conns(dict[asyncio.BaseTransport, Conn]):
    """The open connections by transport, and how many were accepted but are not made yet.

    A burst of connections is accepted in one go: the loop calls the protocol factory for
    each before any ``connection_made`` runs, so a cap that counted only the made ones let a
    burst through (three open under a cap of two, and the wrong one evicted next).
    """

    def __init__(self) -> None:
        super().__init__()
        self.pending = 0  # Tracked protocols made by the factory, connection_made not yet run

    def count(self) -> int:
        """Connections that hold a slot: made or about to be."""
        return len(self) + self.pending


class Tracked(asyncio.Protocol):
    """Wraps aiohttp's protocol for one connection, registered in ``conns`` while it is open
    (a sweeper closes the ones past their deadline; a cap counts them)."""

    def __init__(
        self,
        inner: Any,
        conns: Conns,
        timeout: float,
        reserve: bool = False,
    ):
        self.inner = inner
        self.conns = conns
        self.timeout = timeout
        self.reserve = reserve
        self.transport: asyncio.BaseTransport | None = None
        conns.pending += 1  # holds its slot from now: see Conns

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        self.conns.pending = max(0, self.conns.pending - 1)
        conn = Conn(transport, time.monotonic() + self.timeout, reserve=self.reserve)
        self.conns[transport] = conn
        self.inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is not None:
            self.conns.pop(self.transport, None)
        self.inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        conn = self.conns.get(self.transport) if self.transport is not None else None
        if conn is not None:
            conn.received(data)
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received()  # type: ignore[no-any-return]

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


class Refuse(asyncio.Protocol):
    """Over the connection cap: closed at once (the client sees the connection reset)."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.close()
