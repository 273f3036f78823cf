"""Messages by time: where each message of a session sits, so a player can jump to any instant.

A player asks for "camera T at 12.4 s" many times a second while the operator scrubs; reading
the session from its start for each request would cost the whole file every time. One pass
over the session (every part, through :mod:`.reader`'s damage-tolerant record reader, chunks
decompressed only within their declared size) notes each message's log time, its chunk's
file offset and its offset inside the chunk; a request then reads one chunk (the few newest
are kept) and slices one message out of it.

The pass walks the records inside each chunk itself rather than trusting the message
indexes after it: a file whose writer was killed has chunks without them, and a player
should show what was recorded up to the damage, as ``flowrt info`` does.
"""

from __future__ import annotations

import bisect
import struct
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .reader import MAX_CHUNK_BYTES, RecordedMessage, Recording, _records, chunk_data
from .session import mcap_files

__all__ = ["SessionIndex", "TopicIndex"]

_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
CHUNKS_KEPT = 4  # decompressed chunks kept per index (a few frames of each camera)


@dataclass
class TopicIndex:
    """One topic over every part: log times (ns, sorted) and where each message is."""

    topic: str
    schema: Any  # the mcap Schema record of the first part that has the topic
    encoding: str
    source: str
    times: list[int] = field(default_factory=list)
    where: list[tuple[int, int, int, int]] = field(default_factory=list)  # file, chunk, off, seq

    @property
    def schema_name(self) -> str:
        return str(self.schema.name) if self.schema is not None else ""

    def at(self, t_ns: int) -> int:
        """The index of the newest message logged at or before ``t_ns`` (the first if none)."""
        return max(0, bisect.bisect_right(self.times, t_ns) - 1)


class SessionIndex:
    """Every message's place in a session (a folder of parts, or one file)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files = mcap_files(self.path)
        self.topics: dict[str, TopicIndex] = {}
        self.damage: list[str] = []
        self._chunks: OrderedDict[tuple[int, int], bytes] = OrderedDict()
        self.decoders: dict[int, Any] = {}  # per part: a caller's decoder (schema ids are per file)
        for i, f in enumerate(self.files):
            self._index_file(i, f)
        for t in self.topics.values():
            order = sorted(range(len(t.times)), key=t.times.__getitem__)
            t.times = [t.times[k] for k in order]
            t.where = [t.where[k] for k in order]
        firsts = [t.times[0] for t in self.topics.values() if t.times]
        lasts = [t.times[-1] for t in self.topics.values() if t.times]
        self.start_ns = min(firsts) if firsts else 0
        self.end_ns = max(lasts) if lasts else 0

    @property
    def duration(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def _index_file(self, file_i: int, path: Path) -> None:
        from mcap.records import Channel, Chunk, Message, Schema

        rec = Recording(path)
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}

        def channel(r: Any) -> None:
            channels[r.id] = r
            if r.topic not in self.topics:
                self.topics[r.topic] = TopicIndex(
                    r.topic,
                    schemas.get(r.schema_id),
                    r.message_encoding,
                    r.metadata.get("source", r.topic),
                )

        for r in _records(path, rec, emit_chunks=True):
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                channel(r)
            elif isinstance(r, Message):  # outside chunks (an unchunked file)
                continue
            elif isinstance(r, Chunk):
                at = rec.last_offset
                try:
                    data = chunk_data(r)
                except Exception as e:  # a damaged chunk: keep what came before
                    self.damage.append(f"{path.name}: chunk at {at}: {e}")
                    break
                for kind, offset, parsed in _walk(data):
                    if kind == 0x03:
                        schemas[parsed.id] = parsed
                    elif kind == 0x04:
                        channel(parsed)
                    elif kind == 0x05:
                        ch_id, seq, log_time = parsed
                        ch = channels.get(ch_id)
                        if ch is not None:
                            t = self.topics[ch.topic]
                            t.times.append(log_time)
                            t.where.append((file_i, at, offset, seq))
        if rec.damage is not None:
            self.damage.append(f"{path.name}: {rec.damage}")

    def message(self, topic: str, i: int) -> RecordedMessage:
        """The ``i``-th message of ``topic`` (in time order), read from its chunk."""
        t = self.topics[topic]
        file_i, at, offset, seq = t.where[i]
        data = self._chunk(file_i, at)
        _, length = struct.unpack_from("<BQ", data, offset)
        head = offset + 9
        _, _, log_time, _ = _MESSAGE_HEAD.unpack_from(data, head)
        body = data[head + _MESSAGE_HEAD.size : head + length]
        return RecordedMessage(topic, t.schema, t.encoding, log_time, seq, bytes(body), t.source)

    def _chunk(self, file_i: int, at: int) -> bytes:
        key = (file_i, at)
        data = self._chunks.get(key)
        if data is not None:
            self._chunks.move_to_end(key)
            return data
        from mcap.stream_reader import StreamReader

        with open(self.files[file_i], "rb") as f:
            f.seek(at)
            reader = StreamReader(
                f, skip_magic=True, emit_chunks=True, record_size_limit=MAX_CHUNK_BYTES + 4096
            )
            data = chunk_data(next(iter(reader.records)))
        self._chunks[key] = data
        while len(self._chunks) > CHUNKS_KEPT:
            self._chunks.popitem(last=False)
        return data


def _walk(data: bytes) -> list[tuple[int, int, Any]]:
    """(opcode, offset, what) of the schema, channel and message records of a chunk's data;
    a message is (channel id, sequence, log time), its body left where it is."""
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Schema

    out: list[tuple[int, int, Any]] = []
    offset, end = 0, len(data)
    while offset + 9 <= end:
        opcode, length = struct.unpack_from("<BQ", data, offset)
        body = offset + 9
        if body + length > end:
            break  # a record cut short: nothing after it is trusted
        if opcode == 0x05 and length >= _MESSAGE_HEAD.size:
            ch_id, seq, log_time, _ = _MESSAGE_HEAD.unpack_from(data, body)
            out.append((opcode, offset, (ch_id, seq, log_time)))
        elif opcode in (0x03, 0x04):
            stream = ReadDataStream(io.BytesIO(data[body : body + length]))
            rec = Schema.read(stream) if opcode == 0x03 else Channel.read(stream)
            out.append((opcode, offset, rec))
        offset = body + length
    return out
