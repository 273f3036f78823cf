"""The live view's frames as shown: per source, the newest frame encoded once, shared by all.

The display node lends a source's pixels (``frame`` on the channel); they are encoded here in
a thread, the newest only when frames come faster than the encoder, and the JPEGs (and the
WebSocket message) are kept for every client of the view: the work per frame does not grow
with the number of clients. A client wanting a newer frame than the one held asks for it
(``want``, once per frame), so the node lends pixels only while someone watches.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import pickle
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .render import Mark, render


@dataclass
class Shown:
    """One source as this process knows it: its newest encoded frame, shared by all."""

    name: str
    n: int = 0  # the node's count of the frame held here (0: none yet)
    header: dict[str, Any] = field(default_factory=dict)
    raw: bytes = b""
    processed: bytes = b""
    message: bytes = b""  # the websocket message, built once
    failed: str = ""  # why frame n could not be shown (empty: it could)
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    pending: tuple[dict[str, Any], bytes] | None = None  # pixels waiting for the encoder
    encoding: bool = False
    encodes: int = 0


class ShownFrames:
    """Every source's :class:`Shown`, the encoding of lent pixels and the ``want`` requests."""

    def __init__(self, send: Callable[[dict[str, Any]], None], any_change: asyncio.Event) -> None:
        self._send = send
        self.any_change = any_change  # set on every new frame (the view's feeds wait on it)
        self.sources: dict[str, Shown] = {}
        self._asked: dict[str, int] = {}  # source -> the n a ``want`` was sent after

    def source(self, name: str) -> Shown:
        src = self.sources.get(name)
        if src is None:
            src = self.sources[name] = Shown(name)
        return src

    def frame(self, header: dict[str, Any], body: bytes) -> None:
        """Pixels from the node: encoded once (the newest, when frames come faster)."""
        src = self.source(header["source"])
        src.pending = (header, body)
        if not src.encoding:
            src.encoding = True
            asyncio.get_running_loop().create_task(self._encode(src))

    async def _encode(self, src: Shown) -> None:
        try:
            while src.pending is not None:
                header, pixels = src.pending
                src.pending = None
                try:
                    raw, processed = await asyncio.to_thread(_render, header, pixels)
                except Exception as e:
                    self._send({"op": "done", "source": src.name})
                    if not src.failed:
                        print(f"display: cannot show {src.name} frames: {e}", flush=True)
                    src.n, src.failed = int(header["n"]), str(e) or type(e).__name__
                    self.changed(src)
                    continue
                shown = {k: v for k, v in header.items() if k not in ("op", "dtype", "quality")}
                same = processed is raw
                shown["raw"], shown["processed"] = len(raw), 0 if same else len(processed)
                self._send({"op": "done", "source": src.name})
                head = json.dumps(shown).encode()
                src.n, src.header, src.failed = int(header["n"]), shown, ""
                src.raw, src.processed = raw, processed
                src.message = b"".join(
                    (struct.pack(">I", len(head)), head, raw, b"" if same else processed)
                )
                src.encodes += 1
                self.changed(src)
        finally:
            src.encoding = False

    def changed(self, src: Shown) -> None:
        self._asked.pop(src.name, None)
        src.changed.set()
        src.changed = asyncio.Event()
        self.any_change.set()

    def want(self, name: str, after: int) -> None:
        """Ask the node for a frame of ``name`` newer than ``after`` (once per ``after``)."""
        if self._asked.get(name) != after:
            self._asked[name] = after
            self._send({"op": "want", "source": name, "after": after})

    async def newer(self, name: str, after: int, wait: float) -> Shown | None:
        """The source once it holds a frame newer than ``after`` (or a failure), else None."""
        src = self.source(name)
        end = time.monotonic() + wait
        while src.n <= after:
            self.want(name, after)
            left = end - time.monotonic()
            if left <= 0:
                return None
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(src.changed.wait(), left)
        return src


def _render(header: dict[str, Any], frame: bytes) -> tuple[bytes, bytes]:
    """Both JPEGs of a frame the node lent (a descriptor of a shared-memory slot: mapped here)."""
    data = pickle.loads(frame).data
    marks = [
        Mark(
            label=m["label"],
            found=m["found"],
            bbox=None if m["bbox"] is None else tuple(m["bbox"]),
            centroid=None if m["centroid"] is None else tuple(m["centroid"]),
            confidence=m["confidence"],
        )
        for m in header["marks"]
    ]
    return render(data, header["pixel_format"], marks, int(header["quality"]))
