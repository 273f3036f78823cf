"""Statistics of a recorded CAN bus: per channel and identifier, timing and bus load.

A trace (any format python-can reads: candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ...)
is read frame by frame. Identifiers are kept per channel: the same id on two buses is two
streams, not one at twice the rate. Each frame counts at its worst-case length
(:mod:`flowrt.analysis.can_frames`), so the load is an upper bound of the load on the wire and
comparable with ``flowrt can analyse``: classic frames after Davis et al. 2007, CAN FD frames
(ISO 11898-1:2015) with their real payload, the data phase of a bit-rate-switched frame at
the data bit rate (at the nominal rate, an upper bound, when none is given; counted).
Remote frames count with no data bytes; error frames are counted, not timed.

The load per second is of seconds from a channel's first frame, not of the clock's: a
clock-aligned first and last second hold only part of a second. The busiest second is the
busiest 1 s window starting at a frame, the mean is over the same whole seconds, so the
busiest second is never under the mean (a mean over the trace's span, ragged ends included,
could exceed every whole second of an evenly loaded bus).
"""

from __future__ import annotations

import bisect
import itertools
import os
import statistics
from array import array
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from .can_frames import fd_frame_bits, frame_bits

__all__ = [
    "MIN_PEAK_S",
    "BusLoad",
    "TraceError",
    "bus_load",
    "frame_seconds",
    "read_trace",
    "trace_stats",
]

#: Shortest trace (s) whose busiest second ``peak_load`` is given; a shorter one has its mean.
MIN_PEAK_S = 2.0
_US = 1_000_000  # microseconds a second


class TraceError(Exception):
    """A file that is not a CAN trace python-can reads; the message is one line."""


def frame_seconds(msg: Any, bitrate: int, data_bitrate: int | None) -> tuple[int, float]:
    """(worst-case bits, seconds on the wire) of one python-can message."""
    bits, units = _frame_units(msg, bitrate, data_bitrate)
    return bits, units / (bitrate * (data_bitrate if data_bitrate is not None else bitrate))


def _frame_units(msg: Any, bitrate: int, data_bitrate: int | None) -> tuple[int, int]:
    """(worst-case bits, time on the wire in 1/(bitrate * data rate) s): whole numbers, so
    that windows sum and compare exactly (float sums in another order could put the mean of
    the seconds a rounding above their busiest); the data rate is ``bitrate`` without one."""
    rate = data_bitrate if data_bitrate is not None else bitrate
    ext = bool(msg.is_extended_id)
    n = 0 if msg.is_remote_frame else len(msg.data)
    if msg.is_fd:
        fd = fd_frame_bits(n, ext, bool(msg.bitrate_switch))
        if fd.brs and data_bitrate is not None:
            return fd.total, fd.arbitration * rate + fd.data * bitrate
        return fd.total, fd.total * rate
    bits = frame_bits(min(n, 8), ext)
    return bits, bits * rate


@dataclass(frozen=True)
class BusLoad:
    """A channel's load: ``mean`` and ``peak`` (busiest second) as fractions of the time,
    ``seconds`` the (second from the first frame, bits, load) of each second with frames."""

    mean: float | None
    peak: float | None
    seconds: list[tuple[int, int, float]]


