"""Reading recordings back, damage and all: ``flowrt info``, ``--repair`` and replay.

A file is read front to back with the ``mcap`` library's stream reader, chunk CRCs checked,
so that a file whose writer was killed (no summary, a truncated last chunk) or that was
damaged later is read *up to the damage*, and the damage is reported with its offset
instead of failing the whole file. A cleanly closed file ends with its summary and footer;
:func:`scan` says when it does not ("not closed cleanly"), and :func:`repair` rewrites what
was recovered into a complete, indexed file.

Per-message times and sizes come from the message index records that follow each chunk, so
``info`` does not decompress or copy image data; a chunk whose index was lost in a crash is
opened instead.

A session split into parts (:mod:`.split`) is read as one recording: :func:`scan_session`
describes each file and the streams over all of them (rates and gaps across the file
boundaries), and :func:`iter_session` gives the messages of every part in order.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import statistics
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from .rosbag2 import BagError, db3_messages, db3_topics, is_db3

__all__ = [
    "FileInfo",
    "RecordedMessage",
    "Recording",
    "SessionInfo",
    "StreamInfo",
    "channel_schemas",
    "iter_messages",
    "iter_session",
    "scan",
    "scan_session",
]


class Gap(BaseModel):
    """An interval between two messages longer than two nominal periods."""

    at: float = Field(description="seconds from the start of the recording")
    length: float = Field(description="seconds")


class StreamInfo(BaseModel):
    """One channel of a file, as ``flowrt info`` shows it."""

    topic: str
    schema_name: str
    message_encoding: str
    source: str = ""
    count: int
    first: float | None = Field(description="log time of the first message, Unix seconds")
    last: float | None
    rate_mean: float | None
    rate_min: float | None
    rate_max: float | None
    gaps: list[Gap] = Field(default_factory=list)
    bytes: int


class FileInfo(BaseModel):
    """What a file holds and whether it is whole."""

    path: str
    size: int
    closed_cleanly: bool
    damage: str | None = Field(description="why reading stopped before the end, if it did")
    damage_offset: int | None = None
    start: float | None
    end: float | None
    duration: float
    messages: int
    chunks: int
    streams: list[StreamInfo]
    metadata: dict[str, dict[str, str]] = Field(default_factory=dict)
    attachments: list[str] = Field(default_factory=list)
    graph: str | None = Field(default=None, description="the recorded graph file's text")
    summary_ok: bool = Field(
        default=False, description="the summary/index section reads with the mcap reader"
    )


class SessionInfo(BaseModel):
    """A session (or one file) as one recording: its files, and streams over all of them."""

    path: str
    files: list[FileInfo]
    closed_cleanly: bool = Field(
        description="every file was closed cleanly, and no part of a split session is missing"
    )
    missing: list[str] = Field(
        default_factory=list, description="the parts a split session lacks, by file name"
    )
    size: int
    start: float | None
    end: float | None
    duration: float
    messages: int
    streams: list[StreamInfo] = Field(description="over every file, in time order")
    metadata: dict[str, dict[str, str]] = Field(
        default_factory=dict, description="the first file's"
    )
    graph: str | None = Field(default=None, description="the recorded graph file's text")

    @property
    def damage(self) -> str | None:
        """The first damage found, with its file."""
        if self.missing:
            return f"{', '.join(self.missing)}: missing (a part of this split session)"
        for f in self.files:
            if not f.closed_cleanly:
                return f"{Path(f.path).name}: {f.damage or 'no summary'}"
        return None


@dataclass
class _Chan:
    topic: str
    schema_id: int
    encoding: str
    metadata: dict[str, str]
    times: list[int] = field(default_factory=list)
    bytes: int = 0


@dataclass
class Recording:
    """Everything recovered from one file, in file order (used by :func:`repair`)."""

    path: Path
    schemas: dict[int, Any] = field(default_factory=dict)
    channels: dict[int, Any] = field(default_factory=dict)
    metadata: list[Any] = field(default_factory=list)
    attachments: list[Any] = field(default_factory=list)
    closed_cleanly: bool = False
    damage: str | None = None
    damage_offset: int | None = None
    last_offset: int = 0  # where the record being handled starts


def _describe(e: BaseException, within: str = "the file") -> str:
    """One line for why reading stopped. ``mcap`` raises a record cut short as ``EndOfFile``
    when nothing of it is left, as a bare ``struct.error`` when part of a field is (a cut in
    the summary or the first bytes): the same truncation, said in the same words."""
    from mcap.exceptions import EndOfFile

    if isinstance(e, EndOfFile | struct.error):
        return f"truncated: {within} ends inside a record"
    name = type(e).__name__
    return f"{name}: {e}" if str(e) else name


# A recording is data from anywhere: a chunk is decompressed only up to the size it declares,
# and never past this cap, so a 16 KB file cannot ask for gigabytes (a "chunk bomb"). The cap
# sits near what writers produce: flowrt's writer and the mcap libraries close a chunk at
# 1-4 MiB, and a message larger than that (a 4K BGR frame: 25 MB) is a chunk of its own; a
# reader holds a chunk about three times over (compressed, inflated, its messages), so
# 64 MiB keeps ``info`` and ``replay`` of any file under a few hundred MB.
MAX_CHUNK_BYTES = int(os.environ.get("FLOWRT_MAX_CHUNK_BYTES", 64 * 1024 * 1024))


class ChunkTooLarge(ValueError):
    """A chunk that declares, or decompresses to, more than a reader will hold."""


def chunk_data(chunk: Any, validate_crc: bool = True) -> bytes:
    """The uncompressed records of ``chunk``, in memory bounded by its declared size.

    ``mcap``'s own reader trusts the compressed frame's content size (zstd) or decompresses
    without a limit (lz4); here the output stops one byte past ``uncompressed_size`` (and
    :data:`MAX_CHUNK_BYTES`), which is refused.
    """
    import zlib

    declared = int(chunk.uncompressed_size)
    if declared > MAX_CHUNK_BYTES:
        raise ChunkTooLarge(
            f"a chunk declares {_mib(declared)}, more than the {_mib(MAX_CHUNK_BYTES)} a "
            "reader holds (writers make chunks of a few MiB; FLOWRT_MAX_CHUNK_BYTES raises "
            "the cap for a file you trust)"
        )
    if chunk.compression == "zstd":
        data = _bounded_zstd(chunk.data, declared)
    elif chunk.compression == "lz4":
        import lz4.frame

        d = lz4.frame.LZ4FrameDecompressor()
        data = d.decompress(chunk.data, max_length=declared + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    if len(data) != declared:
        raise ChunkTooLarge(
            f"a chunk decompresses to {'more' if len(data) > declared else 'less'} than "
            f"the {declared} bytes it declares"
        )
    if validate_crc and chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch: the chunk is damaged")
    return bytes(data)


def _mib(n: int) -> str:
    return f"{n / (1 << 20):.1f} MiB" if n >= 1 << 20 else f"{n} bytes"


def _bounded_zstd(data: bytes, declared: int) -> bytes | bytearray:
    """At most ``declared + 1`` bytes out of a zstd stream, whatever its frames claim.

    Streamed into one buffer of that size (``readinto``): no intermediate copies, so the
    peak is the declared size, never what the frames would inflate to.
    """
    import zstandard

    reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data))
    out = bytearray(declared + 1)
    view = memoryview(out)
    n = 0
    while n <= declared:
        got = reader.readinto(view[n:])
        if not got:
            break
        n += got
    view.release()
    del out[n:]
    return out


def chunk_records(chunk: Any, validate_crc: bool = True) -> list[Any]:
    """The schema, channel and message records of ``chunk`` (:func:`chunk_data`, bounded)."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message, Schema

    data = chunk_data(chunk, validate_crc)
    stream = ReadDataStream(io.BytesIO(data))
    out: list[Any] = []
    while stream.count < len(data):
        opcode = stream.read1()
        n = stream.read8()
        if opcode == 0x04:
            out.append(Channel.read(stream))
        elif opcode == 0x05:
            out.append(Message.read(stream, n))
        elif opcode == 0x03:
            out.append(Schema.read(stream))
        else:
            stream.read(n)
    return out


