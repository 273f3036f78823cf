"""The MCAP writer: on its own thread, so the event loop never waits on the disk.

The recorder node hands each message to :meth:`RecordingWriter.submit`, which only appends to
a bounded queue (frames by reference: the node holds a link on the shared-memory slot, so no
pixel is copied on the loop). Two threads follow: the *encoder* turns each message into its
bytes (see :mod:`..encoding`; for a frame that is the one copy of its pixels, after which the
slot goes back to its pool) and the *disk* thread writes them through the official ``mcap``
writer. Encoded messages may wait up to ``max_bytes``, so a disk that stalls for a moment
holds memory, not the camera's pool slots. The disk thread finishes a chunk at least every
``flush_interval`` seconds: after a ``kill -9`` the file is readable up to the last finished
chunk, so at most ``flush_interval`` (1 s by default) or one chunk is lost.

With a :class:`~..split.SplitPolicy` the disk thread also starts a new file, a *part*, when
the current one reaches the size or duration: it finishes the part (summary, indexes: a
complete file) and opens the next with the same metadata and attachments, between two
messages, so no message is dropped or held by the loop; every part is a standalone MCAP.

Nothing is lost silently. A full queue (the disk or the encoder cannot keep up) refuses the
message and counts it against its stream (``lost_behind``); a write error (disk full, file
too large) stops writing, keeps what is in the file, records the error and counts every
message not written from then on (``lost_error``). The graph goes on either way.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ...frames import Frame
from ...stats import Running
from ..chunking import checked_if_large, install_chunks
from ..directio import open_direct
from ..encoding import Encoded, StreamSchema, epoch_ns
from ..gilfree import install
from ..inuse import hold
from ..ros2_profile import ros2_topic
from ..split import SplitPolicy, part_path
from ..streams import StreamBook

__all__ = ["RecordingWriter", "StreamCounters", "count_written"]

PROFILE = "flowrt"
MESSAGE_OVERHEAD = 31 + 16
"""Bytes a message takes in a file besides its data: its record header and index entry."""
THREAD_PREFIX = "mcap writer "
"""Writer threads are not daemons: a process that ends waits for its files to be finished."""


@dataclass
class StreamCounters:
    """What happened to one stream: received, written, lost (and why), bytes, timing."""

    topic: str
    source: str = ""
    received: int = 0
    written: int = 0
    bytes: int = 0
    lost_behind: int = 0
    refused_error: int = 0  # refused at submit after a write error (the loop counts these)
    unwritten: int = 0  # queued but not written: encode or write failed (the writer counts)
    first_time: float | None = None  # seconds, the runtime clock (log time of the first)
    last_time: float | None = None
    first_seen: float | None = None  # runtime clock when the first / last one arrived
    last_seen: float | None = None
    intervals: Running = field(default_factory=Running)

    @property
    def lost_error(self) -> int:
        return self.refused_error + self.unwritten

    @property
    def lost(self) -> int:
        return self.lost_behind + self.lost_error


@dataclass
class _Item:
    topic: str
    value: Any
    t: float
    seq: int


class RecordingWriter:
    """MCAP file(s) written by a thread. Create, :meth:`open`, :meth:`submit`, :meth:`close`.

    Args:
        path: the ``.mcap`` file to create (its directory must exist); with ``split``, the
            parts are named after it: ``NAME_000.mcap``, ``NAME_001.mcap`` ...
        split: when to start a new part (size, duration); None or inactive: one file.
        image_formats: per topic ``raw`` (default), ``jpeg`` or ``png``.
        epoch_offset: added to the runtime clock's seconds to get Unix time (log times are
            nanoseconds since the epoch, as Foxglove expects).
        max_frames: frames a stream may have waiting; each holds a shared-memory slot, and a
            frame pool has 16 by default, so this stays well below.
        max_messages: other messages that may wait, all streams together.
        max_bytes: encoded messages that may wait for the disk (256 MiB by default: more
            than a second of two 1936x1216 cameras at 20 fps).
        direct_io: write with ``O_DIRECT`` (see :mod:`..directio`), where the file system
            allows it.
        crc: chunk CRCs, so that damage inside a chunk is found (``info``, ``replay``); they
            cost as much CPU as the rest of the writing (zlib's CRC-32, ~12 ms per 7 MB frame
            on the loaded dev VM), so a high-rate recording may turn them off.
        on_written: called from the writer thread after a frame was written, so the owner can
            give its link back on the event loop.
        on_result: called from the disk thread with each message's topic, its bytes (-1: not
            written) and its part's index (a writer process reports these to the recorder).
        gil_free: the large copies of the writing with the GIL released (:mod:`..gilfree`);
            False only to measure against ``mcap``'s own buffers (the benchmark's baseline).
        profile: ``flowrt`` (protobuf images, JSON) or ``ros2`` (CDR, :mod:`.ros2_profile`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        image_formats: dict[str, str] | None = None,
        epoch_offset: float = 0.0,
        chunk_size: int = 4 << 20,
        compression: str = "none",
        flush_interval: float = 1.0,
        max_frames: int = 8,
        max_messages: int = 10000,
        max_bytes: int = 256 << 20,
        crc: bool = True,
        direct_io: bool = False,
        on_written: Callable[[], None] | None = None,
        split: SplitPolicy | None = None,
        gil_free: bool = True,
        on_result: Callable[[str, int, int], None] | None = None,
        profile: str = PROFILE,
    ) -> None:
        self.gil_free = gil_free
        self.profile = profile
        self.split = split if split is not None and split.active else None
        self.base = Path(path)
        self.path = self.base.with_name(part_path(self.base.name, 0)) if self.split else self.base
        self.files: list[Path] = []  # every part, in order (one file when not split)
        self.part_messages: list[int] = []  # messages written into each part
        self.image_formats = image_formats or {}
        self.epoch_offset = epoch_offset
        self.chunk_size = chunk_size
        self.compression = compression
        self.flush_interval = flush_interval
        self.max_frames = max_frames
        self.max_messages = max_messages
        self.max_bytes = max_bytes
        self.crc = crc
        self.direct_io = direct_io
        self.on_written = on_written
        self.on_result = on_result
        self.streams: dict[str, StreamCounters] = {}
        self.error: str | None = None
        self.closed = False
        self.done: deque[Frame] = deque()  # frames written: their links go back on the loop
        self._queue: deque[_Item] = deque()
        self._frames_waiting: dict[str, int] = {}
        self._messages_waiting = 0
        self._cond = threading.Condition()
        self._closing = False
        self._thread: threading.Thread | None = None
        self._encoder: threading.Thread | None = None
        self._encoded: deque[tuple[_Item, Encoded | None] | None] = deque()  # None: the end
        self._encoded_bytes = 0
        self._disk = threading.Condition()
        self._file: Any = None
        self._writer: Any = None
        self._channels = _Channels()  # of the current part
        self._channel_meta: dict[str, dict[str, str]] = {}
        self._metadata: dict[str, dict[str, str]] = {}
        self._attachments: list[tuple[str, str, bytes]] = []
        self._part_bytes = 0
        self._part_start: float | None = None  # runtime-clock time of the part's first message
        self._end_attachments: Callable[[], list[tuple[str, str, bytes]]] = list
        self._on_finished: Callable[[], None] | None = None
        self._inflight: Frame | None = None
        self._crc_now = False  # the encoder computes large messages' CRCs (.chunking)
        self._values = value_encoder(self.image_formats, epoch_offset, gil_free, profile)
        self.notes: list[str] = []  # problems other than write errors (said once per stream)
        self._unencodable = Unencodable(self.notes)

    # --- on the event loop ------------------------------------------------------------------

    def open(
        self,
        metadata: dict[str, dict[str, str]],
        attachments: list[tuple[str, str, bytes]] = (),  # type: ignore[assignment]
    ) -> None:
        """Create the file and write header, metadata and attachments; raise OSError if not.

        Every part of a split recording starts with the same metadata and attachments.
        """
        self._metadata = dict(metadata)
        self._attachments = list(attachments)
        self._start_file(self.path)
        self._encoder = threading.Thread(
            target=self._encode_loop, name=f"{THREAD_PREFIX}{self.path.name} encoder"
        )
        self._thread = threading.Thread(target=self._run, name=f"{THREAD_PREFIX}{self.path.name}")
        self._encoder.start()
        self._thread.start()

    def declare(self, topic: str, source: str = "", **meta: str) -> StreamCounters:
        """Name a stream before its first message (its source ``node.port`` and metadata)."""
        s = self.streams.get(topic)
        if s is None:
            s = self.streams[topic] = StreamCounters(topic, source)
        if source:
            s.source = source
        self._channel_meta[topic] = {"source": s.source, **meta}
        return s

    def submit(self, topic: str, value: Any, t: float, seq: int) -> bool:
        """Queue a message logged at runtime-clock time ``t``; False (and counted) if refused.

        A frame is kept by reference: the caller must hold one link on it for the writer and
        take it back from :attr:`done` once written (or at once, when refused).
        """
        s = self.streams.get(topic) or self.declare(topic)
        s.received += 1
        if s.first_seen is None:
            s.first_seen = t
        s.last_seen = t
        if self.error is not None or self.closed:
            s.refused_error += 1
            return False
        is_frame = isinstance(value, Frame)
        with self._cond:
            if is_frame:
                if self._frames_waiting.get(topic, 0) >= self.max_frames:
                    s.lost_behind += 1
                    return False
                self._frames_waiting[topic] = self._frames_waiting.get(topic, 0) + 1
            else:
                if self._messages_waiting >= self.max_messages:
                    s.lost_behind += 1
                    return False
                self._messages_waiting += 1
            self._queue.append(_Item(topic, value, t, seq))
            self._cond.notify()
        return True

    def close(self, attachments: list[tuple[str, str, bytes]] = ()) -> None:  # type: ignore[assignment]
        """Write what is queued, the end attachments and the summary; blocks: use a thread."""
        self.request_close(lambda: list(attachments))
        self.join()

    def request_close(
        self,
        attachments: Callable[[], list[tuple[str, str, bytes]]] = list,
        on_finished: Callable[[], None] | None = None,
    ) -> None:
        """Finish the file after what is queued, without waiting (see :meth:`join`).

        ``attachments`` is called on the writer thread once the queue is written, so what it
        attaches (the per-stream report) counts everything; ``on_finished`` is called there
        after the summary is written (or the write failed).
        """
        self._end_attachments = attachments
        self._on_finished = on_finished
        with self._cond:
            self._closing = True
            self._cond.notify()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for a requested close; True when the file is finished."""
        end = None if timeout is None else time.monotonic() + timeout
        for t in (self._encoder, self._thread):
            if t is not None:
                t.join(None if end is None else max(0.0, end - time.monotonic()))
                if t.is_alive():
                    return False
        self.closed = True
        return True

    def detach_frames(self) -> list[Frame]:
        """Copy the queued frames' pixels to the heap; returns the originals to release.

        At stop the shared-memory pools go away, but a slow disk may still be writing: after
        this (and once :meth:`encoding_frame` is false) the writer holds no pool slot.
        """
        with self._cond:
            return _to_heap(self._queue)

    def encoding_frame(self) -> bool:
        """True while the thread reads a frame's pixels (they are copied into the message)."""
        return self._inflight is not None

    def _start_file(self, path: Path) -> None:
        """Create ``path`` and write its header, metadata and attachments (raises OSError)."""
        from mcap.writer import CompressionType, Writer

        comp = {
            "none": CompressionType.NONE,
            "lz4": CompressionType.LZ4,
            "zstd": CompressionType.ZSTD,
        }[self.compression]
        file = _create(path, self.direct_io)
        try:
            w = Writer(file, chunk_size=self.chunk_size, compression=comp, enable_crcs=self.crc)
            gathered = self.gil_free and install(w) and install_chunks(w)  # .gilfree, .chunking
            w.start(profile=self.profile, library=_library())
            now = time.time_ns()
            for name, data in self._metadata.items():
                w.add_metadata(name, data)
            if self.split is not None:
                w.add_metadata("flowrt.part", _part_record(self.split, self.base, self.files))
            for name, media, blob in self._attachments:
                w.add_attachment(now, now, name, media, blob)
            file.flush()
        except BaseException:
            file.close()
            raise
        self._file, self._writer, self.path, self._crc_now = file, w, path, gathered and self.crc
        self.files.append(path)
        self.part_messages.append(0)
        self._channels = _Channels()  # each part declares its own
        self._part_bytes, self._part_start = file.tell(), None

    # --- on the writer thread ---------------------------------------------------------------

    def _encode_loop(self) -> None:
        """Encoder thread: messages to bytes; a frame's slot goes back right after."""
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    break  # closing and nothing left
                item = self._queue.popleft()
                if isinstance(item.value, Frame):
                    self._inflight = item.value
            enc = self._encode_item(item)
            with self._disk:
                while self._encoded_bytes > self.max_bytes and self.error is None:
                    self._disk.wait(0.1)  # the disk is behind: the queue above fills, counted
                self._encoded.append((item, enc))
                self._encoded_bytes += len(enc.data) if enc is not None else 0
                self._disk.notify()
        with self._disk:
            self._encoded.append(None)
            self._disk.notify()

    def _encode_item(self, item: _Item) -> Encoded | None:
        is_frame = isinstance(item.value, Frame)
        try:
            return None if self.error is not None else _encode(self._values, item, self._crc_now)
        except Exception as e:  # a value that cannot be encoded: counted, said once
            self._unencodable.say(item.topic, item.value, e)
            return None
        finally:
            # The pixels are in the encoded bytes now: the slot goes back to its pool.
            if is_frame:
                self._inflight = None
                self._frame_done(item)
            else:
                with self._cond:
                    self._messages_waiting -= 1

    def _run(self) -> None:
        """Disk thread: encoded messages into the file, a chunk finished every flush_interval."""
        last_flush = time.monotonic()
        while True:
            with self._disk:
                while not self._encoded:
                    self._disk.wait(timeout=max(0.0, self.flush_interval / 2))
                    if time.monotonic() - last_flush >= self.flush_interval:
                        break
                got = bool(self._encoded)
                entry = self._encoded.popleft() if got else None
                if entry is not None:
                    enc = entry[1]
                    self._encoded_bytes -= len(enc.data) if enc is not None else 0
                    self._disk.notify()
            if got and entry is None:
                break  # the encoder's end mark: everything queued is in
            if entry is not None:
                self._write(entry[0], entry[1])
            if self.error is None and time.monotonic() - last_flush >= self.flush_interval:
                self._guard(self._writer.flush)  # a finished chunk survives kill -9
                last_flush = time.monotonic()
        self._finish()
        if self._on_finished is not None:
            self._on_finished()

    def _write(self, item: _Item, enc: Encoded | None) -> None:
        s = self.streams[item.topic]
        n = -1
        if enc is not None and self.error is None:
            if self.split is not None and self.split.due(
                self._part_bytes, self._part_start, len(enc.data) + MESSAGE_OVERHEAD, item.t
            ):
                self._next_part()
            if self.error is None:
                n = self._add(item, enc)
        if n < 0:
            s.unwritten += 1
        else:
            count_written(s, item.t, n)
        if self.on_result is not None:
            self.on_result(item.topic, n, len(self.files) - 1)

    def _add(self, item: _Item, enc: Encoded) -> int:
        """Write one message into the current part: its size, or -1 (a write error)."""
        cid = self._channels.id_for(
            self._writer,
            ros2_topic(item.topic) if self.profile == "ros2" else item.topic,
            enc.schema,
            self._channel_meta.get(item.topic, {}),
        )
        ns = epoch_ns(item.t + self.epoch_offset)
        if not self._guard(
            lambda: self._writer.add_message(cid, ns, enc.data, ns, item.seq & 0xFFFFFFFF)
        ):
            return -1
        self.part_messages[-1] += 1
        self._part_bytes += len(enc.data) + MESSAGE_OVERHEAD
        if self._part_start is None:
            self._part_start = item.t
        return len(enc.data)

    def _next_part(self) -> None:
        """Finish the current part (a complete file) and open the next, on the disk thread.

        The part is closed before the next is created: a ``kill -9`` in between leaves every
        earlier part complete, and the one being written recoverable as any killed file.
        """
        if not self._guard(self._writer.finish):
            return
        if not self._guard(self._file.flush):
            return
        try:
            self._file.close()
        except OSError as e:
            self._fail(e)
            return
        self.path = self.base.with_name(part_path(self.base.name, len(self.files)))
        self._guard(partial(self._start_file, self.path))

    def _frame_done(self, item: _Item) -> None:
        with self._cond:
            self._frames_waiting[item.topic] -= 1
        self.done.append(item.value)
        if self.on_written is not None:
            self.on_written()

    def _guard(self, fn: Callable[[], Any]) -> bool:
        """Run a write; on OSError stop writing for good (what is in the file stays)."""
        if self.error is not None:
            return False
        try:
            fn()
            return True
        except OSError as e:
            self._fail(e)
            return False

    def _fail(self, e: OSError) -> None:
        self.error = f"{self.path}: {os.strerror(e.errno) if e.errno else e}"

    def _finish(self) -> None:
        if self.error is None:
            now = time.time_ns()
            try:
                attachments = self._end_attachments()
            except Exception as e:  # the report failed: the file is still finished
                self.notes.append(f"end attachments: {e}")
                attachments = []
            for name, media, blob in attachments:
                if not self._guard(
                    partial(self._writer.add_attachment, now, now, name, media, blob)
                ):
                    break
            self._guard(self._writer.finish)
        self._guard(self._file.flush)
        # After a write error the buffered tail cannot be written either: close regardless
        # (the descriptor is closed even when the final flush fails); the file stays.
        with contextlib.suppress(OSError, ValueError):
            self._file.close()


