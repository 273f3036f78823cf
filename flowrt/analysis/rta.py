"""Worst-case response times of fixed-priority tasks: preemptive and non-preemptive.

Response-time analysis (RTA) bounds the time from a task's arrival to its completion under a
fixed-priority scheduler, which utilisation tests cannot: a task set with U < 1 can still
miss deadlines, and one with U = 1 can meet them (Burns & Wellings, *Real-Time Systems and
Programming Languages*, ch. 11). The analyses here:

* **Preemptive** fixed priority (worker processes under ``SCHED_FIFO``): the busy-window
  recurrence of Joseph & Pandya (1986) and Audsley, Burns, Richardson, Tindell & Wellings
  (1993), with release jitter ``J`` and blocking ``B`` (Tindell; Audsley et al. 1993), for
  arbitrary deadlines over several instances of the level-i busy period (Lehoczky 1990;
  Tindell, Burns & Wellings 1994)::

      w(q) = B + (q+1) C + sum_{j in hp} ceil((w(q) + J_j) / T_j) C_j
      R    = max_q  J + w(q) - q T            q = 0, 1, ... while J + w(q) > (q+1) T

* **Non-preemptive** fixed priority (inline nodes on the event loop: a running node keeps the
  loop until it returns), after George, Rivierre & Spuri (1996) and Davis, Burns, Bril &
  Lukkien (2007), who showed that looking at the first instance alone is optimistic::

      B    = max C_k - 1 ns over lower-priority k
      w(q) = B + q C + sum_{j in hp} (floor((w(q) + J_j) / T_j) + 1) C_j     (start of q)
      R    = max_q  J + w(q) - q T + C        q = 0 .. Q-1, Q = instances in the busy period

  Davis et al. add one "bit time" so that a higher-priority release at the very instant a
  task would start still goes first; here the time unit is one nanosecond (a blocking job
  started at least one unit before the release, hence C_k - 1 ns).

* **Interrupts**: work above every task of the set that does not wait for the running job
  to finish, even on a non-preemptive resource (a precise node's release thread taking the
  interpreter lock in turns with the event loop's callback), as interrupt handlers compete
  with application tasks (Jeffay & Stone, "Accounting for interrupt handling costs in
  dynamic priority task systems", RTSS 1993). Their work counts over the job's whole window,
  to its completion, where the set's own higher priorities count only until it starts::

      w(q) = B + q C + sum_{j in hp} (floor((w + J_j) / T_j) + 1) C_j
                     + sum_{i in irq} (floor((w + J_i) / T_i) + 1) C_i       (start of q)
      f(q) = B + (q+1) C + sum_{j in hp} (floor((w(q) + J_j) / T_j) + 1) C_j
                     + sum_{i in irq} ceil((f + J_i) / T_i) C_i               (end of q)
      R    = max_q  J + f(q) - q T

Equal priorities are taken to interfere with each other both ways (FIFO order among equals
is not known in advance), which is pessimistic but safe. Times are in milliseconds at the
interface and exact integers (nanoseconds) inside, so that ``ceil`` never suffers a rounding
error. A task whose recurrence has no fixed point (higher-priority utilisation above 1, or a
busy period without end) is reported unschedulable with an infinite response time: the
iteration is bounded by the busy-period length, never a loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction

NS_PER_MS = 1_000_000
MAX_INSTANCES = 100_000  # instances of one busy period examined before giving up
MAX_ITERATIONS = 1_000_000  # fixed-point steps over one task, before giving up


@dataclass(frozen=True)
class Task:
    """One periodic or sporadic task; times in milliseconds.

    ``period`` is the minimum inter-arrival time, ``deadline`` is relative to arrival (the
    period when None), ``jitter`` the latest release after arrival, ``blocking`` the longest
    time a lower-priority task can hold it back (a shared resource, a non-preemptive section).
    ``priority``: higher number = more important.
    """

    name: str
    wcet: float
    period: float
    deadline: float | None = None
    jitter: float = 0.0
    blocking: float = 0.0
    priority: float = 0.0

    def __post_init__(self) -> None:
        for f in ("wcet", "period", "jitter", "blocking"):
            v = getattr(self, f)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"task {self.name}: {f} must be finite and >= 0, got {v}")
        if self.period <= 0:
            raise ValueError(f"task {self.name}: period must be positive")
        if self.deadline is not None and not (math.isfinite(self.deadline) and self.deadline > 0):
            raise ValueError(f"task {self.name}: deadline must be finite and positive")

    @property
    def effective_deadline(self) -> float:
        return self.period if self.deadline is None else self.deadline

    @property
    def utilisation(self) -> float:
        return self.wcet / self.period


@dataclass(frozen=True)
class Response:
    """The analysis of one task. ``response`` is from arrival (includes the jitter: R = J + w);
    ``release_response`` from release (what a runtime measures from activation to finish).
    Both are ``inf`` when the recurrence did not converge. ``blocking`` is the B the
    analysis used: the task's own, or (non-preemptive) the longest lower-priority job."""

    task: Task
    response: float
    release_response: float
    instances: int
    converged: bool
    blocking: float = 0.0

    @property
    def schedulable(self) -> bool:
        return self.converged and self.response <= self.task.effective_deadline + 1e-9

    @property
    def slack(self) -> float:
        return self.task.effective_deadline - self.response


