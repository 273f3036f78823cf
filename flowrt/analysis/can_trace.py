"""Statistics of a recorded CAN bus: per channel and identifier, timing and bus load.

A trace (any format python-can reads: candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ...)
is read frame by frame. Identifiers are kept per channel: the same id on two buses is two
streams, not one at twice the rate. Each frame counts at its worst-case length
(:mod:`flowrt.analysis.can_frames`), so the load is an upper bound of the load on the wire and
comparable with ``flowrt can analyse``: classic frames after Davis et al. 2007, CAN FD frames
(ISO 11898-1:2015) with their real payload, the data phase of a bit-rate-switched frame at
the data bit rate (at the nominal rate, an upper bound, when none is given; counted).
Remote frames count with no data bytes; error frames are counted, not timed.
"""

from __future__ import annotations

import itertools
import statistics
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from .can_frames import fd_frame_bits, frame_bits

__all__ = ["MIN_PEAK_S", "TraceError", "frame_seconds", "read_trace", "trace_stats"]

#: Shortest trace (s) whose busiest second ``peak_load`` is given; a shorter one has its mean.
MIN_PEAK_S = 2.0


class TraceError(Exception):
    """A file that is not a CAN trace python-can reads; the message is one line."""


def frame_seconds(msg: Any, bitrate: int, data_bitrate: int | None) -> tuple[int, float]:
    """(worst-case bits, seconds on the wire) of one python-can message."""
    ext = bool(msg.is_extended_id)
    n = 0 if msg.is_remote_frame else len(msg.data)
    if msg.is_fd:
        fd = fd_frame_bits(n, ext, bool(msg.bitrate_switch))
        if fd.brs and data_bitrate is not None:
            return fd.total, fd.seconds(bitrate, data_bitrate)
        return fd.total, fd.total / bitrate
    bits = frame_bits(min(n, 8), ext)
    return bits, bits / bitrate


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
    busy: dict[int, float] = field(default_factory=dict)  # second -> seconds on the wire
    bits: dict[int, int] = field(default_factory=dict)
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
        if msg.is_error_frame:
            ch.error_frames += 1
            continue
        key = (int(msg.arbitration_id), bool(msg.is_extended_id))
        st = ch.streams.setdefault(key, _Stream())
        st.arrivals.append(t)
        st.length = max(st.length, 0 if msg.is_remote_frame else len(msg.data))
        st.fd = st.fd or bool(msg.is_fd)
        st.brs = st.brs or bool(msg.bitrate_switch)
        st.remote += bool(msg.is_remote_frame)
        bits, secs = frame_seconds(msg, bitrate, data_bitrate)
        brs_nominal += bool(msg.is_fd and msg.bitrate_switch and data_bitrate is None)
        ch.busy[int(t)] = ch.busy.get(int(t), 0.0) + secs
        ch.bits[int(t)] = ch.bits.get(int(t), 0) + bits
    if not chans:
        raise TraceError(f"{path}: no CAN frame in it (not a trace python-can reads?)")
    names: dict[tuple[int, bool], str] = {}
    if db is not None:
        for m in db.messages:
            names[(int(m.frame_id), bool(m.is_extended_frame))] = m.name
    channels = [_channel_doc(c, ch, names) for c, ch in sorted(chans.items())]
    first = min(c.first for c in chans.values() if c.first is not None)
    last = max(c.last for c in chans.values() if c.last is not None)
    return {
        "file": path,
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


def _channel_doc(name: str, ch: _Channel, names: dict[tuple[int, bool], str]) -> dict[str, Any]:
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
    start = int(first)
    load = [
        {"t_s": float(sec - start), "bits": ch.bits[sec], "load": ch.busy[sec]}
        for sec in sorted(ch.busy)
    ]
    busy = sum(ch.busy.values())
    # the busiest whole second, of a trace of 2 s or more (which has at least one whole):
    # the first and last bins hold only part of a second, which says nothing of a second's
    # load, and the busiest of one or two is no figure to give
    last = ch.last if ch.last is not None else first
    whole = [ch.busy[sec] for sec in ch.busy if sec >= first and sec + 1 <= last]
    if duration < MIN_PEAK_S:
        whole = []
    return {
        "channel": name,
        "duration_s": duration,
        "frames": sum(len(s.arrivals) for s in ch.streams.values()),
        "error_frames": ch.error_frames,
        "mean_load": busy / duration if duration > 0 else None,
        "peak_load": max(whole) if whole else None,
        "ids": ids,
        "load": load,
    }
