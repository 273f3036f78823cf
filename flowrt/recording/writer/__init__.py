"""The recording writer: MCAP files written off the event loop, by threads or a process.

Laid out like :mod:`flowrt.workers` (the recorder's side, the child, what they say):

- :mod:`.protocol`: :class:`Writer`, what a recorder may ask of either writer
- :mod:`.threads`: :class:`RecordingWriter`, the encoder and disk threads, per-stream
  counters; the writer itself, whichever process it runs in
- :mod:`.channel`: :class:`ProcessRecordingWriter`, the recorder's side of a writer process
  (the recorder's default): the same interface, the work off the runtime's GIL
- :mod:`.child`: the writer process, running a :class:`RecordingWriter` for its recorder
- :mod:`.wire`: what the two say to each other, framed by the process wire (:mod:`flowrt.ipc`)
"""

from typing import TYPE_CHECKING

from .channel import ProcessRecordingWriter as ProcessRecordingWriter
from .protocol import Writer as Writer
from .threads import THREAD_PREFIX as THREAD_PREFIX
from .threads import RecordingWriter as RecordingWriter
from .threads import StreamCounters as StreamCounters
from .threads import count_written as count_written

__all__ = [
    "THREAD_PREFIX",
    "ProcessRecordingWriter",
    "RecordingWriter",
    "StreamCounters",
    "Writer",
    "count_written",
]

if TYPE_CHECKING:  # mypy --strict checks here that both writers keep the protocol

    def _both(a: RecordingWriter, b: ProcessRecordingWriter) -> tuple[Writer, Writer]:
        return a, b
