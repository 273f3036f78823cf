"""Remote edges: graph outputs exported, and remote streams imported, over Zenoh.

flowrt does not invent a network protocol: a graph's ``export:`` entries become Zenoh
publishers and its ``import:`` entries Zenoh subscribers, on a session configured by the
graph's ``zenoh:`` section (Zenoh's own discovery, routing, reliability, TLS and access
control). As the agent-based control source keeps its network links as sender/receiver agents
outside the real-time router, no network I/O runs on the event loop:

- Export: a buffer on the output (the edge's own policy: ``latest`` for frames, ``queue``
  for messages, counted like any edge) hands one value at a time to a sender thread that
  encodes and publishes it; when that send is done the next value is taken. A slow network
  therefore drops at the edge, where it is counted, and never slows the producer.
- Import: Zenoh's callback thread reads the fixed-size binary header (one ``struct`` call),
  decodes the payload (JSON; JPEG/PNG, never on the loop), and for frames that a worker
  process reads copies the pixels into a frame of the local pool that the loop keeps ready
  (workers map it zero-copy; the loop copies only when no such frame fits); frames that only
  inline nodes read are not copied at all (a read-only heap frame over the received bytes).
  It parks the value in a bounded hand-over queue (frames: ``FRAME_BACKLOG``; overruns
  counted); one ``call_soon_threadsafe`` per batch wakes the loop, which publishes on the
  import node's ``output`` (and writes the RTDB record after the readers).

Every message carries its stream id, sequence number, send time and capture time: the
importing side counts sequence gaps as drops of the remote link (an edge named
``zenoh:KEY->NAME`` in the statistics, beside the local ones) and reports the age at arrival.
Clocks of two machines differ, so each exporter answers a clock query
(``_flowrt/clock/<session id>``); the importer estimates the offset from the round trip
(NTP's method, error <= rtt/2) and reports the age on the exporter's corrected clock, so it
holds without synchronised clocks. An import that hears nothing for ``stale_after`` periods is
stale: its node is in an error state (red, with the reason), a health alert is raised, its
RTDB record (written with that validity) turns stale; it resumes by itself when the exporter
comes back (a restarted exporter is a new stream: its sequence starts again, not a gap).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import queue
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .edges import EMPTY, Buffer, make_buffer
from .events import Event
from .frames import Frame
from .node import Node, Output
from .spec import EdgePolicy, GraphSpec, Placement, TimerTrigger, ZenohSpec
from .stats import EdgeStats, Running
from .zenoh_wire import (
    MAX_HEADER_BYTES,
    MAX_SEQ_JUMP,
    WARN_EVERY,
    Header,
    PlainFormat,
    Refused,
    check_frame,
    decode_frame,
    encode_frame,
    loads_wire,
    payload_encoding,
    to_wire,
)

log = logging.getLogger("flowrt.remote")

FRAME_BACKLOG = 3  # received frames waiting for the loop, at most (each holds a pool slot)
CLOCK_PREFIX = "_flowrt/clock"


class RemoteError(Exception):
    """A remote-edge problem found at start (bad endpoint, a port in use, no zenoh)."""


class BridgeHost(Protocol):
    """What the bridge needs from the runtime (kept narrow: the runtime owns it)."""

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    def now_mono(self) -> float: ...

    def runner_output(self, node: str, port: str) -> list[Buffer]: ...

    def add_buffer(self, buf: Buffer) -> None: ...

    def publish(self, node: str, port: str, value: Any) -> None: ...

    def new_frame(self, owner: str, shape: tuple[int, ...], dtype: Any, pf: str) -> Frame: ...

    def import_node(self, name: str) -> Any: ...

    def is_frame_port(self, node: str, port: str) -> bool: ...

    def emit(self, event: Event) -> None: ...

    def record(self, name: str, value: Any, validity_ms: float | None) -> None: ...


# --- encoding ----------------------------------------------------------------------------


# --- the import node ---------------------------------------------------------------------


class RemoteSourceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    key: str
    period_ms: float | None = Field(default=None, gt=0)
    stale_after: float = Field(default=5.0, gt=0)
    size: int = Field(default=16, ge=1)


class RemoteSource(Node):
    """What an ``import:`` entry becomes: a node whose ``output`` is the remote stream.

    Its activations are liveness checks (every 50 ms); values are published when they
    arrive, not on the checks.
    """

    Params = RemoteSourceParams
    output: Output[Any] = Output(object, doc="the remote stream's values (frames: local pool)")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=50.0)

    def setup(self) -> None:
        self.link: _Import | None = None  # bound by the bridge once the runtime runs

    def process(self) -> None:
        if self.link is not None:
            self.link.check_liveness(self.ctx)


class RemoteFrameSource(RemoteSource):
    """An import with ``frames: true``: its ``output`` is a frame source (every frame a tick)."""

    output: Output[Any] = Output(Frame, doc="the remote frames, in the local frame pool")


# --- statistics of a remote link -----------------------------------------------------------


class RemoteLinkStats(Buffer):
    """The network hop of an import, shown as an edge: published = what the exporter sent
    (by sequence number), delivered = received, dropped = sequence gaps, hand-over overruns
    and undecodable messages (each its own ``drop_reasons`` entry); age = one-way, on the
    exporter's clock corrected by the measured offset."""

    policy = "remote"

    def __init__(self, name: str) -> None:
        super().__init__(name, 1)

    def lost(self, reason: str, n: int = 1) -> None:
        """``n`` messages lost on this hop, counted with ``reason``."""
        self.dropped += n
        self.drop_reasons[reason] = self.drop_reasons.get(reason, 0) + n

    def stats(self) -> EdgeStats:
        return super().stats()

    def pending(self) -> int:
        return 0

    def clear(self) -> None:
        pass


