"""The post-recording check (the acquisition paper's per-stream table): expected vs received
vs written, lost, rate mean/min/max and bytes per stream, lost in red.

``expected`` counts the source's releases whose values the session could hold: a periodic
node releases on a grid (flowrt.kernel.scheduler: a timer at ``origin + phase + n*period``, a
frame reader on the ticks ``k % period == phase`` of its source), so a stream's own values
place its grid, phase included, and :func:`expected_releases` counts the grid's points in
the session's window (its first message to its last: the ``span``). A source that delivered
less than it should shows up as ``missing`` even when the recorder lost nothing.
A value need not be stamped at its release: an audio block carries its first sample's time
and is released once its last sample is in, a block or more later (``leads``,
:func:`build_report`).
The nominal rate comes from the running graph's timing (a timer trigger's period; a frame
trigger's source rate divided by its period), as the runtime's statistics report it, unless
the output declares a rate of its own (``output_hz``: a status every second on a node that
ticks at 100 Hz, a CAN message at its cycle time), or none: an output on events expects
nothing, and nothing of it is ever "missing".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from pydantic import BaseModel, Field

from .writer import StreamCounters

__all__ = [
    "RecordingReport",
    "StreamReport",
    "build_report",
    "expected_releases",
    "nominal_rates",
    "releases_in",
    "report_table",
]

_EPS = 1e-9
"""Periods of float noise forgiven when a release falls on a window's edge: (0.9 - 0.1) / 0.8
is 0.9999999999999999, and a release exactly at a start would otherwise fall before it."""


class StreamReport(BaseModel):
    """One stream of a recording."""

    topic: str
    source: str = Field(description="node.port the stream was recorded from")
    nominal_hz: float | None = Field(description="the source's rate by the graph's timing")
    expected: int | None = Field(
        description="the source's releases within the session, its phase respected "
        "(expected_releases; None: not periodic, or its timing changed during the session)"
    )
    received: int
    written: int
    lost: int = Field(description="received and not written (lost_behind + lost_error)")
    lost_behind: int = Field(description="refused: the writer could not keep up")
    lost_error: int = Field(description="not written after a write error (disk full)")
    missing: int = Field(description="expected - received, when the source delivered less")
    rate_mean: float | None = Field(description="written messages per second")
    rate_min: float | None = Field(description="from the longest interval between messages")
    rate_max: float | None = Field(description="from the shortest interval between messages")
    bytes: int


class RecordingReport(BaseModel):
    """A whole recording: where, how long, and every stream."""

    session: str
    files: list[str]
    start_time: str
    duration: float = Field(description="seconds, start of recording to stop")
    span: float | None = Field(
        default=None,
        description="seconds from the first message to the last: the session's length as "
        "flowrt info, the player and the sessions API give it (None: no message)",
    )
    error: str | None = Field(description="the write error that stopped the recording, if any")
    notes: list[str] = Field(default_factory=list)
    streams: list[StreamReport]

    @property
    def lost(self) -> int:
        return sum(s.lost for s in self.streams)


def nominal_rates(stats: Any, since: float | None = None) -> dict[str, float | None]:
    """Node name -> nominal activations per second, for timer- and frame-triggered nodes;
    ``node.port`` -> the rate an output declares of its own (None: no rate). ``since``
    (runtime clock, seconds since start: a session's start): a node whose timing changed
    after it has no one rate over the session (a mode switched a tracker between periods 1
    and 2: "expected 36, received 41"), nor have the readers of its frames."""
    rows = {n.name: n for n in stats.nodes}
    out: dict[str, float | None] = {}

    def rate(name: str, depth: int = 0) -> float | None:
        if name in out:
            return out[name]
        n = rows.get(name)
        if n is None or depth > 20:
            return None
        changed = getattr(n, "timing_changed", None)
        if since is not None and changed is not None and changed >= since:
            out[name] = None
            return None
        r: float | None = None
        if n.trigger == "timer" and n.timer_ms:  # the numbers, not the shown text (rounded)
            r = 1000.0 / n.timer_ms
        elif n.trigger.startswith("frame ") and n.period_frames:
            src = rate(n.trigger.split()[1].split(".")[0], depth + 1)
            r = None if src is None else src / n.period_frames
        if r is not None:
            out[name] = r
        return r

    for name in rows:
        rate(name)
    for n in stats.nodes:
        for port, hz in (getattr(n, "output_hz", None) or {}).items():
            out[f"{n.name}.{port}"] = hz
    return out


def stream_rate(rates: dict[str, float | None], source: str) -> float | None:
    """The expected rate of the stream recorded from ``source`` (``node.port``): its own,
    else its node's."""
    if source in rates:
        return rates[source]
    return rates.get(source.split(".")[0])


def releases_in(period: float, anchor: float, start: float, end: float) -> int:
    """How many of the releases ``anchor + k * period`` (``k`` any integer) fall in
    ``[start, end)``.

    One release fixes the others: the scheduler releases a timer at ``origin + phase +
    n*period`` and a frame reader on every ``period``-th tick of its source from its
    ``phase`` on (flowrt.kernel.scheduler), so the phase is in ``anchor``.
    """
    if end <= start or period <= 0:
        return 0
    first = math.ceil((start - anchor) / period - _EPS)
    past = math.ceil((end - anchor) / period - _EPS)
    return max(0, past - first)


def expected_releases(
    period: float,
    start: float,
    end: float,
    first: float | None,
    last: float | None,
    *,
    before_first: bool = True,
) -> int:
    """The releases of a stream of nominal ``period`` whose values a session could hold.

    ``start`` and ``end`` are the session's first and last message (any stream), ``first``
    and ``last`` the stream's own (None: it sent nothing), all stamped at (or just after) their
    release; for a stream stamped ahead of its releases (an audio block) ``end`` is first
    shifted onto its stamps (:func:`_on_stamps`).
    Counted: the stream's releases from its first value to its last (gaps included), and
    those of the same grid before its first value from ``start`` on and after its last
    value up to ``end``; so the node's phase decides, not the window's length (the length
    times the rate, plus one, expected 16 of graphs/cambada.yaml's 5 Hz ``bgoal``, whose
    phase puts 15 releases in a 3 s session, and 5 of its 1.25 Hz ``bpost``, which had 4).

    The edges are not alike. At the start nothing before the first message counts: a
    timer armed after its origin skips the release there (``flowrt.clock.next_release``:
    strictly after), so the grid's point before a source's first value was never a
    release. At the end a release less than half a period before the last message is
    taken as at the end and not counted: stamps jitter (a frame is stamped when captured,
    its readers' values with it), and a value released just before a live stop may still
    have been on its way (a tracker's result comes up to its deadline after its frame).
    Only a loss in that last half period goes unseen; one anywhere else is ``missing``.

    ``before_first=False``: a stream whose rate its output declares (a CAN message at its
    cycle time, received from the bus) is not released on a grid of the session: its sender
    may begin later than the session (graphs/can.yaml's ``chassis.WheelSpeeds`` begins a
    cycle after ``wheels``, whose first value the transmitting node had not yet at its
    first cycle: "missing 1" on a complete stream), so nothing before its first value is
    expected, and a loss there goes unseen.
    """
    half = period / 2
    if first is None or last is None:  # no value places the grid: the fewest any phase puts
        return max(0, math.floor((end - half - start) / period + _EPS)) if period > 0 else 0
    own = round((last - first) / period) + 1
    before = releases_in(period, first, start, first - half) if before_first else 0
    after = releases_in(period, last, last + half, end - half)
    return own + before + after


def _stream(
    c: StreamCounters,
    hz: float | None,
    window: tuple[float, float] | None,
    own_rate: bool = False,
) -> StreamReport:
    expected = None
    if hz is not None and hz > 0 and window is not None:
        expected = expected_releases(
            1.0 / hz, *window, c.first_seen, c.last_seen, before_first=not own_rate
        )
    iv = c.intervals
    mean = None
    if iv.count > 0 and c.first_time is not None and c.last_time is not None:
        # the intervals the min and max come from, not ``written``: after the writer
        # process was killed the file's recount made it fewer (Hz mean 14.55, min 19.85)
        span = c.last_time - c.first_time
        mean = iv.count / span if span > 0 else None
    return StreamReport(
        topic=c.topic,
        source=c.source,
        nominal_hz=hz,
        expected=expected,
        received=c.received,
        written=c.written,
        lost=c.lost,
        lost_behind=c.lost_behind,
        lost_error=c.lost_error,
        missing=max(0, expected - c.received) if expected is not None else 0,
        rate_mean=mean,
        rate_min=1.0 / iv.max if iv.count and iv.max > 0 else None,
        rate_max=1.0 / iv.min if iv.count and iv.min > 0 else None,
        bytes=c.bytes,
    )


class Written(Protocol):
    """What a report reads of a writer (the thread's or the process's)."""

    @property
    def streams(self) -> dict[str, StreamCounters]: ...
    @property
    def files(self) -> list[Path]: ...
    @property
    def path(self) -> Path: ...
    @property
    def error(self) -> str | None: ...
    @property
    def notes(self) -> list[str]: ...


def build_report(
    writer: Written,
    session: str,
    start_time: str,
    duration: float,
    rates: dict[str, float | None],
    started: float | None = None,
    leads: Mapping[str, float] | None = None,
) -> RecordingReport:
    """The report of a finished (or stopped) writer.

    ``started`` is when the session opened (the runtime clock, as the stamps): a value
    released before it and still on its way is recorded, and stamped earlier, but the
    other streams' releases before it could not be; none of them is expected.

    ``leads``: topic -> seconds from a value's stamp to its release (the largest lag of the
    stream's last values), for the streams not stamped at their release (an audio block: its
    first sample's time); the session's end is shifted onto their stamps (:func:`_on_stamps`).
    """
    firsts = [c.first_seen for c in writer.streams.values() if c.first_seen is not None]
    lasts = [c.last_seen for c in writer.streams.values() if c.last_seen is not None]
    window = (min(firsts), max(lasts)) if firsts and lasts else None
    counted = window
    if window is not None and started is not None:
        counted = (max(window[0], started), window[1])
    leads = leads or {}
    return RecordingReport(
        session=session,
        files=[str(f) for f in writer.files] or [str(writer.path)],
        start_time=start_time,
        duration=duration,
        span=window[1] - window[0] if window is not None else None,
        error=writer.error,
        notes=list(writer.notes),
        streams=[
            _stream(
                c,
                stream_rate(rates, c.source),
                _on_stamps(counted, leads.get(topic)),
                own_rate=c.source in rates,  # its output's declared rate (stream_rate)
            )
            for topic, c in writer.streams.items()
        ],
    )


def _on_stamps(
    counted: tuple[float, float] | None, lead: float | None
) -> tuple[float, float] | None:
    """The session's ``counted`` window as a stream stamped ``lead`` before its releases sees
    it at the end: its grid is placed by its stamps, but what the session's last message
    bounds is a release.

    An audio block is stamped at its first sample and published once complete, a block
    later or two (nodes/audio.py publishes a block at the first activation after it is
    complete, and its first activation's lateness usually makes that the next one). On
    stamps alone, the grid's point after the last block, released after the session's last
    message and so never made, could fall more than half a block before that message's stamp
    and be expected: ``missing 1`` on a complete stream. With the end shifted by the
    stream's lag (the largest of its last values: after a block published at once, the next
    may wait an activation), the point is expected only if its release would have come half
    a period before the end. A loss in the stream's last lag and half period goes unseen.

    The start is left on the stamps: a block stamped before the session's first message
    would hold samples from before the sources began (the first block of a synthetic source
    starts at its first activation), and a lag that varies by a block (the activation's
    lateness against the first one's) would make a shifted start expect one never made.
    """
    if counted is None or lead is None or lead <= 0:
        return counted
    return (counted[0], counted[1] - lead)


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _hz(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def report_table(report: RecordingReport, width: int | None = None) -> Any:
    """A rich Table of the report; lost (and missing) in red: any missing, since expected
    counts the releases themselves (the operator view warns at one too, station/operator.js).

    At a narrow ``width`` (an 80-column terminal) the rate columns go first, then the bytes
    and the expected count; the stream and what was received, written and lost never go.
    """
    from rich.text import Text

    from ..monitors._columns import Column, fit_table

    title = f"recording {report.session}: {report.duration:.1f} s"
    if report.error:
        title += f" (stopped: {report.error})"
    cols: tuple[Column[StreamReport], ...] = (
        Column("stream", lambda s: s.topic, right=False),
        Column("expected", lambda s: "-" if s.expected is None else str(s.expected), drop=5),
        Column("received", lambda s: str(s.received)),
        Column("written", lambda s: str(s.written)),
        Column("lost", lambda s: Text(str(s.lost), style="bold red" if s.lost else "")),
        Column("missing", lambda s: Text(str(s.missing), style="red" if s.missing else ""), drop=6),
        Column("Hz mean", lambda s: _hz(s.rate_mean), drop=3),
        Column("Hz min", lambda s: _hz(s.rate_min), drop=1),
        Column("Hz max", lambda s: _hz(s.rate_max), drop=2),
        Column("bytes", lambda s: human_bytes(s.bytes), drop=4),
    )
    return fit_table(cols, report.streams, width, title=title)


def report_text(report: RecordingReport) -> str:
    """The table as plain text (for logs)."""
    import io

    from rich.console import Console

    console = Console(width=120, color_system=None, file=io.StringIO())
    console.print(report_table(report, console.width))
    out: str = console.file.getvalue()  # type: ignore[attr-defined]
    return out
