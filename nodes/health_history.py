"""Health over time: the machine and each camera stream, sampled into a ring buffer.

The live view's server process (:mod:`flowrt.nodes.station.server`) samples once a second
(``health_hz``) and keeps ``health_keep_s`` seconds (15 minutes by default), as the
acquisition system the operator's station comes from plotted its machines and sensors over
a campaign: CPU per core, memory, swap, disk use and write rate, network, and per stream its
frame rate, drops and age. Sampling here, in the view's own process at nice 19, costs the
runtime's event loop nothing but the statistics answer it already gives the page.

A stream's rate that falls below ``ALERT_FRACTION`` of what it has held (the median of its
last ``REFERENCE_SAMPLES`` samples), or frames dropped, raise the seed's alert
(``ALERT - FRAME DROPS``) once when the condition starts; the page marks it on the plots.
"""

from __future__ import annotations

import statistics
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

ALERT_TEXT = "ALERT - FRAME DROPS"
ALERT_FRACTION = 0.8  # a rate below this fraction of the stream's usual rate is an alert
REFERENCE_SAMPLES = 30  # samples the usual rate is the median of
MIN_REFERENCE = 5  # samples before a stream's rate can be judged


@dataclass(frozen=True)
class Series:
    """What a series is, for the page's plots: its group (one plot each) and unit."""

    name: str
    group: str
    unit: str
    label: str


@dataclass
class _Stream:
    """A stream between samples: its counters at the last sample and its recent rates."""

    drops_total: int | None = None
    rates: deque[float] = field(default_factory=lambda: deque(maxlen=REFERENCE_SAMPLES))
    alerting: bool = False


@dataclass
class _Sample:
    t: float  # Unix seconds
    values: dict[str, float | None]


