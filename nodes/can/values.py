"""The values a ``can`` node publishes: decoded messages, raw frames and its statistics.

Kept apart from the node so that a recorder, a Foxglove bridge or a user's own node can name
these types without importing the bus machinery. Fields are only ever added (with defaults,
at the end): recordings and other engineers' code build and read them positionally.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = [
    "SUMMARY_NAMES",
    "CanBusStatus",
    "CanBusSummary",
    "CanFrame",
    "CanMessage",
    "MessageStatus",
    "summarise",
]


@dataclass(frozen=True)
class CanMessage:
    """A decoded message: physical signal values plus the raw frame and its validity."""

    name: str
    id: int
    signals: dict[str, Any]
    data: bytes
    timestamp: float  # runtime clock (s) when the frame reached the loop: RTDB-comparable
    valid: bool = True
    reason: str = ""  # why not valid: timeout, counter, checksum
    bus_timestamp: float = 0.0  # the interface's own timestamp
    channel: str | None = None  # the bus channel the frame came from
    fd: bool = False  # came as a CAN FD frame
    brs: bool = False  # ... with bit-rate switch

    def __getitem__(self, signal: str) -> Any:
        return self.signals[signal]


@dataclass(frozen=True)
class CanFrame:
    """A raw CAN frame as received (`frames`: every one; `unknown`: ids the DBC does not know)."""

    id: int
    data: bytes
    extended: bool
    timestamp: float
    bus_timestamp: float = 0.0
    channel: str | None = None
    fd: bool = False
    brs: bool = False
    remote: bool = False
    dlc: int = 0  # the frame's data length code (a remote frame's too)


@dataclass(frozen=True)
class MessageStatus:
    name: str
    id: int
    received: int
    sent: int
    rate_hz: float  # over the last status interval (received + sent)
    age_ms: float | None  # since the last frame received
    timeouts: int
    bad_counter: int
    bad_checksum: int
    bad_length: int
    late: int
    bad_inputs: int  # input values that did not fit the message (not sent)
    valid: bool
    encode_errors: int = 0  # signal sets that could not be encoded (not sent), all causes
    fd: bool = False  # sent and received as CAN FD


@dataclass(frozen=True)
class BusCounters:
    """The bus's own counters: what the full status and the RTDB's summary both carry."""

    t: float  # seconds since the runtime started
    interface: str
    channel: str | None
    open: bool
    received: int
    sent: int
    unknown: int
    error_frames: int
    bus_off: int
    interface_lost: int
    reopens: int
    send_errors: int
    decode_errors: int


@dataclass(frozen=True)
class CanBusStatus(BusCounters):
    messages: tuple[MessageStatus, ...]
    channels: tuple[str, ...] = ()  # the channels frames came from (a multi-channel interface)
    unknown_by_channel: tuple[tuple[str, int], ...] = ()  # (channel, unknown frames)
    trace_frames: int = 0  # frames written to the trace file
    trace_dropped: int = 0  # frames the trace writer could not keep up with (counted, not kept)
    encode_errors: tuple[tuple[str, str, int], ...] = ()  # (message, cause, count)
    #: frames received per (channel, id, extended): the same id on two channels is two streams
    ids_by_channel: tuple[tuple[str, int, bool, int], ...] = ()
    #: when the snapshot was taken (runtime clock; in a recording Unix time, as every
    #: ``timestamp``: ``t`` stays seconds since the start, for the status table)
    timestamp: float = 0.0


#: Invalid messages a :class:`CanBusSummary` names (the first, in DBC order); the count is whole.
SUMMARY_NAMES = 8
#: Longest text a summary keeps (a message name, the interface, the channel), in characters.
SUMMARY_TEXT = 64


@dataclass(frozen=True)
class CanBusSummary(BusCounters):
    """What the RTDB keeps of a ``can`` node's status (record ``<node>.can``): the bus
    counters and totals over the messages, a fixed number of fields whatever the DBC.

    An RTDB value has a size limit (4096 bytes pickled by default); the full table, one row
    per DBC message, grows with the database (a vehicle's 331-message DBC is over 40 kB) and
    goes on the ``status`` output instead. Names and texts are clipped to SUMMARY_TEXT and at
    most SUMMARY_NAMES invalid messages are named, so the pickled summary stays under 2 kB.
    """

    messages: int  # in the DBC
    invalid: int  # messages not valid now (timed out, or too many bad frames)
    invalid_names: tuple[str, ...]  # the first SUMMARY_NAMES of them
    timeouts: int  # totals over the messages
    bad_counter: int
    bad_checksum: int
    bad_length: int
    late: int
    bad_inputs: int
    encode_errors: int
    trace_frames: int = 0
    trace_dropped: int = 0


def _clip(text: str) -> str:
    return text if len(text) <= SUMMARY_TEXT else text[: SUMMARY_TEXT - 3] + "..."


def summarise(status: CanBusStatus) -> CanBusSummary:
    """The bounded summary of a full status (see :class:`CanBusSummary`)."""
    rows = status.messages
    invalid = [r.name for r in rows if not r.valid]
    return CanBusSummary(
        status.t, _clip(status.interface),
        None if status.channel is None else _clip(status.channel),
        status.open, status.received, status.sent, status.unknown, status.error_frames,
        status.bus_off, status.interface_lost, status.reopens, status.send_errors,
        status.decode_errors, len(rows), len(invalid),
        tuple(_clip(n) for n in invalid[:SUMMARY_NAMES]),
        sum(r.timeouts for r in rows), sum(r.bad_counter for r in rows),
        sum(r.bad_checksum for r in rows), sum(r.bad_length for r in rows),
        sum(r.late for r in rows), sum(r.bad_inputs for r in rows),
        sum(r.encode_errors for r in rows), status.trace_frames, status.trace_dropped,
    )  # fmt: skip