# --- the bridge ----------------------------------------------------------------------------


@dataclass
class _Export:
    key: str
    node: str
    port: str
    encoding: str
    quality: int
    buf: Buffer
    publisher: Any = None
    seq: int = 0
    busy: bool = False
    errors: int = 0
    encodings: dict[str, Any] = field(default_factory=dict)  # header kind -> Zenoh encoding


class _Import:
    """One imported stream: hand-over between Zenoh's thread and the loop, liveness."""

    def __init__(
        self,
        bridge: ZenohBridge,
        name: str,
        key: str,
        period_ms: float | None,
        stale_after: float,
        size: int,
    ) -> None:
        self.bridge = bridge
        self.name = name
        self.key = key
        self.period = None if period_ms is None else period_ms / 1000
        self.stale_after = stale_after
        self.lock = threading.Lock()
        self.pending: deque[tuple[Header, Any]] = deque()
        self.size = size
        self.scheduled = False
        self.stream: str | None = None
        self.last_seq = -1
        self.link = RemoteLinkStats(f"zenoh:{key}->{name}")
        self.arrivals = Running()
        self.last_arrival: float | None = None  # loop clock
        self.started = bridge.host.now_mono()
        self.stale = False
        self.decode_errors = 0
        self.restarts = 0  # sequence jumps taken as a restart of the exporter (counted)
        self.max_bytes = 1 << 20  # set from the ImportSpec: larger messages are refused
        self.max_pixels = 8192 * 8192
        self.warned: dict[str, float] = {}  # reason -> last warning (rate-limited)
        self.plain: PlainFormat | None = None  # header-less payloads of a plain program
        self.plain_seq = 0
        self.ctx: Any = None
        # Raw frames are copied into the pool on Zenoh's thread, not on the loop: the loop
        # keeps one pool frame of the last shape ready (``spare``); frames replaced before
        # delivery go back to the pool from the loop (``discard``).
        self.zero_copy = False  # no worker reads the frames: no copy into the pool at all
        self.spare: Frame | None = None
        self.spare_key: tuple[Any, ...] | None = None
        self.discard: list[Frame] = []

    # Zenoh's thread ---------------------------------------------------------------------

    def on_sample(self, sample: Any) -> None:
        try:
            raw_att = sample.attachment
            if self.plain is not None:  # a plain program's payload: the header is made here
                header = self.plain.header(self.key, self.plain_seq)
                self.plain_seq += 1
            elif raw_att is None:
                raise Refused(
                    "undecodable",
                    "no flowrt header: from a plain program? declare the import's format "
                    "(json, bytes, jpeg, png, raw): docs/zenoh.md",
                )
            elif len(raw_att) > MAX_HEADER_BYTES:
                raise Refused("too large", f"a header of {len(raw_att)} bytes")
            else:
                header = Header.decode(raw_att.to_bytes())
            zbytes = sample.payload
            if len(zbytes) > self.max_bytes:  # refused before it is copied or parsed
                raise Refused("too large", f"{len(zbytes)} bytes, the limit is {self.max_bytes}")
            payload = zbytes.to_bytes()
            if header.kind == "frame":
                check_frame(header.frame, payload, self.max_pixels)
                value: Any = self._frame(header.frame, decode_frame(header.frame, payload))
            elif header.kind == "bytes":
                value = payload
            else:
                value = loads_wire(payload)
        except Exception as e:
            reason = e.reason if isinstance(e, Refused) else "undecodable"
            with self.lock:
                self.decode_errors += 1
                self.link.published += 1  # it arrived: published, and dropped with its reason
                self.link.lost(reason)
            self._warn(reason, f"import {self.name}: {reason} message on {self.key}: {e}")
            return
        self.bridge.clock_probe(header.zid)
        with self.lock:
            if header.stream != self.stream:
                self.stream, self.last_seq = header.stream, header.seq - 1
            elif not 0 <= header.seq - self.last_seq <= MAX_SEQ_JUMP:
                # a forged or reset sequence: a restart of the stream, counted, not a gap of
                # 2**70 messages (nor a negative one)
                self.restarts += 1
                self.last_seq = header.seq - 1
            gap = header.seq - self.last_seq - 1
            if gap > 0:  # never received: lost on the way (or dropped by Zenoh's congestion)
                self.link.published += gap
                self.link.lost("sequence gap", gap)
            self.last_seq = max(self.last_seq, header.seq)
            self.link.published += 1
            # Frames hold pool slots: a short backlog (two arriving back to back after an
            # exporter's stall must both get through); messages: the import's ``size``.
            limit = FRAME_BACKLOG if header.kind == "frame" else self.size
            while len(self.pending) >= limit:  # the loop has not taken them in time
                _, old = self.pending.popleft()
                if isinstance(old, Frame):
                    self.discard.append(old)
                self.link.lost("hand-over overrun")
            self.pending.append((header, value))
            if self.scheduled:
                return
            self.scheduled = True
        with contextlib.suppress(RuntimeError):  # the loop is closing
            self.bridge.host.loop.call_soon_threadsafe(self.deliver)

    def _warn(self, reason: str, text: str) -> None:
        """One warning per reason every WARN_EVERY seconds: a flood is counted, not logged."""
        now = time.monotonic()
        last = self.warned.get(reason)
        if last is None or now - last >= WARN_EVERY:
            self.warned[reason] = now
            log.warning("%s (further ones counted, logged at most every %g s)", text, WARN_EVERY)

    def _frame(self, meta: dict[str, Any], arr: np.ndarray) -> Any:
        """The received pixels as a frame: as they are when no worker process reads them
        (``zero_copy``: a heap frame over the received bytes, read-only), else copied into
        the pool frame the loop has ready when its shape fits (else the array, copied into
        the pool on the loop)."""
        key = _frame_key(meta, arr)
        if self.zero_copy:
            return Frame(arr, source=self.name, pixel_format=key[2])
        with self.lock:
            spare = self.spare if self.spare_key == key else None
            if spare is not None:
                self.spare = None
        if spare is None:
            return arr
        np.copyto(spare.data, arr)  # numpy lets go of the GIL for the copy
        return spare

    # the loop ---------------------------------------------------------------------------

    def deliver(self) -> None:
        with self.lock:
            items = list(self.pending)
            self.pending.clear()
            self.scheduled = False
            discard, self.discard = self.discard, []
        for old in discard:
            old.release()
        host = self.bridge.host
        records: list[Any] = []
        key: tuple[Any, ...] | None = None
        for header, value in items:
            now = host.now_mono()
            offset = self.bridge.offset(header.zid)
            wall_now = time.time()
            age = max(0.0, wall_now - (header.sent - offset))
            self.link.delivered += 1
            self.link.age.add(age)
            if self.last_arrival is not None:
                self.arrivals.add(now - self.last_arrival)
            self.last_arrival = now
            captured_mono = now - max(0.0, wall_now - (header.captured - offset))
            if header.kind == "frame":
                if isinstance(value, Frame):  # made on Zenoh's thread
                    frame = value
                    if frame.shared:  # a pool frame: ready the next one
                        key = _frame_key(header.frame, frame.data)
                else:
                    arr = value
                    key = _frame_key(header.frame, arr)
                    frame = host.new_frame(self.name, tuple(arr.shape), arr.dtype, key[2])
                    np.copyto(frame.data, arr)
                frame.seq = int(header.frame.get("seq", header.seq))
                frame.timestamp = captured_mono
                host.publish(self.name, "output", frame)
                frame.release()
            else:
                host.publish(self.name, "output", value)
                records.append(value)
        if self.stale and items:
            self._resumed()
        if records:  # after the readers' activations: an RTDB write is ~0.1 ms (a lock)
            host.loop.call_soon(self._record, records)
        if key is not None:  # after the readers' activations too
            host.loop.call_soon(self._ready_spare, key)

    def _ready_spare(self, key: tuple[Any, ...]) -> None:
        """On the loop: a pool frame of the last shape, for the next arrival to fill."""
        with self.lock:
            if self.spare is not None and self.spare_key == key:
                return
            old, self.spare, self.spare_key = self.spare, None, None
        if old is not None:
            old.release()
        frame = self.bridge.host.new_frame(self.name, key[0], np.dtype(key[1]), key[2])
        with self.lock:
            self.spare, self.spare_key = frame, key

    def close(self) -> None:
        """On the loop, at the end: frames still held go back to the pool."""
        with self.lock:
            held = [v for _, v in self.pending if isinstance(v, Frame)] + self.discard
            if self.spare is not None:
                held.append(self.spare)
            self.pending.clear()
            self.discard, self.spare, self.spare_key = [], None, None
        for frame in held:
            frame.release()

    def _record(self, values: list[Any]) -> None:
        validity = self._validity_ms()
        for value in values:
            self.bridge.host.record(self.name, value, validity)

    def _period(self) -> float | None:
        if self.period is not None:
            return self.period
        s = self.arrivals
        return s.mean if s.count >= 3 else None

    def _validity_ms(self) -> float | None:
        p = self._period()
        return None if p is None else p * self.stale_after * 1000

    def check_liveness(self, ctx: Any) -> None:
        self.ctx = ctx
        now = self.bridge.host.now_mono()
        p = self._period()
        limit = max(0.1, (p if p is not None else 0.2) * self.stale_after)
        since = now - (self.last_arrival if self.last_arrival is not None else self.started)
        if since <= limit or self.stale:
            return
        self.stale = True
        what = "no message yet" if self.last_arrival is None else "stale"
        reason = f"{what} on {self.key} for {since * 1000:.0f} ms (limit {limit * 1000:.0f} ms)"
        ctx.set_error(reason)

    def _resumed(self) -> None:
        self.stale = False
        if self.ctx is not None:
            self.ctx.clear_error()


