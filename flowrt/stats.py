"""Statistics: the process-manager table of the CAMBADA paper, per node and per edge.

Counters are updated on the hot path, so they are plain attributes and a fixed-size ring of
recent samples; percentiles and snapshots are computed only when someone asks. Snapshots are
frozen pydantic models, so ``--stats-json`` has a schema (``flowrt schema stats``).
"""

from __future__ import annotations

import math
from array import array
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, WithJsonSchema

RING = 2048  # recent samples kept for percentiles: ~100 s at 20 Hz


class Running:
    """Min/max/mean/std over every sample (Welford), plus a ring of recent samples.

    ``add`` is on the hot path (a few per activation), so it only does arithmetic and one
    array store; percentiles are computed by ``summary`` with a partial sort.
    """

    __slots__ = ("_last", "count", "i", "m2", "max", "mean", "min", "ring")

    def __init__(self) -> None:
        self.count = 0
        self.mean = 0.0
        self.m2 = 0.0
        self.min = math.inf
        self.max = -math.inf
        self.ring = array("d")
        self.i = 0
        self._last: tuple[int, float, Summary] | None = None  # (count, scale, snapshot)

    def add(self, x: float) -> None:
        self.count += 1
        d = x - self.mean
        self.mean += d / self.count
        self.m2 += d * (x - self.mean)
        if x < self.min:
            self.min = x
        if x > self.max:
            self.max = x
        if len(self.ring) < RING:
            self.ring.append(x)
        else:
            self.ring[self.i] = x
            self.i = (self.i + 1) % RING

    def summary(self, scale: float = 1000.0) -> Summary:
        """Snapshot in milliseconds (samples are seconds).

        Taken on the loop for every node and edge at each ``stats()`` (the live table asks 4
        times a second): with 1000 nodes that was 39 ms a call. A summary whose samples did
        not change is the one made last time. (``model_construct`` was tried: slower than
        pydantic's validation in Rust, 7.5 against 2.6 us.)
        """
        if not self.count:
            return Summary()
        last = self._last
        if last is not None and last[0] == self.count and last[1] == scale:
            return last[2]
        recent = np.frombuffer(self.ring, dtype=np.float64)
        n = len(recent)
        k50, k99 = min(n - 1, int(0.5 * n)), min(n - 1, int(0.99 * n))
        part = np.partition(recent, (k50, k99))
        std = math.sqrt(self.m2 / (self.count - 1)) if self.count > 1 else 0.0
        out = Summary(
            count=self.count,
            min=self.min * scale,
            max=self.max * scale,
            mean=self.mean * scale,
            std=std * scale,
            p50=float(part[k50]) * scale,
            p99=float(part[k99]) * scale,
        )
        self._last = (self.count, scale, out)
        return out


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True)


class Summary(_Frozen):
    """Distribution of a duration, milliseconds. p50/p99 are over the most recent samples."""

    count: int = 0
    min: float = 0.0
    max: float = 0.0
    mean: float = 0.0
    std: float = 0.0
    p50: float = 0.0
    p99: float = 0.0


class NodeStats(_Frozen):
    """One row of the process-manager table."""

    name: str
    kind: str
    placement: str
    trigger: str
    priority: int
    period: str = Field(description="as the table shows it: 66.67ms, 100ms +5ms, each, 1/4 +3")
    period_frames: int | None = Field(
        default=None, description="frame triggers: every this many frames"
    )
    timer_ms: float | None = Field(default=None, description="timer triggers: the period, ms")
    deadline_ms: float | None = None  # (defaults: a live message leaves None out)
    watchdog_ms: float | None = None
    enabled: bool
    state: str = Field(description="idle, running, waiting, backoff, error, failed or disabled")
    reason: str = Field(
        default="", description="why the node is in error, failed or waiting (for an operator)"
    )
    activations: int = Field(
        description="releases: ticks, timer expiries, inputs that asked for a run"
    )
    completions: int
    skipped: int = Field(
        description="releases not run: previous one still running (overrun), node down "
        "(backoff, starting) or a required input missing"
    )
    deadline_misses: int
    discarded: int = Field(description="results dropped by a firm (discard) deadline")
    aborted: int = Field(
        default=0,
        description="activations in flight to a worker lost when it (or the node) failed "
        "under an earlier one (pipelined calls)",
    )
    direct_hops: int = Field(
        default=0,
        description="activations whose input frame came straight from its writer's worker, "
        "the call sent ahead (a direct hop between workers)",
    )
    dropped: int = Field(
        default=0,
        description="data lost at this node: dropped values on its input edges + discarded "
        "and aborted activations; never unread samples",
    )
    paced_lead_max: int = Field(
        default=0,
        description="a period-1 frame reader of a pacing: fast source: the most frames the "
        "source had published that this node had not finished (1: lock-step; a worker node "
        "of its own takes up to its pipeline window, 2 by default)",
    )
    errors: int
    restarts: int
    last_start: float | None = Field(
        default=None, description="runtime clock, seconds since start (None: never run)"
    )
    last_finish: float | None = None
    timing_changed: float | None = Field(
        default=None,
        description="when its release timing (period, phase, timer, enabled) last changed at "
        "run time, runtime clock, seconds since start (None: never); a recording's expected "
        "count of its streams is not computed across it",
    )
    interval: Summary = Field(description="inter-activation time (start to start), ms")
    execution: Summary = Field(description="start to finish, ms")
    response: Summary = Field(description="release (tick) to finish, ms")
    granted: str = Field(default="", description="OS scheduling granted to the worker process")
    output_hz: dict[str, float | None] = Field(
        default_factory=dict,
        description="expected publications per second of the outputs with a rate of their "
        "own (None: no rate, on events); the others publish once per activation",
    )


