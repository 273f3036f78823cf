"""Health monitoring: the machine, the frame streams and the nodes, with alerts.

The ``health`` node (as in the in-vehicle acquisition system it comes from) reports, every
``interval_ms`` (its default timer trigger):

- machine state (psutil): CPU overall and per core, memory, swap, disk and network rates;
- per stream — every input is a frame stream, connected with the ``latest`` policy so the
  node samples the newest frame and never holds the stream back: current/min/max/average
  fps, frame size, inter-frame delta, frames received vs expected and the lost count.
  Arrivals are counted by the edge (``published``), so sampling loses no count. Expected
  frames come from ``expected_fps`` or, when not given, from the highest rate the stream
  has shown (a stream is taken to be healthy when it starts);
- alerts, each a ``flowrt.HealthAlert`` event (so in the status table, and recorded by the
  runtime in the RTDB record ``flowrt.alerts``): a frame-rate drop by ``fps_drop`` against
  the previous measurement, a node still running past its watchdog, a deadline-miss rate
  above ``miss_rate``, loop lag above ``loop_lag_ms``, memory above ``memory_percent``, and
  failed nodes / crashed workers. Conditions that persist are alerted once, when they start.

Outputs a :class:`HealthReport` on ``report`` and writes it to the RTDB (``record``).
The node must run inline (the default): it reads the runtime's statistics on the loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from flowrt import (
    Frame,
    HealthAlert,
    Input,
    Node,
    Output,
    RuntimeStats,
    TimerMs,
    TimerTrigger,
)

__all__ = ["Health", "HealthReport", "MachineState", "StreamState"]


@dataclass(frozen=True)
class MachineState:
    cpu_percent: float
    cpu_per_core: tuple[float, ...]
    memory_percent: float
    memory_used_mb: float
    memory_total_mb: float
    swap_percent: float
    disk_read_mb_s: float
    disk_write_mb_s: float
    net_rx_mb_s: float
    net_tx_mb_s: float


@dataclass(frozen=True)
class StreamState:
    """One frame stream over the last interval (fps) and since the first frame (counts)."""

    name: str  # the health node's input
    source: str  # the node that produced the frames
    fps: float
    fps_min: float
    fps_max: float
    fps_avg: float
    frame_bytes: int
    shape: tuple[int, ...]
    delta_ms: float  # mean time between consecutive frames over the interval
    received: int
    expected: int
    lost: int
    # age of the newest frame at this report: since its publication, or since its capture
    # when that is older (flowrt.freshness); None when unknown (no frame, or in a worker)
    age_ms: float | None = None


@dataclass(frozen=True)
class HealthReport:
    t: float  # runtime clock, seconds since start
    machine: MachineState | None
    streams: tuple[StreamState, ...]
    alerts: tuple[HealthAlert, ...]  # raised by this report
    active: tuple[str, ...]  # conditions that still hold, e.g. "fps_drop front_cam"


Fps = Annotated[float, Field(gt=0, le=1000)]


class HealthParams(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    interval_ms: TimerMs = Field(default=1000.0, description="report period")
    expected_fps: Fps | dict[str, Fps] | None = Field(
        default=None, description="nominal fps, for every stream or per input name"
    )
    fps_drop: float = Field(default=0.2, gt=0, lt=1, description="alert on this relative drop")
    miss_rate: float = Field(default=0.05, gt=0, le=1, description="per-node deadline misses")
    loop_lag_ms: float = Field(
        default=10.0, gt=0, le=3_600_000, description="mean loop lag over the interval"
    )
    memory_percent: float | None = Field(default=90.0, gt=0, le=100)
    watchdog_ms: float | None = Field(
        default=None,
        gt=0,
        le=3_600_000,
        description="for nodes without their own watchdog (None: skip them)",
    )
    watchdogs: dict[str, Annotated[float, Field(gt=0, le=3_600_000)]] = Field(
        default_factory=dict, description="per node, ms"
    )
    machine: bool = Field(default=True, description="report machine state (psutil)")
    record: str | None = Field(default="health", description="RTDB record of the report")


@dataclass
class _Stream:
    first_t: float
    last_t: float
    first_received: int
    last_received: int
    source: str = ""
    frame_ts: float | None = None
    frame_seq: int | None = None
    fps_prev: float | None = None
    fps_min: float = float("inf")
    fps_max: float = 0.0
    expected: float = 0.0
    nbytes: int = 0
    shape: tuple[int, ...] = ()


@dataclass
class _Counters:
    activations: int
    misses: int
    errors: int
    restarts: int


@dataclass
class _State:
    streams: dict[str, _Stream] = field(default_factory=dict)
    nodes: dict[str, _Counters] = field(default_factory=dict)
    lag: tuple[int, float] = (0, 0.0)  # (count, mean) of the loop-lag probe
    active: set[str] = field(default_factory=set)
    watchdog_seen: dict[str, float] = field(default_factory=dict)


class Health(Node):
    """Machine, stream and node health, with alerts (see the module docstring)."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset(
        {"interval_ms", "expected_fps", "fps_drop", "miss_rate", "loop_lag_ms", "memory_percent"}
    )

    Params = HealthParams
    external = True  # it reads the machine: its reports are recorded values, not recomputed
    any_inputs = Input(Frame, required=False, doc="frame streams to watch (any input name)")
    report = Output(HealthReport)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=params.interval_ms)

    def setup(self) -> None:
        self.state = _State()
        self._io: tuple[float, Any, Any] | None = None
        if self.params.machine:
            import psutil

            psutil.cpu_percent(percpu=True)  # the first call only starts the measurement
            self._io = (time.monotonic(), _disk(), psutil.net_io_counters())

    def process(self, **frames: Frame | None) -> HealthReport:
        now = self.ctx.now()
        try:
            stats: RuntimeStats | None = self.ctx.stats()
        except RuntimeError:  # not on the loop: machine and frame-based stream state only
            stats = None
        t = stats.uptime if stats is not None else now
        alerts: list[HealthAlert] = []

        def alert(key: str, subject: str | None, detail: str, severity: str = "warning") -> None:
            alerts.append(HealthAlert(t, subject, key, detail, severity))

        def condition(key: str, subject: str | None, holds: bool, detail: str) -> None:
            """Alert when a condition starts to hold; stay quiet while it goes on."""
            name = f"{key} {subject or 'runtime'}"
            if holds and name not in self.state.active:
                self.state.active.add(name)
                alert(key, subject, detail)
            elif not holds:
                self.state.active.discard(name)

        streams = [
            self._stream(port, frame, now, stats, condition) for port, frame in frames.items()
        ]
        if stats is not None:
            self._nodes(stats, alert, condition)
        machine = self._machine() if self.params.machine else None
        if machine is not None and self.params.memory_percent is not None:
            limit = self.params.memory_percent
            condition(
                "memory",
                None,
                machine.memory_percent > limit,
                f"memory {machine.memory_percent:.0f}% > {limit:g}%",
            )
        for a in alerts:
            self.ctx.emit(a)
        report = HealthReport(
            t,
            machine,
            tuple(s for s in streams if s is not None),
            tuple(alerts),
            tuple(sorted(self.state.active)),
        )
        if self.params.record:
            try:
                self.ctx.rtdb.write(
                    self.params.record, report, validity_ms=self.params.interval_ms * 2
                )
            except (RuntimeError, ValueError) as e:  # no RTDB here, or a report too large
                self.ctx.log.debug("health report not recorded: %s", e)
        return report

    # --- streams --------------------------------------------------------------------------

    def _stream(
        self, port: str, frame: Frame | None, now: float, stats: RuntimeStats | None, condition: Any
    ) -> StreamState | None:
        received = None
        if stats is not None:
            try:
                received = stats.edge(f"{self.ctx.name}.{port}").published
            except KeyError:
                received = None
        st = self.state.streams.get(port)
        if st is None:
            if frame is None and not received:
                return None  # nothing has come yet: the stream starts with its first frame
            count = received if received is not None else 1
            st = _Stream(first_t=now, last_t=now, first_received=count, last_received=count)
            self.state.streams[port] = st
            self._note_frame(st, frame)
            return None
        if received is None:  # outside a runtime: count distinct frames by seq
            seq_step = (
                0 if frame is None or st.frame_seq is None else max(0, frame.seq - st.frame_seq)
            )
            received = st.last_received + seq_step
        dt = now - st.last_t
        if dt <= 0:
            return None
        got = received - st.last_received
        fps = got / dt
        delta_ms = dt * 1000 / got if got else 0.0
        if (
            frame is not None
            and st.frame_seq is not None
            and frame.seq > st.frame_seq
            and frame.timestamp
        ):
            assert st.frame_ts is not None
            delta_ms = (frame.timestamp - st.frame_ts) * 1000 / (frame.seq - st.frame_seq)
        self._note_frame(st, frame)
        st.fps_min = min(st.fps_min, fps)
        st.fps_max = max(st.fps_max, fps)
        nominal = self._expected_fps(port)
        st.expected += (nominal if nominal is not None else st.fps_max) * dt
        total = received - st.first_received
        if st.fps_prev is not None:
            drop = fps < st.fps_prev * (1 - self.params.fps_drop)
            name = st.source or port
            detail = f"{name}: {st.fps_prev:.1f} -> {fps:.1f} fps"
            condition("fps_drop", name, drop, detail)
        st.fps_prev = fps
        st.last_t, st.last_received = now, received
        return StreamState(
            name=port,
            source=st.source,
            fps=fps,
            fps_min=st.fps_min,
            fps_max=st.fps_max,
            fps_avg=total / (now - st.first_t),
            frame_bytes=st.nbytes,
            shape=st.shape,
            delta_ms=delta_ms,
            received=total,
            expected=round(st.expected),
            lost=max(0, round(st.expected) - total),
            age_ms=None if (age := self.ctx.input_age(port, frame)) is None else age * 1000,
        )

    @staticmethod
    def _note_frame(st: _Stream, frame: Frame | None) -> None:
        if frame is None:
            return
        st.source = frame.source or st.source
        st.nbytes, st.shape = frame.nbytes, frame.shape
        st.frame_seq = frame.seq
        st.frame_ts = frame.timestamp

    def _expected_fps(self, port: str) -> float | None:
        exp = self.params.expected_fps
        if isinstance(exp, dict):
            exp = exp.get(port)
        return None if exp is None else float(exp)

    # --- nodes and the loop ---------------------------------------------------------------

    def _nodes(self, stats: RuntimeStats, alert: Any, condition: Any) -> None:
        p = self.params
        seen = self.state.nodes
        for n in stats.nodes:
            if n.name == self.ctx.name:
                continue
            before = seen.get(n.name)
            seen[n.name] = _Counters(n.activations, n.deadline_misses, n.errors, n.restarts)
            # watchdog: still running long after it started
            wd_ms = p.watchdogs.get(n.name) or getattr(n, "watchdog_ms", None) or p.watchdog_ms
            wd = float("inf") if wd_ms is None else wd_ms / 1000
            started = n.last_start
            overdue = n.state == "running" and started is not None and stats.uptime - started > wd
            if overdue and started is not None and self.state.watchdog_seen.get(n.name) != started:
                self.state.watchdog_seen[n.name] = started  # once per activation
                ran = (stats.uptime - started) * 1000
                detail = f"{n.name} running for {ran:.0f} ms (watchdog {wd * 1000:g} ms)"
                alert("watchdog", n.name, detail)
            if before is None:
                continue
            acts = n.activations - before.activations
            misses = n.deadline_misses - before.misses
            # A miss is counted at the deadline, after its activation: they may fall in
            # different intervals, hence the max.
            acts = max(acts, misses)
            rate = misses / acts if acts else 0.0
            condition(
                "deadline_misses",
                n.name,
                rate > p.miss_rate,
                f"{n.name}: {misses} of {acts} activations missed the deadline ({rate:.0%})",
            )
            failed = n.errors - before.errors
            if failed > 0:
                crash = "worker_crash" if n.placement != "inline" else "node_failed"
                restarts = n.restarts - before.restarts
                alert(
                    crash,
                    n.name,
                    f"{n.name}: {failed} failure(s), {restarts} restart(s), now {n.state}",
                    "error",
                )
        count, mean = stats.loop.lag.count, stats.loop.lag.mean
        prev_count, prev_mean = self.state.lag
        self.state.lag = (count, mean)
        if count > prev_count:
            window = (mean * count - prev_mean * prev_count) / (count - prev_count)
            condition(
                "loop_lag",
                None,
                window > p.loop_lag_ms,
                f"loop lag {window:.1f} ms > {p.loop_lag_ms:g} ms",
            )

    # --- the machine ----------------------------------------------------------------------

    def _machine(self) -> MachineState:
        import psutil

        cores = tuple(float(c) for c in psutil.cpu_percent(percpu=True))
        mem = psutil.virtual_memory()
        swap = psutil.swap_memory()
        now, disk, net = time.monotonic(), _disk(), psutil.net_io_counters()
        assert self._io is not None
        t0, disk0, net0 = self._io
        self._io = (now, disk, net)
        dt = max(now - t0, 1e-6)

        def rate(new: Any, old: Any, attr: str) -> float:
            if new is None or old is None:
                return 0.0
            return float(max(0, getattr(new, attr) - getattr(old, attr))) / dt / 1e6

        return MachineState(
            cpu_percent=sum(cores) / len(cores) if cores else 0.0,
            cpu_per_core=cores,
            memory_percent=float(mem.percent),
            memory_used_mb=(mem.total - mem.available) / 1e6,
            memory_total_mb=mem.total / 1e6,
            swap_percent=float(swap.percent),
            disk_read_mb_s=rate(disk, disk0, "read_bytes"),
            disk_write_mb_s=rate(disk, disk0, "write_bytes"),
            net_rx_mb_s=rate(net, net0, "bytes_recv"),
            net_tx_mb_s=rate(net, net0, "bytes_sent"),
        )


def _disk() -> Any:
    import psutil

    try:
        return psutil.disk_io_counters()
    except (RuntimeError, OSError):  # no disks visible (some containers)
        return None
