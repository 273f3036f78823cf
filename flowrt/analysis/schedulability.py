"""Response-time analysis of a whole graph: which node meets its deadline, on which resource.

The graph is mapped onto the classic analyses of :mod:`flowrt.analysis.rta`:

* **Inline nodes** share the event loop, which runs one callback at a time: non-preemptive
  fixed priority (George et al. 1996; Davis et al. 2007). Each inline node is blocked by the
  longest lower-priority inline execution and delayed by every higher-priority one.
* **Worker processes** (``placement: process``) are preempted by the kernel by priority
  (``SCHED_FIFO`` where permitted): preemptive fixed priority (Audsley et al. 1993). A worker
  pinned to one CPU (``cpus: [c]``) is analysed as a uniprocessor task on ``c`` with every
  higher-priority task that may run there, pinned or not. A worker allowed on m >= 2 CPUs
  (``cpus`` of several, or none: all of the machine's) gets the global fixed-priority bound
  of Bertogna & Cirinei (2007) over every higher-priority task that may run on its CPUs: it
  waits only while all m run higher-priority work (sufficient, assuming the kernel keeps the
  m highest-priority runnable tasks running, as Linux's real-time push/pull does).
* **Pool nodes** queue for a shared worker: the same preemptive test plus a blocking term of
  the longest lower-priority pool execution (the job holding the slot they wait for).
* The **event-loop process** runs above every worker (the runtime caps worker priorities
  below the loop's), and it is not pinned: its inline work is counted as highest-priority
  interference on every worker, and a worker's release (sent by the loop on a timer, or when
  a worker's result comes in) is late by up to the longest inline execution — added to the
  worker's release jitter. A worker fed by an inline node is released by that node's own
  callback, whose response already includes that wait.
* **Precise threads** (``timing: precise`` nodes called in their own release thread,
  :mod:`flowrt.kernel.precise`) are not on the loop: the thread sleeps to the instant, so the
  loop neither delays their release nor holds them back with its callbacks. They share only
  the interpreter lock, which is not handed over by priority: each is analysed as a
  preemptive task beside the other precise threads, all at its own priority. Towards the
  rest they are the loop process's highest work: the loop's timers due at their instant
  wait for their call, and a callback already running takes turns with it, so on the loop
  they are interrupts (:func:`flowrt.analysis.rta.response_times`) and on the workers
  interference above every worker, as inline work is. A precise node handed to the loop (a
  coroutine, frames, a lossless input, a worker) is analysed where it runs. flowrt never
  queues a second call of a node, so at most one call of each is carried into a window: it
  is counted with a release jitter of its period.
* **Chains** are analysed holistically (Tindell & Clark 1994): a frame-triggered node is
  released when its source publishes the frame, so its release jitter is the source's
  worst-case response time; an input-triggered node inherits its producers' response times,
  one arrival stream per producer. The passes repeat until the jitters settle. flowrt never
  queues a second activation of a running node (it is skipped and counted), so a producer
  completes at most once between two of its own ticks: the jitter it passes on is at most
  its period, however late it runs, and one overloaded node cannot make the whole graph's
  analysis diverge.

Phases (offsets) are ignored, the synchronous release being the worst case: the bounds hold
for any phases; the per-tick table (:mod:`flowrt.analysis.load`) shows what phases buy.
Responses are reported from the node's release (its activation, as the runtime measures
``response``) and judged against its deadline, or its period when it has none.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from .rta import Response, Task, global_response_time, response_times
from .timing import Budget, NodeTiming, interval_ms

MAX_PASSES = 32
LOOP_PRIORITY = 1000.0  # above every flowrt priority (1..99): the loop process is on top


@dataclass(frozen=True)
class NodeVerdict:
    """One node's analysis. ``response_ms`` is from release; None when not analysed."""

    name: str
    resource: str
    priority: int
    budget: Budget | None
    period_ms: float | None
    deadline_ms: float | None  # what the response is judged against
    has_deadline: bool  # a deadline was declared (a critical node for admission control)
    jitter_ms: float = 0.0
    blocking_ms: float = 0.0
    response_ms: float | None = None
    schedulable: bool | None = None
    note: str = ""