def _ns(ms: float) -> int:
    return round(ms * NS_PER_MS)


def _ms(ns: int | float) -> float:
    return ns / NS_PER_MS if math.isfinite(ns) else math.inf


@dataclass(frozen=True)
class _T:
    c: int
    t: int
    j: int
    b: int


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def _utilisation(ts: Sequence[_T]) -> Fraction:
    return sum((Fraction(x.c, x.t) for x in ts), Fraction(0))


def _horizon(me: _T, hp: Sequence[_T], extra: int) -> int | None:
    """An upper bound on the level-i busy period, or None when there may be none.

    From w <= extra + sum_j ((w + J_j)/T_j + 1) C_j over hp and the task itself:
    w <= (extra + sum_j C_j (1 + J_j/T_j)) / (1 - U) when U < 1. At U = 1 exactly the busy
    period may still end (synchronous harmonic sets do); bound it then by a generous multiple
    of the longest period and report non-convergence past it. Floats with a wide margin (the
    bound only has to be above the busy period); exact fractions only when U is within 1e-9
    of 1, where the float cannot tell.
    """
    allts = [*hp, me]
    u_f = sum(x.c / x.t for x in allts)
    if abs(u_f - 1) < 1e-9:
        u = _utilisation(allts)
        if u > 1:
            return None
        if u == 1:
            return extra + 1000 * max(x.t for x in allts) + sum(x.j for x in allts)
        u_f = float(u)
    elif u_f > 1:
        return None
    num = extra + sum(x.c * (1 + x.j / x.t) for x in allts)
    return math.ceil(num / (1 - u_f) * 1.001) + 1000


def _fixed_point(start: int, step: Callable[[int], int], limit: int) -> int | None:
    """Least fixed point of the monotone ``step`` from ``start`` (<= it), None past ``limit``."""
    w = start
    for _ in range(MAX_ITERATIONS):
        nxt = step(w)
        if nxt == w:
            return w
        if nxt > limit:
            return None
        w = nxt
    return None


def _interferers(tasks: Sequence[Task], i: int) -> tuple[list[int], list[int]]:
    """Indices of tasks at higher-or-equal priority (interfere) and lower priority (block)."""
    p = tasks[i].priority
    hp = [k for k, t in enumerate(tasks) if k != i and t.priority >= p]
    lp = [k for k, t in enumerate(tasks) if t.priority < p]
    return hp, lp


def _preemptive(me: _T, hp: Sequence[_T]) -> tuple[int, int, int] | None:
    limit = _horizon(me, hp, me.b)
    if limit is None:
        return None
    worst = worst_rel = -1
    w = me.b + me.c
    for q in range(MAX_INSTANCES):
        base = me.b + (q + 1) * me.c

        def step(x: int, base: int = base) -> int:
            return base + sum(_ceil_div(x + h.j, h.t) * h.c for h in hp)

        fp = _fixed_point(max(w, base), step, limit)
        if fp is None:
            return None
        w = fp
        worst = max(worst, me.j + w - q * me.t)
        worst_rel = max(worst_rel, w - max(0, q * me.t - me.j))
        if me.j + w <= (q + 1) * me.t:
            return worst, worst_rel, q + 1
        w += me.c
    return None


