"""``flowrt sync measure SESSION --video TOPIC --audio TOPIC``: the measured lag between two
sensors of a recording, from a flashing LED and a beeping speaker (or two cameras seeing one
LED). The estimator is :mod:`flowrt.analysis.avsync`; this reads the recording."""

from __future__ import annotations

import argparse
import importlib.util
import math
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from ..recording.session import not_a_recording
from .common import EXIT_BAD_GRAPH, EXIT_FAILED, EXIT_OK, printable, stdout_console
from .json_output import emit
from .replay import _files

NO_MATPLOTLIB = "--plot needs matplotlib (pip install matplotlib)"


def _read(path: Path, topics: set[str]) -> dict[str, list[tuple[float, Any]]]:
    """(Unix time, value) per topic, in order: images as their mean brightness, audio as
    (first channel's samples, rate). Any recording a replay reads: flowrt's own (protobuf
    images and audio) or a ROS 2 bag (CDR ``sensor_msgs/Image``, ``flowrt_msgs/AudioBlock``,
    which only the protobuf ones were read as: "no image or audio messages")."""
    from ..recording.decoding import MessageDecoder
    from ..recording.reader import iter_session
    from ..recording.session import mcap_files

    decoder = MessageDecoder()
    out: dict[str, list[tuple[float, Any]]] = {t: [] for t in topics}
    for m in iter_session(mcap_files(path), topics, []):
        if m.schema is None or decoder.why_not(m.encoding, m.schema) is not None:
            continue
        d = decoder.decode(m.encoding, m.schema, m.data)
        if d.kind == "image":
            px = d.value[0]
            t = d.stamp / 1e9 if d.stamp else m.log_time / 1e9
            out[m.topic].append((t, float(px.mean()) if px.size else 0.0))
            continue
        block = _audio_block(decoder, m, d)
        if block is not None:
            out[m.topic].append((block.timestamp, (block.samples[:, 0], block.rate)))
    return out


def _audio_block(decoder: Any, m: Any, d: Any) -> Any:
    """The audio block of a message, protobuf ``foxglove.RawAudio`` or a ROS 2 bag's
    ``flowrt_msgs/AudioBlock`` (restored as the replay restores it), in Unix time; None for
    anything else."""
    from ..audio import AudioBlock
    from ..recording.encoding import AUDIO_SCHEMA
    from ..recording.ros2_profile import value_restorer

    if d.kind == "audio" and m.schema.name == AUDIO_SCHEMA:
        return decoder.own.audio(m.schema, m.data, m.sequence, 0.0)  # Unix time kept
    restore = value_restorer(m.schema.name, m.schema.encoding, m.schema.data)
    block = restore(d.value) if d.kind == "value" and restore is not None else None
    return block if isinstance(block, AudioBlock) else None


def _video(rows: list[tuple[float, float]]) -> list[float]:
    from ..analysis.avsync import video_onsets

    if len(rows) < 2:
        return []
    t = [r[0] for r in rows]
    exposure = float(np.median(np.diff(t)))  # a frame integrates light over its period
    return video_onsets(t, [r[1] for r in rows], exposure)


def _audio(rows: list[tuple[float, Any]]) -> list[float]:
    from ..analysis.avsync import audio_onsets

    if not rows:
        return []
    times = np.concatenate([t + np.arange(len(s)) / rate for t, (s, rate) in rows])
    samples = np.concatenate([s for _, (s, _) in rows])
    return audio_onsets(times, samples)


def _missing(path: Path, topic: str) -> str:
    """Why ``topic`` gave nothing: not a stream of the recording (its streams named), or
    one without images or audio."""
    from ..recording.reader import scan_session

    topics = sorted({st.topic for st in scan_session(path).streams})
    if topic not in topics:
        return (
            f"no stream {printable(topic)!r} in {printable(str(path))} (streams: "
            + (", ".join(printable(t) for t in topics) or "none")
            + ")"
        )
    return f"{printable(topic)}: no image or audio messages in {printable(str(path))}"


def _named(path: Path, topic: str) -> str:
    """``topic`` as the recording names it: a ROS 2 bag names ``led.frame`` ``/led/frame``
    (its channel's ``source`` keeps the flowrt name), and the replay takes either."""
    from ..recording.reader import scan_session
    from ..recording.ros2_profile import ros2_topic

    streams = scan_session(path).streams
    if any(st.topic == topic for st in streams):
        return topic
    for st in streams:
        if st.source == topic or st.topic == ros2_topic(topic):
            return st.topic
    return topic


MIN_EVENTS = 2
"""Paired events below which a lag is not reported as measured (exit 1): with one onset in
each stream, any pair was accepted (a lag of -3874 ms between two cameras, exit 0); two
pairs at least agree or not (their spread, ``std_ms``)."""


