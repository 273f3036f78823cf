"""The deterministic replay: every recorded activation re-executed, in order, on recorded time.

Nothing is scheduled: the log says which activation ran when and what each input held, so the
engine walks the activations in the order they started and, for each one of a node it runs,
gathers those exact values (a source's from the recording, a re-executed node's from its own
earlier output with the same sequence number), sets the node's clock to the recorded start,
calls ``process`` and compares each output's digest with the recorded one. A node's outputs
get the sequence numbers the recording gives that activation's outputs, so its readers find
them whatever happened elsewhere. An activation that failed or was discarded in the run is
re-executed (its state changes count) but publishes nothing, as then. Param changes and
restarts are applied before the first activation that followed them.

Nodes run inline, or in worker processes as their placement says (``inline=False``). Each
node's activations run one after the other in the recorded order, which with their recorded
inputs is what makes the replay deterministic; calls of different workers that do not feed each
other may be in flight together (see :meth:`ReplayEngine.run`).

Against another graph: a node that is not in it is not run, and its outputs, where recorded,
stand in for it; a node of it whose input came from something that neither runs nor was
recorded cannot be replayed from that activation on (``not comparable``, with the reason); a
node the recording has no activations of is ``not run``.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..edges import Buffer, QueueBuffer
from ..graph._resolve import Graph, ResolvedNode
from ..graph.spec import Placement, TimerTrigger
from .context import NOW_KEY, TIMES_KEY, ReplayContext, ReplayFactory, maybe_await
from .digest import digest
from .log import Activation, DeterminismLog, Key, OutputRecord, roles
from .report import Divergence, NodeReplay, ReplayReport
from .synthesis import streams, synthesize
from .values import RecordedValues, read_one, show

__all__ = ["ReplayEngine"]

log = logging.getLogger("flowrt.determinism")

UNBOUNDED = 1 << 62
BATCH = 8  # worker calls in flight at once (independent activations of different nodes)


@dataclass
class _Node:
    """One re-executed node: its instance (inline) or worker, and what it did."""

    rnode: ResolvedNode
    ctx: ReplayContext
    worker: bool
    node: Any = None  # the inline instance
    executor: Any = None  # the worker's executor
    params: Any = None
    activations: int = 0
    compared: int = 0
    reason: str = ""  # why it stopped being replayed (empty: it runs)
    new: bool = False  # not in the recording: its activations come from its trigger
    restarts: deque[float] = field(default_factory=deque)
    published: list[tuple[str, Any]] = field(default_factory=list)

    @property
    def outputs(self) -> list[str]:
        cls = self.rnode.cls
        return [*cls.outputs, *cls.params_outputs(self.params)]


class ReplayEngine:
    """Re-executes a deterministic log against ``graph`` (see the module docstring)."""

    def __init__(
        self,
        log_: DeterminismLog,
        graph: Graph,
        *,
        inline: bool = False,
        stop_at_divergence: bool = False,
    ) -> None:
        self.log = log_
        self.graph = graph
        self.inline = inline
        self.stop_at_divergence = stop_at_divergence
        self.roles = roles(graph)
        self.nodes: dict[str, _Node] = {}
        self.produced: dict[Key, Any] = {}
        self.produced_times: dict[Key, float] = {}
        self.needs: dict[Key, int] = {}
        self.subscribers: dict[tuple[str, str], list[Buffer]] = {}
        self.next_seq: dict[tuple[str, str], int] = {}
        self.activations = 0
        self.compared = 0
        self.divergence: Divergence | None = None
        self.stopped_early = False
        self.started = False
        self.values: RecordedValues | None = None
        # A cut log may end between a node's completion and its outputs (a completion is
        # written before its results publish): that activation's unrecorded outputs are not
        # a divergence, only not compared. Each node's last completion in a cut log.
        self.cut_after: dict[str, int] = {}
        if not log_.closed_cleanly:
            for node, n in log_.completions:
                self.cut_after[node] = max(n, self.cut_after.get(node, 0))
        recorded = {a.node for a in log_.activations}
        self.plan: list[Activation] = list(log_.activations)
        self.not_run: dict[str, str] = {}  # new nodes that cannot run, and why
        for name, rnode in graph.nodes.items():
            if self.roles[name] == "replayed" and name in recorded:
                self.nodes[name] = self._node(name, rnode)
        for c in log_.changes:
            if c.what == "restart" and c.node in self.nodes:
                self.nodes[c.node].restarts.append(c.t)
        _plan_new_nodes(self, recorded)

    def _node(self, name: str, rnode: ResolvedNode) -> _Node:
        trig = rnode.trigger
        period = trig.timer / 1000 if isinstance(trig, TimerTrigger) else None
        ctx = ReplayContext(name, self.log.seed, self.log.origin, period, self._publisher(name))
        worker = not self.inline and rnode.spec.placement is not Placement.inline
        return _Node(rnode, ctx, worker and not rnode.cls.inline_only, params=rnode.params)

    def _publisher(self, name: str) -> Any:
        def publish(port: str, value: Any) -> None:
            self.nodes[name].published.append((port, value))

        return publish

    # --- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Set every replayed node up (workers in parallel, then inline ones in file order)."""
        if self.started:
            return
        self.started = True
        uses: dict[tuple[str, int], int] = {}
        for a in self.plan:
            if a.node not in self.nodes:
                continue
            for key in a.inputs.values():
                if key is None:
                    continue
                self.needs[key] = self.needs.get(key, 0) + 1
                if key[0] not in self.nodes:
                    place = self.log.recorded(key)
                    if place is not None:
                        uses[place] = uses.get(place, 0) + 1
        self.values = RecordedValues(self.log, uses)
        workers = [n for n in self.nodes.values() if n.worker]
        if workers:
            from ..workers import start_forkserver

            await asyncio.to_thread(start_forkserver)
        await asyncio.gather(*(self._start_node(n) for n in workers))
        for n in self.nodes.values():
            if not n.worker:
                await self._start_node(n)

    async def _start_node(self, n: _Node, at: float | None = None) -> None:
        """A fresh instance, set up at ``at`` (the run's origin, or when it was restarted)."""
        n.ctx.time = self.log.origin if at is None else at
        n.ctx._random = None  # a fresh instance draws from the start, as a restarted node does
        if n.worker:
            from ..workers import ProcessExecutor

            factory = ReplayFactory(
                n.rnode.cls, n.params, n.rnode.name, self.log.seed, self.log.origin, n.ctx.period
            )
            n.executor = ProcessExecutor(
                n.rnode.name, factory, priority=n.rnode.spec.priority, realtime=False
            )
            await n.executor.start()
        else:
            from ..node import make_node

            n.node = make_node(n.rnode.cls, n.params, n.ctx)
            await maybe_await(n.node.setup())

    async def _stop_node(self, n: _Node) -> None:
        try:
            if n.executor is not None:
                await n.executor.stop()
            elif n.node is not None:
                await maybe_await(n.node.teardown())
        except Exception as e:
            log.warning("replay: %s: teardown failed: %s", n.rnode.name, e)
        n.executor = n.node = None

    async def stop(self) -> None:
        for n in reversed(list(self.nodes.values())):
            await self._stop_node(n)

    def subscribe(self, target: str, size: int | None = None) -> Buffer:
        """A buffer receiving every value a re-executed ``node.port`` publishes (as recorded)."""
        node, _, port = target.partition(".")
        n = self.nodes.get(node)
        if n is None:
            if node in self.graph.nodes:
                raise KeyError(
                    f"{node} is not re-executed by this replay ({_why_not(self.roles, node)})"
                )
            raise KeyError(f"unknown node {node!r}")
        if port not in n.outputs:
            raise KeyError(f"{node} has no output {port!r} (outputs: {', '.join(n.outputs)})")
        buf = QueueBuffer(f"{target}->replay", size or UNBOUNDED, lambda: n.ctx.time)
        self.subscribers.setdefault((node, port), []).append(buf)
        return buf

    # --- the replay --------------------------------------------------------------------------

    async def run(self) -> None:
        """Re-execute every recorded activation of the replayed nodes, in recorded order.

        Consecutive activations of different worker nodes that do not read each other's
        outputs are called together (a *batch*): each node still sees its own activations in
        order and exactly their inputs, so the results are those of one call at a time, and
        they are compared, counted and published in the recorded order.
        """
        await self.start()
        batch: list[tuple[_Node, Activation]] = []
        for a in self.plan:
            n = self.nodes.get(a.node)
            if n is None or n.reason:
                continue
            if batch and not self._joins(batch, n, a):
                if await self._run_batch(batch):
                    return
                batch = []
                if n.reason:  # given up in that batch
                    continue
            batch.append((n, a))
        if batch:
            await self._run_batch(batch)

    @staticmethod
    def _joins(batch: list[tuple[_Node, Activation]], n: _Node, a: Activation) -> bool:
        names = {m.rnode.name for m, _ in batch}
        return (
            n.worker
            and batch[0][0].worker
            and a.node not in names
            and len(batch) < BATCH
            and not any(key is not None and key[0] in names for key in a.inputs.values())
        )

    async def _run_batch(self, batch: list[tuple[_Node, Activation]]) -> bool:
        """Prepare in order, call together, finish in order; True: stop (a divergence)."""
        calls = [(n, a, await self._prepare(n, a)) for n, a in batch]
        results = await asyncio.gather(
            *(self._call(n, a, ready) for n, a, ready in calls if ready is not None)
        )
        it = iter(results)
        for n, a, ready in calls:
            if ready is None:
                continue
            result, error = next(it)
            await self._finish(n, a, result, error)
            if self.divergence is not None and self.stop_at_divergence:
                self.stopped_early = True
                return True
        return False

    async def _prepare(
        self, n: _Node, a: Activation
    ) -> tuple[dict[str, Any], dict[str, float]] | None:
        """Recorded restarts and params applied, the inputs taken: (inputs, their times), or
        None when the node cannot be replayed from here on."""
        while n.restarts and n.restarts[0] <= a.start:
            at = n.restarts.popleft()
            await self._stop_node(n)
            await self._start_node(n, at)
        if a.kind is not None and a.kind != n.rnode.spec.kind:
            self._give_up(n, a, f"swapped to {a.kind} at {a.start - self.log.origin:.3f} s")
            return None
        if a.params is not None or a.swap:
            await self._set_params(n, a.params or {}, a.swap, a.start)
        for port, key in a.inputs.items():  # all there, or none taken (their uses stay right)
            if key is not None and not self._available(key):
                self._give_up(n, a, f"input {port}: {key[0]}.{key[1]} #{key[2]} is not recorded")
                return None
        inputs: dict[str, Any] = dict.fromkeys(n.rnode.cls.inputs)
        times: dict[str, float] = {}
        for port, key in a.inputs.items():
            inputs[port], t = (None, None) if key is None else self._value(key)
            if t is not None:
                times[port] = t
        return inputs, times

    async def _call(
        self, n: _Node, a: Activation, ready: tuple[dict[str, Any], dict[str, float]]
    ) -> tuple[list[tuple[str, Any]], BaseException | None]:
        """``process`` on recorded time: (what it published, in order; its exception)."""
        inputs, times = ready
        n.ctx.time = a.start
        n.ctx.times = times
        n.published = []
        try:
            if n.worker:
                result = await n.executor.call({**inputs, NOW_KEY: a.start, TIMES_KEY: times})
            else:
                result = await maybe_await(n.node.process(**inputs))
        except Exception as e:
            n.published = []
            return [], e
        outputs = n.published + _results(n, result)
        n.published = []
        return outputs, None

    async def _finish(
        self, n: _Node, a: Activation, outputs: list[tuple[str, Any]], error: BaseException | None
    ) -> None:
        n.activations += 1
        self.activations += 1
        if n.new:
            self._publish_new(n, a, outputs, error)
            return
        done = self.log.completions.get((a.node, a.n))
        if done is None or done.discarded:
            return  # it failed or was discarded in the run too: nothing was published then
        if error is not None:
            await self._stop_node(n)
            await self._start_node(n, a.start)  # as supervision would
            self._diverged_raised(n, a, error)
            return
        self._compare(n, a, outputs)

    def _publish_new(
        self, n: _Node, a: Activation, outputs: list[tuple[str, Any]], error: BaseException | None
    ) -> None:
        """A new node's outputs: nothing to compare them with; to its subscribers."""
        if error is not None:
            log.warning("replay: new node %s raised: %s", a.node, error)
            return
        for port, value in outputs:
            seq = self.next_seq.get((a.node, port), 1)
            self.next_seq[(a.node, port)] = seq + 1
            for buf in self.subscribers.get((a.node, port), ()):
                buf.put(value, a.start)

    def _compare(self, n: _Node, a: Activation, outputs: list[tuple[str, Any]]) -> None:
        name = a.node
        expected: dict[str, deque[OutputRecord]] = {}
        for r in self.log.outputs.get((name, a.n), []):
            expected.setdefault(r.port, deque()).append(r)
        for port, value in outputs:
            queue = expected.get(port)
            rec = queue.popleft() if queue else None
            if rec is None:
                seq = self.next_seq.get((name, port), 1)
                if self.cut_after.get(name) != a.n:
                    self._diverged(
                        n, a, port, seq, "an output the recording does not have", None, value
                    )
            else:
                seq = rec.seq
                n.compared += 1
                self.compared += 1
                if digest(value) != rec.digest:
                    self._diverged(
                        n, a, port, seq, "its digest differs from the recorded one", rec, value
                    )
            self.next_seq[(name, port)] = seq + 1
            key = (name, port, seq)
            if self.needs.get(key, 0) > 0:
                self.produced[key] = value
                self.produced_times[key] = a.start if rec is None else rec.t
            for buf in self.subscribers.get((name, port), ()):
                buf.put(value, a.start if rec is None else rec.t)
        for port, queue in expected.items():
            if queue:
                rec = queue[0]
                self._diverged(
                    n, a, port, rec.seq, "the recorded output was not produced", rec, None
                )

    def _from_producer(self, key: Key) -> bool:
        """The value comes from a node this replay re-executes (else from the recording)."""
        n = self.nodes.get(key[0])
        return n is not None and not n.reason

    def _available(self, key: Key) -> bool:
        if self._from_producer(key):
            return key in self.produced
        place = self.log.recorded(key)
        return place is not None and self.values is not None and self.values.has(place)

    def _value(self, key: Key) -> tuple[Any, float | None]:
        """(value, publication time) of the value ``key`` an activation held (one use of it)."""
        if self._from_producer(key):
            value, t = self.produced[key], self.produced_times[key]
            left = self.needs[key] = self.needs.get(key, 1) - 1
            if left <= 0:
                del self.produced[key], self.produced_times[key]
            return value, t
        place = self.log.recorded(key)
        assert place is not None  # checked by _available
        assert self.values is not None
        _, value = self.values.get(place)
        rec = self.log.sources.get(key) or self.log.output_at.get(key)
        return value, None if rec is None else rec.t

    async def _set_params(self, n: _Node, delta: dict[str, Any], swap: bool, at: float) -> None:
        """A recorded params change (what differed from the recorded graph's), over this
        graph's params, as the run made it: inline, the instance gets them (and
        ``params_changed``); a swap (``ctl swap``), or any change of a worker node, is a fresh
        instance taking over, with the old one's ``get_state()`` when both are inline."""
        base = self.graph.nodes[n.rnode.name].params.model_dump(mode="json")
        params = self.graph.validate_params(n.rnode.cls, {**base, **delta})
        old, n.params = n.params, params
        if n.worker or swap:
            getter = getattr(n.node, "get_state", None)
            state = getter() if getter is not None else None
            await self._stop_node(n)
            await self._start_node(n, at)
            setter = getattr(n.node, "set_state", None)
            if getter is not None and setter is not None:
                setter(state)
            return
        n.node.params = params
        hook = getattr(n.node, "params_changed", None)
        if hook is not None:
            hook(old)

    def _give_up(self, n: _Node, a: Activation, reason: str) -> None:
        """``n`` cannot be replayed from activation ``a`` on: its remaining uses are released."""
        n.reason = reason
        for x in self.plan:
            if x.node != a.node or x.n < a.n:
                continue
            for key in x.inputs.values():
                if key is None:
                    continue
                if self._from_producer(key):
                    left = self.needs[key] = self.needs.get(key, 1) - 1
                    if left <= 0:
                        self.produced.pop(key, None)
                        self.produced_times.pop(key, None)
                elif self.values is not None and (place := self.log.recorded(key)) is not None:
                    self.values.release(place)

    # --- divergences -------------------------------------------------------------------------

    def _diverged(
        self,
        n: _Node,
        a: Activation,
        port: str,
        seq: int,
        why: str,
        rec: OutputRecord | None,
        value: Any,
    ) -> None:
        if self.divergence is None:
            self.divergence = _divergence(self.log, a, port, seq, why, rec, value)

    def _diverged_raised(self, n: _Node, a: Activation, error: BaseException) -> None:
        recs = self.log.outputs.get((a.node, a.n), [])
        port, seq = (recs[0].port, recs[0].seq) if recs else ("-", 0)
        summary = getattr(error, "summary", None) or f"{type(error).__name__}: {error}"
        self._diverged(n, a, port, seq, f"it raised {summary}", recs[0] if recs else None, None)

    # --- the report --------------------------------------------------------------------------

    def report(self, wall_s: float) -> ReplayReport:
        """What was compared, what was not and why, the first divergence (if any)."""
        return _report(self, wall_s)