def _records(path: Path, rec: Recording, emit_chunks: bool) -> Iterator[Any]:
    """Records of the file in order; stops quietly at damage, noting it in ``rec``.

    Chunks are broken up here, through :func:`chunk_records` (bounded), not by ``mcap``.
    """
    from mcap.records import Chunk, Footer
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True, validate_crcs=True)
        it = reader.records
        while True:
            pos = f.tell()
            try:
                r = next(it)
            except StopIteration:
                break
            except Exception as e:  # any damage: keep what came before, say where and why
                rec.damage, rec.damage_offset = _describe(e), pos
                return
            try:
                inner = chunk_records(r) if isinstance(r, Chunk) and not emit_chunks else None
            except Exception as e:  # a chunk read whole whose records do not: not the file's end
                rec.damage, rec.damage_offset = _describe(e, "a chunk"), pos
                return
            if isinstance(r, Footer):
                rec.closed_cleanly = True
            rec.last_offset = pos
            if inner is not None:
                yield from inner
            else:
                yield r


def scan(path: str | Path) -> FileInfo:
    """Read a whole file (without decoding images) and describe it; never raises on damage."""
    return _scan(path)[0]


def _scan(path: str | Path) -> tuple[FileInfo, list[tuple[_Chan, str]]]:
    """:func:`scan`, and each channel's times and bytes with its schema name (for sessions)."""
    p = Path(path)
    if is_db3(p):
        return _scan_db3(p)
    rec = Recording(p)
    chans, chunks = _read_channels(p, rec)
    return _file_info(p, rec, chans, chunks)


