"""A host program's own reader of a port: values through a buffer of its own, counted."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

from ..edges import EMPTY, Buffer
from ..frames import Frame


class Subscription:
    """Values published on a port, delivered to the host program through its own buffer.

    Closed when the run ends (:meth:`close`): ``async for`` ends and ``get()`` raises
    LookupError, where both waited for ever before (a program's reader task hung after its
    runtime had stopped). The stop empties the buffer first (a frame's shared memory goes
    with the run)."""

    def __init__(self, buf: Buffer) -> None:
        self._buf = buf
        self._ready = asyncio.Event()
        self.closed = False  # set once: no value will be put after it
        buf.on_put = self._ready.set

    def close(self) -> None:
        """No value will come any more (the runtime stopped): wake every waiting reader."""
        self.closed = True
        self._ready.set()

    def get_nowait(self) -> Any:
        """The next value, or raise LookupError when none is waiting."""
        value = self._buf.take_new()  # type: ignore[attr-defined]
        if value is EMPTY:
            raise LookupError("no value waiting")
        if isinstance(value, Frame):
            value.release()  # the host keeps a plain reference; the slot may be reused later
        return value

    def take_held(self) -> Any:
        """The next value with its frame link kept (the caller must ``release()`` it), or EMPTY.

        For a monitor that hands frames to another thread: the pool slot is not recycled
        before that thread is done with the pixels.
        """
        return self._buf.take_new()  # type: ignore[attr-defined]

    def drain(self) -> list[Any]:
        """Every value waiting now, oldest first (the newest only, for a latest buffer)."""
        out = []
        while self._buf.pending():
            out.append(self.get_nowait())
        return out

    async def get(self) -> Any:
        """The next value, waiting for it; LookupError once the run has ended and none is
        waiting."""
        while not self._buf.pending():
            if self.closed:
                raise LookupError("no value waiting, and none will come: the run has ended")
            self._ready.clear()
            await self._ready.wait()
        return self.get_nowait()

    def __aiter__(self) -> AsyncIterator[Any]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[Any]:
        while True:
            try:
                value = await self.get()
            except LookupError:  # the run has ended: so does the iteration
                return
            yield value

    @property
    def dropped(self) -> int:
        return self._buf.dropped