def _non_preemptive(
    me: _T, hp: Sequence[_T], irq: Sequence[_T] = ()
) -> tuple[int, int, int] | None:
    limit = _horizon(me, [*hp, *irq], me.b)
    if limit is None:
        return None
    everyone = [*hp, *irq, me]

    def busy(x: int) -> int:
        return me.b + sum(_ceil_div(x + h.j, h.t) * h.c for h in everyone)

    length = _fixed_point(max(me.c + me.b, 1), busy, limit)
    if length is None:
        return None
    n = _ceil_div(length + me.j, me.t)
    if n > MAX_INSTANCES:
        return None
    worst = worst_rel = -1
    w = me.b
    for q in range(n):
        base = me.b + q * me.c

        def step(x: int, base: int = base) -> int:
            return base + sum((((x + h.j) // h.t) + 1) * h.c for h in [*hp, *irq])

        fp = _fixed_point(max(w, base), step, limit)
        if fp is None:
            return None
        w = fp
        f = w + me.c
        if irq:  # the start's hp interference is fixed; interrupts go on to the end
            fixed = base + me.c + sum((((w + h.j) // h.t) + 1) * h.c for h in hp)

            def finish(x: int, fixed: int = fixed) -> int:
                return fixed + sum(_ceil_div(x + h.j, h.t) * h.c for h in irq)

            end = _fixed_point(f, finish, limit)
            if end is None:
                return None
            f = max(f, end)
        worst = max(worst, me.j + f - q * me.t)
        worst_rel = max(worst_rel, f - max(0, q * me.t - me.j))
    return worst, worst_rel, n


def response_times(
    tasks: Sequence[Task],
    *,
    preemptive: bool = True,
    only: int | None = None,
    interrupts: Sequence[Task] = (),
) -> list[Response]:
    """Worst-case response time of every task, in the order given (of ``tasks[only]`` alone
    when ``only`` is given: the list then has that one response).

    Preemptive: each task's own ``blocking`` is used as B. Non-preemptive: B is the larger of
    the task's own ``blocking`` and the longest lower-priority execution time (less 1 ns).
    ``interrupts`` are above every task and preempt even a non-preemptive job (see the
    module's docstring); they are not analysed themselves and block nobody.
    """
    ints = [_T(_ns(t.wcet), _ns(t.period), _ns(t.jitter), _ns(t.blocking)) for t in tasks]
    irq = [_T(_ns(t.wcet), _ns(t.period), _ns(t.jitter), 0) for t in interrupts]
    if any(x.t <= 0 for x in [*ints, *irq]):
        raise ValueError("every period must be at least 1 ns")
    out: list[Response] = []
    for i, task in enumerate(tasks):
        if only is not None and i != only:
            continue
        hp_i, lp_i = _interferers(tasks, i)
        me = ints[i]
        hp = [ints[k] for k in hp_i]
        b = me.b
        if preemptive:
            res = _preemptive(me, [*hp, *irq])
        else:
            # a lower-priority job that blocks must have started at least one unit (1 ns)
            # before our release, else we would have gone first (discrete time, as PROSA)
            b = max([me.b, *(ints[k].c - 1 for k in lp_i if ints[k].c > 0)])
            res = _non_preemptive(_T(me.c, me.t, me.j, b), hp, irq)
        if res is None:
            out.append(Response(task, math.inf, math.inf, 0, False, _ms(b)))
        else:
            r, rr, n = res
            out.append(Response(task, _ms(r), _ms(rr), n, True, _ms(b)))
    return out


def utilisation(tasks: Sequence[Task]) -> float:
    """Total processor utilisation sum C/T."""
    return float(sum(t.utilisation for t in tasks))


def by_order(tasks: Sequence[Task]) -> list[Task]:
    """Give tasks listed highest priority first distinct priorities (len..1)."""
    n = len(tasks)
    return [
        Task(t.name, t.wcet, t.period, t.deadline, t.jitter, t.blocking, float(n - k))
        for k, t in enumerate(tasks)
    ]


def global_response_time(
    task: Task, higher: Sequence[Task], cpus: int, horizon: float | None = None
) -> Response:
    """Response-time bound of ``task`` under global fixed priority on ``cpus`` processors.

    After Bertogna & Cirinei (2007), "Response-time analysis for globally scheduled
    symmetric multiprocessor platforms": ``task`` waits only while all ``cpus`` processors
    run higher-priority work, so over a window L its interference is at most
    ``(1/m) sum_j W_j(L)``, with ``W_j`` the most work task j can do in L. (Their bound caps
    each term at ``L - C + 1``; that is tighter but makes the fixed-point iteration creep
    one time unit at a time, so it is left out: still sufficient, never slower.)
    flowrt never queues a second activation of a node that is still running (it is skipped
    and counted), so at most one job of j is carried into the window:
    ``W_j(L) <= (ceil((L + J_j) / T_j) + 1) C_j`` — which needs no response time of j, so an
    overloaded higher-priority node cannot make this bound diverge by itself. ``higher``
    may include tasks pinned to any of the processors. Release jitter and blocking of
    ``task`` are added as in the uniprocessor case; the bound is from release.
    """
    if cpus < 1:
        raise ValueError("cpus must be >= 1")
    c, j, b = _ns(task.wcet), _ns(task.jitter), _ns(task.blocking)
    hp = [(_ns(h.wcet), _ns(h.period), _ns(h.jitter)) for h in higher]
    limit = _ns(horizon if horizon is not None else 1000 * task.period)

    def step(r: int) -> int:
        tot = sum((_ceil_div(r + hj, ht) + 1) * hc for hc, ht, hj in hp)
        return c + b + tot // cpus

    r = _fixed_point(c + b, step, limit)
    if r is None:
        return Response(task, math.inf, math.inf, 0, False)
    return Response(task, _ms(j + r), _ms(r), 1, True)
