"""The values a ``can`` node publishes: decoded messages, raw frames and its statistics.

Kept apart from the node so that a recorder, a Foxglove bridge or a user's own node can name
these types without importing the bus machinery. Fields are only ever added (with defaults,
at the end): recordings and other engineers' code build and read them positionally.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["CanBusStatus", "CanFrame", "CanMessage", "MessageStatus"]


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
    """A raw frame (an id the DBC does not know)."""

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
class CanBusStatus:
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