def bus_load(
    times: Sequence[float], bits: Sequence[int], units: Sequence[int], scale: int
) -> BusLoad:
    """The load of frames at ``times`` (any order) each ``bits`` long and ``units`` / ``scale``
    seconds on the wire; a frame of no bits (an error frame) only marks the trace's span.

    A trace of MIN_PEAK_S or more is cut to its K whole seconds from the first frame (the
    rest, under a second, cannot be a second's load): the mean is over those K seconds, the
    peak the busiest window [t, t + 1 s) starting at a frame among them. Each of the K
    seconds lies in the window starting at its first frame, so peak >= mean, and exactly: the
    sums are of whole units and each figure one rounded division. A shorter trace has no peak
    and its mean over its span (the only figure it gives); one instant has neither.

    Times count in whole microseconds from the first frame: a trace's times are decimals
    (candump's and ASC's in us), which binary floats only approximate, so 0.13 s and 1.13 s
    would be 0.9999999999999999 s apart and two frames of a 10 ms message a second apart
    would fall in one window (101 frames of it in a busiest second).
    """
    n = len(times)
    if n == 0:
        return BusLoad(None, None, [])
    first = min(times)
    order = sorted(range(n), key=times.__getitem__)
    d = [round((times[i] - first) * _US) for i in order]
    u = [units[i] for i in order]
    per_bits: dict[int, int] = {}
    per_units: dict[int, int] = {}
    for k, i in enumerate(order):
        sec = d[k] // _US
        per_bits[sec] = per_bits.get(sec, 0) + bits[i]
        per_units[sec] = per_units.get(sec, 0) + u[k]
    seconds = [(sec, b, per_units[sec] / scale) for sec, b in sorted(per_bits.items()) if b]
    span = d[-1]
    if span < MIN_PEAK_S * _US:
        mean = sum(u) * _US / (span * scale) if span > 0 else None
        return BusLoad(mean, None, seconds)
    whole = span // _US
    counted = bisect.bisect_left(d, whole * _US)  # the frames of the whole seconds
    busiest = window = 0
    hi = 0
    for j in range(counted):
        while hi < n and d[hi] < d[j] + _US:
            window += u[hi]
            hi += 1
        busiest = max(busiest, window)
        window -= u[j]
    return BusLoad(sum(u[:counted]) / (whole * scale), busiest / scale, seconds)


@dataclass
class _Stream:
    arrivals: list[float] = field(default_factory=list)
    length: int = 0
    fd: bool = False
    brs: bool = False
    remote: int = 0


@dataclass
class _Channel:
    streams: dict[tuple[int, bool], _Stream] = field(default_factory=dict)
    # every frame: its time, bits and time on the wire (in _frame_units's units; 0 untimed)
    times: array[float] = field(default_factory=lambda: array("d"))
    bits: array[int] = field(default_factory=lambda: array("q"))
    units: array[int] = field(default_factory=lambda: array("q"))
    error_frames: int = 0
    first: float | None = None
    last: float | None = None


def read_trace(path: str) -> Iterable[Any]:
    """The frames of a trace, or TraceError (one line) for a file python-can cannot read."""
    import can

    from ..files import file_problem

    problem = file_problem(path)  # a FIFO or a device would block or never end
    if problem is not None:
        raise TraceError(problem)
    try:
        empty = os.path.getsize(path) == 0
    except OSError:
        empty = False  # python-can says what is wrong with it
    if empty:  # python-can's BLF reader: "unpack requires a buffer of 72 bytes"
        raise TraceError(f"{path}: an empty file (no CAN frame in it)")
    try:
        reader = can.LogReader(path)
    except Exception as e:  # python-can raises many kinds on unknown suffixes and bad headers
        raise TraceError(f"{path}: cannot read the trace: {_one_line(e)}") from None

    def frames() -> Iterable[Any]:
        with reader:
            try:
                yield from reader
            except Exception as e:  # a damaged record in the middle
                raise TraceError(f"{path}: cannot read the trace: {_one_line(e)}") from None

    return frames()


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def truncated(path: str) -> str | None:
    """Why the trace is shorter than it says it is, or None: a BLF's header holds its file's
    size, and python-can reads a BLF cut short (a logger that lost power) up to the cut
    without a word (78 of 200 frames, as if the whole trace)."""
    if not path.lower().endswith(".blf"):
        return None
    import can

    try:
        with can.BLFReader(path) as r:
            declared = int(r.file_size)
        actual = os.path.getsize(path)
    except Exception:
        return None  # read_trace says what is wrong with it
    if 0 < actual < declared:
        return f"{path}: truncated ({actual} of the {declared} bytes its header declares)"
    return None


