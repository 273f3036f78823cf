"""What a deterministic recording holds beside the streams, and reading it back.

Five JSON channels, written by :class:`~.observer.Observer` through the recorder's writer:

- ``/flowrt/det/activation``: one per activation of a *replayed* node (see :func:`roles`):
  ``node``, ``n`` (its activation number), ``release`` and ``start`` (runtime clock, seconds),
  ``inputs`` (per connected input: ``[source node, port, seq]`` of the value it held, or
  null), and ``params`` (what differs from the graph's params) when they changed since its
  previous activation (a mode, ``ctl set``), ``swap`` when a new instance took over (``ctl
  swap``) and ``kind`` when that was of another kind;
- ``/flowrt/det/completion``: ``node``, ``n``, ``end``, ``discarded`` (a firm deadline
  missed): an activation without one failed or was cut short, and published nothing;
- ``/flowrt/det/output``: every publication of a replayed node: ``node``, ``port``, ``seq``,
  ``n`` (the activation it belongs to), ``t``, ``digest`` (:mod:`.digest`), and ``topic`` and
  ``index`` when the value itself is recorded too (the n-th message of that topic);
- ``/flowrt/det/source``: every publication of a source (a node without inputs, or
  ``external``): ``node``, ``port``, ``seq``, ``t``, ``topic`` and ``index`` of the recorded
  value, and what the encoding would round off: a frame's ``timestamp``, ``seq``, ``source``
  and pixel format, a value's own ``stamp``;
- ``/flowrt/det/change``: timing changes and restarts as they happened (``t``, ``node``,
  ``what``, ``text``, ``origin``).

Times are floats of the runtime clock written by ``repr`` (JSON), so they come back exact: a
tracker's detection carries its frame's timestamp, and its digest must match to the bit.
Sequence numbers count a port's publications from 1; every edge of the port sees the same
numbers (:attr:`flowrt.edges.Buffer.taken_seq`). The metadata record ``flowrt.determinism``
holds the format, the seed of ``ctx.random`` and the clock's origin.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ..graph._resolve import Graph, ResolvedNode

__all__ = [
    "ACTIVATION",
    "CHANGE",
    "COMPLETION",
    "METADATA",
    "OUTPUT",
    "SOURCE",
    "TOPICS",
    "Activation",
    "Change",
    "Completion",
    "DeterminismLog",
    "LogError",
    "OutputRecord",
    "Role",
    "SourceRecord",
    "read_log",
    "roles",
]

PREFIX = "/flowrt/det/"
ACTIVATION = PREFIX + "activation"
COMPLETION = PREFIX + "completion"
OUTPUT = PREFIX + "output"
SOURCE = PREFIX + "source"
CHANGE = PREFIX + "change"
TOPICS = (ACTIVATION, COMPLETION, OUTPUT, SOURCE, CHANGE)
METADATA = "flowrt.determinism"
FORMAT = "1"

Role = Literal["source", "replayed", "sink"]
"""``source``: its outputs are recorded values (no inputs, or ``Node.external``); ``replayed``:
re-executed by replay; ``sink``: no outputs (a recorder, a display): nothing to re-execute."""

Key = tuple[str, str, int]
"""(node, port, seq): one published value."""


def role(rnode: ResolvedNode, has_inputs: bool) -> Role:
    if not has_inputs or rnode.cls.external:
        return "source"
    if not {**rnode.cls.outputs, **rnode.cls.params_outputs(rnode.params)}:
        return "sink"
    return "replayed"


def roles(graph: Graph) -> dict[str, Role]:
    """Every node's role in a deterministic recording or replay of ``graph``."""
    fed = {e.dst for e in graph.edges}
    return {name: role(n, name in fed) for name, n in graph.nodes.items()}


@dataclass(frozen=True)
class Activation:
    node: str
    n: int
    release: float
    start: float
    inputs: dict[str, Key | None]
    params: dict[str, Any] | None = None
    kind: str | None = None
    swap: bool = False


@dataclass(frozen=True)
class Completion:
    node: str
    n: int
    end: float
    discarded: bool


@dataclass(frozen=True)
class OutputRecord:
    node: str
    port: str
    seq: int
    n: int
    t: float
    digest: str
    topic: str | None = None
    index: int | None = None
    stamp: float | None = None  # the value's own timestamp, runtime clock (recorded: Unix ns)


@dataclass(frozen=True)
class SourceRecord:
    node: str
    port: str
    seq: int
    t: float
    topic: str
    index: int
    frame: dict[str, Any] | None = None
    stamp: float | None = None


@dataclass(frozen=True)
class Change:
    t: float
    node: str | None
    what: str
    text: str
    origin: str = ""


class LogError(Exception):
    """A session that holds no (readable) deterministic log: the message says why, in one line."""


@dataclass
class DeterminismLog:
    """Everything a replay needs, indexed."""

    path: Path
    activations: list[Activation] = field(default_factory=list)
    completions: dict[tuple[str, int], Completion] = field(default_factory=dict)
    outputs: dict[tuple[str, int], list[OutputRecord]] = field(default_factory=dict)
    output_at: dict[Key, OutputRecord] = field(default_factory=dict)
    sources: dict[Key, SourceRecord] = field(default_factory=dict)
    changes: list[Change] = field(default_factory=list)
    seed: str = "0"
    origin: float = 0.0
    graph: str | None = None
    version: str = ""
    duration: float = 0.0
    closed_cleanly: bool = True
    damage: str | None = None

    def recorded(self, key: Key) -> tuple[str, int] | None:
        """(topic, index) of the recorded value ``key``, or None when only its digest is."""
        src = self.sources.get(key)
        if src is not None:
            return src.topic, src.index
        out = self.output_at.get(key)
        if out is not None and out.topic is not None and out.index is not None:
            return out.topic, out.index
        return None


