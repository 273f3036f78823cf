"""The recording's ``expected`` counts the source's releases in the session, its phase respected.

``flowrt record graphs/cambada.yaml --duration 3`` said ``bgoal.detection expected 16 received
15 missing 1`` and ``bpost.detection expected 5 received 4 missing 1`` on a clean run: the
count was the session's length times the rate, plus one, as if every stream released at both
ends of the window. ``bgoal`` releases on omni ticks 1, 5, 9 ... and ``bpost`` on 2, 18, 34 ...
(graphs/cambada.yaml: frame period/phase, flowrt.kernel.scheduler.Scheduler.tick), so 3 s hold
15 and 4 of them. Pure numbers here: the scheduler's release rules on a nominal timeline.
"""

from __future__ import annotations

import math

import pytest
from flowrt.nodes.recorder import LAGS_KEPT
from test_stream_rates import _Written  # what a report reads of a writer

from flowrt.clock import next_release
from flowrt.recording import build_report
from flowrt.recording.report import expected_releases, releases_in
from flowrt.recording.writer import StreamCounters

ORIGIN = 100.0  # the runtime clock's origin: stamps are absolute (time.monotonic())

# graphs/cambada.yaml: camera -> (timer ms, timer phase ms); tracker -> (camera, period, phase)
CAMERAS = {"front_cam": (50.0, 0.0), "omni_cam": (50.0, 25.0)}
TRACKERS = {
    "avoid_fr": ("front_cam", 1, 0),
    "ball_fr": ("front_cam", 1, 0),
    "avoid_om": ("omni_cam", 1, 0),
    "ball_om": ("omni_cam", 1, 0),
    "bgoal": ("omni_cam", 4, 1),
    "ygoal": ("omni_cam", 4, 3),
    "line": ("omni_cam", 8, 0),
    "bpost": ("omni_cam", 16, 2),
    "ypost": ("omni_cam", 16, 4),
}


def _camera_ticks(name: str, on: float, off: float) -> list[float]:
    """The camera's releases while the sources run: its timer armed at ``on`` fires first
    strictly after it (flowrt.clock.next_release), and no release from ``off`` on."""
    period, phase = (v / 1000 for v in CAMERAS[name])
    t, _ = next_release(ORIGIN, period, phase, on)
    ticks = []
    while t < off:
        ticks.append(t)
        t += period
    return ticks


def _releases(on: float, off: float) -> dict[str, list[float]]:
    """Every stream's releases (its values' stamps): a tracker on ticks k % period == phase
    of its camera's frame clock, which counts from the camera's first frame (Scheduler.tick)."""
    ticks = {cam: _camera_ticks(cam, on, off) for cam in CAMERAS}
    out = {f"{cam}.frame": t for cam, t in ticks.items()}
    for name, (cam, period, phase) in TRACKERS.items():
        out[f"{name}.detection"] = [t for k, t in enumerate(ticks[cam]) if k % period == phase]
    return out


def _rates() -> dict[str, float | None]:
    """nominal_rates of the cambada graph: node -> releases per second."""
    rates: dict[str, float | None] = {cam: 1000.0 / ms for cam, (ms, _) in CAMERAS.items()}
    for name, (cam, period, _) in TRACKERS.items():
        rates[name] = 1000.0 / CAMERAS[cam][0] / period
    return rates


def _report(
    stamps: dict[str, list[float]], jitter: float = 0.0, started: float | None = None
) -> dict[str, tuple[int | None, int, int]]:
    """topic -> (expected, received, missing) of a session that recorded ``stamps``; a
    tick's values are stamped ``jitter`` late on every third tick (one frame stamp each)."""
    streams = {}
    for topic, times in stamps.items():
        late = [t + (jitter if round((t - ORIGIN) / 0.025) % 3 == 0 else 0.0) for t in times]
        streams[topic] = StreamCounters(
            topic, topic, received=len(late), written=len(late),
            first_seen=late[0] if late else None, last_seen=late[-1] if late else None,
        )  # fmt: skip
    report = build_report(_Written(streams), "rec_001", "t", 3.0, _rates(), started)
    return {s.topic: (s.expected, s.received, s.missing) for s in report.streams}


