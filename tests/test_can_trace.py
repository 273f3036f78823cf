"""Traces: the ``can`` node logs its bus in python-can's formats (rotated by size), python-can
and ``flowrt can stats`` read them back identically; stats keep channels apart and time FD
frames at their real length; replay sends FD, BRS, remote and error frames as recorded."""

from __future__ import annotations

import asyncio
import contextlib
import io
import itertools
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from _can_dbcs import FD_DBC, write
from flowrt.nodes.can.node import Can
from hypothesis import given, settings
from hypothesis import strategies as st

from flowrt import GraphBuilder, Runtime, VirtualClock, cli
from flowrt.analysis.can_frames import fd_frame_bits, frame_bits
from flowrt.analysis.can_trace import MIN_PEAK_S, bus_load

pytestmark = pytest.mark.timeout(30)
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"test-can-trace-{time.monotonic_ns()}-{next(_channels)}"


@pytest.fixture
def peer(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def _run(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return rc, out.getvalue(), err.getvalue()


async def _opened(rt: Runtime) -> Can:
    end = time.monotonic() + 5
    while True:
        n = rt.scheduler.runners["bus"].executor.node  # type: ignore[attr-defined]
        if n is not None and n.bus is not None:
            assert isinstance(n, Can)
            return n
        assert time.monotonic() < end, "bus did not open"
        await asyncio.sleep(0.005)


async def _until(cond: Callable[[], bool], within: float = 5.0) -> None:
    """Wait in real time for frames to cross the reader thread (not a timing assertion)."""
    end = time.monotonic() + within
    while not cond():
        assert time.monotonic() < end, "condition not reached"
        await asyncio.sleep(0.005)


def _frames() -> list[can.Message]:
    """What the peer sends: classic, extended, FD with and without BRS, a remote frame."""
    return [
        can.Message(arbitration_id=0x10 + k % 3, data=bytes([k, 1, 2]), is_extended_id=False)
        for k in range(20)
    ] + [
        can.Message(arbitration_id=0x1ABCDE, data=bytes(8), is_extended_id=True),
        can.Message(
            arbitration_id=257,
            data=bytes(range(12)),
            is_fd=True,
            bitrate_switch=True,
            is_extended_id=False,
        ),
        can.Message(
            arbitration_id=256,
            data=bytes(range(64)),
            is_fd=True,
            bitrate_switch=False,
            is_extended_id=False,
        ),
        can.Message(arbitration_id=0x55, is_remote_frame=True, dlc=4, is_extended_id=False),
    ]


def _key(m: can.Message) -> tuple[Any, ...]:
    data = b"" if m.is_remote_frame else bytes(m.data)
    return (m.arbitration_id, m.is_extended_id, m.is_fd, m.bitrate_switch, m.is_remote_frame, data)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
async def test_the_trace_reads_back_identically(
    channel: str, peer: can.BusABC, tmp_path: Path, suffix: str
) -> None:
    trace = tmp_path / f"bus{suffix}"
    g = GraphBuilder()
    g.add("kick", "can-signals", params={"rate_ms": 20, "signals": {"C": {"value": 7}}})
    params = {
        "interface": "virtual",
        "channel": channel,
        "dbc": write(tmp_path, FD_DBC),
        "fd": True,
        "trace": str(trace),
    }
    g.add("bus", "can", params=params, inputs={"Classic": "kick.values"})
    sent = _frames()
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        n = await _opened(rt)
        for m in sent:
            peer.send(m)
        await _until(lambda: n.received >= len(sent))
        await clock.advance(0.1)  # Classic every 10 ms from the DBC
        await asyncio.sleep(0.05)
        ours = n.msgs["Classic"].sent
    assert ours >= 5
    with can.LogReader(str(trace)) as reader:
        back = list(reader)
    received = [m for m in back if m.is_rx]
    transmitted = [m for m in back if not m.is_rx]
    assert [_key(m) for m in received] == [_key(m) for m in sent]
    assert len(transmitted) == ours
    assert all(m.arbitration_id == 768 and m.data[0] == 7 for m in transmitted)
    rc, out, err = _run("can", "stats", str(trace), "--json")
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["frames"] == len(back)
    ids = {(r["id"], r["extended"]): r for r in doc["ids"]}
    assert ids[(256, False)]["dlc"] == 64
    assert ids[(256, False)]["fd"]
    assert ids[(0x55, False)]["remote"] == 1


async def test_the_trace_rotates_by_size(channel: str, peer: can.BusABC, tmp_path: Path) -> None:
    trace = tmp_path / "rot.log"
    params = {
        "interface": "virtual",
        "channel": channel,
        "dbc": write(tmp_path, FD_DBC),
        "trace": str(trace),
        "trace_max_bytes": 2000,
    }
    g = GraphBuilder()
    g.add("bus", "can", params=params)
    async with Runtime(g.build()) as rt:
        n = await _opened(rt)
        for k in range(300):
            peer.send(
                can.Message(arbitration_id=0x20, data=k.to_bytes(2, "big"), is_extended_id=False)
            )
        await _until(lambda: n.received >= 300)
    files = sorted(tmp_path.glob("rot*.log"))  # noqa: ASYNC240 (a test, after the run)
    assert len(files) >= 3  # rolled over: ~40 bytes a line, 2000 bytes a file
    back: list[can.Message] = []
    for f in sorted(files, key=lambda f: f.stat().st_mtime_ns):
        with can.LogReader(str(f)) as reader:
            back.extend(reader)
    assert sorted(int.from_bytes(m.data, "big") for m in back) == list(range(300))
    assert all(f.stat().st_size < 2000 + 200 for f in files)


def test_a_two_channel_trace_gives_two_tables(tmp_path: Path) -> None:
    trace = tmp_path / "two.asc"
    with can.ASCWriter(str(trace)) as w:
        for k in range(100):
            for ch, offset in ((1, 0.0), (2, 0.002)):
                w.on_message_received(
                    can.Message(
                        timestamp=10 + k * 0.01 + offset,
                        arbitration_id=0x100,
                        data=bytes(8),
                        is_extended_id=False,
                        channel=ch,
                    )
                )
    rc, out, _ = _run("can", "stats", str(trace), "--bitrate", "500k", "--json")
    assert rc == 0
    doc = json.loads(out)
    chans = {c["channel"]: c for c in doc["channels"]}
    assert len(chans) == 2
    for c in chans.values():
        (row,) = c["ids"]
        assert row["count"] == 100
        assert row["period_ms"] == pytest.approx(10.0, abs=1e-3)  # not 5 ms: not merged
        assert c["mean_load"] == pytest.approx(100 * 135 / 500_000 / c["duration_s"], rel=1e-6)
    rc, out, _ = _run("can", "stats", str(trace))
    assert out.count("bus load at") == 2
    assert "channel 1" in out
    assert "channel 2" in out


def test_stats_times_fd_frames_at_their_length(tmp_path: Path) -> None:
    trace = tmp_path / "fd.log"
    with can.CanutilsLogWriter(str(trace), channel="can0") as w:
        for k in range(50):
            w.on_message_received(
                can.Message(
                    timestamp=100 + k * 0.01,
                    arbitration_id=0x200,
                    data=bytes(64),
                    is_fd=True,
                    bitrate_switch=True,
                    is_extended_id=False,
                )
            )
    rc, out, _ = _run("can", "stats", str(trace), "--data-bitrate", "2M", "--json")
    assert rc == 0
    doc = json.loads(out)
    (row,) = doc["ids"]
    assert row["dlc"] == 64  # not 8
    assert row["fd"]
    assert row["brs"]
    per_frame = 34 / 500_000 + 678 / 2_000_000
    assert doc["load"][0]["load"] == pytest.approx(50 * per_frame)
    assert doc["load"][0]["bits"] == 50 * fd_frame_bits(64).total
    assert doc["brs_at_nominal_rate"] == 0
    rc, out, _ = _run("can", "stats", str(trace), "--json")  # no data rate: nominal, said so
    doc = json.loads(out)
    assert doc["brs_at_nominal_rate"] == 50
    assert doc["load"][0]["load"] == pytest.approx(50 * 712 / 500_000)
    assert frame_bits(8) < 712


@pytest.mark.parametrize(
    ("name", "content"),
    [("notes.log", "hello\nthis is not a trace\n"), ("notes.txt", "hello"), ("empty.asc", "")],
)
def test_stats_on_a_file_that_is_not_a_trace(tmp_path: Path, name: str, content: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    rc, out, err = _run("can", "stats", str(path))
    assert rc == 2
    assert out == ""
    assert len(err.strip().splitlines()) == 1
    assert str(path) in err
    assert "Traceback" not in err


@pytest.mark.parametrize("suffix", [".blf", ".log"])
async def test_replay_keeps_fd_brs_remote_and_error_frames(
    channel: str, peer: can.BusABC, tmp_path: Path, suffix: str
) -> None:
    trace = tmp_path / f"mixed{suffix}"
    recorded = [
        can.Message(arbitration_id=0x10, data=bytes(8), is_extended_id=False),
        can.Message(
            arbitration_id=0x11,
            data=bytes(range(64)),
            is_fd=True,
            bitrate_switch=True,
            is_extended_id=False,
        ),
        can.Message(
            arbitration_id=0x12,
            data=bytes(range(12)),
            is_fd=True,
            bitrate_switch=False,
            is_extended_id=False,
        ),
        can.Message(arbitration_id=0x13, is_remote_frame=True, dlc=3, is_extended_id=False),
        can.Message(arbitration_id=0x4, is_error_frame=True, data=bytes(8), is_extended_id=False),
    ]
    with can.Logger(str(trace)) as w:
        for k, m in enumerate(recorded):
            m.timestamp = 5 + 0.01 * k
            w.on_message_received(m)
    params = {
        "interface": "virtual",
        "channel": channel,
        "dbc": write(tmp_path, FD_DBC),
        "fd": True,
        "replay": str(trace),
        "tick_ms": 10,
    }
    g = GraphBuilder()
    g.add("bus", "can", params=params)
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        await _opened(rt)
        await clock.advance(0.1)
        await asyncio.sleep(0.1)
        got = []
        while (m := peer.recv(0)) is not None:
            got.append(m)
    with can.LogReader(str(trace)) as reader:
        expected = list(reader)  # the frames as python-can reads them from the trace
    assert [(m.is_error_frame, *_key(m)) for m in got] == [
        (m.is_error_frame, *_key(m)) for m in expected
    ]
    assert [m.is_error_frame for m in got] == [False, False, False, False, True]
    # a remote frame keeps its requested length where the format does (candump's drops it)
    assert got[3].dlc == expected[3].dlc == (3 if suffix == ".blf" else 0)


async def test_a_trace_that_cannot_open_leaves_the_bus_running_in_error(
    channel: str, peer: can.BusABC, tmp_path: Path
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    params = {
        "interface": "virtual",
        "channel": channel,
        "dbc": write(tmp_path, FD_DBC),
        "trace": str(blocker / "bus.log"),
    }
    g = GraphBuilder()
    g.add("bus", "can", params=params)
    async with Runtime(g.build()) as rt:
        n = await _opened(rt)
        runner = rt.scheduler.runners["bus"]
        peer.send(can.Message(arbitration_id=0x300, data=bytes(8), is_extended_id=False))
        await _until(lambda: n.received == 1)
        assert runner.error_reason is not None
        assert "CAN trace" in runner.error_reason
        assert "cannot open" in runner.error_reason
        assert runner.counts.errors == 0  # nothing raised out of the node


_TICK = 1 / 64  # s: exact in binary and in candump's 6 decimals, so no window edge is rounded
_BACKGROUND = [1000.75 + k * _TICK for k in range(256)]  # 64 frames/s from mid-second, 3.98 s


@pytest.mark.parametrize(
    ("times", "mean_fps", "peak_fps", "second_frames"),
    [
        # the tester's trace: starting mid-second, the clock's first and last seconds are
        # partial (16 and 48 frames) and the mean over the span (64.25/s) beat every second
        pytest.param(_BACKGROUND, 64.0, 64.0, [64, 64, 64, 64], id="partial-clock-seconds"),
        # 16 more frames astride the third second from the first frame (at 1002.75): those
        # seconds have 72 each, the window over the burst 80
        pytest.param(
            sorted(_BACKGROUND + [1002.75 + m * _TICK for m in range(-8, 8)]),
            208 / 3,
            80.0,
            [64, 72, 72, 64],
            id="burst-across-a-clock-second",
        ),
        # a frame a whole second after another is in the next second (and past the 3 whole
        # seconds, out of the mean); the clock gave a mean of 4/3 and a busiest second of 1
        pytest.param([1000.5, 1001.5, 1002.5, 1003.5], 1.0, 1.0, [1, 1, 1, 1], id="on-edges"),
        # under MIN_PEAK_S: no busiest second, the mean over the span
        pytest.param(_BACKGROUND[:97], 97 / 1.5, None, [64, 33], id="short"),
    ],
)
def test_stats_busiest_second_is_a_whole_second_never_under_the_mean(
    tmp_path: Path,
    times: list[float],
    mean_fps: float,
    peak_fps: float | None,
    second_frames: list[int],
) -> None:
    trace = tmp_path / "t.log"
    with can.CanutilsLogWriter(str(trace), channel="can0") as w:
        for t in times:
            w.on_message_received(
                can.Message(timestamp=t, arbitration_id=0x10, data=bytes(8), is_extended_id=False)
            )
    rc, out, _ = _run("can", "stats", str(trace), "--bitrate", "500k", "--json")
    assert rc == 0
    doc = json.loads(out)
    per_frame = frame_bits(8) / 500_000
    assert doc["mean_load"] == pytest.approx(mean_fps * per_frame, rel=1e-12)
    if peak_fps is None:
        assert doc["peak_load"] is None
    else:
        assert doc["peak_load"] == pytest.approx(peak_fps * per_frame, rel=1e-12)
        assert doc["peak_load"] >= doc["mean_load"]
    assert [s["t_s"] for s in doc["load"]] == [float(k) for k in range(len(second_frames))]
    assert [s["bits"] for s in doc["load"]] == [n * frame_bits(8) for n in second_frames]


@settings(max_examples=300, deadline=None)
@given(
    base=st.sampled_from([0.0, 1000.2, 1.7e9 + 0.123456]),
    frames=st.lists(
        st.tuples(
            st.one_of(  # any time, or a trace's decimal microseconds
                st.floats(0, 8, allow_nan=False), st.integers(0, 8_000_000).map(lambda us: us / 1e6)
            ),
            st.integers(1, 2000),
        ),
        min_size=1,
        max_size=60,
    ),
    scale=st.sampled_from([125_000**2, 500_000 * 2_000_000, 1_000_000**2]),
)
def test_bus_load_peak_is_never_under_the_mean(
    base: float, frames: list[tuple[float, int]], scale: int
) -> None:
    """Any frame times and lengths: the busiest second is at least the mean, exactly (no
    rounding slack), and is the busiest window [t, t + 1 s) starting at a frame of the whole
    seconds (from the first frame, in microseconds) the mean is over."""
    times = [base + x for x, _ in frames]
    units = [n * 4000 for _, n in frames]
    bits = [n for _, n in frames]
    load = bus_load(times, bits, units, scale)
    assert sum(b for _, b, _ in load.seconds) == sum(bits)
    first = min(times)
    d = sorted((round((t - first) * 1e6), u) for t, u in zip(times, units, strict=True))
    span = d[-1][0]
    if span < MIN_PEAK_S * 1e6:
        assert load.peak is None
        return
    assert load.mean is not None
    assert load.peak is not None
    assert load.peak >= load.mean
    whole = span // 1_000_000
    starts = [x for x, _ in d if x < whole * 1_000_000]
    busiest = max(sum(u for y, u in d if x <= y < x + 1_000_000) for x in starts)
    assert load.peak == busiest / scale
    assert load.mean == sum(u for x, u in d if x < whole * 1_000_000) / (whole * scale)


@pytest.mark.parametrize(
    ("name", "make", "said"),
    [
        ("garbage.blf", lambda p: p.write_bytes(b"garbage\n"), "cannot read the trace"),
        ("empty.asc", lambda p: p.write_bytes(b""), "an empty file (no CAN frame in it)"),
        (
            "header.asc",
            lambda p: p.write_text("date Fri Nov 27 12:00:00.000 am 2026\nbase hex\n"),
            "no CAN frame in it",
        ),
    ],
)
def test_a_replay_that_cannot_be_read_is_fatal_and_names_the_file(
    tmp_path: Path, name: str, make: Callable[[Path], Any], said: str
) -> None:
    """A BLF of garbage failed every activation with 'unpack requires a buffer of 72
    bytes', naming neither file nor replay, and restarted the node over and over; an empty
    one replayed nothing, exit 0."""
    from flowrt.nodes.can.bus import TraceReplay

    from flowrt import FatalError

    path = tmp_path / name
    make(path)
    with pytest.raises(FatalError) as e:
        TraceReplay(str(path), False, None, 0.0)
    assert str(e.value).startswith(f"replay {path}")
    assert said in str(e.value)


def test_a_blf_cut_short_is_said_not_read_as_the_whole_trace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """python-can reads a BLF cut short (a logger that lost power) up to the cut without a
    word: 78 of 200 frames, read as if it were the whole trace."""
    from flowrt.analysis.can_trace import truncated

    whole = tmp_path / "whole.blf"
    with can.BLFWriter(str(whole)) as w:
        for k in range(200):
            w.on_message_received(can.Message(timestamp=k * 0.01, arbitration_id=0x10, data=[k]))
    cut = tmp_path / "cut.blf"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert truncated(str(whole)) is None
    said = truncated(str(cut))
    assert (
        said == f"{cut}: truncated ({len(data) // 2} of the {len(data)} bytes its header declares)"
    )
    assert cli.main(["can", "stats", str(cut)]) == 0
    assert f"{said}: the figures are those before the cut" in capsys.readouterr().out
