"""Per-tick load: how much work each frame of a source sets off, per CPU and per placement.

The CAMBADA paper chose periods and phases *in frames* so that no frame carries too much
work (its timeline figure); this is that table with budgets: over one hyperperiod of the
frame periods of a source's readers, which nodes run on each tick and their summed budget on
the event loop, in the workers (and on each CPU they are pinned to), in the pool, against the
frame interval. A tick whose work exceeds the frame interval on one resource cannot be done
before the next frame arrives there, whatever the priorities.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from math import lcm

from .timing import NodeTiming, interval_ms

MAX_TICKS = 256


@dataclass(frozen=True)
class TickLoad:
    tick: int
    nodes: list[str]
    total_ms: float
    loop_ms: float
    workers_ms: float
    pool_ms: float
    per_cpu_ms: dict[str, float] = field(default_factory=dict)  # "cpu 0", ..., "any cpu"
    per_worker_ms: dict[str, float] = field(default_factory=dict)
    unbudgeted: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class LoadTable:
    source: str
    frame_ms: float | None
    ticks: list[TickLoad]
    truncated: bool = False  # the hyperperiod was longer than MAX_TICKS

    @property
    def heaviest(self) -> int:
        """Index of the tick with the largest total budget (the most nodes if none known)."""
        return max(
            range(len(self.ticks)), key=lambda k: (self.ticks[k].total_ms, len(self.ticks[k].nodes))
        )

    @property
    def peak_ms(self) -> float:
        return max((t.total_ms for t in self.ticks), default=0.0)

    @property
    def peak_nodes(self) -> int:
        return max((len(t.nodes) for t in self.ticks), default=0)


def frame_readers(timing: Mapping[str, NodeTiming]) -> dict[str, list[NodeTiming]]:
    """Enabled frame-triggered nodes per source, in dispatch order (priority, file order)."""
    out: dict[str, list[NodeTiming]] = {}
    for t in timing.values():
        if t.enabled and t.trigger == "frame" and t.source is not None:
            out.setdefault(t.source, []).append(t)
    for readers in out.values():
        readers.sort(key=lambda t: (-t.priority, t.order))
    return out


def load_tables(timing: Mapping[str, NodeTiming]) -> list[LoadTable]:
    """One table per frame source over one hyperperiod of its readers' periods."""
    tables = []
    for source, readers in frame_readers(timing).items():
        h = lcm(*(r.period for r in readers))
        ticks = []
        for k in range(min(h, MAX_TICKS)):
            active = [r for r in readers if k % r.period == r.phase % r.period]
            loop = workers = pool = 0.0
            per_cpu: dict[str, float] = {}
            per_worker: dict[str, float] = {}
            unbudgeted = []
            for r in active:
                if r.budget is None:
                    unbudgeted.append(r.name)
                    continue
                c = r.budget.ms
                if r.placement == "inline":
                    loop += c
                elif r.placement == "pool":
                    pool += c
                else:
                    workers += c
                    per_worker[r.name] = c
                    key = "any cpu" if r.cpus is None else ",".join(f"cpu {x}" for x in r.cpus)
                    per_cpu[key] = per_cpu.get(key, 0.0) + c
            ticks.append(
                TickLoad(
                    k,
                    [r.name for r in active],
                    loop + workers + pool,
                    loop,
                    workers,
                    pool,
                    dict(sorted(per_cpu.items())),
                    per_worker,
                    unbudgeted,
                )
            )
        tables.append(LoadTable(source, interval_ms(timing, source), ticks, h > MAX_TICKS))
    return tables