class ZenohBridge:
    """The graph's Zenoh session, its exports and imports (see the module docstring)."""

    def __init__(self, host: BridgeHost, spec: GraphSpec) -> None:
        self.host = host
        self.spec = spec
        self.zspec = spec.zenoh or ZenohSpec()
        self.session: Any = None
        self.stream = uuid.uuid4().hex[:16]
        self.zid = ""
        self.exports: list[_Export] = []
        self.imports: dict[str, _Import] = {}
        self._subs: list[Any] = []
        self._queryable: Any = None
        self._jobs: queue.SimpleQueue[tuple[_Export, Any] | None] = queue.SimpleQueue()
        self._sender: threading.Thread | None = None
        self._offsets: dict[str, tuple[float, float]] = {}  # zid -> (offset s, rtt s)
        self._probing: set[str] = set()

    # --- lifecycle ----------------------------------------------------------------------

    def config(self) -> Any:
        import zenoh

        z = self.zspec
        cfg = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(z.mode))
        cfg.insert_json5("listen/endpoints", json.dumps(z.listen if z.mode == "peer" else []))
        cfg.insert_json5("connect/endpoints", json.dumps(z.connect))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(z.scouting))
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(z.scouting))
        for path, value in z.config.items():
            cfg.insert_json5(path, json.dumps(value))
        return cfg

    async def open(self) -> None:
        """Open the session (before any node runs): a port in use fails here, in one line."""
        try:
            import zenoh
        except ImportError as e:  # pragma: no cover - a dependency
            raise RemoteError(f"zenoh: the eclipse-zenoh package is missing ({e})") from None
        try:
            cfg = self.config()
            self.session = await asyncio.to_thread(zenoh.open, cfg)
        except Exception as e:
            text = _first_line(e)
            if "Address already in use" in text:
                where = self.zspec.listen
                raise RemoteError(
                    f"zenoh: cannot listen on {', '.join(where)}: address already in use "
                    "(change zenoh.listen in the graph file, or stop the other process)"
                ) from None
            if "Unable to connect" in text:
                raise RemoteError(
                    f"zenoh: cannot connect to {', '.join(self.zspec.connect) or 'any endpoint'}"
                    " (in client mode a router or peer must answer at start; peer mode keeps"
                    " trying)"
                ) from None
            raise RemoteError(f"zenoh: {text}") from None
        self.zid = str(self.session.info.zid())
        self._queryable = self.session.declare_queryable(
            f"{CLOCK_PREFIX}/{self.zid}", _answer_clock
        )

    def attach_exports(self) -> None:
        """Buffers on the exported outputs, before the nodes start publishing."""
        for key, ex in self.spec.exports.items():
            node, port = ex.source.split(".")
            outs = self.host.runner_output(node, port)
            policy = ex.policy
            if policy is None:
                frames = self.host.is_frame_port(node, port)
                policy = EdgePolicy.latest if frames else EdgePolicy.queue
            buf = make_buffer(
                policy.value, f"{ex.source}->zenoh:{key}", ex.size, self.host.now_mono
            )
            exp = _Export(key, node, port, ex.encoding, ex.quality, buf)
            exp.publisher = self.session.declare_publisher(key)
            buf.on_put = lambda exp=exp: self._take(exp)
            outs.append(buf)
            self.host.add_buffer(buf)
            self.exports.append(exp)
        if self.exports:
            self._sender = threading.Thread(
                target=self._send_loop, name="flowrt-zenoh-send", daemon=True
            )
            self._sender.start()

    def attach_imports(self) -> None:
        """Subscribers for the imports, bound to their nodes (once the nodes are set up)."""
        for name, im in self.spec.imports.items():
            imp = _Import(self, name, im.key, im.period, im.stale_after, im.size)
            imp.max_bytes, imp.max_pixels = im.byte_limit, im.max_pixels
            imp.zero_copy = not worker_downstream(self.spec, name)
            imp.plain = (
                PlainFormat(im.format, im.shape, im.dtype) if im.format != "flowrt" else None
            )
            node = self.host.import_node(name)
            if node is not None:
                node.link = imp
            self.imports[name] = imp
            self.host.add_buffer(imp.link)
            self._subs.append(self.session.declare_subscriber(im.key, imp.on_sample))

    async def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        self._subs.clear()
        for imp in self.imports.values():
            imp.close()
        if self._sender is not None:
            self._jobs.put(None)
            await asyncio.to_thread(self._sender.join, 2.0)
            self._sender = None
        if self.session is not None:
            session, self.session = self.session, None
            with contextlib.suppress(Exception):
                await asyncio.to_thread(session.close)

    # --- exports ------------------------------------------------------------------------

    def _take(self, exp: _Export) -> None:
        """On the loop: hand the next value to the sender when the previous one is sent."""
        if exp.busy or self._sender is None:
            return
        value = exp.buf.take()
        if value is EMPTY:
            return
        exp.busy = True
        self._jobs.put((exp, value))

    def _sent(self, exp: _Export, value: Any) -> None:
        if isinstance(value, Frame):
            value.release()
        exp.busy = False
        if exp.buf.pending():
            self._take(exp)

    def _send_loop(self) -> None:
        mono0, wall0 = time.monotonic(), time.time()
        while True:
            job = self._jobs.get()
            if job is None:
                return
            exp, value = job
            try:
                now_wall = time.time()
                if isinstance(value, Frame):
                    meta, payload = encode_frame(value, exp.encoding, exp.quality)
                    captured = wall0 + (value.timestamp - mono0) if value.timestamp else now_wall
                    header = Header(
                        self.stream, self.zid, exp.seq, now_wall, captured, "frame", meta
                    )
                else:
                    payload = json.dumps(to_wire(value), separators=(",", ":")).encode()
                    header = Header(self.stream, self.zid, exp.seq, now_wall, now_wall, "json")
                exp.seq += 1
                encoding = exp.encodings.get(header.kind)
                if encoding is None:  # one per kind: a Zenoh object made once, not per put
                    encoding = exp.encodings[header.kind] = payload_encoding(header)
                exp.publisher.put(payload, attachment=header.encode(), encoding=encoding)
            except Exception as e:
                exp.errors += 1
                log.warning("export %s: %s", exp.key, e)
            try:
                self.host.loop.call_soon_threadsafe(self._sent, exp, value)
            except RuntimeError:  # the loop is closed
                return

    # --- clocks -------------------------------------------------------------------------

    def offset(self, zid: str) -> float:
        """Exporter clock minus ours, seconds (0 until measured; same host: ~0)."""
        got = self._offsets.get(zid)
        return 0.0 if got is None else got[0]

    def clock_probe(self, zid: str) -> None:
        """From Zenoh's thread: measure an exporter's clock once, off the loop."""
        if zid in self._offsets or zid in self._probing or self.session is None:
            return
        self._probing.add(zid)
        threading.Thread(target=self._probe, args=(zid,), daemon=True).start()

    def _probe(self, zid: str) -> None:
        best: tuple[float, float] | None = None
        for _ in range(5):
            t0 = time.time()
            try:
                replies = list(self.session.get(f"{CLOCK_PREFIX}/{zid}", timeout=1.0))
            except Exception:
                break
            t1 = time.time()
            for r in replies:
                ok = getattr(r, "ok", None)
                if ok is None:
                    continue
                remote = float(ok.payload.to_bytes())
                rtt = t1 - t0
                if best is None or rtt < best[1]:
                    best = (remote - (t0 + t1) / 2, rtt)
        if best is not None:
            self._offsets[zid] = best
            log.info(
                "zenoh: clock of %s: offset %.3f ms, rtt %.3f ms", zid, best[0] * 1e3, best[1] * 1e3
            )
        self._probing.discard(zid)

    def clocks(self) -> dict[str, tuple[float, float]]:
        return dict(self._offsets)


