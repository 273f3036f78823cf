"""An import's fast path (flowrt/remote/wire.py ``FixedParts``): a message whose header
repeats the last accepted one's but for its sequence number and times skips the header's
decoding and, when the exporter numbers its schemas (header byte 7), the reading of the
sample's Zenoh encoding. Table-driven on synthetic samples: the values, their types and every
count must be what the general path gives, whatever the mix of streams, schemas and faults.
"""

from __future__ import annotations

import types
from typing import Any

import pytest
from test_remote_liveness import _Bytes
from test_remote_restart import _link as restart_link

from flowrt.remote import wire
from flowrt.remote._export import Export, ExportSender
from flowrt.remote._importer import ImportLink
from flowrt.remote.wire import Header, MessageHeaders, header_ids

T0 = 1_700_000_000.0


class _Sample:
    """A Zenoh sample as the importer reads it; the samples whose encoding was read are
    counted (``reads``)."""

    reads = 0

    def __init__(self, att: bytes, payload: bytes, encoding: str) -> None:
        self.attachment = _Bytes(att)
        self.payload = _Bytes(payload)
        self._encoding = encoding
        self._read = False

    @property
    def encoding(self) -> str:
        if not self._read:
            self._read = True
            _Sample.reads += 1
        return self._encoding


def _link(max_bytes: int = 1 << 20) -> ImportLink:
    imp = restart_link(100.0)  # listening long before: a first stream's values are counted
    imp.max_bytes = max_bytes
    return imp


SCHEMAS = {1: "builtins.int", 2: "builtins.dict"}
PAYLOADS = {1: b'{"value":5}', 2: b'{"a":1}'}
VALUES = {1: 5, 2: {"a": 1}}


def _sample(stream: str, seq: int, schema_no: int, numbered: bool = True, payload: bytes = b""):
    """Message ``seq`` of ``stream`` in schema ``schema_no`` (1: an int, 2: a flat mapping);
    ``numbered``: the header says the schema's number (an older exporter's says 0)."""
    head = MessageHeaders(header_ids(stream, "z"), "json", int(T0), schema_no if numbered else 0)
    att = head(seq, T0 + seq, T0 + seq)
    body = payload or PAYLOADS[schema_no]
    return _Sample(att, body, f"application/json;{SCHEMAS[schema_no]}")


# (what, samples [(stream, seq, schema, numbered, payload)], values delivered, drop reasons,
# published, encoding reads at most)
CASES: list[tuple[str, list[tuple[Any, ...]], list[Any], dict[str, int], int, int]] = [
    (
        "one-schema",
        [("a", 0, 1, True, b""), ("a", 1, 1, True, b""), ("a", 2, 1, True, b"")],
        [5, 5, 5],
        {},
        3,
        1,  # read once: the header's number says the rest
    ),
    (
        "two-schemas-alternating",
        [("a", i, 1 + i % 2, True, b"") for i in range(6)],
        [5, {"a": 1}] * 3,
        {},
        6,
        6,  # each change of number takes the general path (which reads it)
    ),
    (
        "older-exporter-two-schemas",  # not numbered: read from every sample, each typed right
        [("a", i, 1 + i % 2, False, b"") for i in range(4)],
        [5, {"a": 1}] * 2,
        {},
        4,
        4,
    ),
    (
        "gap-on-the-fast-path",
        [("a", 0, 1, True, b""), ("a", 1, 1, True, b""), ("a", 5, 1, True, b"")],
        [5, 5, 5],
        {"sequence gap": 3},
        6,
        1,
    ),
    (
        "undecodable-on-the-fast-path",  # counted once: no gap after it
        [("a", 0, 1, True, b""), ("a", 1, 1, True, b"{nope"), ("a", 2, 1, True, b"")],
        [5, 5],
        {"undecodable": 1},
        3,
        1,
    ),
    (
        "too-large-on-the-fast-path",
        [("a", 0, 1, True, b""), ("a", 1, 1, True, b'{"value":' + b"1" * 64 + b"}")],
        [5],
        {"too large": 1},
        2,
        1,
    ),
    (
        "two-exporters-interleaved",  # each stream counted from its own numbers
        [
            ("a", 0, 1, True, b""),
            ("b", 0, 2, True, b""),
            ("a", 1, 1, True, b""),
            ("b", 2, 2, True, b""),
            ("a", 2, 1, True, b""),
        ],
        [5, {"a": 1}, 5, {"a": 1}, 5],
        {"sequence gap": 1},
        6,
        5,
    ),
]


