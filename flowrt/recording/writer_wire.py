"""The wire between a recorder and its writer process: length-prefixed pickles, both ways.

One AF_UNIX stream socketpair per writer process. Each message is a 4-byte little-endian
length and a pickle of a tuple whose first item names it. A frame in a shared-memory slot
pickles to the descriptor of its slot (:mod:`flowrt.frames`), so a 1936x1216 frame costs the
socket ~200 bytes: the writer process maps the slot and reads the pixels where they are.
Every other value is encoded on the recorder's side (its message bytes travel, a few hundred
bytes for a detection), so that the writer process never needs the value's class.

Recorder -> writer, in this order over a session:

- ``(OPEN, config, metadata, attachments)``: the ``RecordingWriter`` keyword arguments, then
  what ``RecordingWriter.open`` takes; answered by ``(OPENED, None | (errno, strerror,
  filename))``.
- ``(DECLARE, topic, meta)``: a stream and its channel metadata (``source`` included).
- ``(MESSAGE, id, topic, value, t, seq)``: ``value`` a :class:`~flowrt.frames.Frame` or an
  :class:`~.encoding.Encoded`; ``id`` numbers the messages of the session from 0.
- ``(DETACH,)``: copy every frame not read yet off its slot, then say ``DETACHED``: from then
  on the writer holds no slot (the runtime may free its pools).
- ``(CLOSE,)``: write what is queued, then say ``DRAINED`` and wait for ``(ATTACH,
  attachments)`` (the per-stream report, which needs every result), then finish the file and
  say ``FINISHED``.

Writer -> recorder:

- ``(ACKS, released, results, error)``: ``released`` the ids of frames whose slot the writer
  no longer reads (their link goes back), ``results`` ``(id, nbytes, part)`` per message
  (``nbytes`` -1: not written; ``part`` the index of the file it went into), ``error`` the
  write error that stopped the file, or None.
- ``(DETACHED,)``, ``(DRAINED,)``, ``(FINISHED, error, notes, files, part_messages)``.

End of file on either side means the other process is gone.
"""

from __future__ import annotations

import contextlib
import pickle
import socket
import struct
from typing import Any

__all__ = ["HDR", "PICKLE", "Framer", "pack", "recv_message", "send_message"]

HDR = struct.Struct("<I")
PICKLE = pickle.HIGHEST_PROTOCOL

OPEN = "open"
DECLARE = "declare"
MESSAGE = "msg"
DETACH = "detach"
CLOSE = "close"
ATTACH = "attach"
OPENED = "opened"
ACKS = "acks"
DETACHED = "detached"
DRAINED = "drained"
FINISHED = "finished"


def pack(msg: tuple[Any, ...]) -> bytes:
    """One message, ready for the socket."""
    data = pickle.dumps(msg, PICKLE)
    return HDR.pack(len(data)) + data


class Framer:
    """Bytes from a socket in, whole messages out (their pickles; unpickled by the caller)."""

    def __init__(self) -> None:
        self._buf = bytearray()

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


def recv_message(sock: socket.socket, framer: Framer, pending: list[bytes]) -> bytes | None:
    """The next message of a blocking socket (``pending``: messages read ahead); None at EOF."""
    while not pending:
        try:
            chunk = sock.recv(1 << 16)
        except (ConnectionResetError, OSError):
            return None
        if not chunk:
            return None
        pending.extend(framer.feed(chunk))
    return pending.pop(0)


def send_message(sock: socket.socket, msg: tuple[Any, ...]) -> bool:
    """Send on a blocking socket; False when the other side is gone."""
    with contextlib.suppress(BrokenPipeError, ConnectionResetError, OSError):
        sock.sendall(pack(msg))
        return True
    return False