@dataclass(frozen=True)
class GraphVerdict:
    nodes: list[NodeVerdict]
    utilisation: float  # sum C/T over the analysed nodes

    @property
    def schedulable(self) -> bool:
        """Every enabled node shown to meet its deadline (a node without budget is not)."""
        return all(v.schedulable is True for v in self.nodes)

    def node(self, name: str) -> NodeVerdict:
        for v in self.nodes:
            if v.name == name:
                return v
        raise KeyError(name)


@dataclass(frozen=True)
class _Stream:
    node: str
    period: float
    producer: str | None  # whose response is this stream's release jitter


def _resource(t: NodeTiming) -> str:
    if t.thread:
        return "precise thread"
    if t.placement == "inline":
        return "loop"
    if t.placement == "pool":
        return "pool"
    if t.cpus is None:
        return "any cpu"
    return f"cpu {t.cpus[0]}" if len(t.cpus) == 1 else "cpus " + ",".join(map(str, t.cpus))


def _overlap(a: NodeTiming, b: NodeTiming) -> bool:
    return a.cpus is None or b.cpus is None or bool(set(a.cpus) & set(b.cpus))


def analyse(timing: Mapping[str, NodeTiming], cpus: int = 1) -> GraphVerdict:
    """Worst-case response time of every enabled node of ``timing`` on ``cpus`` CPUs."""
    nodes = [t for t in timing.values() if t.enabled]
    nodes.sort(key=lambda t: (-t.priority, t.order))
    streams, notes, idle = _streams_of(timing, nodes)
    by_name = {t.name: t for t in nodes}
    budget: dict[str, float] = {}
    for n in streams:
        b = by_name[n].budget
        assert b is not None  # nodes without a budget have no stream
        budget[n] = b.ms
    inline = [n for n in streams if by_name[n].placement == "inline" and not by_name[n].thread]
    threads = [n for n in streams if by_name[n].thread]
    # what the loop may be busy with when it should release a worker: a callback, or (its
    # timers waiting for them) a precise thread's call
    loop_block = max((budget[n] for n in [*inline, *threads]), default=0.0)

    arrival_r: dict[str, float] = dict.fromkeys(streams, 0.0)  # R from arrival, per node
    release_r: dict[str, float] = {}
    jit: dict[tuple[str, int], float] = {}
    blocking: dict[str, float] = {}
    stable = False
    for _ in range(MAX_PASSES):
        new_jit = _jitters(timing, streams, by_name, arrival_r, loop_block)
        if new_jit == jit:
            stable = True
            break
        jit = new_jit
        arrival_r, release_r, blocking = _pass(streams, by_name, budget, jit, inline, threads, cpus)
    verdicts = []
    for t in nodes:
        n = t.name
        period = interval_ms(timing, n)
        dl = t.deadline_ms if t.deadline_ms is not None else period
        v = NodeVerdict(
            n, _resource(t), t.priority, t.budget, period, dl, t.deadline_ms is not None
        )
        if n in streams:
            r = release_r[n] if stable else math.inf
            j = max(jit.get((n, k), 0.0) for k in range(len(streams[n])))
            v = _judged(v, r, j, budget[n], blocking.get(n, 0.0))
        elif n in idle:
            v = replace(v, schedulable=True, note="never activated: every producer is disabled")
        else:
            v = replace(v, note=notes.get(n, ""))
        verdicts.append(v)
    util = sum(budget[n] / s.period for n, ss in streams.items() for s in ss)
    return GraphVerdict(verdicts, util)


