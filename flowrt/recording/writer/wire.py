"""What a recorder and its writer process say to each other, both ways.

One AF_UNIX stream socketpair per writer process, framed as every process the runtime forks
(:mod:`flowrt.ipc`: length-prefixed pickles); each message is a tuple whose first item names
it (below). A frame in a shared-memory slot pickles to the descriptor of its slot
(:mod:`flowrt.frames`), so a 1936x1216 frame costs the socket ~200 bytes: the writer process
maps the slot and reads the pixels where they are.
Every other value is encoded on the recorder's side (its message bytes travel, a few hundred
bytes for a detection), so that the writer process never needs the value's class.

Recorder -> writer, in this order over a session:

- ``(OPEN, config, metadata, attachments)``: the ``RecordingWriter`` keyword arguments, then
  what ``RecordingWriter.open`` takes; answered by ``(OPENED, None | (errno, strerror,
  filename))``.
- ``(DECLARE, topic, meta)``: a stream and its channel metadata (``source`` included).
- ``(MESSAGE, id, topic, value, t, seq)``: ``value`` a :class:`~flowrt.frames.Frame` or an
  :class:`~flowrt.recording.encoding.Encoded`; ``id`` numbers the messages of the session from 0.
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

__all__ = [
    "ACKS",
    "ATTACH",
    "CLOSE",
    "DECLARE",
    "DETACH",
    "DETACHED",
    "DRAINED",
    "FINISHED",
    "MESSAGE",
    "OPEN",
    "OPENED",
]

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