class EdgeStats(_Frozen):
    """One input's buffer. Every published value ends up in exactly one of ``delivered``,
    ``dropped``, ``unread``, or is still held (at most ``size``)."""

    name: str
    policy: str
    size: int
    published: int
    delivered: int
    dropped: int = Field(
        description="values lost that the reader wanted: a full queue's oldest, a latest value "
        "overwritten before an input-triggered reader ran or while a sampling reader's "
        "release was skipped"
    )
    unread: int = Field(
        default=0,
        description="values a sampling reader (frame/timer trigger on a latest edge) never "
        "needed: e.g. 3 frames in 4 for a period-4 reader; by design, not a loss",
    )
    drop_reasons: dict[str, int] = Field(
        default_factory=dict,
        description="every drop by its reason: overwritten (latest), queue full (queue) while "
        "running; stop, drain timeout, interrupted, reader failed at the end",
    )
    sampled: bool = Field(
        description="the reader samples the newest value; unread values are expected"
    )
    age: Summary = Field(description="age of data when consumed, ms")


class LoopStats(_Frozen):
    lag: Summary = Field(description="lateness of a 10 ms probe timer on the event loop, ms")
    blocked_calls: int = Field(
        description="inline calls that blocked the loop longer than the threshold"
    )
    starvation_events: int = Field(
        default=0,
        description="worker calls past their watchdog spared because the worker was starved "
        "of CPU (waiting on the run queue), not hung",
    )


class FramePoolStats(_Frozen):
    """A producer's frame pool: a frame is dropped (counted) only when every slot is held."""

    owner: str
    slots: int
    slots_in_use: int
    max_slots: int
    grown: int
    dropped: int


class WorkerFrameStats(_Frozen):
    """Frames a worker node made and how they reached the main process (flowrt.frames.lending)."""

    node: str
    in_slots: int = Field(description="frames written into a slot lent to the worker: zero copy")
    by_socket: dict[str, int] = Field(
        default_factory=dict,
        description="frames whose pixels crossed the worker's socket, by reason (not-granted, "
        "no-free-slot, too-large, nested)",
    )
    granted: int = Field(description="slots lent to the worker so far")
    outstanding: int = Field(description="slots lent now")
    refused: int = Field(description="grants the pool could not serve (every slot held)")
    reclaimed: int = Field(description="slots taken back from a worker that died or restarted")


class RuntimeStats(_Frozen):
    """Everything ``rt.stats()`` and ``--stats-json`` report."""

    graph: str
    uptime: float = Field(description="seconds since the runtime started")
    mode: str | None = None
    realtime: str = ""
    loop_scheduling: str = Field(
        default="", description="OS scheduling of the loop process, e.g. SCHED_FIFO 90 or nice -20"
    )
    cpu_latency: str = Field(
        default="",
        description="the PM QoS CPU latency request of --cpu-latency: 'held at 0 us', or why "
        "not ('not held: ...'); empty when not asked for",
    )
    nodes: list[NodeStats]
    edges: list[EdgeStats]
    loop: LoopStats
    frames: list[FramePoolStats] = Field(
        default_factory=list, description="shared-memory frame pools: slots, growth, drops"
    )
    worker_frames: list[WorkerFrameStats] = Field(
        default_factory=list,
        description="frames made in worker processes: in shared-memory slots or by the socket",
    )
    events: int = Field(description="events published so far (misses, errors, restarts, changes)")
    # A node's report() may return any JSON-able value (node.py), and the recorder's is a
    # list, not an object; only None is never stored (kernel/views.py reports_of). So the
    # schema of a report says "any value but null", the most that holds for every kind.
    reports: dict[str, Annotated[Any, WithJsonSchema({"not": {"type": "null"}})]] = Field(
        default_factory=dict,
        description="what nodes report about themselves (their optional report() hook), by "
        "node name: e.g. a recorder's per-stream table of each recording",
    )

    def node(self, name: str) -> NodeStats:
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(name)

    def edge(self, name: str) -> EdgeStats:
        """By full name ``src.port->dst.port`` or by its reader ``dst.port``."""
        for e in self.edges:
            if e.name == name or e.name.endswith("->" + name):
                return e
        raise KeyError(name)
