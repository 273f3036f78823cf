"""The post-recording check (the acquisition paper's per-stream table): expected vs received
vs written, lost, rate mean/min/max and bytes per stream, lost in red.

``expected`` is the source's nominal rate times the recording's active window (from the
first to the last message the recorder received, any stream, plus one): a source that
delivered less than it should shows up as ``missing`` even when the recorder lost nothing.
The nominal rate comes from the running graph's timing (a timer trigger's period; a frame
trigger's source rate divided by its period), as the runtime's statistics report it, unless
the output declares a rate of its own (``output_hz``: a status every second on a node that
ticks at 100 Hz, a CAN message at its cycle time), or none: an output on events expects
nothing, and nothing of it is ever "missing".
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from pydantic import BaseModel, Field

from .writer import StreamCounters

__all__ = ["RecordingReport", "StreamReport", "build_report", "nominal_rates", "report_table"]


class StreamReport(BaseModel):
    """One stream of a recording."""

    topic: str
    source: str = Field(description="node.port the stream was recorded from")
    nominal_hz: float | None = Field(description="the source's rate by the graph's timing")
    expected: int | None = Field(description="nominal rate x duration (None: not periodic)")
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


def nominal_rates(stats: Any) -> dict[str, float | None]:
    """Node name -> nominal activations per second, for timer- and frame-triggered nodes;
    ``node.port`` -> the rate an output declares of its own (None: no rate)."""
    rows = {n.name: n for n in stats.nodes}
    out: dict[str, float | None] = {}

    def rate(name: str, depth: int = 0) -> float | None:
        if name in out:
            return out[name]
        n = rows.get(name)
        if n is None or depth > 20:
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


def _stream(c: StreamCounters, hz: float | None, window: float | None) -> StreamReport:
    expected = None if hz is None or window is None else round(hz * window) + 1
    iv = c.intervals
    mean = None
    if c.written > 1 and c.first_time is not None and c.last_time is not None:
        span = c.last_time - c.first_time
        mean = (c.written - 1) / span if span > 0 else None
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
) -> RecordingReport:
    """The report of a finished (or stopped) writer."""
    firsts = [c.first_seen for c in writer.streams.values() if c.first_seen is not None]
    lasts = [c.last_seen for c in writer.streams.values() if c.last_seen is not None]
    window = max(lasts) - min(firsts) if firsts else None
    return RecordingReport(
        session=session,
        files=[str(f) for f in writer.files] or [str(writer.path)],
        start_time=start_time,
        duration=duration,
        span=window,
        error=writer.error,
        notes=list(writer.notes),
        streams=[_stream(c, stream_rate(rates, c.source), window) for c in writer.streams.values()],
    )


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _hz(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def report_table(report: RecordingReport, width: int | None = None) -> Any:
    """A rich Table of the report; lost (and missing) in red.

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
        Column(
            "missing", lambda s: Text(str(s.missing), style="red" if s.missing > 1 else ""), drop=6
        ),
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