def _read_channels(p: Path, rec: Recording) -> tuple[dict[int, _Chan], int]:
    """Every channel's message times and bytes, and the chunks read (damage noted in ``rec``):
    from the message indexes where the file has them, else from the chunks themselves."""
    from mcap.records import Attachment, Chunk, MessageIndex, Metadata

    chans: dict[int, _Chan] = {}
    chunks = 0
    pending: Chunk | None = None  # a chunk whose message indexes have not come (yet)
    indexed = False
    sizes: dict[int, int] = {}

    take = _Tally(rec, chans).take

    def open_pending() -> None:
        nonlocal pending
        if pending is not None and not indexed:
            try:
                for inner in chunk_records(pending):
                    take(inner)
            except Exception as e:
                rec.damage = rec.damage or f"chunk: {_describe(e, 'the chunk')}"
        pending = None

    for r in _records(p, rec, emit_chunks=True):
        if isinstance(r, MessageIndex):
            indexed = True
            c = chans.get(r.channel_id)
            if c is not None and pending is not None:
                for t, off in r.records:
                    c.times.append(t)
                    c.bytes += sizes.get(off, 0)
            continue
        open_pending()
        if isinstance(r, Chunk):
            # channels and schemas live inside chunks: read them without the message data
            try:
                defs, sizes = _chunk_definitions(r)
            except Exception as e:  # a damaged chunk: what follows is not trusted either
                rec.damage = f"chunk {chunks + 1}: {_describe(e, 'the chunk')}"
                rec.damage_offset = rec.last_offset
                break
            chunks += 1
            pending, indexed = r, False
            for inner in defs:
                take(inner)
        elif isinstance(r, Metadata):
            rec.metadata.append(r)
        elif isinstance(r, Attachment):
            rec.attachments.append(r)
        else:
            take(r)
    open_pending()

    return chans, chunks