def worker_downstream(spec: GraphSpec, source: str) -> bool:
    """Whether a worker process may read what node ``source`` publishes: a ``process`` or
    ``pool`` node fed by it, directly or through inline nodes. Only then is an imported
    frame worth its copy into the shared-memory pool (a heap frame would travel to a worker
    with its pixels); a node swapped into a worker later still gets the pixels, pickled."""
    seen: set[str] = set()
    todo = [source]
    while todo:
        upstream = todo.pop()
        for name, node in spec.nodes.items():
            if name in seen or all(i.node != upstream for i in node.inputs.values()):
                continue
            if node.placement != Placement.inline:
                return True
            seen.add(name)
            todo.append(name)
    return False


def _frame_key(meta: dict[str, Any], arr: np.ndarray) -> tuple[Any, ...]:
    """(shape, dtype, pixel format) of a received frame: what a spare pool frame must match."""
    pf = str(meta.get("pf", "BGR"))
    if meta.get("enc", "raw") != "raw" and arr.ndim == 3:
        pf = "BGR"  # decoded by OpenCV
    return (tuple(arr.shape), str(arr.dtype), pf)


def _answer_clock(query: Any) -> None:
    query.reply(query.key_expr, repr(time.time()).encode())


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    # Zenoh's errors end with " at /path/to/source.rs:line." twice; keep the message.
    cut = text.find(" at /")
    return text[:cut] if cut > 0 else text