def _results(n: _Node, result: Any) -> list[tuple[str, Any]]:
    """``process``'s return as (port, value) pairs, as the runner publishes it."""
    if result is None:
        return []
    outs = n.outputs
    if len(outs) == 1:
        return [(outs[0], result)]
    if not isinstance(result, Mapping):
        return [("?", result)]
    return [(p, v) for p, v in result.items() if v is not None]


def _why_not(roles: Mapping[str, str], name: str, recorded: bool = True) -> str:
    """Why a node of the graph was not compared, in words for the report (``recorded``:
    the recording holds activations or values of it)."""
    role = roles.get(name)
    if role == "source":
        if not recorded:  # it said "its values are the recording's" of a source not in it
            return "a source the recording does not hold (recorded with another graph?)"
        return "a source: its values are the recording's"
    if role == "sink":
        return "it has no outputs"
    return "the recording has no activation of it"


def _report(self: ReplayEngine, wall_s: float) -> ReplayReport:
    """See :meth:`ReplayEngine.report`."""
    nodes: list[NodeReplay] = []
    recorded_nodes = {a.node for a in self.log.activations} | {s[0] for s in self.log.sources}
    for name in self.graph.nodes:
        n = self.nodes.get(name)
        if n is not None:
            nodes.append(
                NodeReplay(
                    node=name,
                    status="not comparable" if n.reason else "new" if n.new else "compared",
                    activations=n.activations,
                    compared=n.compared,
                    reason=n.reason,
                )
            )
        elif self.roles[name] == "source" and name in recorded_nodes:
            nodes.append(NodeReplay(node=name, status="source"))
        else:
            why = self.not_run.get(name) or _why_not(self.roles, name, name in recorded_nodes)
            nodes.append(NodeReplay(node=name, status="not run", reason=why))
    for name in sorted(recorded_nodes - set(self.graph.nodes)):
        nodes.append(
            NodeReplay(
                node=name,
                status="not run",
                reason="not in this graph (its recorded outputs stand in for it)",
            )
        )
    changes = [
        f"{c.t - self.log.origin:.3f} s {c.node or ''}: {c.what} {c.text}"
        + (f" ({c.origin})" if c.origin else "")
        for c in self.log.changes
    ]
    # nothing compared (every node given up: a session begun mid-run, its inputs from before
    # it never recorded; or no node of this graph in the recording): no divergence, and no
    # claim of "identical" either
    nothing = self.compared == 0
    return ReplayReport(
        identical=self.divergence is None and self.log.closed_cleanly and not nothing,
        activations=self.activations,
        compared=self.compared,
        first_divergence=self.divergence,
        wall_s=wall_s,
        recorded_s=self.log.duration,
        nodes=nodes,
        changes=changes,
        stopped_early=self.stopped_early,
        log_cut=None if self.log.closed_cleanly else (self.log.damage or "not closed"),
    )