@pytest.mark.parametrize(
    ("samples", "values", "lost", "published", "reads"),
    [c[1:] for c in CASES],
    ids=[c[0] for c in CASES],
)
def test_the_fast_path_gives_what_the_general_one_does(
    samples: list[tuple[Any, ...]],
    values: list[Any],
    lost: dict[str, int],
    published: int,
    reads: int,
) -> None:
    imp = _link(max_bytes=32)
    _Sample.reads = 0
    for stream, seq, schema, numbered, payload in samples:
        imp.on_sample(_sample(stream, seq, schema, numbered, payload))
    got = [v for _, v in imp.pending]
    assert got == values
    assert [type(v) for v in got] == [type(v) for v in values]
    assert imp.link.drop_reasons == lost
    assert imp.link.published == published
    assert _Sample.reads <= reads


def test_a_stream_of_one_schema_decodes_one_header(monkeypatch: pytest.MonkeyPatch) -> None:
    """What the fast path is for: the header's full decoding once per stream, not per message
    (it cost 25 us a message on Zenoh's thread, cold)."""
    calls = []
    decode = Header.decode.__func__  # type: ignore[attr-defined]
    monkeypatch.setattr(
        wire.Header, "decode", classmethod(lambda cls, raw: calls.append(1) or decode(cls, raw))
    )
    imp = _link()
    for seq in range(10):
        imp.on_sample(_sample("a", seq, 1))
    assert len(calls) == 1
    headers = [h for h, _ in imp.pending]
    assert [h.seq for h in headers] == list(range(10))
    assert {(h.stream, h.zid, h.kind, h.started) for h in headers} == {("a", "z", "json", T0)}
    assert [h.sent for h in headers] == [T0 + s for s in range(10)]


def test_a_header_says_its_schemas_number_in_the_reserved_byte() -> None:
    made = MessageHeaders(header_ids("s", "z"), "json", 0, 7)(1, 2.0, 3.0)
    assert made[7] == 7
    assert Header.decode(made) == Header("s", "z", 1, 2.0, 3.0, "json", {}, 0)  # else as before
    with pytest.raises(ValueError, match="0-255"):
        MessageHeaders(header_ids("s", "z"), "json", 0, 256)


class _Publisher:
    def __init__(self) -> None:
        self.puts: list[tuple[bytes, bytes, Any]] = []

    def put(self, data: bytes, attachment: bytes, encoding: Any) -> None:
        self.puts.append((data, attachment, encoding))


def test_an_export_numbers_each_schema_it_sends() -> None:
    """Values of three types on one export: their headers carry 1, 2, 3, each kept; the
    import reads every value back typed as sent, reading each schema's encoding once."""
    sender = ExportSender(types.SimpleNamespace(), "stream1", "zid1")  # type: ignore[arg-type]
    exp = Export("k", "src", "out", "json", 90, buf=None)  # type: ignore[arg-type]
    exp.publisher = _Publisher()
    sent = [5, {"a": 1}, "text", 6, {"a": 2}, "more", 7]
    for value in sent:
        sender._send_message(exp, value)
    puts = exp.publisher.puts
    assert [att[7] for _, att, _ in puts] == [1, 2, 3, 1, 2, 3, 1]
    imp = _link()
    _Sample.reads = 0
    for data, att, encoding in puts:
        imp.on_sample(_Sample(att, data, str(encoding)))
    assert [v for _, v in imp.pending] == sent
    assert imp.link.dropped == 0
    assert imp.link.published == len(sent)


async def test_what_an_export_takes_after_its_sender_stopped_is_counted() -> None:
    """The runtime closes the bridge before its sources stop: a value published in between
    was left in the export's buffer and cleared with it (the drain takes a buffer without a
    reader node for a host's own), published and neither delivered nor dropped."""
    from flowrt.edges import QueueBuffer

    sender = ExportSender(types.SimpleNamespace(), "stream1", "zid1")  # type: ignore[arg-type]
    buf = QueueBuffer("src.out->zenoh:k", 4)
    exp = Export("k", "src", "out", "json", 90, buf)
    exp.publisher = _Publisher()
    buf.on_put = lambda: sender.take(exp)
    sender.start()
    buf.put({"a": 1}, 0.0)
    await sender.stop()
    buf.put({"a": 2}, 0.0)  # published once the sender is gone
    assert len(exp.publisher.puts) == 1
    assert (buf.published, buf.delivered, buf.dropped) == (2, 1, 1)
    assert buf.drop_reasons == {"stop": 1}
    assert buf.pending() == 0
