"""The CAN node's per-message state: receive counters, the value to send and its schedule."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from flowrt.analysis.can_frames import fd_payload_length

from .dbc import SignalDecoder, checksum
from .params import MessageParams
from .values import CanMessage


@dataclass
class MessageState:
    """One DBC message as the node sees it: what it received (and what was wrong with it)
    and what it sends (the value, its grid, its counter). Plain fields: the node's tick and
    its reader's callback (handed over by the link) both update them on the event loop."""

    dbc: Any  # cantools Message
    cycle: float | None  # ms
    opts: MessageParams
    timeout: float | None = None  # s
    fd: bool = False
    brs: bool = False
    # receive
    received: int = 0
    last_rx: float | None = None
    last: CanMessage | None = None
    timed_out: bool = False
    fail: int = 0
    last_counter: int | None = None
    bad_counter: int = 0
    bad_checksum: int = 0
    bad_length: int = 0
    timeouts: int = 0
    # transmit
    tx: bool = False
    value: dict[str, Any] = field(default_factory=dict)
    have_value: bool = False
    fresh: bool = False
    due: float = 0.0  # seconds since start
    counter: int = 0
    sent: int = 0
    late: int = 0
    bad_inputs: int = 0
    encode_errors: int = 0
    window: int = 0  # frames since the last status
    # The frame's bytes for ``value`` when it has no counter or checksum (which change at
    # every send): a periodic message whose value did not change is not encoded again, so
    # the sends of a tick follow its release closely (cantools' strict encode is the
    # slowest step between the release and ``bus.send``).
    encoded: bytes | None = None
    signal_names: frozenset[str] = frozenset()
    # Set when cantools refuses to decode the message whole (overlapping signals, loaded
    # non-strictly): decoded signal by signal from then on (can_dbc.SignalDecoder).
    by_signal: SignalDecoder | None = None

    @property
    def checksum_byte(self) -> int | None:
        if self.opts.checksum is None:
            return None
        return int(self.dbc.get_signal_by_name(self.opts.checksum).start // 8)

    def integrity(self, signals: Mapping[str, Any], data: bytes) -> str:
        """Check the counter and checksum of a received frame: the reason it is bad, or ""."""
        reason = ""
        opts = self.opts
        if opts.counter is not None and opts.counter in signals:
            sig = self.dbc.get_signal_by_name(opts.counter)
            raw = round((signals[opts.counter] - sig.offset) / sig.scale)
            if self.last_counter is not None and raw != (self.last_counter + 1) % (1 << sig.length):
                self.bad_counter += 1
                reason = "counter"
            self.last_counter = raw
        idx = self.checksum_byte
        if idx is not None and checksum(opts.checksum_kind, data, idx) != data[idx]:
            self.bad_checksum += 1
            reason = "checksum"
        return reason

    def fits(self, data: bytes) -> bool:
        """The DBC's length, or (FD) that length padded to the next FD length."""
        n = int(self.dbc.length)
        return len(data) == n or (self.fd and n <= 64 and len(data) == fd_payload_length(n))