class HealthHistory:
    """The ring of samples; :meth:`sample` once per period, :meth:`window` for the page."""

    def __init__(self, keep_s: float = 900.0, hz: float = 1.0, disk_path: str = "/") -> None:
        self.hz = hz
        self.disk_path = disk_path
        self.samples: deque[_Sample] = deque(maxlen=max(2, int(keep_s * hz) + 1))
        self.series: dict[str, Series] = {}
        self.alerts: deque[dict[str, Any]] = deque(maxlen=1000)
        self._streams: dict[str, _Stream] = {}
        self._io: tuple[float, Any, Any] | None = None
        self._psutil: Any = None

    # --- sampling ---------------------------------------------------------------------------

    def sample(self, stats: dict[str, Any] | None, now: float | None = None) -> None:
        """One sample: the machine now, and the streams from the view's statistics answer
        (``{"runtime": RuntimeStats, "display": {...}}``, or None when none came)."""
        t = time.time() if now is None else now
        values: dict[str, float | None] = {}
        self._machine(values)
        if stats is not None:
            self._stream_values(stats, values, t)
        self.samples.append(_Sample(t, values))

    def _declare(self, name: str, group: str, unit: str, label: str) -> str:
        if name not in self.series:
            self.series[name] = Series(name, group, unit, label)
        return name

    def _machine(self, values: dict[str, float | None]) -> None:
        if self._psutil is None:
            import psutil

            self._psutil = psutil
            psutil.cpu_percent(percpu=True)  # the first call starts the measurement
        ps = self._psutil
        for i, pct in enumerate(ps.cpu_percent(percpu=True)):
            values[self._declare(f"cpu.{i}", "cpu", "%", f"core {i}")] = float(pct)
        values[self._declare("memory", "memory", "%", "memory")] = ps.virtual_memory().percent
        values[self._declare("swap", "memory", "%", "swap")] = ps.swap_memory().percent
        try:
            disk: float | None = ps.disk_usage(self.disk_path).percent
        except OSError:
            disk = None
        values[self._declare("disk", "memory", "%", f"disk {self.disk_path}")] = disk
        mono = time.monotonic()
        io, net = ps.disk_io_counters(), ps.net_io_counters()
        write = sent = received = None
        if self._io is not None:
            last_t, last_io, last_net = self._io
            dt = mono - last_t
            if dt > 0:
                if io is not None and last_io is not None:
                    write = max(0.0, (io.write_bytes - last_io.write_bytes) / dt)
                if net is not None and last_net is not None:
                    sent = max(0.0, (net.bytes_sent - last_net.bytes_sent) / dt)
                    received = max(0.0, (net.bytes_recv - last_net.bytes_recv) / dt)
        self._io = (mono, io, net)
        values[self._declare("disk.write", "disk", "B/s", "disk write")] = _or_zero(write, io)
        values[self._declare("net.sent", "network", "B/s", "sent")] = _or_zero(sent, net)
        values[self._declare("net.received", "network", "B/s", "received")] = _or_zero(
            received, net
        )

    def _stream_values(
        self, stats: dict[str, Any], values: dict[str, float | None], t: float
    ) -> None:
        runtime = stats.get("runtime") or {}
        display = stats.get("display") or {}
        nodes = {n.get("name"): n for n in runtime.get("nodes", [])}
        pools = {p.get("owner"): p for p in runtime.get("frames", [])}
        for src in sorted(display.get("sources", []), key=lambda s: str(s.get("name"))):
            name = str(src.get("name"))
            node = nodes.get(src.get("node"), {})
            pool = pools.get(src.get("node"), {})
            total = int(node.get("skipped", 0)) + int(node.get("dropped", 0))
            total += int(pool.get("dropped", 0))
            state = self._streams.setdefault(name, _Stream())
            drops = 0 if state.drops_total is None else max(0, total - state.drops_total)
            state.drops_total = total
            fps = float(src.get("fps") or 0.0)
            age = src.get("age")
            values[self._declare(f"stream.{name}.fps", "fps", "fps", name)] = fps
            values[self._declare(f"stream.{name}.drops", "drops", "frames", name)] = drops
            values[self._declare(f"stream.{name}.age", "age", "ms", name)] = (
                None if age is None else float(age) * 1000.0
            )
            self._judge(name, state, fps, drops, t)

    def _judge(self, name: str, state: _Stream, fps: float, drops: int, t: float) -> None:
        """An alert when the rate falls well below its usual value, or frames drop."""
        usual = statistics.median(state.rates) if len(state.rates) >= MIN_REFERENCE else None
        low = usual is not None and fps < ALERT_FRACTION * usual
        bad = low or drops > 0
        if bad and not state.alerting:
            self.alerts.append(
                {
                    "t": t,
                    "stream": name,
                    "text": ALERT_TEXT,
                    "fps": round(fps, 2),
                    "usual_fps": None if usual is None else round(usual, 2),
                    "drops": drops,
                }
            )
        state.alerting = bad
        if not low:  # the usual rate is learnt from healthy samples only
            state.rates.append(fps)

    # --- reading ----------------------------------------------------------------------------

    def window(self, seconds: float) -> dict[str, Any]:
        """The samples of the last ``seconds``: one time axis, every series aligned on it
        (None where a series had no value, e.g. a stream that had not started)."""
        end = self.samples[-1].t if self.samples else time.time()
        chosen = [s for s in self.samples if s.t > end - seconds]
        names = [n for n in self.series if any(n in s.values for s in chosen)]
        first = chosen[0].t if chosen else end
        return {
            "interval_s": 1.0 / self.hz,
            "keep_s": (self.samples.maxlen or 0) / self.hz,
            "t": [round(s.t, 3) for s in chosen],
            "series": [
                {
                    "name": n,
                    "group": self.series[n].group,
                    "unit": self.series[n].unit,
                    "label": self.series[n].label,
                    "values": [_round(s.values.get(n)) for s in chosen],
                }
                for n in names
            ],
            "alerts": [a for a in self.alerts if a["t"] >= first],
        }


def _or_zero(rate: float | None, counters: Any) -> float | None:
    """The first sample has no rate yet: 0 there, so every series starts with the machine;
    None only when the machine gives no counters at all (some containers)."""
    if counters is None:
        return None
    return 0.0 if rate is None else rate


def _round(v: float | None) -> float | None:
    return None if v is None else round(float(v), 3)