class _Tally:
    """A scan's schemas, channels and per-channel message times and bytes, record by record
    (the classes imported once: ``take`` runs for every message of an unindexed file)."""

    def __init__(self, rec: Recording, chans: dict[int, _Chan]) -> None:
        from mcap.records import Channel, Message, Schema

        self.rec, self.chans = rec, chans
        self.kinds = Schema, Channel, Message

    def take(self, r: Any, size: int | None = None) -> None:
        schema_cls, channel_cls, message_cls = self.kinds
        if isinstance(r, schema_cls):
            self.rec.schemas[r.id] = r
        elif isinstance(r, channel_cls):
            self.rec.channels[r.id] = r
            self.chans.setdefault(r.id, _Chan(r.topic, r.schema_id, r.message_encoding, r.metadata))
        elif isinstance(r, message_cls):
            c = self.chans.get(r.channel_id)
            if c is not None:
                c.times.append(r.log_time)
                c.bytes += len(r.data) if size is None else size


def _file_info(
    p: Path, rec: Recording, chans: dict[int, _Chan], chunks: int
) -> tuple[FileInfo, list[tuple[_Chan, str]]]:
    """What was read, as the file's description: streams, span, attachments, damage."""
    streams = []
    starts, ends = [], []
    named: list[tuple[_Chan, str]] = []
    for c in chans.values():
        c.times.sort()
        schema = rec.schemas.get(c.schema_id)
        named.append((c, schema.name if schema is not None else "?"))
        streams.append(_stream_info(c, named[-1][1]))
        if c.times:
            starts.append(c.times[0])
            ends.append(c.times[-1])
    start = min(starts) / 1e9 if starts else None
    end = max(ends) / 1e9 if ends else None
    for s in streams:
        for g in s.gaps:
            g.at = g.at - (start or 0.0)
    graph = None
    attachments = []
    for a in rec.attachments:
        attachments.append(f"{a.name} ({a.media_type}, {len(a.data)} bytes)")
        if a.name == "graph.yaml":
            graph = a.data.decode("utf-8", "replace")
    size = p.stat().st_size
    if size == 0:  # "truncated: the file ends inside a record at byte 0" said it poorly
        rec.damage, rec.damage_offset = "empty: not one byte (killed as it was created)", None
    info = FileInfo(
        path=str(p),
        size=size,
        closed_cleanly=rec.closed_cleanly and rec.damage is None,
        damage=rec.damage,
        damage_offset=rec.damage_offset,
        start=start,
        end=end,
        duration=(end - start) if start is not None and end is not None else 0.0,
        messages=sum(s.count for s in streams),
        chunks=chunks,
        streams=streams,
        metadata={m.name: dict(m.metadata) for m in rec.metadata},
        attachments=attachments,
        graph=graph,
        summary_ok=_summary_ok(p),
    )
    return info, named


def _scan_db3(p: Path) -> tuple[FileInfo, list[tuple[_Chan, str]]]:
    """A rosbag2 SQLite3 file described as an MCAP file is (:mod:`.rosbag2`)."""
    named = []
    try:
        topics = db3_topics(p)
    except BagError as e:  # a damaged database: a damaged file, as an MCAP one is
        return FileInfo(
            path=str(p),
            size=p.stat().st_size,
            closed_cleanly=False,
            damage=str(e).removeprefix(f"{p}: "),
            start=None,
            end=None,
            duration=0.0,
            messages=0,
            chunks=0,
            streams=[],
        ), []
    for top in topics.values():
        c = _Chan(top.name, top.schema.id, top.encoding, {}, top.times, top.bytes)
        named.append((c, top.type))
    streams = [_stream_info(c, name) for c, name in named]
    start = min((s.first for s in streams if s.first is not None), default=None)
    end = max((s.last for s in streams if s.last is not None), default=None)
    for s in streams:
        for g in s.gaps:
            g.at = g.at - (start or 0.0)
    info = FileInfo(
        path=str(p),
        size=p.stat().st_size,
        closed_cleanly=True,
        damage=None,
        start=start,
        end=end,
        duration=(end - start) if start is not None and end is not None else 0.0,
        messages=sum(s.count for s in streams),
        chunks=0,
        streams=streams,
        summary_ok=True,
    )
    return info, named


