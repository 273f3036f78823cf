"""Worst-case lengths of CAN frames on the wire: classic CAN and CAN FD.

Classic CAN (ISO 11898-1, CAN 2.0): R. I. Davis, A. Burns, R. J. Bril and J. J. Lukkien,
"Controller Area Network (CAN) schedulability analysis: Refuted, revisited and revised",
Real-Time Systems 35(3), 2007, eq. 2: ``g + 8n + 13 + floor((g + 8n - 1) / 4)`` bits with
``g = 34`` (11-bit identifier) or ``54`` (29-bit), the 3-bit interframe space included.

CAN FD (ISO 11898-1:2015, clause 10): the same worst-case stuffing rule (a stuff bit after the
first five equal bits, then one every four) applies from SOF to the end of the data field
only. The CRC field then carries the *stuff count* (3 Gray-coded bits and a parity bit) and
a CRC-17 (payloads up to 16 bytes) or CRC-21 (more), with *fixed* stuff bits: one before the
stuff count and one after every four bits of the field, 6 for CRC-17 and 7 for CRC-21.
With bit-rate switching (BRS) the bits from the BRS bit's sample point to the CRC delimiter's
sample point go at the data bit rate. This follows the frame-length model of U. D. Bordoloi
and S. Samii, "The frame packing problem for CAN-FD", IEEE RTSS 2014 (section II), and
F. Hartwich, "CAN with Flexible Data-Rate", 13th iCC, CiA 2012; we count worst-case dynamic
stuff bits inside the arbitration phase at the nominal rate (where they cost most) and the
CRC delimiter wholly at the nominal rate, so the figure is an upper bound for any sample
point. Base format (11-bit identifier), ``n`` payload bytes (a DLC length), CRC length
``L`` and fixed stuff bits ``F``:

- arbitration phase: SOF, 11 id bits, RRS, IDE, FDF, res, BRS = 17 bits, at most
  ``floor(16/4) = 4`` stuff bits in them, and CRC delimiter, ACK slot and delimiter, EOF (7)
  and interframe space (3) = 13 bits: **34 bits** (extended: 36 header bits + 8 stuff + 13
  = **57**);
- data phase: ESI, DLC (4), ``8n`` data bits, the remaining dynamic stuff bits
  ``floor((22 + 8n - 1)/4) - 4`` (extended ``floor((41 + 8n - 1)/4) - 8``), stuff count (4),
  CRC (``L``) and ``F`` fixed stuff bits.

Without BRS every bit goes at the nominal rate. Worked examples (base format):
8 bytes: 34 + (5 + 64 + 17 + 4 + 17 + 6) = 34 + 113 = 147 bits; 64 bytes: 34 + (5 + 512 +
129 + 4 + 21 + 7) = 34 + 678 = 712 bits.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

__all__ = [
    "FD_LENGTHS",
    "FdFrameBits",
    "bit_rate",
    "fd_frame_bits",
    "fd_payload_length",
    "frame_bits",
]

#: The payload lengths a CAN FD DLC can express (ISO 11898-1:2015, table 5).
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


#: Bit rates a CAN controller runs at: 1 kbit/s up to CAN FD data phases of 20 Mbit/s.
MIN_BITRATE, MAX_BITRATE = 1_000, 20_000_000
_RATE = re.compile(
    r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([kKmM]?)\s*(?:bit/s|bps|b/s)?\s*$"
)


def bit_rate(value: Any) -> int:
    """A bit rate as people write it: ``500000``, ``500k``, ``1e6``, ``1M``, ``2Mbit/s``;
    a whole number of bit/s from 1k to 20M (ValueError otherwise)."""
    if isinstance(value, bool):
        raise ValueError("expected bit/s such as 500000, 500k, 1e6 or 2M")
    m = _RATE.match(str(value))
    if m is None:
        raise ValueError("expected bit/s such as 500000, 500k, 1e6 or 2M")
    scale = {"": 1, "k": 1_000, "m": 1_000_000}[m.group(2).lower()]
    rate = float(m.group(1)) * scale
    if not math.isfinite(rate) or not MIN_BITRATE <= rate <= MAX_BITRATE:
        raise ValueError("must be between 1k and 20M bit/s")
    if rate != int(rate):
        raise ValueError("not a whole number of bit/s")
    return int(rate)


def frame_bits(dlc: int, extended: bool = False) -> int:
    """Worst-case length in bits of a classic data frame with ``dlc`` data bytes (0..8),
    stuff bits and the 3-bit interframe space included (Davis et al. 2007, eq. 2)."""
    if not 0 <= dlc <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {dlc} (more is CAN FD)")
    n8 = 8 * dlc
    if extended:
        return 67 + n8 + (54 + n8 - 1) // 4
    return 47 + n8 + (34 + n8 - 1) // 4


def fd_payload_length(n: int) -> int:
    """The bytes a CAN FD frame carries for ``n`` bytes of data: the next DLC length (a 10-byte
    message goes out as 12, padded)."""
    for length in FD_LENGTHS:
        if n <= length:
            return length
    raise ValueError(f"a CAN FD frame carries 0..64 data bytes, not {n}")


@dataclass(frozen=True)
class FdFrameBits:
    """A CAN FD frame's worst-case bits at each rate (see the module docstring)."""

    arbitration: int  # at the nominal bit rate
    data: int  # at the data bit rate with BRS, else also at the nominal rate
    payload: int  # bytes on the wire (a DLC length)
    crc_bits: int  # 17 or 21
    stuff_bits: int  # dynamic (worst case) and fixed stuff bits together
    brs: bool

    @property
    def total(self) -> int:
        return self.arbitration + self.data

    def seconds(self, bitrate: float, data_bitrate: float | None) -> float:
        """Time on the wire; ``data_bitrate`` is needed only with BRS."""
        if not self.brs:
            return self.total / bitrate
        if data_bitrate is None:
            raise ValueError("a CAN FD frame with bit-rate switch needs a data bit rate")
        return self.arbitration / bitrate + self.data / data_bitrate


def fd_frame_bits(n: int, extended: bool = False, brs: bool = True) -> FdFrameBits:
    """Worst-case bits of a CAN FD data frame carrying ``n`` data bytes (rounded up to a DLC
    length), after ISO 11898-1:2015 and Bordoloi & Samii 2014 (module docstring)."""
    payload = fd_payload_length(n)
    header = 36 if extended else 17  # SOF .. BRS
    stuffed = header + 5 + 8 * payload  # SOF .. end of data: dynamic stuffing
    dynamic = (stuffed - 1) // 4
    header_stuff = (header - 1) // 4
    crc = 17 if payload <= 16 else 21
    fixed = 6 if crc == 17 else 7
    arbitration = header + header_stuff + 13  # + CRC delim, ACK, ACK delim, EOF, IFS
    data = 5 + 8 * payload + (dynamic - header_stuff) + 4 + crc + fixed
    return FdFrameBits(arbitration, data, payload, crc, dynamic + fixed, brs)
