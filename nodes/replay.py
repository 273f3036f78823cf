"""The ``replay`` source: recorded streams published again with their recorded timing.

    front_cam:
      kind: replay
      params: {path: recordings/drive_001, topic: front_cam.frame, rate: 1.0}

A ``replay`` node publishes one recorded stream (or several: ``topics``) on its ``frame``
output (images) and ``message`` output (everything else). ``flowrt replay --graph`` goes one
step further: each source of the user's graph that has recorded streams is replaced by a
replay node *with that source's own output ports* (:meth:`ReplayBase.standing_in_for`), so
the rest of the graph — trackers, their frame triggers and phases — runs unchanged on
recorded data.

Frames go into the runtime's frame pool (``ctx.new_frame``), keep their recorded sequence
number, and tick frame triggers like a camera does; reading and decoding the file runs on a
thread, only the pixel copy into the pool slot happens on the loop. Messages are released at
``start + LEAD + (log_time - first) / rate`` on the runtime clock, ``start`` being the first
activation of any replay node of the run, which the runtime makes once every node is set up:
the replay nodes of a run stay in step, and a worker that took a second to start does not
make the first second of frames due at once (a burst its readers skip frames of). With
``on_end: stop``, the run stops when the last of its replay nodes with ``on_end: stop`` has
played to its end, not the first: a stream that ends early (4 detections in 3 s) does not cut
the others short (a looping node never ends). A session split into several files is replayed
as one recording, the parts one after the other in their order (a part that ends before
``start`` is skipped unread). A damaged file is replayed up to the damage, which is logged
and reported as the node's error state. A value recorded with the ``ros2`` profile is
published as the value it was recorded from (:func:`_as_recorded`): a mapping (written as
``flowrt_msgs/KeyValue[]``) as the mapping, a ``std_msgs`` scalar as the scalar, an
``AudioBlock`` as one.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import keyword
import weakref
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from flowrt import AudioBlock, FatalError, Frame, LoopTrigger, Node, Output, resolve_path
from flowrt.recording.decoding import MessageDecoder
from flowrt.recording.encoding import ANNOTATIONS_SCHEMA
from flowrt.recording.images import is_image_schema
from flowrt.recording.reader import (
    Recording,
    channel_schemas,
    iter_messages,
    iter_session,
    last_log_time,
)
from flowrt.recording.ros2_profile import ros2_topic, value_restorer
from flowrt.recording.session import mcap_files, not_a_recording, sessions_hint
from flowrt.recording.streams import join_set

LEAD = 0.05
"""Seconds between the first activation of the run's replay nodes and the first message."""


STAMP_SPAN = 60.0
"""Seconds a message's own stamp may lie before its log time and still be its frame's time."""


@dataclasses.dataclass
class _Pixels:
    """A decoded image: its pixels, flowrt pixel format and own stamp (ns), for a frame."""

    data: np.ndarray
    format: str
    stamp: int | None


#: Output types a replayed value has exactly (everything else comes back as plain values).
_REPLAYED_AS_IS: tuple[Any, ...] = (Frame, AudioBlock, int, float, str, bool, bytes, list, dict)


class _Item:
    __slots__ = ("log_time", "port", "seq", "value")

    def __init__(self, port: str, log_time: int, seq: int, value: Any) -> None:
        self.port, self.log_time, self.seq, self.value = port, log_time, seq, value


@dataclasses.dataclass(eq=False)
class _Run:
    """What the replay nodes of one run share: the time their messages are due from, and
    which of them still play, so that the run stops after the last one ends."""

    graph: Callable[[], Any] | None  # the running graph (weak): which run this is
    start: float | None = None  # ctx.elapsed() at the first activation of any of them
    members: set[str] = dataclasses.field(default_factory=set)  # set up, not torn down
    stopping: set[str] = dataclasses.field(default_factory=set)  # members with on_end: stop
    ended: set[str] = dataclasses.field(default_factory=set)  # members at their end


_RUNS: dict[int, _Run] = {}
"""The replay nodes' shared state per running graph (by id, the graph checked through a weak
reference); an entry goes when its last member is torn down, so a graph run again starts anew."""


