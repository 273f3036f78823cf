"""One imported Zenoh stream: from Zenoh's callback thread to the import node's output.

Zenoh's thread reads the fixed-size binary header (one ``struct`` call), decodes the payload
(JSON; JPEG/PNG, never on the loop), and for frames that a worker process reads copies the
pixels into a frame of the local pool that the loop keeps ready (workers map it zero-copy;
the loop copies only when no such frame fits); frames that only inline nodes read are not
copied at all (a read-only heap frame over the received bytes). It parks the value in a
bounded hand-over queue (frames: :data:`FRAME_BACKLOG`; overruns counted); one
``call_soon_threadsafe`` per batch wakes the loop, which publishes on the import node's
``output`` (and writes the RTDB record after the readers).

Sequence gaps (also a new stream's first values, when the import could have had them:
:class:`StreamStarts`), overruns and undecodable messages are drops of the remote link
(:class:`RemoteLinkStats`, an edge ``zenoh:KEY->NAME`` in the statistics); an import that
hears nothing for ``stale_after`` periods puts its node in the error state until it resumes.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from typing import Any, Protocol

import numpy as np

from ..audio import AudioBlock
from ..edges import Buffer
from ..frames import Frame
from ..graph.spec import GraphSpec, Placement
from ..stats import EdgeStats
from ._host import BridgeHost
from ._liveness import ImportLiveness
from ._streams import AUDIO_SCHEMA, decode_audio, decode_json, schema_of_sample
from .wire import (
    HEADER,
    MAX_HEADER_BYTES,
    MAX_SEQ_JUMP,
    WARN_EVERY,
    FixedParts,
    Header,
    PlainFormat,
    Refused,
    frame_decoder,
    own_timestamp,
    set_timestamp,
)

__all__ = [
    "FRAME_BACKLOG",
    "ImportBridge",
    "ImportLink",
    "RemoteLinkStats",
    "StreamStarts",
    "frame_key",
    "worker_downstream",
]

log = logging.getLogger("flowrt.remote._bridge")

FRAME_BACKLOG = 3  # received frames waiting for the loop, at most (each holds a pool slot)
STREAMS_KEPT = 64  # other streams of a key whose last sequence number is remembered
BEFORE_LINK = "before the link was up"  # a new stream's values before the first one heard
_SCHEMA_KINDS = ("json", "protobuf")  # messages whose Zenoh encoding names their schema


class ImportBridge(Protocol):
    """What an import needs of the bridge: the runtime, and the exporters' clock offsets."""

    @property
    def host(self) -> BridgeHost: ...

    def clock_probe(self, zid: str) -> None: ...

    def offset(self, zid: str) -> float: ...

    def clock_known(self, zid: str) -> bool: ...


class RemoteLinkStats(Buffer):
    """The network hop of an import, shown as an edge: published = what the exporter sent
    (by sequence number), delivered = received, dropped = sequence gaps, a new stream's
    values before the first one heard, hand-over overruns and undecodable messages (each its
    own ``drop_reasons`` entry); age = one-way, on the exporter's clock corrected by the
    measured offset."""

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


class StreamStarts:
    """Where an import's count starts on a stream other than the last one it heard.

    A stream heard before (two exporters on one key) goes on from its own last number. A new
    one starts at 0 (every export's numbers do): the values before the first one heard are
    lost (:data:`BEFORE_LINK`: a restarted exporter publishes before Zenoh's link to the
    import is back) when the import was listening as the stream began, so that it could
    have had them: the stream's age at that sample, ``sent - started`` on the exporter's
    clock alone (no offset needed), is less than the time the import has listened. A late
    joiner to an exporter that has run for an hour never could have had that hour: not
    counted. A header that does not say its start (an older flowrt) has them counted only for
    a restart: after another stream was heard on the key. Runs only when the stream changes,
    never per message of a stream."""

    def __init__(self) -> None:
        self.heard: dict[str, int] = {}  # other streams heard on the key -> their last number
        self.listening = time.monotonic()  # since when (the subscriber is declared next)

    def switch(self, imp: ImportLink, header: Header) -> None:
        """``imp`` hears ``header``'s stream after another (under its lock): its count goes
        on from that stream's last number, or starts at its first, the values before counted
        if the import could have had them."""
        heard = self.heard
        if imp.stream is not None:
            heard[imp.stream] = imp.last_seq
        imp.stream = header.stream
        last = heard.pop(header.stream, None)
        if last is not None:
            imp.last_seq = last
            return
        imp.last_seq = header.seq - 1
        if len(heard) > STREAMS_KEPT:  # exporters' restarts: forget the oldest ended stream
            del heard[next(iter(heard))]
        if 0 < header.seq <= MAX_SEQ_JUMP and self._began_listened(header, bool(heard)):
            imp.link.published += header.seq
            imp.link.lost(BEFORE_LINK, header.seq)

    def _began_listened(self, header: Header, heard_before: bool) -> bool:
        """Whether the stream began while the import was listening (see the class)."""
        if header.started:  # whole seconds, rounded down: older than it is, never younger
            return header.sent - header.started < time.monotonic() - self.listening
        return heard_before