# (sources on, sources off, jitter): seconds after the origin; a session records all of it
SESSIONS = [
    (0.010, 3.010, 0.0),  # `flowrt record --duration 3`: front first, omni 25 ms later
    (0.030, 3.030, 0.0),  # omni's release comes first
    (0.010, 2.210, 0.0),
    (0.010, 4.510, 0.0),
    (0.010, 5.010, 0.0),
    (0.012, 3.061, 0.0),  # a release of omni right at the end: never made
    (0.010, 3.010, 0.004),  # stamps a few ms late, as a loaded machine's
    (0.030, 4.530, 0.012),
]


@pytest.mark.parametrize(("on", "off", "jitter"), SESSIONS)
def test_a_clean_cambada_session_misses_nothing(on: float, off: float, jitter: float) -> None:
    releases = _releases(ORIGIN + on, ORIGIN + off)
    by = _report(releases, jitter)
    for topic, times in releases.items():
        assert by[topic] == (len(times), len(times), 0), topic


def test_the_repro_counts_are_the_releases() -> None:
    """The reported session: 3 s, front first. 16/5 expected before."""
    by = _report(_releases(ORIGIN + 0.010, ORIGIN + 3.010))
    assert by["bgoal.detection"] == (15, 15, 0)
    assert by["bpost.detection"] == (4, 4, 0)
    assert by["line.detection"] == (8, 8, 0)
    assert by["omni_cam.frame"] == (60, 60, 0)


# (period, anchor, start, end, releases in [start, end))
RELEASES_IN = [
    (1.0, 0.0, 0.0, 3.0, 3),  # one at the start counts, one at the end does not
    (1.0, 0.0, 0.0, 3.0001, 4),
    (1.0, 0.5, 0.0, 3.0, 3),
    (0.8, 0.1, 0.0, 3.07, 4),  # bpost at 1.25 Hz, 0.1 s phase: 0.1 0.9 1.7 2.5
    (0.8, 2.5, 0.0, 3.07, 4),  # the same grid, placed by its last release
    (0.8, 0.1, 0.9, 1.7, 1),  # edges on releases (float noise: 0.9 - 0.1 is not 0.8)
    (0.2, 0.075, 0.0, 3.0, 15),  # bgoal: omni's phase 25 ms + one 50 ms frame
    (0.05, 0.025, 0.0, 3.0, 60),
    (1.0, 0.0, 2.0, 2.0, 0),
    (1.0, 0.0, 3.0, 2.0, 0),
]


@pytest.mark.parametrize(("period", "anchor", "start", "end", "n"), RELEASES_IN)
def test_releases_in_a_window(
    period: float, anchor: float, start: float, end: float, n: int
) -> None:
    assert releases_in(period, anchor, start, end) == n


# (period, session first/last message, stream first/last value, expected)
EXPECTED = [
    (0.8, 0.0, 2.9743, 0.1243, 2.5241, 4),  # the repro's bpost (stamps from its MCAP)
    (0.2, 0.0, 2.9743, 0.0742, 2.8742, 15),  # bgoal
    (0.2, 0.0, 2.9743, 0.1743, 2.9743, 15),  # ygoal: the session's last message is its own
    (0.4, 0.0, 2.9743, 0.0251, 2.8243, 8),  # line
    (0.05, 0.0, 2.9743, 0.0, 2.9492, 60),  # front_cam: its next release, 2.9992, is after
    (1.0, 0.0, 3.0, 1.0, 2.0, 3),  # a release at the session's first message counts
    (1.0, 0.0, 3.0, 0.0, 2.0, 3),  # one at its last message does not
    (1.0, 0.0, 3.2, 0.0, 2.0, 3),  # nor one just before it (within half a period)
    (1.0, 0.3, 3.0, 1.0, 2.0, 2),  # nor one before the first message (sources not on)
    (0.8, 0.0, 2.9743, None, None, 3),  # nothing sent: the fewest any phase puts there
]


@pytest.mark.parametrize(("period", "start", "end", "first", "last", "n"), EXPECTED)
def test_expected_releases(
    period: float, start: float, end: float, first: float | None, last: float | None, n: int
) -> None:
    assert expected_releases(period, start, end, first, last) == n