def _run_of(ctx: Any) -> _Run:
    """The state this node shares with the run's other replay nodes (its own outside one)."""
    try:
        graph = ctx.graph
    except RuntimeError:  # no runtime around the node (a node harness): a run of its own
        return _Run(None)
    run = _RUNS.get(id(graph))
    if run is None or run.graph is None or run.graph() is not graph:
        run = _RUNS[id(graph)] = _Run(weakref.ref(graph))
    return run


class ReplayBase(Node):
    """A replay source without ports of its own: see ``Replay`` and ``standing_in_for``."""

    swappable = frozenset({"rate", "loop"})  # over the control endpoint: flowrt kinds
    opened = False  # its recording opened (setup): report() has something to say

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        path: str = Field(
            description="a session folder or an .mcap file (relative: beside the graph file)"
        )

        @field_validator("path", mode="after")
        @classmethod
        def _beside_the_graph(cls, v: str, info: ValidationInfo) -> str:
            path = resolve_path(v, info)
            if not Path(path).exists():  # a graph error at its line, not a node failing
                raise ValueError(f"no such file or folder: {path}")
            return path

        topics: list[str] | None = Field(default=None, description="streams to publish")
        topic: str | None = Field(default=None, description="one stream (same as topics: [x])")
        node: str | None = Field(
            default=None, description="publish the streams recorded from this node, by port"
        )
        rate: float = Field(default=1.0, gt=0, description="playback speed (2.0 = twice)")
        start: float = Field(default=0.0, ge=0, description="seconds into the recording")
        loop: bool = False
        on_end: Literal["stop", "idle"] = Field(
            default="stop",
            description="at the end: ask the runtime to stop (once every replay node with "
            "stop has ended), or stay idle",
        )

    inline_only = True
    stands_in_for: str | None = None

    @classmethod
    def default_trigger(cls, params: Any) -> LoopTrigger:
        return LoopTrigger()

    @classmethod
    def standing_in_for(cls, node_cls: type[Node], name: str) -> type[ReplayBase]:
        """A replay kind with ``node_cls``'s output ports, to take its place in a graph.

        A port keeps its declared type where replay gives that type back (frames, audio,
        plain values); a class of the node's own (``JoyState``) comes back as the plain
        value it was recorded as (a recording never names code to import), so that port
        is declared ``object``: the producer's type check must not refuse what replay is.
        """
        ports = {
            p: Output(o.type if o.type in _REPLAYED_AS_IS else object, doc=o.doc)
            for p, o in node_cls.outputs.items()
        }
        sub = type(f"ReplayAs{node_cls.__name__}", (ReplayBase,), ports)
        sub.__module__ = __name__
        sub.stands_in_for = name
        return sub

    @classmethod
    def with_ports(cls, ports: Mapping[str, Any], name: str) -> type[ReplayBase] | None:
        """A replay kind publishing on ``ports`` (port -> type): the ports a node's streams
        were recorded from, so that ``flowrt replay REC`` (no graph) serves them under their
        recorded names (``wheels.values``), each a channel of its own, as recorded. None
        (the generic ``Replay`` then) when a name is no plain identifier.

        The names are a recording's (data): the ports are given as the class's ``outputs``
        only, never as its attributes, where one could shadow what a replay node is made of
        (a port ``process``, ``run``, ``params``).
        """
        if not ports or any(
            not p.isidentifier() or p.startswith("_") or keyword.iskeyword(p) for p in ports
        ):
            return None
        sub = type(f"ReplayOf{name.title().replace('_', '')}", (ReplayBase,), {})
        sub.__module__ = __name__
        outs = {p: Output(t, doc="recorded", rate_hz=None) for p, t in ports.items()}
        for p, out in outs.items():
            out.name = p
        sub.outputs = outs
        return sub

    # --- lifecycle ---------------------------------------------------------------------

    def setup(self) -> None:
        try:
            self._open()
            self.opened = True
        except (OSError, ValueError) as e:  # no bag, a damaged one, a misspelt topic
            raise FatalError(str(e)) from None  # one line, given up: a restart cannot help
        # Set up before any node's first activation (the runtime arms loop triggers after
        # every setup): each node that can stop the run is known before one can end.
        self.run = run = _run_of(self.ctx)
        name = self.ctx.name
        run.members.add(name)
        run.ended.discard(name)
        if self.params.on_end == "stop":
            run.stopping.add(name)

    def _open(self) -> None:
        p = self.params
        files = mcap_files(p.path)
        if not files or not files[0].exists():
            hint = sessions_hint(Path(p.path)) if Path(p.path).is_dir() else ""
            raise FileNotFoundError(f"{p.path}: no MCAP file{hint}")
        for f in files:  # said as `flowrt replay` says it
            if (why := not_a_recording(f)) is not None:
                raise ValueError(f"{f}: {why}")
        self.files = files
        self.file = files[0]
        channels = channel_schemas(files)
        wanted = {
            # a ros2 recording's channels are the streams' ROS names: a flowrt name finds its own
            ros2_topic(t) if t not in channels and ros2_topic(t) in channels else t
            for t in [*(p.topics or []), *([p.topic] if p.topic else [])]
        }
        self.wanted = wanted or None
        self.read: list[Recording] = []  # every part read (the last one read says any damage)
        self.origin = _first_log_time(self.file)
        end = last_log_time(files[-1])  # the progress line's length (None: not closed)
        self.span_s = None if end is None else max(0.0, (end - self.origin) / 1e9)
        self.position_s = 0.0  # the last published message's, from the recording's start
        self.loops = 0
        self.decoder = MessageDecoder()
        self.left_out: dict[str, list[Any]] = {}  # topic -> [why, messages not replayed]
        # a channel no decoder reads is left out whole; a message that fails to decode (a
        # damaged payload) is skipped alone, its channel's others replayed (it took the rest
        # of the channel with it, uncounted)
        self.skipped: dict[str, list[Any]] = {}  # topic -> [why, messages skipped]
        self._said_left_out: set[str] = set()
        missing = sorted((wanted or set()) - set(channels))
        if missing:  # a misspelt topic would otherwise replay nothing, silently
            raise ValueError(
                f"{p.path}: no topic {', '.join(map(repr, missing))} "
                f"(recorded: {', '.join(sorted(channels))})"
            )
        for topic in wanted:  # said on the first activation, before any message
            why = self.decoder.why_not(*channels[topic])
            if why is not None:
                self.left_out[topic] = [why, 0]
        self.members: dict[str, Any] = {}  # a sync set's members (TOPIC/KEY), newest each
        self.cycle = 0.0  # seconds added per completed loop
        self.last_due = 0.0
        self.published = 0
        self.ended = False
        self._said_damage = False
        self._it: Iterator[_Item] = self._items()
        self._next: asyncio.Future[_Item | None] | None = None

    def _port(self, topic: str, source: str, is_image: bool) -> str | None:
        """The output a message goes to, or None when this node does not publish it."""
        node, _, port = source.partition(".")
        if self.params.node is not None:
            if node != self.params.node:
                return None
            return port if port in self.outputs else None
        if self.wanted is not None and topic not in self.wanted:
            return None
        if is_image:
            return "frame" if "frame" in self.outputs else None
        return "message" if "message" in self.outputs else None

    def _items(self) -> Iterator[_Item]:
        """Decoded messages in file order (on the reader thread).

        A channel none of the decoders reads is left out, a message that fails to decode is
        skipped; both said once per channel and counted (:meth:`_left_out`, :meth:`report`).
        """
        skip_before = self.origin + round(self.params.start * 1e9)
        self.read = []
        seqs: dict[str, int] = {}
        # every topic read (the filter is per message either way): _port picks, and a sync
        # set's members (TOPIC/KEY) are wanted with their set
        for m in iter_session(self.files, None, self.read, skip_before):
            if m.log_time < skip_before:
                continue
            name = m.schema.name if m.schema is not None else ""
            if name == ANNOTATIONS_SCHEMA:
                continue  # drawn from the detections, which are replayed themselves
            image = is_image_schema(name)
            port = self._port(m.topic, m.source, image)
            parent, _, _ = m.topic.rpartition("/")
            member = port is None and bool(parent) and self._port(parent, parent, False)
            if port is None and not member:
                continue
            if m.topic in self.left_out:
                self.left_out[m.topic][1] += 1
                continue
            try:
                d = self.decoder.decode(m.encoding, m.schema, m.data)
                value: Any = d.value
                if d.kind == "image":
                    value = _Pixels(d.value[0], d.value[1], d.stamp)
                elif d.kind == "audio":  # stamped in Unix time: moved to this run at publish
                    value = self.decoder.own.audio(m.schema, m.data, m.sequence, 0.0)
                else:
                    # (ros2: the index names flowrt streams, the channels ROS topics)
                    channel = ros2_topic if m.encoding == "cdr" else None
                    value = join_set(m.topic, _as_recorded(m, value), self.members, channel)
            except Exception as e:
                self.skipped.setdefault(m.topic, [str(e) or type(e).__name__, 0])[1] += 1
                continue
            if port is None:  # a member of a sync set: joined into the set's index later
                if isinstance(value, _Pixels):  # a heap frame, stamped with the set's time
                    value = Frame(
                        value.data, source=m.topic, seq=m.sequence, pixel_format=value.format
                    )
                self.members[m.topic] = value
                continue
            # A writer that numbers nothing (rosbag2: 0 for every message) gets 0, 1, 2 ...
            last = seqs.get(m.topic, -1)
            seq = seqs[m.topic] = m.sequence if m.sequence > last else last + 1
            yield _Item(port, m.log_time, seq, value)

    def _prefetch(self) -> asyncio.Future[_Item | None]:
        return asyncio.ensure_future(asyncio.to_thread(next, self._it, None))

    async def process(self) -> dict[str, Any] | None:
        if len(self.left_out) + len(self.skipped) > len(self._said_left_out):
            self._left_out()
        run = self.run
        if run.start is None:  # the whole graph is set up: its workers are ready
            run.start = self.ctx.elapsed()
        start = run.start
        if self.ended:
            self._stop_if_last()  # a peer given up (torn down) has left the run meanwhile
            await asyncio.sleep(0.2)
            return None
        fut = self._next or self._prefetch()
        item = await fut
        if item is None:
            self._next = None
            self._report_damage()
            self._left_out()
            if self.params.loop and self.published:
                self.loops += 1
                self.cycle = self.last_due + LEAD
                self._it = self._items()
                return None
            self.ended = True
            run.ended.add(self.ctx.name)
            self._stop_if_last()
            return None
        self._next = self._prefetch()  # decode the next one while this one waits
        due = (
            self.cycle
            + LEAD
            + (item.log_time - self.origin - self.params.start * 1e9) / 1e9 / self.params.rate
        )
        self.last_due = due
        wait = start + due - self.ctx.elapsed()
        if wait > 0:
            await asyncio.sleep(wait)
        self.published += 1
        self.position_s = (item.log_time - self.origin) / 1e9
        value = self._value(item)
        return value if len(self.outputs) == 1 else {item.port: value}  # one port: bare

    def _stop_if_last(self) -> None:
        """``on_end: stop``: the run stops once every replay node with it has ended."""
        run = self.run
        if self.params.on_end == "stop" and run.stopping <= run.ended:
            self.ctx.request_stop()

    def _value(self, item: _Item) -> Any:
        if not isinstance(item.value, _Pixels):
            return self._restamped(item)
        px = item.value
        frame: Frame = self.ctx.new_frame(px.data.shape, px.data.dtype, px.format)
        np.copyto(frame.data, px.data)
        frame.seq = item.seq
        # The message's own stamp (header.stamp), as old relative to its publication as it
        # was to its log time; a stamp on another clock (simulated time) is not used.
        now = self.ctx.now()
        age = (item.log_time - px.stamp) / 1e9 if px.stamp is not None else 0.0
        frame.timestamp = now - age / self.params.rate if 0 <= age < STAMP_SPAN else now
        return frame

    def _left_out(self) -> None:
        """Say each channel left out, or with a message skipped, once (one line naming it
        and why), as the node's error; how many, in :meth:`report`."""
        said = [
            *(
                (t, f"{t}: left out, cannot decode ({why})")
                for t, (why, _) in self.left_out.items()
            ),
            *(
                (t, f"{t}: a message skipped, cannot decode ({why}); the others are replayed")
                for t, (why, _) in self.skipped.items()
            ),
        ]
        for topic, msg in said:
            if topic in self._said_left_out:
                continue
            self._said_left_out.add(topic)
            self.ctx.log.warning("%s: %s", self.ctx.name, msg)
            with contextlib.suppress(RuntimeError):
                self.ctx.set_error(msg)

    def report(self) -> dict[str, Any] | None:
        """Where the replay is (the status table's progress line) and the messages not
        replayed, per channel, with why (``--stats-json`` ``reports``)."""
        if not self.opened:  # its file could not be opened: nothing to report
            return None
        progress = {
            "position_s": round(self.position_s, 3),
            "duration_s": None if self.span_s is None else round(self.span_s, 3),
            "loops": self.loops,
        }
        rows = {
            **{t: {"messages": n, "why": f"left out: {w}"} for t, (w, n) in self.left_out.items()},
            **{
                t: {"messages": n, "why": f"cannot decode: {w}"}
                for t, (w, n) in self.skipped.items()
            },
        }
        return {"progress": progress, **({"not_replayed": rows} if rows else {})}

    def _restamped(self, item: _Item) -> Any:
        """A recorded ``timestamp`` is epoch nanoseconds (the recording's time base): mapped
        to this run's clock, as old relative to its publication as it was when recorded."""
        value = item.value
        if isinstance(value, AudioBlock):  # its first sample's Unix time, as recorded
            lead = max(0.0, item.log_time / 1e9 - value.timestamp)
            return dataclasses.replace(value, timestamp=self.ctx.now() - lead / self.params.rate)
        ts = (
            value.get("timestamp") if isinstance(value, dict) else getattr(value, "timestamp", None)
        )
        if not isinstance(ts, int) or isinstance(ts, bool) or ts < 10**17:  # not epoch ns
            return value
        mapped = self.ctx.now() - max(0, item.log_time - ts) / 1e9 / self.params.rate
        if isinstance(value, dict):
            out = {**value, "timestamp": mapped}
            if "stamp" in value:  # a sync set's (streams.join_set): its frames at its time
                out["stamp"] = mapped
                for v in out.values():
                    if isinstance(v, Frame) and v.timestamp == 0.0:
                        v.timestamp = mapped
            return out
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return dataclasses.replace(value, timestamp=mapped)
        with contextlib.suppress(AttributeError, TypeError):
            value.timestamp = mapped
        return value

    def _report_damage(self) -> None:
        damaged = next((r for r in self.read if r.damage), None)
        if damaged is not None and not self._said_damage:
            self._said_damage = True
            msg = f"{damaged.path}: replayed up to the damage at byte {damaged.damage_offset}"
            self.ctx.log.warning("%s: %s (%s)", self.ctx.name, msg, damaged.damage)
            with contextlib.suppress(RuntimeError):
                self.ctx.set_error(f"{msg}: {damaged.damage}")

    async def teardown(self) -> None:
        run: _Run | None = getattr(self, "run", None)
        if run is not None:  # given up or the run's end: it no longer holds the run open
            name = self.ctx.name
            run.members.discard(name)
            run.stopping.discard(name)
            run.ended.discard(name)
            if not run.members and run.graph is not None:
                for key, r in list(_RUNS.items()):
                    if r is run:
                        del _RUNS[key]
        nxt = getattr(self, "_next", None)
        if nxt is not None:
            # The read in flight ends on its own (its thread cannot be cancelled); wait() does
            # not raise when the read was cancelled with the process call that awaited it.
            await asyncio.wait([nxt])


class Replay(ReplayBase):
    """The ``replay`` kind: images on ``frame``, every other stream on ``message``."""

    frame = Output(Frame, doc="recorded images, as frames in the runtime's pool")
    message = Output(object, doc="recorded messages (detections as their dataclass)")


def _as_recorded(m: Any, value: Any) -> Any:
    """A decoded CDR message as the value the ``ros2`` profile wrote it from
    (:func:`~flowrt.recording.ros2_profile.value_restorer`): a graph's reader gets
    ``{"LeftSpeed": 0.25}`` as it did live, not ``{"items": [...]}``, a counter's ``3``, not
    ``{"data": 3}``, and an ``AudioBlock``, each of which its typed port takes."""
    s = m.schema
    if m.encoding != "cdr" or s is None:
        return value
    restore = value_restorer(s.name, s.encoding, bytes(s.data))
    return value if restore is None else restore(value)


def _first_log_time(path: Path) -> int:
    """Earliest log time near the file's start, ns: the time origin every replay node shares.

    Streams interleave in arrival order, so the earliest of the first few messages is taken.
    """
    first: int | None = None
    for i, m in enumerate(iter_messages(path)):
        first = m.log_time if first is None else min(first, m.log_time)
        if i >= 64:
            break
    return first or 0