class ImportLink:
    """One imported stream: hand-over between Zenoh's thread and the loop (its liveness:
    :class:`~flowrt.remote._liveness.ImportLiveness`)."""

    def __init__(
        self,
        bridge: ImportBridge,
        name: str,
        key: str,
        period_ms: float | None,
        stale_after: float | None,
        size: int,
        stale_is: str = "error",
    ) -> None:
        self.bridge = bridge
        self.name = name
        self.key = key
        period = None if period_ms is None else period_ms / 1000
        self.live = ImportLiveness(bridge.host, name, key, period, stale_after, stale_is)
        self.lock = threading.Lock()
        self.pending: deque[tuple[Header, Any]] = deque()
        self.size = size
        self.scheduled = False
        self.stream: str | None = None
        self.last_seq = -1
        self.starts = StreamStarts()  # where the counting of a stream not heard last starts
        self.link = RemoteLinkStats(f"zenoh:{key}->{name}")
        self.decode_errors = 0
        self.restarts = 0  # sequence jumps taken as a restart of the exporter (counted)
        self.max_bytes = 1 << 20  # set from the ImportSpec: larger messages are refused
        self.max_pixels = 8192 * 8192
        self.warned: dict[str, float] = {}  # reason -> last warning (rate-limited)
        self.plain: PlainFormat | None = None  # header-less payloads of a plain program
        self.plain_seq = 0
        self._wake: Any = None  # the loop's call_soon_threadsafe
        # The last sample's Zenoh encoding and the schema it names, swapped as one tuple
        # (Zenoh's threads of two exporters may call on_sample at once).
        self._named: tuple[Any, str] = (None, "")
        # The last accepted message header's fixed parts: the next one like it takes the
        # fast path (:meth:`_message`). Replaced whole, never changed (two Zenoh threads).
        self.fixed: FixedParts | None = None
        # Raw frames are copied into the pool on Zenoh's thread, not on the loop: the loop
        # keeps one pool frame of the last shape ready (``spare``); frames replaced before
        # delivery go back to the pool from the loop (``discard``).
        self.zero_copy = False  # no worker reads the frames: no copy into the pool at all
        self.spare: Frame | None = None
        self.spare_key: tuple[Any, ...] | None = None
        self.discard: list[Frame] = []
        self.closed = False  # set by close(): no frame is kept after it

    # Zenoh's thread ---------------------------------------------------------------------

    def on_sample(self, sample: Any) -> None:
        fixed = self.fixed
        if fixed is not None:  # the fast path: a message like the last one accepted
            att = sample.attachment
            if att is not None and len(att) == HEADER.size:
                raw = att.to_bytes()
                if fixed.same(raw):
                    self._message(sample, fixed, raw)
                    return
        plain = self.plain is not None
        try:
            header, zbytes, raw = self._header(sample)
            if plain:  # its sequence number is taken once the payload is accepted: a refused
                value = self._value(header, zbytes, "")  # sample is never also a gap
        except Exception as e:
            self._refused(e, counted=False)
            return
        if plain:
            self.plain_seq += 1
        self.bridge.clock_probe(header.zid)
        with self.lock:
            self._sequence(header)
        if not plain:
            # The payload after the header's accounting: copying a large frame evicts the
            # CPU's caches, and every line after the copy runs cold (on the way to the loop).
            try:
                schema = self._schema(sample) if header.kind in _SCHEMA_KINDS else ""
                value = self._value(header, zbytes, schema)
            except Exception as e:
                self._refused(e, counted=True)
                return
            if raw is not None and header.kind != "frame":
                self.fixed = FixedParts(raw, header, schema)
        self._hand_over(header, value, False)

    def _message(self, sample: Any, fixed: FixedParts, raw: bytes) -> None:
        """:meth:`on_sample` for a message whose header repeats the last accepted one's but
        for its sequence number and times (:class:`FixedParts`): one lock, no decoding of
        the header, the schema read again only when the exporter does not number them."""
        header = fixed.header_of(raw)
        try:
            zbytes = self._payload(sample)
            schema = fixed.schema
            value = self._value(header, zbytes, self._schema(sample) if schema is None else schema)
        except Exception as e:
            with self.lock:
                self._sequence(header)
            self._refused(e, counted=True)
            return
        self._hand_over(header, value, True)

    def _hand_over(self, header: Header, value: Any, account: bool) -> None:
        """Park ``value`` for the loop and wake it (once per batch); ``account``: count the
        sample's sequence number first, under the same lock."""
        with self.lock:
            if account:
                self._sequence(header)
            if self.closed:  # closed while this one was copied: its pool slot goes back
                if isinstance(value, Frame):
                    self.discard.append(value)  # (released on the loop, by deliver)
            else:
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
        wake = self._wake
        if wake is None:  # the loop's method, looked up once (this path runs cold)
            wake = self._wake = self.bridge.host.loop.call_soon_threadsafe
        try:
            wake(self.deliver)
        except RuntimeError:  # the loop is closing (no contextlib: its code runs cold here)
            return

    def _sequence(self, header: Header) -> None:
        """Count a sample that arrived (under the lock): published, and the sequence numbers
        it skipped as lost on the way."""
        if header.stream != self.stream:  # rare: a stream's first sample, or another exporter
            self.starts.switch(self, header)
        if not 0 <= header.seq - self.last_seq <= MAX_SEQ_JUMP:
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

    def _refused(self, e: Exception, counted: bool) -> None:
        """A sample not taken, dropped with its reason (``counted``: already published)."""
        reason = e.reason if isinstance(e, Refused) else "undecodable"
        with self.lock:
            self.decode_errors += 1
            if not counted:
                self.link.published += 1  # it arrived: published, and dropped with its reason
            self.link.lost(reason)
        self._warn(reason, f"import {self.name}: {reason} message on {self.key}: {e}")

    def _header(self, sample: Any) -> tuple[Header, Any, bytes | None]:
        """The sample's header, payload (not copied) and the header's bytes (None: made
        here, for a plain program's payload); raises :class:`Refused`."""
        raw_att = sample.attachment
        raw = None
        if self.plain is not None:  # a plain program's payload: the header is made here
            header = self.plain.header(self.key, self.plain_seq)
        elif raw_att is None:
            raise Refused(
                "undecodable",
                "no flowrt header: from a plain program? declare the import's format "
                "(json, bytes, jpeg, png, raw): docs/zenoh.md",
            )
        elif len(raw_att) > MAX_HEADER_BYTES:
            raise Refused("too large", f"a header of {len(raw_att)} bytes")
        else:
            raw = raw_att.to_bytes()
            header = Header.decode(raw)
        return header, self._payload(sample), raw

    def _payload(self, sample: Any) -> Any:
        """The sample's payload, not copied; refused (too large) before it is copied or
        parsed."""
        zbytes = sample.payload
        if len(zbytes) > self.max_bytes:
            raise Refused("too large", f"{len(zbytes)} bytes, the limit is {self.max_bytes}")
        return zbytes

    def _value(self, header: Header, zbytes: Any, schema: str) -> Any:
        """The payload's value, checked before anything is copied; raises (a
        :class:`Refused` with its reason, or any decoder's error: undecodable). ``schema``:
        what the sample's encoding names (JSON and protobuf messages of flowrt)."""
        if header.kind == "frame":  # checked before the copy (see frame_decoder)
            pixels = frame_decoder(header.frame, len(zbytes), self.max_pixels)
            return self._frame(header.frame, pixels(zbytes.to_bytes()))
        if header.kind == "bytes":
            return zbytes.to_bytes()
        if header.kind == "protobuf":  # the recording's protobuf message (audio)
            if schema != AUDIO_SCHEMA:
                raise Refused("undecodable", f"a protobuf message of schema {schema!r}")
            return decode_audio(zbytes.to_bytes(), header.seq, 0.0)  # its time: on delivery
        # the recording's JSON message; typed by the schema its encoding names
        return decode_json(zbytes.to_bytes(), schema)

    def _schema(self, sample: Any) -> str:
        """The schema the sample's encoding names, read again only when the encoding is not
        the last one's: ``str()`` of a Zenoh encoding cost 18-21 us on this thread, cold, and
        comparing two 5 (a stream's messages are of one schema, mostly)."""
        enc = getattr(sample, "encoding", None)
        last = self._named
        if enc is None or enc != last[0]:
            last = self._named = (enc, schema_of_sample(sample))
        return last[1]

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
        key = frame_key(meta, arr)
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
        """On the loop: publish what arrived; the link's accounting follows in a callback of
        its own, after the readers' activations (which the publication queued first): at
        20 Hz this runs cold, and every line before the publication delays the readers."""
        with self.lock:
            items = list(self.pending)
            self.pending.clear()
            self.scheduled = False
            discard, self.discard = self.discard, []
        for old in discard:
            old.release()
        if not items:
            return
        host = self.bridge.host
        arrived: list[tuple[Header, float, float]] = []  # (header, loop clock, wall clock)
        records: list[Any] = []
        key: tuple[Any, ...] | None = None
        for header, value in items:
            now, wall_now = host.now_mono(), time.time()
            arrived.append((header, now, wall_now))
            if header.kind == "frame":
                if isinstance(value, Frame):  # made on Zenoh's thread
                    frame = value
                    if frame.shared:  # a pool frame: ready the next one
                        key = frame_key(header.frame, frame.data)
                else:
                    arr = value
                    key = frame_key(header.frame, arr)
                    frame = host.new_frame(self.name, tuple(arr.shape), arr.dtype, key[2])
                    np.copyto(frame.data, arr)
                frame.seq = int(header.frame.get("seq", header.seq))
                frame.timestamp = self._captured(header, now, wall_now)
                host.publish(self.name, "output", frame)
                frame.release()
            else:
                if self.plain is None and own_timestamp(value) is not None:
                    # the exporter's monotonic stamp means nothing here: the capture time,
                    # on its corrected clock, mapped onto ours (header.captured carries it)
                    stamp = self._captured(header, now, wall_now)
                    if isinstance(value, AudioBlock):  # frozen: a copy with its time
                        value = dataclasses.replace(value, timestamp=stamp)
                    else:
                        set_timestamp(value, stamp)
                host.publish(self.name, "output", value)
                records.append(value)
        host.loop.call_soon(self._account, arrived, records, key)

    def _offset(self, header: Header) -> float | None:
        """The exporter's clock offset; None until it is measured (0 would be a guess: a
        robot 5 s off read "age max 5001 ms" for good)."""
        if header.zid and not self.bridge.clock_known(header.zid):
            return None
        return self.bridge.offset(header.zid)

    def _captured(self, header: Header, now: float, wall_now: float) -> float:
        """A value's capture time on our loop clock, from the exporter's corrected clock."""
        offset = self._offset(header)
        if offset is None:
            return now  # its clock not measured yet: arrival beats a guess
        return now - max(0.0, wall_now - (header.captured - offset))

    def _account(
        self,
        arrived: list[tuple[Header, float, float]],
        records: list[Any],
        key: tuple[Any, ...] | None,
    ) -> None:
        """On the loop, after the readers of a delivery: the link's counts and ages, the
        import's liveness, the RTDB records (a write is ~0.1 ms: a lock), the next spare."""
        for header, now, wall_now in arrived:
            self.link.delivered += 1
            offset = self._offset(header)  # an age needs the exporter's clock measured
            if offset is not None:
                self.link.age.add(max(0.0, wall_now - (header.sent - offset)))
            self.live.arrived(now)
        self.live.contact()
        if records:
            self._record(records)
        if key is not None:
            self._ready_spare(key)

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
            if not self.closed:
                self.spare, self.spare_key = frame, key
                return
        frame.release()  # a delivery's accounting after the end

    def close(self) -> None:
        """On the loop, at the end: frames still held go back to the pool (a frame Zenoh's
        thread is still copying, after this, by :meth:`deliver`)."""
        with self.lock:
            self.closed = True
            held = [v for _, v in self.pending if isinstance(v, Frame)] + self.discard
            if self.spare is not None:
                held.append(self.spare)
            self.pending.clear()
            self.discard, self.spare, self.spare_key = [], None, None
        for frame in held:
            frame.release()

    def _record(self, values: list[Any]) -> None:
        validity = self.live.validity_ms()
        for value in values:
            self.bridge.host.record(self.name, value, validity)

    @property
    def stale(self) -> bool:
        return self.live.stale

    def check_liveness(self, ctx: Any) -> None:
        self.live.check(ctx)

    def report(self) -> dict[str, Any]:
        return self.live.report()


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


def frame_key(meta: dict[str, Any], arr: np.ndarray) -> tuple[Any, ...]:
    """(shape, dtype, pixel format) of a received frame: what a spare pool frame must match."""
    pf = str(meta.get("pf", "BGR"))
    if meta.get("enc", "raw") != "raw" and arr.ndim == 3:
        pf = "BGR"  # decoded by OpenCV
    return (tuple(arr.shape), str(arr.dtype), pf)