def cmd_measure(args: argparse.Namespace) -> int:
    from ..analysis.avsync import measure_lag

    err = Console(stderr=True, highlight=False, soft_wrap=True)
    path = Path(args.session)
    files = _files(args.session, err, "sync measure")  # (no such file, no .mcap in it)
    if files is None:
        return EXIT_BAD_GRAPH
    for f in files:
        if (why := not_a_recording(f)) is not None:  # a video file given for a recording
            err.print(f"flowrt sync measure: {printable(str(f))}: {why}", markup=False)
            return EXIT_BAD_GRAPH
    videos = list(args.video or [])
    if len(videos) != (1 if args.audio else 2):  # (a third stream was ignored, silently)
        err.print(
            "flowrt sync measure: give --video TOPIC --audio TOPIC, or --video A --video B",
            markup=False,
        )
        return EXIT_BAD_GRAPH
    if args.plot and importlib.util.find_spec("matplotlib") is None:  # said before the work
        err.print(f"flowrt sync measure: {NO_MATPLOTLIB}", markup=False)
        return EXIT_BAD_GRAPH
    videos[0], other = (_named(path, t) for t in (videos[0], args.audio or videos[1]))
    data = _read(path, {videos[0], other})
    wanted = {videos[0]: "video", other: "audio" if args.audio else "video"}
    for topic, kind in wanted.items():
        if not data[topic]:
            err.print(f"flowrt sync measure: {_missing(path, topic)}", markup=False)
            return EXIT_BAD_GRAPH
        found = "audio" if isinstance(data[topic][0][1], tuple) else "video"
        if found != kind:
            flag = "--audio takes an audio topic" if kind == "audio" else "--video takes images"
            err.print(
                f"flowrt sync measure: {printable(topic)} is {found}, not {kind} ({flag})",
                markup=False,
            )
            return EXIT_BAD_GRAPH
    ref = _video(data[videos[0]])
    oth = _audio(data[other]) if args.audio else _video(data[other])
    report = measure_lag(ref, oth)
    if args.json:
        emit({k: (None if isinstance(v, float) and math.isnan(v) else v)
                          for k, v in report.json().items()})  # fmt: skip
    else:
        _show(stdout_console(), videos[0], other, report, len(ref), len(oth))
    if args.plot and report.events:
        problem = _plot(report, args.plot, other)
        if problem:
            err.print(f"flowrt sync measure: {problem}", markup=False)
            return EXIT_BAD_GRAPH
    # a verdict, as nothing paired is (exit 1 with the result, said with it: not an error)
    return EXIT_OK if report.events >= MIN_EVENTS else EXIT_FAILED


def _show(console: Console, ref: str, other: str, r: Any, n_ref: int, n_other: int) -> None:
    console.print(
        f"lag of {printable(other)} against {printable(ref)} (positive: {printable(other)} late)",
        markup=False,
    )
    console.print(
        f"onsets: {n_ref} in {ref}, {n_other} in {other}; paired {r.events}", markup=False
    )
    if not r.events:
        console.print("no event could be paired", style="red")
        return
    if r.events < MIN_EVENTS:  # any single pair is "paired": no measure of a lag
        console.print(
            f"only {r.events} event(s) paired: too few to measure a lag (at least {MIN_EVENTS}; "
            "record longer, or check that both streams see them)",
            style="red",
            markup=False,
        )
        return
    console.print(
        f"lag mean {r.lag_ms:.2f} ms  min {r.min_ms:.2f}  max {r.max_ms:.2f}  "
        f"std {r.std_ms:.2f}  events {r.events}",
        markup=False,
    )
    lo, hi = min(r.lags_ms), max(r.lags_ms)
    span = max(hi - lo, 1e-6)
    width = 40
    console.print("lag per event (ms):", markup=False)
    t0 = r.times[0]
    for t, lag in zip(r.times, r.lags_ms, strict=True):
        bar = "#" * (1 + round((lag - lo) / span * (width - 1)))
        console.print(f"  {t - t0:7.2f} s  {lag:8.2f}  {bar}", markup=False)


def _plot(r: Any, path: str, other: str) -> str | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return NO_MATPLOTLIB
    fig, ax = plt.subplots(figsize=(8, 3))
    t0 = r.times[0]
    ax.plot([t - t0 for t in r.times], r.lags_ms, "o-")
    ax.axhline(r.lag_ms, linestyle="--")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"lag of {other} (ms)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return None


def add_parsers(sub: Any) -> None:
    s = sub.add_parser("sync", help="sensors in sync: measure the lag between two streams")
    what = s.add_subparsers(dest="sync_command", required=True)
    m = what.add_parser(
        "measure", help="lag of an audio (or second video) stream against a video stream"
    )
    m.add_argument("session", help="a session folder or an .mcap file")
    m.add_argument(
        "--video", action="append", metavar="TOPIC", help="the LED camera (twice: camera B)"
    )
    m.add_argument("--audio", metavar="TOPIC", help="the microphone hearing the beeps")
    m.add_argument("--json", action="store_true", help="print one JSON document")
    m.add_argument("--plot", metavar="PNG", help="also plot the lag per event (matplotlib)")
    m.set_defaults(func=cmd_measure)
