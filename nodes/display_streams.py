"""MJPEG clients of the live view: how many, from whom, and how far behind each may fall.

An MJPEG stream (``/stream/SOURCE.mjpg``) holds its connection for as long as its client
wants, and a client that stops reading still gets frames written until buffers fill. Measured
on the socket alone, a stalled client was seen only once the kernel's buffers (ours and the
client's, hundreds of KB: seconds of small frames) were full, so 40 clients that never read,
reconnecting every 20 s, kept the live view full for good (issue 37 item 5). Here:

- **One frame queued per client in the application**: a frame is written only once the
  previous one has left the process; a newer frame replaces one that could not be written
  (the client gets the newest when it reads again, never a backlog).
- **Behind by more than** :data:`MAX_BEHIND` **seconds: dropped** (counted ``stalled``). How
  far behind a client is comes from what it has acknowledged: the bytes written minus those
  still in our buffer and the kernel's send queue (``SIOCOUTQ``), matched to when each frame
  was written.
- **Capped**: at most ``max_per_peer`` streams per peer address and ``max_streams`` in all
  (refused with 503, counted ``refused_streams``), so that the view's other slots (the page,
  its WebSocket, ``/stats.json``, the station's API) are never taken by streams.
"""

from __future__ import annotations

import contextlib
import fcntl
import socket
import struct
import termios
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

MAX_BEHIND = 1.0  # seconds a stream client may fall behind before it is dropped
STREAM_SNDBUF = 64 << 10  # bytes of kernel send buffer per stream: little to hide behind
MAX_PER_PEER = 4  # streams one peer address may hold at once (the display's param)


def unsent(sock: Any) -> int:
    """Bytes the kernel holds for the peer, not yet acknowledged (0 when it cannot say)."""
    if sock is None:
        return 0
    try:
        raw = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
    except (OSError, ValueError, AttributeError):
        return 0
    return int(struct.unpack("i", raw)[0])


@dataclass(eq=False)
class StreamClient:
    """One MJPEG client: the frames written to it not yet acknowledged, oldest first."""

    peer: str
    transport: Any
    sock: Any
    written: int = 0  # bytes handed to the transport in all
    frames: deque[tuple[int, float]] = field(default_factory=deque)  # (end offset, when)
    skipped: int = 0  # frames not written: the previous one had not left the process

    def ready(self) -> bool:
        """The previous frame has left the process: one more may be queued."""
        return self.transport is None or self.transport.get_write_buffer_size() == 0

    def wrote(self, size: int, now: float) -> None:
        self.written += size
        self.frames.append((self.written, now))

    def behind(self, now: float) -> float:
        """Seconds since the oldest frame the client has not taken yet was written (0: none)."""
        buffered = self.transport.get_write_buffer_size() if self.transport is not None else 0
        taken = self.written - buffered - unsent(self.sock)
        while self.frames and self.frames[0][0] <= taken:
            self.frames.popleft()
        return now - self.frames[0][1] if self.frames else 0.0


class StreamSlots:
    """Who holds a stream: at most ``max_per_peer`` per address and ``max_streams`` in all."""

    def __init__(self, max_streams: int, max_per_peer: int) -> None:
        self.max_streams = max_streams
        self.max_per_peer = max_per_peer
        self.clients: set[StreamClient] = set()
        self.refused = 0  # streams refused at a cap
        self.stalled = 0  # streams dropped: behind by more than MAX_BEHIND

    def refusal(self, peer: str, others: int = 0) -> str | None:
        """Why a new stream from ``peer`` is refused (counted), or None; ``others``: the
        page WebSockets, which share ``max_streams`` with the streams."""
        if len(self.clients) + others >= self.max_streams:
            self.refused += 1
            return f"{self.max_streams} streams already: the view keeps its other slots free"
        if sum(1 for c in self.clients if c.peer == peer) >= self.max_per_peer:
            self.refused += 1
            return f"{peer} holds {self.max_per_peer} streams already (max_streams_per_peer)"
        return None

    def open(self, peer: str, transport: Any) -> StreamClient:
        sock = transport.get_extra_info("socket") if transport is not None else None
        if sock is not None:  # a small kernel buffer: a client that stops reading shows soon
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, STREAM_SNDBUF)
        client = StreamClient(peer, transport, sock)
        self.clients.add(client)
        return client

    def close(self, client: StreamClient) -> None:
        self.clients.discard(client)

    def check(self, client: StreamClient) -> bool:
        """False (counted, the connection aborted) once ``client`` is too far behind."""
        if client.behind(time.monotonic()) <= MAX_BEHIND:
            return True
        self.stalled += 1
        if client.transport is not None:
            client.transport.abort()
        return False
