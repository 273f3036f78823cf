"""The observer a deterministic recording installs in the scheduler (through ``ctx.observe``).

The scheduler calls it at three instants, on the event loop (see ``observer`` in
:mod:`flowrt.kernel.runner`):

- ``activation(node, release, start, held, rnode)`` when an activation starts to run, with
  the sequence number of the value each input took (``Buffer.taken_seq``);
- ``completed(node, release, end, discarded)`` when it ends (before its results publish);
- ``published(node, port, value, t)`` for every publication.

It turns them into the records of :mod:`.log` and hands them to a :class:`Sink` (the recorder
node), which writes them with the streams. Sources' values go to the sink whole (the streams
a plain recording has); other outputs as digests, and whole too when the recorder reads them.

Which activation an output belongs to: a node's calls complete in the order they started (one
at a time, or pipelined in order), so a completion is matched with the oldest open activation
of the same release time (older open ones failed or were cut short); what a node publishes
after that, until it starts again, is that activation's, and what it publishes while running
(``ctx.publish``) is the running one's.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Any, Protocol

from ..events import Event, NodeRestarted, TimingChanged
from ..frames import Frame
from ..graph._resolve import Graph, ResolvedNode
from .digest import digest
from .log import ACTIVATION, CHANGE, COMPLETION, FORMAT, OUTPUT, SOURCE, Role, roles

__all__ = ["Observer", "Sink"]

log = logging.getLogger("flowrt.determinism")


class Sink(Protocol):
    """Where the observer's records go (the recorder's writer)."""

    @property
    def recording(self) -> bool:
        """False between sessions (``ctl record stop``): records are not kept then."""
        ...

    def log(self, topic: str, record: dict[str, Any], t: float) -> None:
        """Write one log record at runtime-clock time ``t``."""
        ...

    def value(self, topic: str, source: str, value: Any) -> int | None:
        """Record a published value on ``topic``; its index among that topic's messages, or
        None when refused (the writer is behind or stopped)."""
        ...


def _params_delta(base: dict[str, Any], now: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in now.items() if base.get(k, object()) != v}


class Observer:
    """Records one graph's activations and publications into a :class:`Sink`."""

    def __init__(self, sink: Sink, recorder: str = "") -> None:
        self.sink = sink
        self.recorder = recorder  # its inputs' names are the topics of the values it reads
        self.graph: Graph | None = None
        self.origin = 0.0
        self.roles: dict[str, Role] = {}
        self.topics: dict[tuple[str, str], str] = {}  # (node, port) -> topic of its values
        self.feeds: dict[tuple[str, str], tuple[str, str]] = {}  # input -> its source output
        self.seqs: dict[tuple[str, str], int] = {}
        self.counts: dict[str, int] = {}  # activations per node
        self.open: dict[str, deque[tuple[int, float]]] = {}  # (n, release) not completed
        self.current: dict[str, int] = {}  # the activation a publication belongs to
        self.rnodes: dict[str, ResolvedNode] = {}  # what the last activation ran
        self.base: dict[str, dict[str, Any]] = {}  # the graph's params, as JSON
        self.refused = 0  # values the sink refused: their readers' activations cannot replay
        self.previous: Observer | None = None  # logs on until this one's sink records

    def attach(self, graph: Graph, scheduler: Any) -> None:
        """Called by ``ctx.observe``: learn the graph and hear its events (timing, restarts).

        A recorder swapped while recording installs its observer before its own file is
        open: the observer it replaces (``scheduler.observer`` still) goes on logging into
        its session until this one records (:attr:`previous`), and this one's numbers go on
        from its (they began at 0 again, mid-run, and a session's numbers are the run's)."""
        previous = getattr(scheduler, "observer", None)
        if isinstance(previous, Observer) and previous is not self:
            self.previous = previous
            self.seqs, self.counts = dict(previous.seqs), dict(previous.counts)
            self.open = {n: deque(q) for n, q in previous.open.items()}
            self.current, self.rnodes = dict(previous.current), dict(previous.rnodes)
        self.graph = graph
        self.origin = float(scheduler.clock.origin)
        self.roles = roles(graph)
        for e in graph.edges:
            self.feeds[(e.dst, e.dst_port)] = (e.src, e.src_port)
            if e.dst == self.recorder:
                self.topics[(e.src, e.src_port)] = e.dst_port
        for name, n in graph.nodes.items():
            self.rnodes[name] = n
            if self.roles[name] == "replayed":
                self.base[name] = n.params.model_dump(mode="json")
        emit = scheduler.emit

        def tee(event: Event) -> None:
            self.event(event)
            emit(event)

        scheduler.emit = tee

    def metadata(self, seed: str) -> dict[str, str]:
        """The ``flowrt.determinism`` metadata record."""
        return {"format": FORMAT, "seed": seed, "origin": repr(self.origin)}

    # --- the scheduler's calls ---------------------------------------------------------------

    def _handed_over(self) -> Observer | None:
        """The observer this one replaced, while this one's sink does not record yet (called
        only while there is one: every publication passes here)."""
        prev = self.previous
        if prev is not None and self.sink.recording:
            self.previous = prev = None  # this session has begun: the old one has ended
        return prev

    def activation(
        self,
        node: str,
        release: float,
        start: float,
        held: dict[str, int | None],
        rnode: ResolvedNode,
    ) -> None:
        if self.previous is not None and (prev := self._handed_over()) is not None:
            prev.activation(node, release, start, held, rnode)
        if self.roles.get(node) != "replayed":
            return
        n = self.counts[node] = self.counts.get(node, 0) + 1
        self.open.setdefault(node, deque()).append((n, release))
        self.current[node] = n
        if not self.sink.recording or self.graph is None:
            return
        inputs: dict[str, list[Any] | None] = {}
        for port, seq in held.items():
            src = self.feeds.get((node, port))
            inputs[port] = None if seq is None or src is None else [src[0], src[1], seq]
        record: dict[str, Any] = {
            "node": node,
            "n": n,
            "release": release,
            "start": start,
            "inputs": inputs,
        }
        last = self.rnodes.get(node)
        if last is not None and rnode is not last:
            self.rnodes[node] = rnode
            if rnode.params is not last.params:
                now = rnode.params.model_dump(mode="json")
                record["params"] = _params_delta(self.base.get(node, {}), now)
            if rnode.spec is not last.spec:  # a swap (set_params keeps the spec)
                record["swap"] = True
            if rnode.spec.kind != last.spec.kind or rnode.cls is not last.cls:
                record["kind"] = rnode.spec.kind
        self.sink.log(ACTIVATION, record, start)

    def completed(self, node: str, release: float, end: float, discarded: bool) -> None:
        if self.previous is not None and (prev := self._handed_over()) is not None:
            prev.completed(node, release, end, discarded)
        pending = self.open.get(node)
        if not pending:
            return
        while pending:
            n, r = pending.popleft()
            if r == release:
                break
        else:
            return  # no open activation of that release: not one of the recorded ones
        self.current[node] = n
        if self.sink.recording:
            record = {"node": node, "n": n, "end": end, "discarded": discarded}
            self.sink.log(COMPLETION, record, end)

    def published(self, node: str, port: str, value: Any, t: float) -> None:
        if self.previous is not None and (prev := self._handed_over()) is not None:
            prev.published(node, port, value, t)
        key = (node, port)
        seq = self.seqs[key] = self.seqs.get(key, 0) + 1
        role = self.roles.get(node)
        if not self.sink.recording or role is None or role == "sink":
            return
        topic = self.topics.get(key)
        if role == "source":
            topic = topic or f"{node}.{port}"
            index = self.sink.value(topic, f"{node}.{port}", value)
            if index is None:
                self.refused += 1
                return
            record: dict[str, Any] = {
                "node": node,
                "port": port,
                "seq": seq,
                "t": t,
                "topic": topic,
                "index": index,
            }
            if isinstance(value, Frame):
                record["frame"] = {
                    "timestamp": value.timestamp,
                    "seq": value.seq,
                    "source": value.source,
                    "pixel_format": value.pixel_format,
                }
            elif (stamp := _own_stamp(value)) is not None:
                record["stamp"] = stamp
            self.sink.log(SOURCE, record, t)
            return
        record = {
            "node": node,
            "port": port,
            "seq": seq,
            "n": self.current.get(node, 0),
            "t": t,
            "digest": digest(value),
        }
        if topic is not None:
            index = self.sink.value(topic, f"{node}.{port}", value)
            if index is not None:
                record["topic"], record["index"] = topic, index
                if (stamp := _own_stamp(value)) is not None:  # the recording has it in
                    record["stamp"] = stamp  # Unix ns: a divergence shows it as replayed
        self.sink.log(OUTPUT, record, t)

    def event(self, event: Event) -> None:
        """Timing changes and restarts, as they happen (replay applies the restarts)."""
        if not self.sink.recording:
            return
        t = self.origin + event.t
        if isinstance(event, TimingChanged):
            record = {
                "t": t,
                "node": event.node,
                "what": "timing",
                "text": event.change,
                "origin": event.origin,
            }
        elif isinstance(event, NodeRestarted):
            record = {"t": t, "node": event.node, "what": "restart", "text": "", "origin": ""}
        else:
            return
        self.sink.log(CHANGE, record, t)


def _own_stamp(value: Any) -> float | None:
    """A value's own ``timestamp`` on the runtime clock (a detection's frame time), if any."""
    stamp = value.get("timestamp") if isinstance(value, dict) else getattr(value, "timestamp", None)
    return stamp if isinstance(stamp, float) else None