def _encode(values: Any, item: _Item, crc_now: bool) -> Encoded:
    """``item``'s message; with ``crc_now`` a frame's CRC too, on the encoder thread, while
    its bytes are in the cache (:mod:`..chunking` combines it into its chunk's)."""
    enc: Encoded = values.encode(item.topic, item.value)
    return Encoded(enc.schema, checked_if_large(enc.data)) if crc_now else enc


def count_written(s: StreamCounters, t: float, nbytes: int) -> None:
    """One message of ``s`` logged at ``t`` written, ``nbytes`` long."""
    s.written += 1
    s.bytes += nbytes
    if s.last_time is not None:
        s.intervals.add(t - s.last_time)
    else:
        s.first_time = t
    s.last_time = t


def _to_heap(queue: deque[_Item]) -> list[Frame]:
    """The shared frames of ``queue`` replaced by heap copies; returns the originals."""
    originals: list[Frame] = []
    for item in queue:
        v = item.value
        if isinstance(v, Frame) and v.shared:
            item.value = Frame(
                np.array(v.data),
                source=v.source,
                seq=v.seq,
                timestamp=v.timestamp,
                pixel_format=v.pixel_format,
            )
            originals.append(v)
    return originals


class Unencodable:
    """Says, in ``notes``, why a stream's values could not be encoded (the caller counts
    them): once per topic and value type, so an int stream's text values and its floats are
    two reasons (a refusal of 4 NaN floats went unsaid behind 8 strings)."""

    def __init__(self, notes: list[str]) -> None:
        self._notes = notes
        self._said: set[tuple[str, str]] = set()

    def say(self, topic: str, value: Any, e: Exception) -> None:
        key = (topic, type(value).__name__)
        if key not in self._said:
            self._said.add(key)
            self._notes.append(f"{topic}: cannot encode {key[1]}: {e}")


