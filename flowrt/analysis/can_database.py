"""Loading CAN databases as vehicles have them: what cantools loads, with its complaints named.

Production DBC files (opendbc's, every OEM's) have overlapping signals, signals past the end
of their message and multiplexed layouts that cantools' *strict* loading refuses, although
nothing in a bus analysis or in decoding the other messages depends on them. So a database
is loaded non-strictly, and what strict loading would have refused is reported once per
problem as a :class:`DatabaseWarning` (message, signal, reason); ``strict=True`` turns the
first of them into a :class:`CanDatabaseError` as before. A file cantools cannot parse at
all is a :class:`CanDatabaseError` of one line with the line number cantools found.

It also reads the attributes a DBC uses for the timing of CAN FD and sporadic messages:
``BaudrateCANFD`` (network: the data-phase bit rate), ``CANFD_BRS`` (message: bit-rate
switch, default on for FD messages) and ``GenMsgDelayTime`` (message: the minimum time
between two transmissions, Vector's interaction-layer attribute, the minimum inter-arrival
time of a sporadic message).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "CanDatabaseError",
    "DatabaseWarning",
    "data_bitrate_of",
    "load_database",
    "message_attribute",
    "message_brs",
    "message_is_fd",
    "strict_warnings",
]

#: Biggest database file read (a DBC of a whole vehicle is a few MB).
MAX_DATABASE_BYTES = 64 * 1024 * 1024


class CanDatabaseError(Exception):
    """A CAN database that does not load; the message is one line naming the file."""


@dataclass(frozen=True)
class DatabaseWarning:
    """What strict loading would have refused, once per problem."""

    message: str
    signal: str | None
    reason: str

    def __str__(self) -> str:
        where = f"{self.message}.{self.signal}" if self.signal else self.message
        return f"{where}: {self.reason}"


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    if len(text) > 1 and text[0] == text[-1] and text[0] in "'\"":  # a KeyError's quotes
        text = text[1:-1]  # only a pair: "... got 'yaml'" keeps the quote closing 'yaml'
    return text or type(e).__name__


def load_database(path: str | Path, strict: bool = False) -> tuple[Any, list[DatabaseWarning]]:
    """A cantools database and the strict-loading warnings, or a one-line CanDatabaseError."""
    import cantools

    from ..files import file_problem

    p = Path(path)
    # only a regular file, its size checked before cantools reads it (not /dev/zero)
    problem = file_problem(p, MAX_DATABASE_BYTES)
    if problem is not None:
        raise CanDatabaseError(problem)
    try:
        db = cantools.database.load_file(str(p), strict=False)
    except Exception as e:  # cantools raises parser, value and key errors of several kinds
        text = _one_line(e)
        m = re.search(r"line (\d+)", text)
        line = m.group(1) if m else _message_line(p, text)
        at = f":{line}" if line else ""
        raise CanDatabaseError(f"{path}{at}: not a valid CAN database: {text}") from None
    warnings = list(strict_warnings(db))
    if strict and warnings:
        raise CanDatabaseError(f"{path}: refused by strict loading: {warnings[0]}")
    return db, warnings


def _message_line(path: Path, text: str) -> str | None:
    """The line of the message an error names (``... in message MEB_Camera_04``), where the
    parser gave none: the README promises ``FILE:LINE`` for a database error."""
    m = re.search(r"in message (\w+)", text)
    if m is None:
        return None
    pattern = re.compile(rf"^\s*BO_\s+\d+\s+{re.escape(m.group(1))}\s*:")
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return next((str(n) for n, row in enumerate(f, 1) if pattern.match(row)), None)
    except OSError:
        return None


def strict_warnings(db: Any) -> Iterator[DatabaseWarning]:
    """Every signal cantools' strict check refuses, per message (not only the first)."""
    for m in db.messages:
        seen: set[tuple[str | None, str]] = set()
        for w in _message_problems(m):
            if (w.signal, w.reason) not in seen:
                seen.add((w.signal, w.reason))
                yield w


def _message_problems(m: Any) -> Iterator[DatabaseWarning]:
    """cantools' own check (``Message._check_signal``) run signal by signal, each branch of a
    multiplexer on its own copy of the bits, so that one problem does not hide the next."""
    check = getattr(m, "_check_signal", None)
    if check is None:  # another cantools: ask it once for the first problem
        try:
            m.refresh(strict=True)
        except Exception as e:
            yield DatabaseWarning(m.name, None, _one_line(e))
        return
    bits: list[str | None] = [None] * (8 * int(m.length))
    yield from _tree_problems(m, check, bits, m.signal_tree)


def _tree_problems(m: Any, check: Any, bits: list[str | None], tree: Any) -> Iterator[Any]:
    for node in tree:
        if isinstance(node, dict):
            for mux_name, children in node.items():
                yield from _signal_problem(m, check, bits, mux_name)
                base = list(bits)
                for branch in children.values():
                    child = list(base)
                    yield from _tree_problems(m, check, child, branch)
                    for i, b in enumerate(child):
                        if b is not None:
                            bits[i] = b
        else:
            yield from _signal_problem(m, check, bits, node)


def _signal_problem(m: Any, check: Any, bits: list[str | None], name: str) -> Iterator[Any]:
    try:
        check(bits, m.get_signal_by_name(name))
    except Exception as e:
        text = _one_line(e)
        reason = "overlaps another signal" if "overlapping" in text else text
        if "does not fit" in text:
            reason = f"does not fit in the message's {m.length} bytes"
        if "overlapping" in text:
            other = re.search(r"signals (\S+) and (\S+) are", text)
            if other:
                reason = f"overlaps signal {other.group(2)}"
        yield DatabaseWarning(m.name, name, reason)


def _attr(attrs: Any, name: str) -> Any:
    if not attrs or name not in attrs:
        return None
    return getattr(attrs[name], "value", None)


def message_attribute(m: Any, name: str) -> Any:
    """A message's DBC attribute value (or its definition's default), None without one."""
    dbc = getattr(m, "dbc", None)
    if dbc is None:
        return None
    value = _attr(getattr(dbc, "attributes", None), name)
    if value is None:
        definition = (getattr(dbc, "attribute_definitions", None) or {}).get(name)
        value = getattr(definition, "default_value", None) if definition is not None else None
    return value


def message_is_fd(m: Any) -> bool:
    """CAN FD: marked so in the DBC (``VFrameFormat``), or more than 8 data bytes (which only
    an FD frame can carry)."""
    return bool(getattr(m, "is_fd", False)) or int(m.length) > 8


def message_brs(m: Any) -> bool:
    """Bit-rate switch of an FD message: ``CANFD_BRS`` when the DBC gives it, else on."""
    value = message_attribute(m, "CANFD_BRS")
    if value is None:
        return True
    return str(value).strip().strip('"') not in ("0", "False", "false", "no")


def data_bitrate_of(db: Any) -> int | None:
    """The data-phase bit rate the DBC declares (``BaudrateCANFD``, bit/s), if any."""
    dbc = getattr(db, "dbc", None)
    value = _attr(getattr(dbc, "attributes", None), "BaudrateCANFD") if dbc else None
    try:
        rate = int(float(value)) if value is not None else 0
    except (TypeError, ValueError):
        return None
    return rate if rate > 0 else None
