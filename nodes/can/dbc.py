"""The ``can`` node's DBC handling: finding and loading the database, encoding a message's
signals (the selected branch of a multiplexed one), and the checksums vehicles use.

Loading is :func:`flowrt.analysis.can_database.load_database`: non-strict, as cantools loads
production databases, with what strict loading would refuse logged once per problem as a
named warning (message, signal, reason); the node's ``strict: true`` refuses such a file.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from flowrt.analysis.can_database import (
    CanDatabaseError,
    DatabaseWarning,
    load_database,
    message_brs,
    message_is_fd,
)

__all__ = [
    "EncodeProblem",
    "SignalDecoder",
    "acceptance_filters",
    "checksum",
    "dbc_path",
    "dbc_warnings",
    "encode_signals",
    "load_dbc",
    "message_brs",
    "message_is_fd",
]

log = logging.getLogger("flowrt.nodes.can.node")

#: Strict-loading problems of one DBC logged one by one; the rest are counted in one line.
WARNINGS_SHOWN = 5


def dbc_path(path: str) -> Path:
    """The file ``path`` names: as given (relative to the working directory), else shipped
    with flowrt.nodes (``robot.dbc``)."""
    p = Path(path)
    if p.is_file():
        return p
    shipped = Path(__file__).resolve().parent.parent / path
    if not p.is_absolute() and shipped.is_file():
        return shipped
    raise ValueError(f"{path}: no such file (looked in {os.getcwd()} and the flowrt.nodes package)")


@functools.lru_cache(maxsize=16)
def _load(path: str, mtime_ns: int) -> tuple[Any, tuple[DatabaseWarning, ...]]:
    try:
        db, warnings = load_database(path)
    except CanDatabaseError as e:
        raise ValueError(str(e)) from None
    # once per file and version (the cache keeps the load), and the first few only: a
    # vehicle's DBC has hundreds (opendbc's gm_global_a_lowspeed: 1675 overlapping signals)
    for w in warnings[:WARNINGS_SHOWN]:
        log.warning("%s: %s (cantools' strict loading would refuse it)", path, w)
    if len(warnings) > WARNINGS_SHOWN:
        log.warning(
            "%s: %d more that cantools' strict loading would refuse "
            "(flowrt can analyse %s --json lists them all)",
            path,
            len(warnings) - WARNINGS_SHOWN,
            path,
        )
    return db, tuple(warnings)


def load_dbc(path: str) -> Any:
    """The cantools database of ``path`` (cached while the file is unchanged)."""
    p = dbc_path(path)
    return _load(str(p), p.stat().st_mtime_ns)[0]


def dbc_warnings(path: str) -> tuple[DatabaseWarning, ...]:
    """What strict loading would refuse in ``path``."""
    p = dbc_path(path)
    return _load(str(p), p.stat().st_mtime_ns)[1]


class EncodeProblem(Exception):
    """A signal set the message cannot take; ``cause`` is the same text for every value that
    fails the same way (numbers left out), so it is counted and reported once per cause."""

    def __init__(self, cause: str, detail: str) -> None:
        super().__init__(detail)
        self.cause = cause


_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?")


def encode_signals(msg: Any, values: Mapping[str, Any]) -> bytes:
    """Encode ``values`` into ``msg``: of a multiplexed message only the multiplexers and the
    signals of the branch their values select (cantools refuses the others' values); raises
    EncodeProblem. The node keeps every signal's last value, so switching the branch back
    restores that branch's signals."""
    try:
        if msg.is_multiplexed():
            names = msg.gather_signals(dict(values))
            values = {n: values[n] for n in names}
        return bytes(msg.encode(dict(values), strict=True))
    except Exception as e:  # cantools raises EncodeError, KeyError, ValueError, TypeError
        detail = " ".join(str(e).split()).strip("'\"") or type(e).__name__
        cause = _NUMBER.sub("#", detail)
        raise EncodeProblem(cause if len(cause) <= 160 else cause[:157] + "...", detail) from None


class SignalDecoder:
    """Decodes a message signal by signal, each as cantools decodes it alone.

    cantools decodes a message in one unpack, which refuses overlapping fields: opendbc's GM
    databases have ``...Group`` signals that cover their parts (177 of the 367 messages of
    ``gm_global_a_lowspeed_1818125``), and every frame of those was a decode error. Loaded
    non-strictly, such a message is decoded by this instead (a non-multiplexed one only: a
    multiplexed message's branches must be chosen by its multiplexer).
    """

    def __init__(self, msg: Any) -> None:
        from cantools.database.utils import create_encode_decode_formats

        self.length = int(msg.length)
        self.parts = [
            ([sig], create_encode_decode_formats([sig], self.length)) for sig in msg.signals
        ]

    def __call__(self, data: bytes) -> dict[str, Any]:
        from cantools.database.utils import decode_data

        out: dict[str, Any] = {}
        for sigs, formats in self.parts:
            out.update(decode_data(data, self.length, sigs, formats, False, True, False, False))
        return out


def acceptance_filters(db: Any, names: list[str]) -> list[dict[str, Any]]:
    """python-can acceptance filters for the messages ``names`` (applied in the adapter where
    it has them, else in python-can before a frame reaches the node)."""
    out = []
    for name in names:
        m = db.get_message_by_name(name)
        ext = bool(m.is_extended_frame)
        out.append(
            {"can_id": m.frame_id, "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext}
        )
    # none at all: a filter no frame matches (an empty list would accept everything)
    return out or [{"can_id": 0, "can_mask": 0x1FFFFFFF, "extended": True}]


# --- checksums (what the vehicles use; python-can and cantools compute none) -----------------


def _crc8_j1850(data: bytes) -> int:
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def checksum(kind: str, data: bytes, skip: int) -> int:
    """Checksum of ``data`` without its byte ``skip`` (where the checksum itself goes)."""
    rest = bytes(b for i, b in enumerate(data) if i != skip)
    if kind == "xor":
        x = 0
        for b in rest:
            x ^= b
        return x
    if kind == "sum":
        return sum(rest) & 0xFF
    return _crc8_j1850(rest)
