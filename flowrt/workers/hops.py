"""Worker-to-worker hops: a frame sent straight to the worker of the node that reads it.

A hop of a worker pipeline goes worker -> loop -> worker: two wake-ups of a sleeping process
and the loop's own turn between (measured on the 8-relay pipe of the peer benchmark, 30 Hz:
~110 us of the loop's Python and ~25 us of its write a hop, besides the wake-ups; RESULTS.md).
When the loop has decided ahead that the reader runs on the writer's next value
(:mod:`flowrt.kernel.hops`), it sends the reader's call at once with its input marked
``FromPeer(tag)``, and the writer's call with a :data:`Forward`: the writer's worker sends
the value (a slot descriptor, ~150 bytes) straight to the reader's worker, which runs on it
at once. The loop is off the path: it still publishes the value to every reader, counts and
records it as always, from the writer's reply, which it gets in parallel.

Only frames that already carry their time stamp are sent this way (the loop stamps the others
when it publishes them); anything else goes as a skip (``(tag, None)``) and the reader's call
returns ``R_SKIP``: the kernel then sends it the usual way.

Each worker listens on an abstract AF_UNIX address named after the runtime's pid and its
own (Linux; nothing on the file system to clean up); a writer connects on its first hop. An
abstract address has no file permissions, so both ends check the other's user id
(``SO_PEERCRED``): a process of another user is neither heard (a pickle is code) nor told.
"""

from __future__ import annotations

import os
import pickle
import select
import socket
import struct
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..frames import Frame
from ..frames.lending import WorkerSlots
from ..ipc import PICKLE, BlockingConn, frame
from .wire import OP_SKIP

__all__ = ["SKIPPED", "Forward", "FromPeer", "Hops", "address"]


@dataclass(frozen=True, slots=True)
class FromPeer:
    """An input value to come from the worker of the node that writes it (its hop's tag)."""

    tag: int


# Where a call's output goes: (the reader's worker's address, the tag its call waits for, the
# writer's output port, None when it has one output and the result is its value).
Forward = tuple[str, int, str | None]


class _Skipped:
    def __repr__(self) -> str:
        return "SKIPPED"


SKIPPED: Any = _Skipped()  # a call's input from another worker did not come (R_SKIP)


def address(main_pid: int, worker_pid: int) -> str | None:
    """The abstract address a worker listens on for hops (None: not Linux, no hops)."""
    if not sys.platform.startswith("linux"):
        return None
    return f"\0flowrt-hop-{main_pid}-{worker_pid}"


class Hops:
    """A worker's ends of its hops: its listener, and its connections to and from others."""

    def __init__(self, main_pid: int) -> None:
        self.listener: socket.socket | None = None
        addr = address(main_pid, os.getpid())
        if addr is not None:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.bind(addr)
                s.listen(64)
            except OSError:
                s.close()
            else:
                self.listener = s
        self.inbound: dict[int, BlockingConn] = {}  # by fd: writers that sent to us
        self.outbound: dict[str, BlockingConn | None] = {}  # by address (None: unreachable)

    # -- the writer's side ---------------------------------------------------------------

    def forward(self, to: Forward, result: Any, slots: WorkerSlots) -> None:
        """Send the output ``to`` names to the reader's worker (a skip when it is not a
        stamped frame, or cannot go)."""
        addr, tag, port = to
        value = result.get(port) if port is not None and isinstance(result, Mapping) else result
        data = None
        if isinstance(value, Frame) and value.timestamp != 0.0:
            slots.reply(result)  # the output values take their slots now (the reply's too)
            try:
                data = pickle.dumps((tag, value), PICKLE)
            except Exception:
                data = None
        self._send(addr, data if data is not None else pickle.dumps((tag, None), PICKLE))

    def skip(self, to: Forward | None) -> None:
        """The writer's call ended without its value: the reader's worker stops waiting."""
        if to is not None:
            self._send(to[0], pickle.dumps((to[1], None), PICKLE))

    def _send(self, addr: str, data: bytes) -> None:
        conn = self.outbound.get(addr)
        if conn is None and addr not in self.outbound:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.connect(addr)
            except OSError:
                s.close()  # the reader's worker is gone: the loop tells its call (OP_SKIP)
            else:
                conn = BlockingConn(s) if _same_user(s) else None
                if conn is None:
                    s.close()
            self.outbound[addr] = conn
        if conn is not None and not conn.send(data):
            conn.sock.close()
            self.outbound[addr] = None

    # -- the reader's side ---------------------------------------------------------------

    def wait(self, tag: int, loop: BlockingConn) -> Any:
        """The value hop ``tag`` brings, or SKIPPED: the writer skipped it, or the loop said
        it will not come (OP_SKIP), or the loop is gone. Stale values (earlier tags) are
        dropped; a request of the loop's other than OP_SKIP is left for the main loop."""
        listener = self.listener
        if listener is None:
            return SKIPPED  # nobody can reach us (the address was taken): the usual way
        poller = select.poll()
        poller.register(listener, select.POLLIN)
        poller.register(loop.sock, select.POLLIN)
        for fd in self.inbound:
            poller.register(fd, select.POLLIN)
        while True:
            got = self._buffered(tag, loop)
            for fd, _ in poller.poll() if got is _NOT_YET else ():
                if fd == listener.fileno():
                    self._accept(listener, poller)
                elif fd == loop.sock.fileno():
                    got = self._from_loop(loop, tag)
                elif fd in self.inbound:
                    got = self._take(self.inbound[fd], tag, fd, poller)
                if got is not _NOT_YET:
                    break
            if got is not _NOT_YET:
                return got

    def _buffered(self, tag: int, loop: BlockingConn) -> Any:
        """What whole messages already read say (several may come in one read)."""
        for conn in list(self.inbound.values()):
            while conn.complete():
                got = self._take(conn, tag)
                if got is not _NOT_YET:
                    return got
        return self._from_loop(loop, tag) if loop.complete() else _NOT_YET

    def _accept(self, listener: socket.socket, poller: Any) -> None:
        s, _addr = listener.accept()
        if not _same_user(s):
            s.close()
            return
        self.inbound[s.fileno()] = BlockingConn(s)
        poller.register(s.fileno(), select.POLLIN)

    def _take(self, conn: BlockingConn, tag: int, fd: int = -1, poller: Any = None) -> Any:
        raw = conn.recv()
        if raw is None:  # the writer's worker is gone (the loop tells us if our call waits)
            conn.sock.close()
            self.inbound.pop(fd, None)
            if poller is not None:
                poller.unregister(fd)
            return _NOT_YET
        got_tag, value = pickle.loads(raw)
        if got_tag != tag:
            return _NOT_YET  # a stale hop (its call was skipped by the loop)
        return SKIPPED if value is None else value

    def _from_loop(self, loop: BlockingConn, tag: int) -> Any:
        raw = loop.recv()
        if raw is None:
            return SKIPPED  # the runtime is gone: the main loop sees the end of file next
        msg = pickle.loads(raw)
        if msg[0] == OP_SKIP:
            return SKIPPED if msg[1] == tag else _NOT_YET
        loop.buf[0:0] = frame(raw)  # a request: the main loop's, after this call
        return SKIPPED


_NOT_YET: Any = object()
_CREDS = struct.Struct("3i")  # struct ucred: pid, uid, gid


def _same_user(s: socket.socket) -> bool:
    """The process at the other end runs as our user."""
    try:
        _pid, uid, _gid = _CREDS.unpack(
            s.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _CREDS.size)
        )
    except OSError:
        return False
    return bool(uid == os.getuid())
