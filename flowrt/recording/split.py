"""When a recording starts a new file: ``--split-size 4GiB`` / ``--split-duration 10m``.

A long recording in one file is awkward: a 200 GB file cannot be copied in pieces, opened
quickly, or lost partly. So a session may hold several MCAP files, *parts*
(``drive_001/drive_001_000.mcap``, ``drive_001_001.mcap`` ...), each complete, indexed and
standalone (its own schemas, channels, metadata and attachments), like rosbag2's
``max_bagfile_size`` / ``max_bagfile_duration`` splitting. The writer thread starts the next
part before the message that would take the current one past the size, or whose log time is
``duration`` or more after the part's first message; the event loop never waits for it.

Sizes read like ``4GiB``, ``500MB``, ``1.5G`` (a bare ``K``/``M``/``G`` is binary, as ``ls
-h`` and ``dd`` use it; ``KB``/``MB``/``GB`` are decimal); durations like ``10m``, ``30s``,
``1h``, ``500ms`` (a bare number is seconds).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from ..graph.spec import parse_seconds

__all__ = ["MIN_SPLIT_SIZE", "SplitPolicy", "parse_duration", "parse_size", "part_path"]

MIN_SPLIT_SIZE = 64 << 10
"""Smallest part size: below it a part would hold little more than its metadata."""

_SIZE = re.compile(r"^\s*(?P<num>\d+(?:\.\d*)?|\.\d+)\s*(?P<unit>[A-Za-z]*)\s*$")
_SIZE_UNITS = {
    "": 1,
    "b": 1,
    "k": 1 << 10,
    "kib": 1 << 10,
    "kb": 10**3,
    "m": 1 << 20,
    "mib": 1 << 20,
    "mb": 10**6,
    "g": 1 << 30,
    "gib": 1 << 30,
    "gb": 10**9,
    "t": 1 << 40,
    "tib": 1 << 40,
    "tb": 10**12,
}


def parse_size(text: str) -> int:
    """Bytes of ``4GiB``, ``500MB``, ``1.5G``, ``65536``; ValueError with the reason."""
    if text.startswith("-"):
        raise ValueError(f"{text!r}: must be more than 0 (a part's size)")
    m = _SIZE.match(text)
    unit = m.group("unit").lower() if m else ""
    if m is None or unit not in _SIZE_UNITS:
        raise ValueError(f"{text!r} is not a size (e.g. 4GiB, 500MB, 1.5G)")
    n = float(m.group("num")) * _SIZE_UNITS[unit]
    if not math.isfinite(n) or n < MIN_SPLIT_SIZE:
        raise ValueError(f"{text!r}: a part must hold at least {MIN_SPLIT_SIZE >> 10} KiB")
    return int(n)


def parse_duration(text: str) -> float:
    """Seconds of ``10m``, ``30s``, ``1h``, ``500ms``, ``90``; ValueError with the reason."""
    s = parse_seconds(text.removeprefix("-"))
    if s <= 0 or text.startswith("-"):
        raise ValueError(f"{text!r}: must be more than 0 (a part's length)")
    return s


@dataclass(frozen=True)
class SplitPolicy:
    """When to start the next part: past ``size`` bytes or ``duration`` seconds (either)."""

    size: int | None = None
    duration: float | None = None

    @property
    def active(self) -> bool:
        return self.size is not None or self.duration is not None

    def due(self, part_bytes: int, part_start: float | None, message: int, t: float) -> bool:
        """True when a message of ``message`` bytes logged at ``t`` belongs in a new part.

        Never for a part's first message: a message larger than the size gets a part of its
        own rather than an endless run of empty ones.
        """
        if part_start is None:
            return False
        if self.size is not None and part_bytes + message > self.size:
            return True
        return self.duration is not None and t - part_start >= self.duration


def part_path(base: str, index: int) -> str:
    """``drive_001.mcap`` -> ``drive_001_000.mcap`` (part 0), ``drive_001_001.mcap`` ..."""
    stem = base[: -len(".mcap")] if base.endswith(".mcap") else base
    return f"{stem}_{index:03d}.mcap"