def scan_session(path: str | Path) -> SessionInfo:
    """Describe a session folder (every part) or one file as one recording.

    Streams are merged by topic across the files, so a rate or gap is computed over the
    whole recording: the boundary between two parts is not a gap (no message is lost
    there), and a gap that spans one is found.
    """
    from .session import mcap_files, missing_parts

    files: list[FileInfo] = []
    merged: dict[str, tuple[_Chan, str]] = {}
    paths = mcap_files(path)
    missing = missing_parts(path, paths)
    for f in paths:
        info, named = _scan(f)
        files.append(info)
        for c, schema in named:
            m = merged.get(c.topic)
            if m is None:
                merged[c.topic] = (_Chan(c.topic, 0, c.encoding, c.metadata), schema)
                m = merged[c.topic]
            m[0].times.extend(c.times)
            m[0].bytes += c.bytes
    streams = []
    for c, schema in merged.values():
        c.times.sort()
        streams.append(_stream_info(c, schema))
    starts = [f.start for f in files if f.start is not None]
    ends = [f.end for f in files if f.end is not None]
    start = min(starts) if starts else None
    end = max(ends) if ends else None
    for s in streams:
        for g in s.gaps:
            g.at = g.at - (start or 0.0)
    first = files[0] if files else None
    return SessionInfo(
        path=str(path),
        files=files,
        closed_cleanly=all(f.closed_cleanly for f in files) and not missing,
        missing=missing,
        size=sum(f.size for f in files),
        start=start,
        end=end,
        duration=(end - start) if start is not None and end is not None else 0.0,
        messages=sum(s.count for s in streams),
        streams=streams,
        metadata=first.metadata if first is not None else {},
        graph=next((f.graph for f in files if f.graph), None),
    )


def _summary_ok(path: Path) -> bool:
    """True when the mcap library's seeking reader finds the summary (indexes, statistics)."""
    from mcap.reader import SeekingReader

    try:
        with open(path, "rb") as f:
            return SeekingReader(f, validate_crcs=True).get_summary() is not None
    except Exception:
        return False


def _chunk_definitions(chunk: Any) -> tuple[list[Any], dict[int, int]]:
    """Schema and channel records of a chunk, and its messages' data sizes by offset.

    Checks the chunk's CRC, then walks the record headers only (message data is skipped).
    """
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Schema

    out: list[Any] = []
    sizes: dict[int, int] = {}
    data = chunk_data(chunk)  # raises when damaged or a bomb
    stream, length = ReadDataStream(io.BytesIO(data)), len(data)
    while stream.count < length:
        offset = stream.count
        opcode = stream.read1()
        n = stream.read8()
        if opcode == 0x03:  # schema
            out.append(Schema.read(stream))
        elif opcode == 0x04:  # channel
            out.append(Channel.read(stream))
        else:
            if opcode == 0x05:  # message: data size = record length - 22 bytes of header
                sizes[offset] = n - 22
            stream.read(n)
    return out, sizes


def _stream_info(c: _Chan, schema: str) -> StreamInfo:
    t = c.times
    count = len(t)
    mean = rmin = rmax = None
    gaps: list[Gap] = []
    if count > 1:
        iv = [(b - a) / 1e9 for a, b in itertools.pairwise(t)]
        span = (t[-1] - t[0]) / 1e9
        mean = (count - 1) / span if span > 0 else None
        longest, shortest = max(iv), min(iv)
        rmin = 1 / longest if longest > 0 else None
        rmax = 1 / shortest if shortest > 0 else None
        period = statistics.median(iv)
        # an event stream (a deterministic log) has no period: a pause there is not a gap
        if period > 0 and c.metadata.get("irregular") != "true":
            gaps = [Gap(at=t[i] / 1e9, length=d) for i, d in enumerate(iv) if d > 2 * period]
    return StreamInfo(
        topic=c.topic,
        schema_name=schema,
        message_encoding=c.encoding,
        source=c.metadata.get("source", ""),
        count=count,
        first=t[0] / 1e9 if t else None,
        last=t[-1] / 1e9 if t else None,
        rate_mean=mean,
        rate_min=rmin,
        rate_max=rmax,
        gaps=gaps,
        bytes=c.bytes,
    )