# A stream whose output declares its rate (a CAN message received at its cycle time) expects
# nothing before its first value: graphs/can.yaml's chassis.WheelSpeeds (stamps from its
# MCAP) begins a cycle after the session, whose sender had no value at its first cycle, and
# showed "missing 1" on a complete stream.
OWN_RATE = [
    (0.01, 0.0, 2.99029, 0.010291, 2.990260, 299, 300),
    (1.0, 0.0, 3.0, 1.0, 2.0, 2, 3),  # within its span and at its end as any stream
]


@pytest.mark.parametrize(("period", "start", "end", "first", "last", "own", "grid"), OWN_RATE)
def test_a_stream_of_a_declared_rate_expects_nothing_before_its_first_value(
    period: float, start: float, end: float, first: float, last: float, own: int, grid: int
) -> None:
    assert expected_releases(period, start, end, first, last, before_first=False) == own
    assert expected_releases(period, start, end, first, last) == grid


def _without(stamps: dict[str, list[float]], topic: str, *index: int) -> dict[str, list[float]]:
    out = dict(stamps)
    out[topic] = [t for i, t in enumerate(stamps[topic]) if i not in index]
    return out


@pytest.mark.parametrize(
    ("topic", "lost", "missing"),
    [
        ("bgoal.detection", (7,), 1),  # a gap in the middle
        ("bgoal.detection", (6, 7, 8), 3),
        ("bpost.detection", (0,), 1),  # its first release: 0.1 s into the session
        ("bpost.detection", (3,), 1),  # its last: 0.45 s before the session's end
        ("line.detection", (0,), 1),  # on the session's very first omni tick
        ("omni_cam.frame", (30,), 1),
        ("ypost.detection", (0, 1, 2, 3), 3),  # nothing at all: at least 3 of 4 counted
    ],
)
def test_a_genuine_loss_is_still_missing(topic: str, lost: tuple[int, ...], missing: int) -> None:
    releases = _releases(ORIGIN + 0.010, ORIGIN + 3.010)
    by = _report(_without(releases, topic, *lost))
    assert by[topic] == (
        len(releases[topic]) - len(lost) + missing,
        len(releases[topic]) - len(lost),
        missing,
    )
    assert [t for t, (_, _, m) in by.items() if m] == [topic]  # the others unchanged


def test_a_value_from_before_a_live_start_expects_nothing_else_before_it() -> None:
    """A session started from the live view at ``started``: a tracker's value released
    before it and still on its way is recorded with its frame's (earlier) stamp; the frames
    of that time were published before the session and could not be."""
    releases = _releases(ORIGIN + 0.010, ORIGIN + 3.010)
    started = releases["omni_cam.frame"][4] + 0.001  # omni tick 5 is the first one recorded
    recorded = {t: [s for s in v if s >= started] for t, v in releases.items()}
    recorded["bgoal.detection"].insert(0, releases["omni_cam.frame"][1])  # tick 1, in flight
    by = _report(recorded, started=started)
    assert by["omni_cam.frame"] == (55, 55, 0)
    assert by["front_cam.frame"][2] == 0
    assert by["bgoal.detection"] == (15, 15, 0)  # 14 from the start on, and the one on its way
    assert _report(recorded)["omni_cam.frame"] == (59, 55, 4)  # from the old stamp on: wrong


# --- an audio stream: graphs/avsync.yaml's mic beside its two cameras -------------------------
#
# `flowrt record graphs/avsync.yaml --duration 8` said `mic.audio expected 374 received 373
# missing 1` (233/232 at 5 s) on a complete stream: a block is stamped at its first sample and
# published once complete, one or two blocks later, so on stamps alone the grid's point after
# the last block (published after the cameras' last frame, never made) fell more than half a
# block before that frame's stamp. The recorder hands the report each audio stream's lead.

BLOCK = 1024 / 48000  # nodes/audio.py: 1024 samples at 48 kHz, its timer's period
LEDS = {"led.frame": (1 / 30, 0.0), "led2.frame": (1 / 30, 0.004)}  # timer, phase (seconds)