def trace_stats(
    path: str, bitrate: int, db: Any = None, data_bitrate: int | None = None
) -> dict[str, Any]:
    """The ``flowrt can stats --json`` document: per channel its identifiers (count, length,
    mean period and inter-arrival spread) and its load per second; the channels together in
    ``ids`` (each with its ``channel``) and the first channel's load in ``load``."""
    chans: dict[str, _Channel] = {}
    brs_nominal = 0
    for msg in read_trace(path):
        name = "" if msg.channel is None else str(msg.channel)
        ch = chans.setdefault(name, _Channel())
        t = float(msg.timestamp)
        ch.first = t if ch.first is None else min(ch.first, t)
        ch.last = t if ch.last is None else max(ch.last, t)
        if msg.is_error_frame:  # untimed, but the trace's span (and so the mean's) is up to it
            ch.error_frames += 1
            ch.times.append(t)
            ch.bits.append(0)
            ch.units.append(0)
            continue
        key = (int(msg.arbitration_id), bool(msg.is_extended_id))
        st = ch.streams.setdefault(key, _Stream())
        st.arrivals.append(t)
        st.length = max(st.length, 0 if msg.is_remote_frame else len(msg.data))
        st.fd = st.fd or bool(msg.is_fd)
        st.brs = st.brs or bool(msg.bitrate_switch)
        st.remote += bool(msg.is_remote_frame)
        bits, units = _frame_units(msg, bitrate, data_bitrate)
        brs_nominal += bool(msg.is_fd and msg.bitrate_switch and data_bitrate is None)
        ch.times.append(t)
        ch.bits.append(bits)
        ch.units.append(units)
    if not chans:
        raise TraceError(f"{path}: no CAN frame in it (not a trace python-can reads?)")
    names: dict[tuple[int, bool], str] = {}
    if db is not None:
        for m in db.messages:
            names[(int(m.frame_id), bool(m.is_extended_frame))] = m.name
    scale = bitrate * (data_bitrate if data_bitrate is not None else bitrate)
    channels = [_channel_doc(c, ch, names, scale) for c, ch in sorted(chans.items())]
    first = min(c.first for c in chans.values() if c.first is not None)
    last = max(c.last for c in chans.values() if c.last is not None)
    return {
        "file": path,
        "truncated": truncated(path),
        "bitrate": bitrate,
        "data_bitrate": data_bitrate,
        "duration_s": last - first,
        "frames": sum(c["frames"] for c in channels),
        "error_frames": sum(c["error_frames"] for c in channels),
        "brs_at_nominal_rate": brs_nominal,
        "mean_load": channels[0]["mean_load"] if len(channels) == 1 else None,
        "peak_load": channels[0]["peak_load"] if len(channels) == 1 else None,
        "ids": [{**r, "channel": c["channel"]} for c in channels for r in c["ids"]],
        "load": channels[0]["load"],
        "channels": channels,
    }


def _channel_doc(
    name: str, ch: _Channel, names: dict[tuple[int, bool], str], scale: int
) -> dict[str, Any]:
    ids: list[dict[str, Any]] = []
    for key in sorted(ch.streams):
        st = ch.streams[key]
        ts = sorted(st.arrivals)
        gaps = [(b - a) * 1000.0 for a, b in itertools.pairwise(ts)]
        ids.append(
            {
                "id": key[0],
                "extended": key[1],
                "name": names.get(key),
                "dlc": st.length,
                "fd": st.fd,
                "brs": st.brs,
                "remote": st.remote,
                "count": len(ts),
                "period_ms": statistics.fmean(gaps) if gaps else None,
                "std_ms": statistics.pstdev(gaps) if len(gaps) > 1 else (0.0 if gaps else None),
                "min_ms": min(gaps) if gaps else None,
                "max_ms": max(gaps) if gaps else None,
            }
        )
    first = ch.first if ch.first is not None else 0.0
    duration = (ch.last - first) if ch.last is not None else 0.0
    load = bus_load(ch.times, ch.bits, ch.units, scale)
    return {
        "channel": name,
        "duration_s": duration,
        "frames": sum(len(s.arrivals) for s in ch.streams.values()),
        "error_frames": ch.error_frames,
        "mean_load": load.mean,
        "peak_load": load.peak,
        "ids": ids,
        "load": [{"t_s": float(sec), "bits": b, "load": x} for sec, b, x in load.seconds],
    }