@dataclass
class RecordedMessage:
    """One message of a replay: topic, schema, log time (ns), sequence and raw bytes."""

    topic: str
    schema: Any
    encoding: str
    log_time: int
    sequence: int
    data: bytes
    source: str


def iter_messages(
    path: str | Path,
    topics: set[str] | None = None,
    damage: Recording | None = None,
) -> Iterator[RecordedMessage]:
    """Messages of a file in file order, up to any damage (noted in ``damage``)."""
    from mcap.records import Channel, Message, Schema

    rec = damage if damage is not None else Recording(Path(path))
    if is_db3(Path(path)):
        for top, t, data in db3_messages(Path(path), topics):
            yield RecordedMessage(top.name, top.schema, top.encoding, t, 0, data, top.name)
        rec.closed_cleanly = True
        return
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    for r in _records(Path(path), rec, emit_chunks=False):
        if isinstance(r, Schema):
            schemas[r.id] = r
        elif isinstance(r, Channel):
            channels[r.id] = r
        elif isinstance(r, Message):
            ch = channels.get(r.channel_id)
            if ch is None or (topics is not None and ch.topic not in topics):
                continue
            yield RecordedMessage(
                ch.topic,
                schemas.get(ch.schema_id),
                ch.message_encoding,
                r.log_time,
                r.sequence,
                r.data,
                ch.metadata.get("source", ch.topic),
            )


def iter_session(
    files: list[Path],
    topics: set[str] | None = None,
    damage: list[Recording] | None = None,
    after: int = 0,
) -> Iterator[RecordedMessage]:
    """Messages of every part in order, as one recording; stops at the first damage.

    A part whose summary says it ends before ``after`` (log time, ns) is skipped unread, so
    a replay from an offset does not read the parts before it. Each part read appends its
    :class:`Recording` to ``damage``.
    """
    for f in files:
        if after and _ends_before(f, after):
            continue
        rec = Recording(f)
        if damage is not None:
            damage.append(rec)
        yield from iter_messages(f, topics, rec)
        if rec.damage is not None:
            return


def channel_schemas(files: list[Path]) -> dict[str, tuple[str, Any]]:
    """topic -> (message encoding, schema record or None) over the files of a recording.

    From each file's summary when it has one (no message is read), else by reading it.
    """
    from mcap.reader import SeekingReader
    from mcap.records import Channel, Schema

    out: dict[str, tuple[str, Any]] = {}
    for f in files:
        if is_db3(f):
            for top in db3_topics(f, with_times=False).values():
                out.setdefault(top.name, (top.encoding, top.schema))
            continue
        summary = None
        with contextlib.suppress(Exception), open(f, "rb") as fh:
            summary = SeekingReader(fh).get_summary()
        if summary is not None:
            for ch in summary.channels.values():
                out.setdefault(ch.topic, (ch.message_encoding, summary.schemas.get(ch.schema_id)))
            continue
        schemas: dict[int, Any] = {}
        for r in _records(f, Recording(f), emit_chunks=False):
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                out.setdefault(r.topic, (r.message_encoding, schemas.get(r.schema_id)))
    return out


def last_log_time(path: Path) -> int | None:
    """The last message's log time (ns) by the file's summary; None without one (a file
    not closed cleanly). A rosbag2 ``.db3`` file: its last message's (the replay's progress
    line had no length for one)."""
    from mcap.reader import SeekingReader

    from .rosbag2 import db3_last_time, is_db3

    if is_db3(path):
        return db3_last_time(path)

    try:
        with open(path, "rb") as f:
            summary = SeekingReader(f).get_summary()
    except Exception:
        return None
    stats = summary.statistics if summary is not None else None
    return stats.message_end_time if stats is not None and stats.message_count > 0 else None


def _ends_before(path: Path, t: int) -> bool:
    """True when the file's summary says its last message is logged before ``t`` (ns)."""
    end = last_log_time(path)
    return end is not None and end < t