def _audio(
    on: float, off: float, first_late: float, late: tuple[float, ...], jitter: float
) -> list[tuple[float, float]]:
    """(stamp, publication) of each block of nodes/audio.py's synthetic source.

    Its timer armed at ``on`` fires first at ``a``; the first activation reads the clock
    ``first_late`` after it (t0) and publishes nothing; block ``k`` holds the samples from
    ``t0 + k * BLOCK`` and is published at the first activation (``a + n * BLOCK``, read
    ``late[n % len(late)]`` after it) at which it is complete: the next one or the one after.
    Nothing from ``off`` on. Stamps off by -jitter, 0, +jitter in turn: a microphone's blocks
    are stamped when drained.
    """
    a, _ = next_release(ORIGIN, BLOCK, 0.0, on)
    t0 = a + first_late
    out: list[tuple[float, float]] = []
    n = 1
    while (act := a + n * BLOCK + late[n % len(late)]) < off:
        while t0 + (len(out) + 1) * BLOCK <= act + 1e-9:
            k = len(out)
            out.append((t0 + k * BLOCK + jitter * (k % 3 - 1), act))
        n += 1
    return out


def _av_report(
    on: float,
    off: float,
    first_late: float,
    late: tuple[float, ...],
    jitter: float,
    lost: tuple[int, ...] = (),
    leads: bool = True,
) -> dict[str, tuple[int | None, int, int]]:
    """topic -> (expected, received, missing) of the session's cameras and microphone, the
    blocks ``lost`` not received; the audio's lead as the recorder gives it (the largest lag
    of its last LAGS_KEPT blocks), or none (``leads=False``: on stamps alone)."""
    on, off = ORIGIN + on, ORIGIN + off
    streams = {}
    for topic, (period, phase) in LEDS.items():
        t, _ = next_release(ORIGIN, period, phase, on)
        n = math.ceil((off - t) / period)
        streams[topic] = StreamCounters(
            topic, topic, received=n, written=n, first_seen=t, last_seen=t + (n - 1) * period
        )
    blocks = [b for i, b in enumerate(_audio(on, off, first_late, late, jitter)) if i not in lost]
    streams["mic.audio"] = StreamCounters(
        "mic.audio", "mic.audio", received=len(blocks), written=len(blocks),
        first_seen=blocks[0][0], last_seen=blocks[-1][0],
    )  # fmt: skip
    lead = {"mic.audio": max(r - s for s, r in blocks[-LAGS_KEPT:])} if leads else None
    rates = {"led": 30.0, "led2": 30.0, "mic": 1 / BLOCK}
    report = build_report(_Written(streams), "rec_001", "t", off - on, rates, None, lead)
    return {s.topic: (s.expected, s.received, s.missing) for s in report.streams}


# (sources on, sources off, first activation's lateness, the others', stamp jitter): seconds;
# and what the report said on stamps alone (missing)
AV_SESSIONS = [
    # each block published two activations on: the first activation ran later than the rest
    (0.0003, 8.0003, 0.001, (0.0001,), 0.0, 1),
    (0.0043, 5.0043, 0.001, (0.0001,), 0.0, 2),
    (0.0163, 8.0163, 0.0002, (0.0001, 0.0004), 0.0, 1),  # blocks published two at a time
    (0.0343, 8.0343, 0.0002, (0.0001, 0.0004), 0.0, 2),
    (0.0363, 3.1363, 0.0002, (0.0001, 0.0004), 0.0, 2),
    (0.0203, 5.0203, 0.0005, (0.0, 0.0009, 0.0002), 0.004, 1),  # and stamps a few ms apart
    (0.0083, 5.0083, 0.0005, (0.0, 0.0009, 0.0002), 0.004, 2),
    (0.0263, 5.0263, 0.001, (0.0001,), 0.003, 1),
    (0.0063, 5.0063, 0.0, (0.0,), 0.0, 1),  # each block published at the next activation
    (0.0383, 8.0383, 0.0, (0.0,), 0.002, 1),
    (0.0003, 5.0003, 0.0, (0.0,), 0.0, 0),
]


