"""Activations for a node the recording has none of: a new node reading recorded streams.

Its trigger is applied to what was recorded, the way the scheduler would have applied it: a
frame trigger's period and phase to the publications of its frame source (tick k is the k-th
publication, from 0), an input trigger to each publication on a triggering input (that value,
and the newest of the others), a timer to its instants over the recorded span. Each input holds
the newest value published at or before the activation's time. What the live run would have
added (overruns, skipped releases, a mode changing its timing) is not invented: the node runs
on every release, as if it were never late. Its outputs are not compared (nothing was recorded
of them), only published to its readers and subscribers.
"""

from __future__ import annotations

import bisect
import math

from ..graph._resolve import Graph
from ..graph.spec import FrameTrigger, InputTrigger, TimerTrigger
from .log import Activation, DeterminismLog, Key

__all__ = ["streams", "synthesize"]

Stream = list[tuple[float, int]]  # (publication time, seq), in order


def streams(log: DeterminismLog, replayed: set[str]) -> dict[tuple[str, str], Stream]:
    """Every recorded stream a new node could read: the sources', and the outputs of nodes
    that are re-executed or whose values the recorder kept."""
    out: dict[tuple[str, str], Stream] = {}
    for (node, port, seq), s in log.sources.items():
        out.setdefault((node, port), []).append((s.t, seq))
    for (node, port, seq), o in log.output_at.items():
        if node in replayed or (o.topic is not None and o.index is not None):
            out.setdefault((node, port), []).append((o.t, seq))
    for stream in out.values():
        stream.sort()
    return out


def _newest(stream: Stream, t: float) -> int | None:
    i = bisect.bisect_right(stream, (t, math.inf))
    return stream[i - 1][1] if i else None


def synthesize(
    graph: Graph, name: str, log: DeterminismLog, available: dict[tuple[str, str], Stream]
) -> tuple[list[Activation], str]:
    """The activations of new node ``name`` (and "" ), or ([], why it cannot run)."""
    rnode = graph.nodes[name]
    feeds = {e.dst_port: (e.src, e.src_port) for e in graph.edges if e.dst == name}
    for port, src in feeds.items():
        if src not in available:
            return [], f"input {port}: {src[0]}.{src[1]} is neither recorded nor re-executed"
    trig = rnode.trigger
    releases: list[tuple[float, dict[str, Key]]] = []  # (time, inputs fixed by the trigger)
    if isinstance(trig, FrameTrigger):
        fnode, _, fport = graph.frame_port(trig.frame).partition(".")
        ticks = available.get((fnode, fport), [])
        releases = [(t, {}) for k, (t, _) in enumerate(ticks) if k % trig.period == trig.phase]
    elif isinstance(trig, InputTrigger):
        wanted = [trig.input] if isinstance(trig.input, str) else trig.input
        events = [
            (t, port, seq)
            for port, src in feeds.items()
            if "any" in wanted or port in wanted
            for t, seq in available[src]
        ]
        events.sort()
        releases = [(t, {port: (*feeds[port], seq)}) for t, port, seq in events]
    elif isinstance(trig, TimerTrigger):
        times = [a.start for a in log.activations] + [s.t for s in log.sources.values()]
        if times:
            period, phase = trig.timer / 1000, trig.phase / 1000
            k = max(0, math.ceil((min(times) - log.origin - phase) / period))
            while (t := log.origin + phase + k * period) <= max(times):
                releases.append((t, {}))
                k += 1
    else:
        return [], "loop-triggered and not in the recording: nothing says when it would run"
    required = [p for p, i in rnode.cls.inputs.items() if i.required]
    acts: list[Activation] = []
    for t, fixed in releases:
        inputs: dict[str, Key | None] = {}
        for port, src in feeds.items():
            if port in fixed:
                inputs[port] = fixed[port]
                continue
            seq = _newest(available[src], t)
            inputs[port] = None if seq is None else (src[0], src[1], seq)
        if any(inputs.get(p) is None for p in required):
            continue  # a required input holds nothing yet: the runner skips such a release
        acts.append(Activation(name, len(acts) + 1, t, t, inputs))
    return acts, ""
