"""Phase advice: offsets that spread work over the ticks while keeping every period.

Choosing offsets so that periodic tasks released on a common tick grid do not pile up is the
offset-assignment problem (Goossens 2003, "Scheduling of offset free systems"; Grenier,
Goossens & Navet 2008 for the CAN case); the CAMBADA paper did it by hand for its trackers
(Table 2: at most 5 trackers on a frame instead of 9). Here, per frame source, the phase of
each reader (in frames, ``0 <= phase < period``) is chosen to minimise the heaviest tick —
its summed budget, or the number of nodes when budgets are missing — then the spread
(sum of squared tick loads), then the number of phases changed. The search is exact
(branch and bound, heaviest node first) up to :data:`MAX_STEPS` partial assignments and the
best found so far (never worse than the current phases) beyond.

Timers get the same treatment on a grid of ``gcd(timer periods) / number of timers`` ms, each
timer weighted by its own budget plus the mean per-frame work of the nodes its frames
trigger, so that two cameras are advised apart and their trackers do not contend.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from math import gcd, lcm

from .load import frame_readers
from .timing import NodeTiming

MAX_STEPS = 200_000
MAX_SLOTS = 2048


@dataclass(frozen=True)
class PhaseAdvice:
    """Advised phases of the nodes on one tick grid (a frame source, or the timers)."""

    clock: str  # frame source name, or "timers"
    unit: str  # "frame" or "ms"
    measure: str  # "ms" (summed budget) or "nodes" (no budgets known)
    periods: dict[str, float]
    before: dict[str, float]
    after: dict[str, float]
    peak_before: float
    peak_after: float

    @property
    def changed(self) -> dict[str, float]:
        return {n: p for n, p in self.after.items() if p != self.before[n]}


@dataclass(frozen=True)
class _Item:
    name: str
    period: int  # slots
    phase: int  # slots, current
    weight: float


def _loads(items: Sequence[_Item], phases: Sequence[int], h: int) -> list[float]:
    load = [0.0] * h
    for it, ph in zip(items, phases, strict=True):
        for k in range(ph, h, it.period):
            load[k] += it.weight
    return load


def _key(load: Sequence[float], changes: int) -> tuple[float, float, int]:
    return (round(max(load, default=0.0), 9), round(sum(x * x for x in load), 9), changes)


def search(items: Sequence[_Item], h: int) -> list[int]:
    """Phases for ``items`` on ``h`` slots minimising (peak, spread, changes)."""
    order = sorted(range(len(items)), key=lambda i: (-items[i].weight, -items[i].period))
    current = [it.phase for it in items]
    best = list(current)
    best_key = _key(_loads(items, current, h), 0)
    chosen = [0] * len(items)
    load = [0.0] * h
    steps = 0

    def dfs(depth: int, changes: int) -> None:
        nonlocal best, best_key, steps
        steps += 1
        if steps > MAX_STEPS:
            return
        if max(load, default=0.0) > best_key[0] + 1e-9:
            return  # the peak only grows as more nodes are placed
        if depth == len(order):
            key = _key(load, changes)
            if key < best_key:
                best, best_key = list(chosen), key
            return
        i = order[depth]
        it = items[i]
        candidates = [it.phase, *(p for p in range(it.period) if p != it.phase)]
        for ph in candidates:
            for k in range(ph, h, it.period):
                load[k] += it.weight
            chosen[i] = ph
            dfs(depth + 1, changes + (ph != it.phase))
            for k in range(ph, h, it.period):
                load[k] -= it.weight

    dfs(0, 0)
    return best


def _advice(
    clock: str, unit: str, measure: str, items: list[_Item], h: int, scale: float
) -> PhaseAdvice:
    after = search(items, h)
    before_l = _loads(items, [it.phase for it in items], h)
    after_l = _loads(items, after, h)
    return PhaseAdvice(
        clock,
        unit,
        measure,
        {it.name: it.period * scale for it in items},
        {it.name: it.phase * scale for it in items},
        {it.name: ph * scale for it, ph in zip(items, after, strict=True)},
        max(before_l, default=0.0),
        max(after_l, default=0.0),
    )


def advise(timing: Mapping[str, NodeTiming]) -> list[PhaseAdvice]:
    """Phase advice for every frame source with readers, then for the timers."""
    out = []
    readers_of = frame_readers(timing)
    for source, readers in readers_of.items():
        budgets = all(r.budget is not None for r in readers)
        items = [
            _Item(
                r.name, r.period, r.phase % r.period, r.budget.ms if budgets and r.budget else 1.0
            )
            for r in readers
        ]
        h = lcm(*(it.period for it in items))
        if h <= MAX_SLOTS:
            out.append(_advice(source, "frame", "ms" if budgets else "nodes", items, h, 1))
    timers = [t for t in timing.values() if t.enabled and t.trigger == "timer" and t.timer_ms]
    if len(timers) >= 2:
        advice = _timer_advice(timers, readers_of)
        if advice is not None:
            out.append(advice)
    return out


def _timer_advice(
    timers: list[NodeTiming],
    readers_of: Mapping[str, list[NodeTiming]],
) -> PhaseAdvice | None:
    periods = [Fraction(str(t.timer_ms)) for t in timers]
    g = periods[0]
    for p in periods[1:]:
        g = Fraction(
            gcd(g.numerator * p.denominator, p.numerator * g.denominator),
            g.denominator * p.denominator,
        )
    slot = g / len(timers)
    slots = [int(p / slot) for p in periods]
    h = lcm(*slots)
    if h > MAX_SLOTS:
        return None
    budgets = all(t.budget is not None for t in timers) and all(
        r.budget is not None for t in timers for r in readers_of.get(t.name, [])
    )
    items = []
    for t, n in zip(timers, slots, strict=True):
        w = 1.0
        if budgets:
            assert t.budget is not None
            w = t.budget.ms + sum(
                r.budget.ms / r.period for r in readers_of.get(t.name, []) if r.budget
            )
        phase = round(Fraction(str(t.timer_phase_ms)) / slot) % n
        items.append(_Item(t.name, n, phase, w))
    return _advice("timers", "ms", "ms" if budgets else "nodes", items, h, float(slot))


def snippet(advice: Sequence[PhaseAdvice], timing: Mapping[str, NodeTiming]) -> str:
    """The changed triggers as a graph-file fragment to paste over the current ones."""
    lines = []
    for a in advice:
        if not a.changed:
            continue
        unit = "ms" if a.measure == "ms" else " nodes"
        lines.append(
            f"# {a.clock}: heaviest tick {a.peak_before:.4g}{unit} -> {a.peak_after:.4g}{unit}"
        )
        for name, ph in a.changed.items():
            t = timing[name]
            if a.unit == "frame":
                trig = f"{{frame: {t.source}, period: {t.period}, phase: {int(ph)}}}"
            else:
                trig = f"{{timer: {t.timer_ms:g}ms, phase: {ph:g}ms}}"
            lines.append(f"  {name}:\n    trigger: {trig}")
    if not lines:
        return ""
    return "nodes:\n" + "\n".join(lines) + "\n"