def _streams_of(
    timing: Mapping[str, NodeTiming], nodes: list[NodeTiming]
) -> tuple[dict[str, list[_Stream]], dict[str, str], set[str]]:
    """Each analysable node's activation streams (one per producer for an input trigger);
    why the others are not analysed; and the nodes never activated."""
    notes: dict[str, str] = {}
    idle: set[str] = set()  # never activated: nothing to miss
    streams: dict[str, list[_Stream]] = {}
    for t in nodes:
        period = interval_ms(timing, t.name)
        if t.budget is None:
            notes[t.name] = "no budget (wcet:, --wcet-from or --measure)"
        elif period is None:
            notes[t.name] = "no known period (free-running or fed by one)"
        elif t.trigger == "input":
            if not any(p in timing and timing[p].enabled for p in t.producers):
                idle.add(t.name)
                continue
            streams[t.name] = []
            for p in t.producers:
                if p not in timing or not timing[p].enabled:
                    continue  # a disabled producer sends nothing
                pi = interval_ms(timing, p)
                assert pi is not None  # interval_ms(t) is known only if all producers' are
                streams[t.name].append(_Stream(t.name, pi, p))
        else:
            streams[t.name] = [_Stream(t.name, period, t.source if t.trigger == "frame" else None)]
    return streams, notes, idle


def _jitters(
    timing: Mapping[str, NodeTiming],
    streams: Mapping[str, list[_Stream]],
    by_name: Mapping[str, NodeTiming],
    arrival_r: Mapping[str, float],
    loop_block: float,
) -> dict[tuple[str, int], float]:
    """Each stream's release jitter from its producer's response of the last pass."""
    new_jit = {}
    for n, ss in streams.items():
        for k, s in enumerate(ss):
            j = 0.0
            p = s.producer
            if p is not None and p in arrival_r:
                j = arrival_r[p]
                if timing[p].trigger != "input":
                    # completes at most once per own tick (overruns are skipped)
                    j = min(j, streams[p][0].period)
            # released by an inline producer's callback, whose response includes the loop's
            # wait; a precise thread's outcome is handed to the loop after its response
            fed_by_loop = (
                s.producer is not None
                and timing[s.producer].placement == "inline"
                and not timing[s.producer].thread
            )
            if by_name[n].placement != "inline" and not fed_by_loop:
                j += loop_block  # the loop may be in an inline node when it should release
            new_jit[(n, k)] = j
    return new_jit


def _judged(v: NodeVerdict, r: float, j: float, own: float, bl: float) -> NodeVerdict:
    """The verdict of an analysed node: its response ``r`` against its deadline, and why."""
    dl = v.deadline_ms
    ok = math.isfinite(r) and dl is not None and r <= dl + 1e-6
    note = "" if math.isfinite(r) else "no fixed point: overloaded"
    if math.isfinite(r) and dl is not None and not ok:
        note = (
            f"MISS: response {r:.4g} > deadline {dl:g} ms = own budget {own:.4g} + "
            f"blocking {bl:.4g} + interference of higher priorities "
            f"{max(0.0, r - own - bl):.4g}"
        )
    return replace(v, jitter_ms=j, blocking_ms=bl, response_ms=r, schedulable=ok, note=note)


