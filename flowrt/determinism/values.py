"""The recorded values a replay needs, read once in file order and kept only while needed.

A replay asks for values in roughly the order they were recorded (the order of the run), so
the file is read front to back once; a value read before it is asked for waits in memory, and
is dropped once every activation that holds it has run (a count per value, from the log).
Frames come back with their recorded timestamp, sequence number and source to the bit (the
log has them exactly); other values with their own ``timestamp`` restored likewise.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..frames import Frame
from ..recording.encoding import Decoder, to_jsonable
from ..recording.reader import RecordedMessage, iter_session
from ..recording.session import mcap_files
from .log import DeterminismLog, SourceRecord

__all__ = ["RecordedValues", "show"]


class RecordedValues:
    """Values of the recording by ``(topic, index)``, with a use count each."""

    def __init__(self, log: DeterminismLog, uses: dict[tuple[str, int], int]) -> None:
        self.log = log
        self.uses = dict(uses)
        self.files = mcap_files(log.path)
        self.decoder = Decoder()
        self.cache: dict[tuple[str, int], Any] = {}
        self.counts: dict[str, int] = {}
        self._it: Iterator[RecordedMessage] | None = None
        self.read = 0
        self.sources = {(s.topic, s.index): s for s in log.sources.values()}

    def _messages(self) -> Iterator[RecordedMessage]:
        topics = {topic for topic, _ in self.uses}
        return iter_session(self.files, topics) if topics else iter([])

    def get(self, place: tuple[str, int]) -> tuple[bool, Any]:
        """(found, value) of the recorded message ``place``; one of its uses is consumed."""
        if place not in self.cache:
            self._read_until(place)
        if place not in self.cache:
            return False, None
        value = self.cache[place]
        self.release(place)
        return True, value

    def has(self, place: tuple[str, int]) -> bool:
        """The recording holds ``place`` (read up to it if needed; no use consumed)."""
        if place not in self.cache:
            self._read_until(place)
        return place in self.cache

    def _read_until(self, place: tuple[str, int]) -> None:
        if self._it is None:
            self._it = self._messages()
        for m in self._it:
            index = self.counts.get(m.topic, 0)
            self.counts[m.topic] = index + 1
            at = (m.topic, index)
            if self.uses.get(at, 0) > 0:
                self.cache[at] = self.decode(m, self.sources.get(at))
                self.read += 1
                if at == place:
                    return

    def release(self, place: tuple[str, int]) -> None:
        """One use of ``place`` done (or that will not happen: its reader was given up)."""
        left = self.uses.get(place, 0) - 1
        self.uses[place] = left
        if left <= 0:
            self.cache.pop(place, None)

    def decode(self, m: RecordedMessage, src: SourceRecord | None) -> Any:
        name = m.schema.name if m.schema is not None else ""
        if self.decoder.is_image(name):
            px, fmt = self.decoder.image(m.schema, m.data)
            value: Any = Frame(np.array(px), pixel_format=fmt)
        else:
            value = self.decoder.message(name, m.data)
        return value if src is None else _restore(value, src)


def _restore(value: Any, src: SourceRecord) -> Any:
    """What the encoding rounded off, back from the log: a frame's stamps, a value's time."""
    if isinstance(value, Frame):
        f = src.frame or {}
        frame = Frame(
            value.data,
            source=str(f.get("source", value.source)),
            seq=int(f.get("seq", value.seq)),
            timestamp=float(f.get("timestamp", value.timestamp)),
            pixel_format=str(f.get("pixel_format", value.pixel_format)),
        )
        return frame
    return _with_stamp(value, src.stamp)


def _with_stamp(value: Any, stamp: float | None) -> Any:
    """``value`` with its own ``timestamp`` set back to ``stamp`` (runtime clock, seconds;
    the recording holds Unix nanoseconds), where it has one."""
    if stamp is None:
        return value
    if isinstance(value, dict):
        return {**value, "timestamp": stamp} if "timestamp" in value else value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        try:
            return dataclasses.replace(value, timestamp=stamp)
        except TypeError:
            return value
    return value


def read_one(path: Path, topic: str, index: int, stamp: float | None = None) -> Any:
    """The ``index``-th recorded message of ``topic``, decoded (None if absent): to show it
    beside a replayed value, its ``timestamp`` on the runtime clock when ``stamp`` is known."""
    decoder = Decoder()
    for n, m in enumerate(iter_session(mcap_files(path), {topic})):
        if n == index:
            name = m.schema.name if m.schema is not None else ""
            if decoder.is_image(name):
                px, fmt = decoder.image(m.schema, m.data)
                return Frame(np.array(px), pixel_format=fmt)
            return _with_stamp(decoder.message(name, m.data), stamp)
    return None


def show(value: Any, limit: int = 400) -> str:
    """A value in one line, for people: JSON of its fields, frames by their shape."""
    if isinstance(value, Frame):
        return f"Frame {value.pixel_format} {tuple(value.data.shape)} seq {value.seq}"
    try:
        text = json.dumps(to_jsonable(value), separators=(", ", ": "))
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
