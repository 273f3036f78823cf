"""The process wire: length-prefixed pickles over an AF_UNIX stream socketpair.

Every process the runtime forks (a worker, :mod:`flowrt.workers`; a recording writer,
:mod:`flowrt.recording.writer`) talks to it over one socketpair with this framing: a 4-byte
little-endian length, then a pickle (highest protocol) of a tuple whose first item says what
it is. What the tuples mean is each protocol's own (``workers/wire.py``,
``recording/writer/wire.py``); how they travel is here, once.

Frames in a shared-memory slot pickle to the descriptor of their slot (:mod:`flowrt.frames`),
so a 1080p frame costs the socket ~200 bytes. The runtime's side reads without blocking (an
asyncio protocol or ``loop.add_reader``, feeding a :class:`Framer`); the child's side is a
plain blocking socket (:class:`BlockingConn`). End of file on either side means the other
process is gone: ``recv`` returns None and ``send`` False, never an exception, since a peer
that died is an event both sides handle, not an error of the wire.
"""

from __future__ import annotations

import contextlib
import pickle
import socket
import struct
from typing import Any

__all__ = ["HDR", "PICKLE", "BlockingConn", "Framer", "frame", "pack"]

HDR = struct.Struct("<I")
PICKLE = pickle.HIGHEST_PROTOCOL


def frame(payload: bytes) -> bytes:
    """A pickled message with its length in front, ready for the socket."""
    return HDR.pack(len(payload)) + payload


def pack(msg: tuple[Any, ...]) -> bytes:
    """One message, pickled and framed."""
    return frame(pickle.dumps(msg, PICKLE))


class Framer:
    """Bytes from a non-blocking socket in, whole messages out (their pickles; the caller
    unpickles, so that a message it cannot read is its own business, not the stream's)."""

    def __init__(self, ahead: bytes = b"") -> None:
        self._buf = bytearray(ahead)

    def rest(self) -> bytes:
        """The bytes of a message not complete yet (for a :class:`BlockingConn` taking over)."""
        return bytes(self._buf)

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        out: list[bytes] = []
        start = 0
        while len(buf) - start >= 4:
            (n,) = HDR.unpack_from(buf, start)
            if len(buf) - start < 4 + n:
                break
            out.append(bytes(buf[start + 4 : start + 4 + n]))
            start += 4 + n
        if start:
            del buf[:start]
        return out


class BlockingConn:
    """A blocking end of the socketpair (the child's; the runtime's while it opens or closes
    a writer process, off the loop): blocking reads of whole messages, sends that say
    False when the runtime is gone (the next ``recv`` then sees the end of file).

    ``buf`` holds bytes read ahead (``ahead``: from a :class:`Framer` that read the socket
    before, its :meth:`Framer.rest`); a caller that polls the socket itself (a worker spinning
    for a call it expects, :mod:`flowrt.workers.child`) appends what it reads there.
    """

    def __init__(self, sock: socket.socket, ahead: bytes = b"") -> None:
        self.sock = sock
        self.buf = bytearray(ahead)

    def complete(self) -> bool:
        """A whole message is buffered: ``recv`` returns without reading the socket."""
        buf = self.buf
        return len(buf) >= 4 and len(buf) >= 4 + HDR.unpack_from(buf)[0]

    def recv(self) -> bytes | None:
        """The next message's pickle; None at the end of file (or a reset: the peer died)."""
        buf = self.buf
        while True:
            if len(buf) >= 4:
                (n,) = HDR.unpack_from(buf)
                if len(buf) >= 4 + n:
                    msg = bytes(buf[4 : 4 + n])
                    del buf[: 4 + n]
                    return msg
                want = 4 + n - len(buf)
            else:
                want = 4
            try:
                chunk = self.sock.recv(max(want, 1 << 16))
            except OSError:  # reset (the peer was killed) or a timeout: as the end of file
                return None
            if not chunk:
                return None
            buf += chunk

    def recv_message(self) -> tuple[Any, ...] | None:
        """The next message, unpickled; None at the end of file."""
        raw = self.recv()
        return None if raw is None else pickle.loads(raw)

    def send(self, payload: bytes) -> bool:
        """Send one pickled message; False when the other side is gone."""
        with contextlib.suppress(OSError):
            self.sock.sendall(frame(payload))
            return True
        return False

    def send_message(self, msg: tuple[Any, ...]) -> bool:
        """Pickle and send one message; False when the other side is gone."""
        return self.send(pickle.dumps(msg, PICKLE))