def _pass(
    streams: Mapping[str, list[_Stream]],
    by_name: Mapping[str, NodeTiming],
    budget: Mapping[str, float],
    jit: Mapping[tuple[str, int], float],
    inline: list[str],
    threads: list[str],
    cpus: int,
) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """One holistic pass: every node's worst response from arrival and from release."""

    def task(n: str, k: int, prio: float, blocking: float = 0.0) -> Task | None:
        j = jit[(n, k)]
        if not math.isfinite(j):
            return None
        return Task(f"{n}#{k}", budget[n], streams[n][k].period, None, j, blocking, prio)

    # every stream's task once per pass: as itself, and (inline) as the loop seen by a worker
    own = {
        (n, k): task(n, k, by_name[n].priority) for n, ss in streams.items() for k in range(len(ss))
    }
    as_loop = {(n, k): task(n, k, LOOP_PRIORITY) for n in inline for k in range(len(streams[n]))}
    # a precise thread's calls, above the loop's and the workers' (one carried in at most)
    for n in threads:
        period = streams[n][0].period
        as_loop[(n, 0)] = Task(f"{n}#0", budget[n], period, None, period, 0.0, LOOP_PRIORITY)
    irq = [t for n in threads if (t := as_loop[(n, 0)]) is not None]
    results: dict[str, list[Response | None]] = {}
    blocking: dict[str, float] = {}
    # each precise thread: preemptive, the others' calls taking turns with it on the GIL
    for n in threads:
        mine = own[(n, 0)]
        others = [replace(t, priority=by_name[n].priority) for t in irq if t.name != f"{n}#0"]
        results[n] = [None if mine is None else response_times([mine, *others], only=0)[0]]
        blocking[n] = 0.0
    # the event loop: non-preemptive fixed priority among inline nodes
    loop_tasks = [(n, own[(n, k)]) for n in inline for k in range(len(streams[n]))]
    if any(t is None for _, t in loop_tasks):
        for n in inline:
            results[n] = [None]
    else:
        res = response_times(
            [t for _, t in loop_tasks if t is not None], preemptive=False, interrupts=irq
        )
        for (n, _), r in zip(loop_tasks, res, strict=True):
            results.setdefault(n, []).append(r)
        for n in inline:
            lower = [budget[m] for m in inline if by_name[m].priority < by_name[n].priority]
            blocking[n] = max(lower, default=0.0)
    # workers and the pool: preemptive fixed priority per CPU, the loop on top
    for n in streams:
        if by_name[n].placement != "inline" and not by_name[n].thread:
            blocking[n], results[n] = _worker_responses(
                n, streams, by_name, budget, own, as_loop, task, cpus
            )
    arrival: dict[str, float] = {}
    release: dict[str, float] = {}
    for n, rs in results.items():
        arrival[n] = max((r.response if r else math.inf) for r in rs)
        release[n] = max((r.release_response if r else math.inf) for r in rs)
    return arrival, release, blocking


def _worker_responses(
    n: str,
    streams: Mapping[str, list[_Stream]],
    by_name: Mapping[str, NodeTiming],
    budget: Mapping[str, float],
    own: Mapping[tuple[str, int], Task | None],
    as_loop: Mapping[tuple[str, int], Task | None],
    task: Callable[[str, int, float, float], Task | None],
    cpus: int,
) -> tuple[float, list[Response | None]]:
    """A node in a worker or the pool: its blocking, and each stream's response (None:
    unbounded) under preemptive fixed priority on its CPUs, the event loop above it."""
    me = by_name[n]
    b = 0.0
    if me.placement == "pool":  # a pool worker runs a lower-priority call to its end
        b = max(
            (
                budget[m]
                for m in streams
                if by_name[m].placement == "pool" and by_name[m].priority < me.priority
            ),
            default=0.0,
        )
    out: list[Response | None] = []
    for k in range(len(streams[n])):
        mine = task(n, k, me.priority, b) if b else own[(n, k)]
        others: list[Task | None] = []
        for other, oss in streams.items():
            o = by_name[other]
            if o.placement == "inline":
                others += [as_loop[(other, i)] for i in range(len(oss))]
            elif _overlap(me, o) and o.priority >= me.priority:
                others += [own[(other, i)] for i in range(len(oss)) if (other, i) != (n, k)]
        if mine is None or any(o is None for o in others):
            out.append(None)
            continue
        hp = [o for o in others if o is not None]
        m = len(me.cpus) if me.cpus else cpus
        if m >= 2:
            out.append(global_response_time(mine, hp, m))
        else:
            out.append(response_times([mine, *hp], only=0)[0])
    return b, out