def _divergence(
    log_: DeterminismLog,
    a: Activation,
    port: str,
    seq: int,
    why: str,
    rec: OutputRecord | None,
    value: Any,
) -> Divergence:
    """The first divergence, with both values where the recording holds the recorded one."""
    recorded = None
    if rec is not None and rec.topic is not None and rec.index is not None:
        recorded = show(read_one(log_.path, rec.topic, rec.index, rec.stamp))
    return Divergence(
        node=a.node,
        port=port,
        seq=seq,
        time=round(a.start - log_.origin, 6),
        why=why,
        recorded=recorded,
        replayed=None if value is None else show(value),
    )


def _plan_new_nodes(self: ReplayEngine, recorded: set[str]) -> None:
    """Nodes of the graph the recording has no activation of, run on their trigger over
    the recorded streams (:mod:`.synthesis`), merged into the recorded order by time."""
    new = [n for n in self.graph.nodes if self.roles[n] == "replayed" and n not in recorded]
    if not new:
        return
    available = streams(self.log, set(self.nodes))
    for name in new:
        acts, why = synthesize(self.graph, name, self.log, available)
        if not acts:
            self.not_run[name] = why or "its trigger never fired on the recorded streams"
            continue
        existing = self.nodes[name] = self._node(name, self.graph.nodes[name])
        existing.new = True
        self.plan.extend(acts)
    # recorded activations keep their order (their starts never decrease); a new one goes
    # after those that started at or before its time
    self.plan.sort(
        key=lambda a: (a.start, self.nodes[a.node].new if a.node in self.nodes else False)
    )