def _key(v: Any) -> Key | None:
    if v is None:
        return None
    node, port, seq = v
    return str(node), str(port), int(seq)


def _float(v: Any) -> float:
    if isinstance(v, int | float) and math.isfinite(v):
        return float(v)
    raise ValueError(f"not a time: {v!r}")


def _add(log: DeterminismLog, topic: str, r: dict[str, Any]) -> None:
    if topic == ACTIVATION:
        log.activations.append(
            Activation(
                str(r["node"]),
                int(r["n"]),
                _float(r["release"]),
                _float(r["start"]),
                {str(p): _key(v) for p, v in dict(r["inputs"]).items()},
                r.get("params"),
                r.get("kind"),
                bool(r.get("swap", False)),
            )
        )
    elif topic == COMPLETION:
        c = Completion(str(r["node"]), int(r["n"]), _float(r["end"]), bool(r["discarded"]))
        log.completions[(c.node, c.n)] = c
    elif topic == OUTPUT:
        o = OutputRecord(
            str(r["node"]),
            str(r["port"]),
            int(r["seq"]),
            int(r["n"]),
            _float(r["t"]),
            str(r["digest"]),
            r.get("topic"),
            r.get("index"),
            r.get("stamp"),
        )
        log.outputs.setdefault((o.node, o.n), []).append(o)
        log.output_at[(o.node, o.port, o.seq)] = o
    elif topic == SOURCE:
        s = SourceRecord(
            str(r["node"]),
            str(r["port"]),
            int(r["seq"]),
            _float(r["t"]),
            str(r["topic"]),
            int(r["index"]),
            r.get("frame"),
            r.get("stamp"),
        )
        log.sources[(s.node, s.port, s.seq)] = s
    elif topic == CHANGE:
        log.changes.append(
            Change(
                _float(r["t"]), r.get("node"), str(r["what"]), str(r["text"]), r.get("origin", "")
            )
        )


def _facts(files: list[Path]) -> dict[str, Any] | None:
    """Metadata, graph, duration from the files' summaries (a millisecond, where a full scan
    reads every message); None when a file has no summary (not closed cleanly)."""
    from mcap.reader import SeekingReader

    facts: dict[str, Any] = {"metadata": {}, "graph": None, "start": None, "end": None}
    try:
        for f in files:
            with open(f, "rb") as fh:
                reader = SeekingReader(fh)
                summary = reader.get_summary()
                if summary is None or summary.statistics is None:
                    return None
                st = summary.statistics
                if st.message_count:
                    start, end = st.message_start_time, st.message_end_time
                    facts["start"] = start if facts["start"] is None else min(facts["start"], start)
                    facts["end"] = end if facts["end"] is None else max(facts["end"], end)
                for m in reader.iter_metadata():
                    facts["metadata"].setdefault(m.name, dict(m.metadata))
                for a in reader.iter_attachments():
                    if a.name == "graph.yaml" and facts["graph"] is None:
                        facts["graph"] = a.data.decode("utf-8", "replace")
    except Exception:  # a damaged file: the full scan says what is wrong
        return None
    return facts


def read_log(path: str | Path) -> DeterminismLog:
    """The deterministic log of a session folder or file; LogError when it has none."""
    from ..recording.reader import iter_session, scan_session
    from ..recording.repair import REPAIR_METADATA
    from ..recording.session import mcap_files, missing_parts

    p = Path(path)
    if not p.exists():
        raise LogError(f"{path}: no such file or folder")
    files = mcap_files(p)
    if not files or not files[0].exists():
        raise LogError(f"{path}: no .mcap file")
    facts = _facts(files)
    log = DeterminismLog(p)
    if facts is None:
        info = scan_session(p)
        metadata, log.graph = info.metadata, info.graph
        log.duration, log.closed_cleanly, log.damage = (
            info.duration,
            info.closed_cleanly,
            info.damage,
        )
    else:
        metadata, log.graph = facts["metadata"], facts["graph"]
        if facts["start"] is not None:
            log.duration = (facts["end"] - facts["start"]) / 1e9
    missing = missing_parts(p, files)
    if missing:  # what the part held was never compared: never "identical"
        log.closed_cleanly = False
        log.damage = f"{', '.join(missing)}: missing (a part of this split session)"
    repair = metadata.get(REPAIR_METADATA)
    if repair is not None:  # `flowrt info --repair` made it whole, but what the cut lost
        log.closed_cleanly = False  # is lost: never "identical"
        log.damage = f"repaired after {repair.get('damage') or 'damage'}"
    meta = metadata.get(METADATA)
    if meta is None:
        raise LogError(
            f"{path}: not a deterministic recording (record it with flowrt record --deterministic)"
        )
    log.seed = meta.get("seed", "0")
    try:
        log.origin = float(meta.get("origin", "0"))
    except ValueError:
        raise LogError(f"{path}: bad clock origin {meta.get('origin')!r}") from None
    log.version = metadata.get("flowrt", {}).get("flowrt_version", "")
    for m in iter_session(files, set(TOPICS)):
        try:
            _add(log, m.topic, json.loads(m.data))
        except (ValueError, KeyError, TypeError) as e:
            raise LogError(f"{path}: bad {m.topic} record #{m.sequence}: {e}") from None
    if not log.activations and not log.sources:
        raise LogError(f"{path}: the deterministic log is empty")
    return log
