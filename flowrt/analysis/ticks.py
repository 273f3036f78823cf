"""Static views of a graph: which nodes run on which tick over one hyperperiod.

The same table the CAMBADA paper draws to choose phases: with it a user sees which ticks are
crowded before running anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from math import gcd

from ..graph._resolve import Graph, hyperperiod
from ..graph.spec import FrameTrigger, TimerTrigger


@dataclass(frozen=True)
class ActivationTable:
    """Rows are nodes (dispatch order), columns ticks; ``unit`` says what a tick is."""

    clock: str
    unit: str
    ticks: int
    rows: list[tuple[str, int, list[bool]]]  # name, priority, active per tick

    def load(self) -> list[int]:
        """Number of activations on each tick."""
        return [sum(r[2][k] for r in self.rows) for k in range(self.ticks)]


def activation_tables(graph: Graph, max_ticks: int = 64) -> list[ActivationTable]:
    tables: list[ActivationTable] = []
    by_source: dict[str, list[tuple[str, int, FrameTrigger, int]]] = {}
    timers: list[tuple[str, int, TimerTrigger, int]] = []
    for name, node in graph.nodes.items():
        trig = node.trigger
        if isinstance(trig, FrameTrigger):
            by_source.setdefault(graph.frame_port(trig.frame), []).append(
                (name, node.spec.priority, trig, node.order)
            )
        elif isinstance(trig, TimerTrigger):
            timers.append((name, node.spec.priority, trig, node.order))
    for source, readers in by_source.items():
        readers.sort(key=lambda r: (-r[1], r[3]))
        h = min(hyperperiod([t.period for _, _, t, _ in readers]), max_ticks)
        rows = [(n, p, [k % t.period == t.phase for k in range(h)]) for n, p, t, _ in readers]
        interval = graph.frame_interval_ms(source)
        unit = "frame" + (f" ({interval:g} ms)" if interval else "")
        tables.append(ActivationTable(source, unit, h, rows))
    if timers:
        timers.sort(key=lambda r: (-r[1], r[3]))
        fracs = [Fraction(str(v)) for _, _, t, _ in timers for v in (t.timer, t.phase) if v]
        base = fracs[0]
        for f in fracs[1:]:
            num = gcd(base.numerator * f.denominator, f.numerator * base.denominator)
            base = Fraction(num, base.denominator * f.denominator)
        periods = [int(Fraction(str(t.timer)) / base) for _, _, t, _ in timers]
        h = min(hyperperiod(periods), max_ticks)
        rows = []
        for (n, p, t, _), per in zip(timers, periods, strict=True):
            ph = int(Fraction(str(t.phase)) / base)
            rows.append((n, p, [k % per == ph for k in range(h)]))
        tables.append(ActivationTable("timers", f"{float(base):g} ms", h, rows))
    return tables
