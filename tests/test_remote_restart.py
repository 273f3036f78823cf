"""The first values of an exporter's new life, as an import counts them (no network).

An export numbers a stream's values from 0. An import that first hears a stream at number N
counts the N values before as lost (``before the link was up``) when it was listening as the
stream began (an exporter restarting, an exporter started after the import), never when the
stream is older than the import (a late joiner could not have had them). The ImportLink is
fed synthetic samples; only the header's fields and the time it has listened matter.
"""

from __future__ import annotations

import time
import types
from typing import Any

import pytest
from test_remote_liveness import _Bytes

from flowrt.remote._importer import BEFORE_LINK, ImportLink
from flowrt.remote.wire import HEADER, Header, MessageHeaders, header_ids

T0 = 1_700_000_000  # a stream's start, whole seconds of the exporter's wall clock


class _Sample:
    def __init__(self, header: Header) -> None:
        self.attachment = _Bytes(header.encode())
        self.payload = _Bytes(b"x")


def _link(listened_s: float) -> ImportLink:
    host = types.SimpleNamespace(
        loop=types.SimpleNamespace(call_soon_threadsafe=lambda f: None), now_mono=lambda: 0.0
    )
    bridge = types.SimpleNamespace(host=host, clock_probe=lambda zid: None)
    imp = ImportLink(bridge, "rx", "k", None, 5.0, 1 << 16)  # type: ignore[arg-type]
    imp.starts.listening = time.monotonic() - listened_s
    return imp


def _sample(stream: str, seq: int, age_s: float | None) -> _Sample:
    """Value ``seq`` of ``stream``, sent ``age_s`` after the stream began (None: a header
    that does not say when its stream began, as an older flowrt's)."""
    started = 0 if age_s is None else T0
    sent = T0 + (age_s or 0.0)
    return _Sample(Header(stream, "z", seq, sent, sent, "bytes", {}, started))


# (what, seconds the import has listened, [(stream, seq, age of the stream)], lost: reason ->
# count, published)
CASES: list[tuple[str, float, list[tuple[str, int, float | None]], dict[str, int], int]] = [
    (
        "exporter-restart",  # the user's case: heard from 0, the next life first heard at 8
        100.0,
        [("a", 0, 0.1), ("a", 1, 0.12), ("a", 2, 0.14), ("b", 8, 0.4), ("b", 9, 0.42)],
        {BEFORE_LINK: 8},
        3 + 10,
    ),
    (
        "exporter-started-after-the-import",  # the first stream, but younger than the import
        10.0,
        [("a", 12, 0.5), ("a", 13, 0.52)],
        {BEFORE_LINK: 12},
        14,
    ),
    (
        "late-joiner",  # the exporter has run for an hour; the import listens for 2 s
        2.0,
        [("a", 180_000, 3600.0), ("a", 180_001, 3600.02)],
        {},
        2,
    ),
    (
        "late-joiner-to-a-second-exporter",  # it ran before the import did: not counted
        10.0,
        [("a", 0, 0.1), ("b", 5000, 3600.0), ("a", 1, 0.12), ("b", 5001, 3600.02)],
        {},
        4,
    ),
    (
        "restart-of-an-older-exporter",  # no start in the header: counted after another stream
        100.0,
        [("a", 40, None), ("a", 41, None), ("b", 6, None)],
        {BEFORE_LINK: 6},
        2 + 7,
    ),
    (
        "first-stream-of-an-older-exporter",  # no start, nothing heard before: not counted
        100.0,
        [("a", 40, None), ("a", 41, None)],
        {},
        2,
    ),
    (
        "two-exporters-interleaved",  # each goes on from its own number; a's 2 never came
        100.0,
        [("a", 0, 0.1), ("b", 0, 0.1), ("a", 1, 0.2), ("b", 1, 0.2), ("a", 3, 0.3)],
        {"sequence gap": 1},
        6,
    ),
    (
        "forged-first-number",  # past 2**32: not 2**63 values lost
        100.0,
        [("a", 1 << 63, 0.1)],
        {},
        1,
    ),
]


@pytest.mark.parametrize(
    ("listened_s", "samples", "lost", "published"),
    [c[1:] for c in CASES],
    ids=[c[0] for c in CASES],
)
def test_a_new_streams_first_values_are_lost_only_if_the_import_could_have_had_them(
    listened_s: float,
    samples: list[tuple[str, int, float | None]],
    lost: dict[str, int],
    published: int,
) -> None:
    imp = _link(listened_s)
    for stream, seq, age in samples:
        imp.on_sample(_sample(stream, seq, age))
    assert imp.link.drop_reasons == lost
    assert imp.link.dropped == sum(lost.values())
    assert imp.link.published == published
    assert len(imp.pending) == len(samples)  # every sample that came is delivered


def test_every_header_of_an_export_says_when_its_stream_began() -> None:
    """The start is in the 4 bytes that were padding: the layout's size is unchanged, and a
    reader of the older layout (``4x`` there) reads every other field as before."""
    import struct

    made = MessageHeaders(header_ids("s", "z"), "json", T0)(7, T0 + 1.5, T0 + 1.25)
    assert Header.decode(made) == Header("s", "z", 7, T0 + 1.5, T0 + 1.25, "json", {}, T0)
    assert HEADER.size == len(made) == 120
    older: Any = struct.unpack("<4sBBBB16s32sQddQIII4x8s8s", made)
    assert older[7:10] == (7, T0 + 1.5, T0 + 1.25)