def value_encoder(
    image_formats: dict[str, str], epoch_offset: float, gil_free: bool, profile: str = PROFILE
) -> Any:
    """The encoder of a profile: flowrt's own (:class:`_ValueEncoder`) or ROS 2's."""
    if profile == "ros2":
        from ..ros2_profile import Ros2Encoder

        return Ros2Encoder(image_formats, epoch_offset)
    return _ValueEncoder(image_formats, epoch_offset, gil_free)


class _ValueEncoder(StreamBook):
    """The writer's stream book (:mod:`.streams`): frames raw unless a topic says otherwise."""

    def __init__(self, image_formats: dict[str, str], epoch_offset: float, gil_free: bool) -> None:
        super().__init__(image_formats, epoch_offset, gil_free=gil_free)


class _Channels:
    """The schemas and channels one part (one MCAP file) has declared: a channel per topic
    and schema, so every message matches its own channel's schema. A stream of one type
    (every built-in stream, any typed output) has one channel; an ``Output(object)`` whose
    values change type has one per type on its topic (its text values were written under
    the schema of its first value, an integer, which a validator refused)."""

    def __init__(self) -> None:
        self._schemas: dict[StreamSchema, int] = {}
        self._channels: dict[tuple[str, StreamSchema], int] = {}

    def id_for(self, writer: Any, topic: str, schema: StreamSchema, meta: dict[str, str]) -> int:
        cid = self._channels.get((topic, schema))
        if cid is not None:
            return cid
        sid = self._schemas.get(schema)
        if sid is None:
            sid = self._schemas[schema] = writer.register_schema(
                schema.name, schema.encoding, schema.data
            )
        new: int = writer.register_channel(topic, schema.message_encoding, sid, meta)
        self._channels[(topic, schema)] = new
        return new


def _part_record(split: SplitPolicy | None, base: Path, files: list[Path]) -> dict[str, str]:
    """The ``flowrt.part`` metadata: which part of which session, and the policy."""
    assert split is not None
    index = len(files)
    out = {"index": str(index), "first": part_path(base.name, 0)}
    if index:
        out["previous"] = files[-1].name
    if split.size is not None:
        out["split_size"] = str(split.size)
    if split.duration is not None:
        out["split_duration"] = f"{split.duration:g}"
    return out


def _library() -> str:
    from ...version import __version__

    try:
        from importlib.metadata import version

        mcap_version = version("mcap")
    except Exception:
        mcap_version = "?"
    return f"flowrt {__version__} (mcap {mcap_version})"


def _create(path: Path, direct_io: bool) -> Any:
    """``path`` created for writing (direct I/O where it may), held while it is written:
    ``flowrt info`` and ``--repair`` tell it from a killed recorder's file (:mod:`..inuse`)."""
    file: Any = open_direct(path) if direct_io else None
    if file is None:
        file = open(path, "xb")  # noqa: SIM115 - closed by the writer thread
    hold(file.fileno())
    return file
