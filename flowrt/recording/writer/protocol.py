"""What a recorder may ask of a writer, whichever writes the file: its threads or a process.

:class:`~.threads.RecordingWriter` (threads in the runtime's process) and
:class:`~.channel.ProcessRecordingWriter` (a process of its own, the recorder's default)
implement it; the ``recorder`` node, the report and the benchmark hold a :class:`Writer`
and never ask which. The contract both keep: ``submit`` never blocks the loop (it counts and
queues; a refusal is counted against its stream, never silent), a frame submitted holds one
link of the caller's until it comes back through ``done``, and ``request_close`` then
``join`` leaves every message either written or counted as lost.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from ...frames import Frame
from .threads import StreamCounters

__all__ = ["Writer"]


@runtime_checkable
class Writer(Protocol):
    """An MCAP recording being written: open, declare, submit, request_close, join."""

    path: Path  # the file being written (the current part of a split recording)
    files: list[Path]  # every part so far, in order
    part_messages: list[int]  # messages written into each part
    streams: dict[str, StreamCounters]
    error: str | None  # the write error that stopped the file, once there is one
    notes: list[str]  # problems other than write errors, said once per stream
    done: deque[Frame]  # frames let go of: the caller gives their links back on the loop

    def open(
        self,
        metadata: dict[str, dict[str, str]],
        attachments: list[tuple[str, str, bytes]] = ...,
    ) -> None:
        """Create the file; OSError if it cannot be. Blocking: call it off the loop."""
        ...

    def declare(self, topic: str, source: str = "", **meta: str) -> StreamCounters:
        """Name a stream before its first message (its source ``node.port`` and metadata)."""
        ...

    def submit(self, topic: str, value: Any, t: float, seq: int) -> bool:
        """Queue a message logged at runtime-clock time ``t``; False (and counted) if refused."""
        ...

    def request_close(
        self,
        attachments: Callable[[], list[tuple[str, str, bytes]]] = ...,
        on_finished: Callable[[], None] | None = None,
    ) -> None:
        """Finish the file after what is queued, without waiting (see :meth:`join`)."""
        ...

    def join(self, timeout: float | None = None) -> bool:
        """Wait for a requested close; True when the file is finished."""
        ...

    def detach_frames(self) -> list[Frame]:
        """Let go of every shared-memory slot still queued (the pools are about to go);
        returns the frames whose links the caller gives back now."""
        ...

    def encoding_frame(self) -> bool:
        """True while a frame's slot is still being read (its link must not go back yet)."""
        ...