@pytest.mark.parametrize(("on", "off", "first_late", "late", "jitter", "before"), AV_SESSIONS)
def test_a_complete_audio_stream_misses_nothing(
    on: float, off: float, first_late: float, late: tuple[float, ...], jitter: float, before: int
) -> None:
    by = _av_report(on, off, first_late, late, jitter)
    n = len(_audio(ORIGIN + on, ORIGIN + off, first_late, late, jitter))
    assert by["mic.audio"] == (n, n, 0)
    assert [t for t, (_, _, m) in by.items() if m] == []
    stamps_alone = _av_report(on, off, first_late, late, jitter, leads=False)
    assert stamps_alone["mic.audio"] == (n + before, n, before)  # the report before the fix


def test_the_repro_recording_is_complete() -> None:
    """Stamps of `flowrt record graphs/avsync.yaml --duration 8` from its MCAP (seconds from
    its first message): 373 blocks, the last 36 ms before the session's last message;
    nodes/audio.py published each block 1.95 blocks after its stamp (a probe's figures)."""
    stamps = {  # topic: (first, last, count)
        "mic.audio": (0.0, 7.935999744, 373),
        "led.frame": (0.001303296, 7.968080384, 240),
        "led2.frame": (0.00529664, 7.971932672, 240),
        "pair.set": (0.006184448, 7.97221632, 240),
    }
    streams = {
        t: StreamCounters(t, t, received=n, written=n, first_seen=a, last_seen=b)
        for t, (a, b, n) in stamps.items()
    }
    rates = {"led": 30.0, "led2": 30.0, "mic": 1 / BLOCK, "pair.set": None}
    (mic,) = (
        s
        for s in build_report(_Written(streams), "r", "t", 8.3, rates).streams
        if s.topic == "mic.audio"
    )
    assert (mic.expected, mic.missing) == (374, 1)  # on stamps alone
    report = build_report(
        _Written(streams), "r", "t", 8.3, rates, None, {"mic.audio": 1.95 * BLOCK}
    )
    by = {s.topic: (s.expected, s.received, s.missing) for s in report.streams}
    assert by["mic.audio"] == (373, 373, 0)
    assert by["led.frame"] == (240, 240, 0)


@pytest.mark.parametrize(
    ("session", "lost", "missing"),
    [
        (0, (100,), 1),  # a block in the middle
        (2, (100,), 1),  # published two at a time: one of a pair
        (2, (100, 101), 2),  # the pair
        (5, (100, 101, 102), 3),  # stamps a few ms apart
        (8, (200, 201), 2),
        (3, (1,), 1),  # the second block
        (0, (0,), 1),  # the first: a frame came before its stamp
        (1, (-1,), 1),  # the last: due more than half a block before the end
        (0, (-1,), 0),  # due in the stream's lag and half a block before the end: unseen
        (1, (-2, -1), 2),
        (7, (-3, -2, -1), 2),
    ],
)
def test_a_genuine_audio_loss_is_still_missing(
    session: int, lost: tuple[int, ...], missing: int
) -> None:
    on, off, first_late, late, jitter, _ = AV_SESSIONS[session]
    n = len(_audio(ORIGIN + on, ORIGIN + off, first_late, late, jitter))
    lost = tuple(i % n for i in lost)
    by = _av_report(on, off, first_late, late, jitter, lost)
    assert by["mic.audio"] == (n - len(lost) + missing, n - len(lost), missing)
    assert [t for t, (_, _, m) in by.items() if m] == (["mic.audio"] if missing else [])


def test_the_mean_rate_comes_from_the_intervals_the_min_and_max_do() -> None:
    """After a killed writer process the file's recount made ``written`` fewer than the
    messages timed: Hz mean 14.55 beside Hz min 19.85."""
    from flowrt.recording.report import _stream
    from flowrt.recording.writer.threads import count_written

    c = StreamCounters("cam.frame", "cam.frame")
    for k in range(21):  # 20 Hz for 1 s
        count_written(c, k * 0.05, 100)
    c.received = 21
    c.written = 15  # recounted from the file
    r = _stream(c, 20.0, (0.0, 1.0))
    assert r.rate_min is not None
    assert r.rate_max is not None
    assert r.rate_mean is not None
    assert r.rate_min <= r.rate_mean <= r.rate_max
    assert r.rate_mean == pytest.approx(20.0)
