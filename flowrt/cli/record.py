"""``flowrt record``, ``flowrt info`` and ``flowrt replay``: MCAP sessions from the CLI.

- ``record GRAPH -o DIR``: the graph with a ``recorder`` node added on the chosen outputs
  (lossless edges), into the next free session ``DIR/NAME_NNN/``; the per-stream table at
  the end. Bad arguments (an unwritable folder, a topic pattern matching nothing) are one
  line and exit 2 before anything runs.
- ``info PATH``: what a session or file holds, whether it was closed cleanly, ``--repair``.
- ``replay PATH``: the recorded streams stand in for the graph's sources of the same names.

The recorder and replay node classes are found through the node registry, like any kind.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import errno
import fnmatch
import itertools
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.text import Text

from ..recording.session import not_a_recording
from .common import (
    EXIT_BAD_GRAPH,
    EXIT_FAILED,
    EXIT_OK,
    load,
    positive_float_arg,
    printable,
    seconds_arg,
    stdout_console,
)
from .json_output import emit
from .recorders import graph_outputs, select_outputs, split_patterns, with_recorder
from .replay import _files, cmd_replay
from .run import add_run_options, run_graph

# --- record ------------------------------------------------------------------------------


def _image_formats(text: str | None, topics: list[str]) -> dict[str, str] | str:
    """``jpeg`` (every image stream) or ``front_cam.frame=jpeg,omni_cam.frame=png``."""
    out: dict[str, str] = {}
    for part in split_patterns(text):
        pattern, eq, fmt = part.rpartition("=")
        if not eq:
            pattern, fmt = "*", part
        if fmt not in ("raw", "jpeg", "png"):
            return f"--images {part!r}: the format is raw, jpeg or png"
        matched = [t for t in topics if fnmatch.fnmatchcase(t, pattern)]
        if not matched:
            return f"--images {part!r}: {pattern!r} matches no recorded stream"
        out.update(dict.fromkeys(matched, fmt))
    return out


def _split_policy(args: argparse.Namespace) -> Any:
    """The ``--split-size`` / ``--split-duration`` policy, or the one-line reason it is bad."""
    from ..recording.split import SplitPolicy, parse_duration, parse_size

    try:
        size = None if args.split_size is None else parse_size(args.split_size)
    except ValueError as e:
        return f"--split-size {e}"
    try:
        duration = None if args.split_duration is None else parse_duration(args.split_duration)
    except ValueError as e:
        return f"--split-duration {e}"
    return SplitPolicy(size, duration)


def cmd_record(args: argparse.Namespace) -> int:
    err = Console(stderr=True, highlight=False, soft_wrap=True)
    graph = load(args.file, err)
    if graph is None:  # before the folder is made: a wrong path leaves nothing behind
        return EXIT_BAD_GRAPH
    made = _missing_folders(Path(args.output))  # what a record that never starts removes
    try:
        return _record(args, graph, err)
    finally:  # stopped before it began (a bad option, a taken port): nothing left behind
        _remove_empty(made)


def _record(args: argparse.Namespace, graph: Any, err: Console) -> int:
    from ..graph._resolve import resolve
    from ..recording import check_writable, new_session

    problem = check_writable(args.output)
    if problem is not None:
        err.print(f"flowrt record: {problem}", markup=False)
        return EXIT_BAD_GRAPH
    outputs = graph_outputs(graph)
    topics, unmatched = select_outputs(outputs, split_patterns(args.topics))
    if unmatched:
        err.print(
            f"flowrt record: --topics {', '.join(map(repr, unmatched))} matches no output "
            f"of {args.file} (outputs: {', '.join(outputs)})",
            markup=False,
        )
        return EXIT_BAD_GRAPH
    split = _split_policy(args)
    if isinstance(split, str):
        err.print(f"flowrt record: {split}", markup=False)
        return EXIT_BAD_GRAPH
    if args.writer == "thread" and args.writer_priority != "normal":
        err.print("flowrt record: --writer-priority idle needs --writer process", markup=False)
        return EXIT_BAD_GRAPH
    if args.profile == "ros2" and args.deterministic:
        err.print("flowrt record: --deterministic needs the flowrt profile", markup=False)
        return EXIT_BAD_GRAPH
    images = _image_formats(args.images, topics)
    if isinstance(images, str):
        err.print(f"flowrt record: {images}", markup=False)
        return EXIT_BAD_GRAPH
    try:
        session = new_session(args.output, args.name)
    except (ValueError, OSError) as e:
        err.print(f"flowrt record: {_no_space(e)}", markup=False)
        return EXIT_BAD_GRAPH
    params = {
        # absolute: -o is relative to where the command runs, not to the graph file
        "session": str(Path(session).resolve()),
        "path": str(Path(args.output).resolve()),  # where a session started later goes
        "name": args.name,
        "graph_file": str(Path(args.file).resolve()),
        "images": images,
        "compression": args.compression,
        "crc": not args.no_crc,
        "writer": args.writer,
        "writer_priority": args.writer_priority,
        "annotations": not args.no_annotations,
        "split_size": split.size,
        "split_duration": split.duration,
        "log_report": False,  # printed below, once
        "deterministic": args.deterministic,
        "profile": args.profile,
    }
    try:
        # relative paths of the graph resolve beside its file, as when it was loaded
        base_dir = Path(args.file).resolve().parent
        rgraph = resolve(with_recorder(graph.spec, topics, params), base_dir=base_dir)
    except Exception as e:  # a recorder the graph cannot take: say so, leave no empty session
        _remove_empty([session])
        err.print(f"flowrt record: {e}", markup=False)
        return EXIT_BAD_GRAPH
    rgraph.file = graph.file
    recorder = next(n for n in rgraph.spec.nodes if n not in graph.spec.nodes)
    console = stdout_console()

    def started(run_console: Console) -> None:  # said once true: the recorder's file is open
        run_console.print(
            f"recording {len(topics)} stream(s) into {session}", highlight=False, soft_wrap=True
        )

    result: dict[str, Any] = {"session": str(session)}

    def report(rt: Any) -> int:
        return _report_all(console, err, _sessions(rt, recorder, session) or [session], result)

    try:
        return run_graph(
            rgraph,
            args,
            err,
            prog="flowrt record",
            settle=wait_for_writers,
            after=report,
            result=result,
            started=started,
        )
    finally:  # stopped before it began (a taken port, a bad option): no empty session
        _remove_empty([session])


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first."""
    out: list[Path] = []
    for p in [path, *path.absolute().parents]:
        if p.exists():
            break
        out.append(p)
    return out


def _remove_empty(folders: list[Path]) -> None:
    """Remove each folder (deepest first) that exists and is empty: a record that never
    started leaves nothing behind (issue 43 item 4)."""
    for folder in folders:
        with contextlib.suppress(OSError):
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()


def _no_space(e: Exception) -> str:
    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{e.filename or 'the output folder'}: no space left on device (the disk is full)"
    return str(e)


def _sessions(rt: Any, recorder: str, first: Path) -> list[Path]:
    """Every session the recorder made, in order: a ``flowrt ctl record stop`` then
    ``start`` makes a second one, which the end's table and ``--json`` left out."""
    reports = rt.stats().reports.get(recorder)
    if not isinstance(reports, list):
        return []
    out: list[Path] = []
    for r in reports:
        files = r.get("files") if isinstance(r, dict) else None
        if isinstance(files, list) and files and isinstance(files[0], str):
            out.append(Path(files[0]).parent)  # (absolute: the recorder's path is)
        elif isinstance(r, dict) and isinstance(r.get("session"), str):
            out.append(first.parent / r["session"])
    return out


def _report_all(
    console: Console, err: Console, sessions: list[Path], result: dict[str, Any]
) -> int:
    """:func:`_report` for each session; ``--json``'s ``recording`` is the first's (as it
    was), ``recordings`` every one's."""
    code = EXIT_OK
    reports: list[Any] = []
    for session in sessions:  # (each table names its session)
        one: dict[str, Any] = {}
        code = max(code, _report(console, err, session, one))
        if "recording" in one:
            reports.append(one["recording"])
    if reports:
        result["recording"] = reports[0]
        result["recordings"] = reports
    return code


def _report(
    console: Console, err: Console, session: Path, result: dict[str, Any] | None = None
) -> int:
    """The per-stream table once the files are finished; exit 1 on any loss. ``result``
    (the ``--json`` document) gets the report."""
    if not session.is_dir() or not any(session.iterdir()):  # it never started (the run's
        return EXIT_OK  # verdict says why): nothing to report, and the folder goes
    from ..recording import RecordingReport, report_table
    from ..recording.session import SESSION_FILE

    report_path = session / SESSION_FILE
    if not report_path.exists():
        err.print(f"flowrt record: {session}: the recording did not finish", markup=False)
        return EXIT_FAILED
    try:
        report = RecordingReport.model_validate_json(report_path.read_text())
    except (OSError, ValueError) as e:  # a disk that filled up as it was written
        err.print(
            f"flowrt record: {session}: the recording's report is unreadable "
            f"({_no_space(e) if isinstance(e, OSError) else 'not valid JSON'})",
            markup=False,
        )
        return EXIT_FAILED
    if result is not None:
        result["recording"] = report.model_dump(mode="json")
    console.print(report_table(report, console.width))
    if report.error:
        err.print(f"flowrt record: recording stopped early: {report.error}", markup=False)
        return EXIT_FAILED
    if report.lost:
        err.print(f"flowrt record: {report.lost} message(s) lost", markup=False)
        return EXIT_FAILED
    return EXIT_OK


def wait_for_writers() -> None:
    """Until every MCAP file of this process is finished (a slow disk may still be writing)."""
    import threading

    from ..recording.writer import THREAD_PREFIX

    for t in threading.enumerate():
        if t.name.startswith(THREAD_PREFIX):
            t.join()


# --- info --------------------------------------------------------------------------------


def _when(t: float | None) -> str:
    if t is None:
        return "-"
    return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="milliseconds")


def _hz(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def print_info(
    console: Console, info: Any, streams_only: bool = False, show_graph: bool = False
) -> None:
    """One file: whether it is whole, its streams, metadata, attachments and graph."""

    from ..monitors._columns import Column, fit_table
    from ..recording.inuse import being_recorded
    from ..recording.report import human_bytes

    if not streams_only:
        console.print(
            Text(printable(str(info.path)), style="bold") + f"  {human_bytes(info.size)}",
            highlight=False,
        )
        if info.closed_cleanly:
            how = (  # a rosbag2 SQLite3 file has no MCAP summary: what was read, in its words
                "its SQLite3 database read"
                if Path(info.path).suffix == ".db3"
                else "summary and index read"
            )
            console.print(f"closed cleanly: yes ({how})", highlight=False)
        elif being_recorded(info.path):  # no summary yet: not damaged
            console.print(
                Text("still being recorded", style="bold yellow")
                + f": read so far, {info.messages} messages in {info.chunks} chunks",
                highlight=False,
            )
        else:
            why = info.damage or "no summary"
            console.print(
                Text("NOT closed cleanly", style="bold red")
                + f": {printable(why)}"
                + (f" at byte {info.damage_offset}" if info.damage_offset is not None else "")
                + f"; recovered {info.messages} messages in {info.chunks} chunks"
                + _repair_hint(Path(info.path)),
                highlight=False,
            )
        console.print(
            f"start {_when(info.start)}  end {_when(info.end)}  duration {info.duration:.3f} s"
            f"  messages {info.messages}  chunks {info.chunks}",
            highlight=False,
        )

    def gaps(s: Any) -> Text:
        if not s.gaps:
            return Text("0")
        longest = max(g.length for g in s.gaps)
        return Text(f"{len(s.gaps)} (longest {longest * 1000:.0f} ms)", style="red")

    cols: tuple[Column[Any], ...] = (
        Column("stream", lambda s: Text(printable(s.topic)), right=False),
        Column("schema", lambda s: Text(printable(s.schema_name)), drop=3, right=False),
        Column("count", lambda s: str(s.count)),
        Column("Hz mean", lambda s: _hz(s.rate_mean), drop=4),
        Column("Hz min", lambda s: _hz(s.rate_min), drop=1),
        Column("Hz max", lambda s: _hz(s.rate_max), drop=2),
        Column("gaps", gaps),
        Column("size", lambda s: human_bytes(s.bytes), drop=5),
    )
    t = fit_table(cols, info.streams, console.width)
    console.print(t)
    for line in _audio_lines(info):
        console.print(line, markup=False, highlight=False)
    for name, meta in info.metadata.items():
        console.print(
            printable(
                f"metadata {name}: " + ", ".join(f"{k}={_short(v)}" for k, v in meta.items())
            ),
            highlight=False,
            markup=False,
        )
    if info.attachments:
        console.print(printable("attachments: " + ", ".join(info.attachments)), markup=False)
    if info.graph and show_graph:
        console.print("recorded graph:", style="bold")
        console.print(printable(info.graph.rstrip()), markup=False, highlight=False, soft_wrap=True)
    elif info.graph:
        lines = len(info.graph.strip().splitlines())
        console.print(
            f"recorded graph: {lines} lines (flowrt info --graph prints it)", highlight=False
        )


def _short(value: str) -> str:
    """A metadata value on one line (rosbag2 keeps a copy of metadata.yaml in one)."""
    lines = value.splitlines()
    return value if len(lines) < 2 else f"({len(lines)} lines of text)"


def _audio_lines(info: Any) -> list[str]:
    """Per foxglove.RawAudio stream: its rate and channels (from its first block) and the
    blocks lost (sequence gaps of the recorded blocks)."""
    from ..recording.encoding import Decoder
    from ..recording.reader import iter_messages

    audio = [s.topic for s in info.streams if s.schema_name == "foxglove.RawAudio"]
    lines = []
    decoder = Decoder()
    for topic in audio:
        rate = channels = 0
        seqs: list[int] = []
        for m in iter_messages(Path(info.path), {topic}):
            if not seqs and m.schema is not None:  # the first block says rate and channels
                msg = decoder.protobuf(m.schema, m.data)
                rate, channels = int(msg.sample_rate), int(msg.number_of_channels)
            seqs.append(int(m.sequence))
        lost = sum(max(0, b - a - 1) for a, b in itertools.pairwise(seqs))
        lines.append(
            f"audio {printable(topic)}: {rate} Hz, {channels} channel(s), {len(seqs)} blocks, "
            f"{lost} lost"
        )
    return lines


def print_session(console: Console, session: Any, show_graph: bool = False) -> None:
    """A session of several parts: its files, then the streams over all of them."""

    from ..monitors._columns import Column, fit_table
    from ..recording.report import human_bytes

    if len(session.files) == 1:
        print_info(console, session.files[0], show_graph=show_graph)
        return
    console.print(
        Text(printable(str(session.path)), style="bold")
        + f"  {len(session.files)} files  {human_bytes(session.size)}",
        highlight=False,
    )

    def clean(f: Any) -> Text:
        if f.closed_cleanly:
            return Text("yes")
        return Text(printable(f"NO: {f.damage or 'no summary'}"), style="bold red")

    file_cols: tuple[Column[Any], ...] = (
        Column("file", lambda f: Text(printable(Path(f.path).name)), right=False),
        Column("size", lambda f: human_bytes(f.size), drop=3),
        Column("start", lambda f: _when(f.start), drop=1, right=False),
        Column("duration", lambda f: f"{f.duration:.3f} s", drop=2),
        Column("messages", lambda f: str(f.messages)),
        Column("closed cleanly", clean, right=False),
    )
    files = fit_table(file_cols, session.files, console.width)
    console.print(files)
    console.print(
        f"start {_when(session.start)}  end {_when(session.end)}  "
        f"duration {session.duration:.3f} s  messages {session.messages}",
        highlight=False,
    )
    first = session.files[0]
    print_info(
        console,
        first.model_copy(update={"streams": session.streams}),
        streams_only=True,
        show_graph=show_graph,
    )


def _print_session_report(console: Console, path: Path) -> None:
    """A session's own post-recording table (expected / received / written / lost)."""
    from ..recording import RecordingReport, report_table
    from ..recording.session import SESSION_FILE

    report = path / SESSION_FILE
    if path.is_dir() and report.exists():
        try:
            console.print(
                report_table(RecordingReport.model_validate_json(report.read_text()), console.width)
            )
        except ValueError:
            console.print(f"{report}: unreadable", style="red", markup=False)


def _repair_hint(path: Path) -> str:
    """What ``--repair`` does for it: MCAP only (it refused the SQLite3 file it was offered)."""
    from ..recording.rosbag2 import is_db3

    return "" if is_db3(path) else " (flowrt info --repair rewrites the summary)"


def cmd_info(args: argparse.Namespace) -> int:
    from ..recording.inuse import being_recorded
    from ..recording.reader import scan, scan_session
    from ..recording.repair import repair

    err = Console(stderr=True, highlight=False, soft_wrap=True)
    console = stdout_console()
    files = _files(args.path, err, "info")
    if files is None:
        return EXIT_BAD_GRAPH
    for f in files:
        if (why := not_a_recording(f)) is not None:
            err.print(f"flowrt info: {f}: {why}", markup=False)
            return EXIT_BAD_GRAPH
    live = [f for f in files if being_recorded(f)]  # no summary yet: not damaged
    if args.repair:
        for f in files:
            if f in live:
                err.print(
                    f"flowrt info: {printable(str(f))}: cannot repair: still being recorded "
                    "(a recorder writes it; it is whole once that stops)",
                    markup=False,
                )
                return EXIT_FAILED
            if not scan(f).closed_cleanly:
                try:
                    fixed, kept, original = repair(f)
                except OSError as e:  # read-only folder, full disk: the original untouched
                    err.print(
                        f"flowrt info: {printable(str(f))}: cannot repair: "
                        f"{e.strerror or e} (the original is untouched)",
                        markup=False,
                    )
                    return EXIT_FAILED
                err.print(
                    f"flowrt info: {printable(str(fixed))}: rewritten with {kept} messages and "
                    f"a summary; the original is kept as {printable(original.name)}",
                    markup=False,
                )
    session = scan_session(args.path)
    if args.json:
        emit(session.model_dump(mode="json"))
    else:
        print_session(console, session, show_graph=args.graph)
        _print_session_report(console, Path(args.path))
    if live:
        err.print(
            f"flowrt info: {', '.join(printable(str(f)) for f in live)}: still being recorded "
            "(what is read so far; its summary comes when the recorder stops)",
            markup=False,
        )
    if session.missing:  # read as one recording with a long gap, exit 0, before
        err.print(
            f"flowrt info: {args.path}: {printable(session.damage or '')}: what it held is "
            "not in the recording",
            markup=False,
        )
        return EXIT_FAILED
    held = {f.resolve() for f in live}
    damaged = [i.path for i in session.files if not i.closed_cleanly]
    damaged = [d for d in damaged if Path(d).resolve() not in held]
    if damaged:
        err.print(
            f"flowrt info: {', '.join(damaged)} not closed cleanly (damaged or the recorder "
            "was killed)",
            markup=False,
        )
        return EXIT_FAILED
    return EXIT_OK


# --- replay ------------------------------------------------------------------------------


def add_parsers(sub: Any) -> None:
    rec = sub.add_parser("record", help="run a graph and record its outputs into an MCAP session")
    rec.add_argument("file", help="graph file")
    rec.add_argument("-o", "--output", default="recordings", help="sessions folder")
    rec.add_argument("--name", default="rec", help="session prefix: NAME_001, NAME_002 ...")
    rec.add_argument(
        "--topics",
        metavar="PATTERNS",
        help="outputs to record, comma-separated node.port patterns (default: every output)",
    )
    rec.add_argument(
        "--images",
        metavar="FORMATS",
        help="jpeg|png|raw for every image stream, or TOPIC=jpeg,... (default raw RawImage)",
    )
    rec.add_argument(
        "--compression",
        choices=("none", "lz4", "zstd"),
        default="none",
        help="chunk compression (default none: images are already compressed or raw)",
    )
    rec.add_argument(
        "--no-crc",
        action="store_true",
        help="no chunk CRCs: half the writer's CPU, but damage inside a chunk goes unseen",
    )
    rec.add_argument(
        "--writer",
        choices=("process", "thread"),
        default="process",
        help="where the files are written: a process of its own reading the frames from "
        "shared memory (default), or threads of the runtime's process",
    )
    rec.add_argument(
        "--writer-priority",
        choices=("normal", "idle"),
        default="normal",
        help="idle: the writer process takes only CPU time nobody else wants (the loop's "
        "timers never wait for it; under load it falls behind, counted)",
    )
    rec.add_argument(
        "--split-size",
        metavar="SIZE",
        help="start a new file past this size: 4GiB, 500MB, 1.5G",
    )
    rec.add_argument(
        "--split-duration",
        metavar="T",
        help="start a new file after this long: 10m, 30s, 1h",
    )
    rec.add_argument(
        "--no-annotations",
        action="store_true",
        help="do not also draw detections as foxglove.ImageAnnotations on their camera",
    )
    rec.add_argument(
        "--deterministic",
        action="store_true",
        help="also record every activation's inputs and a digest of every output, for "
        "flowrt replay --deterministic (the sources' values are recorded whatever --topics says)",
    )
    rec.add_argument(
        "--profile",
        choices=("flowrt", "ros2"),
        default="flowrt",
        help="ros2: a rosbag2 folder (metadata.yaml + MCAP of CDR messages, ros2msg schemas: "
        "sensor_msgs/Image, geometry_msgs/Twist, std_msgs...) that ROS 2 tools open",
    )
    add_run_options(rec)  # --duration, --realtime, --control ...: a recording is a run
    rec.set_defaults(func=cmd_record)

    info = sub.add_parser("info", help="what a recording holds (session folder or .mcap)")
    info.add_argument("path", help="a session folder or an .mcap file")
    info.add_argument("--json", action="store_true", help="machine-readable")
    info.add_argument("--graph", action="store_true", help="also print the recorded graph file")
    info.add_argument(
        "--repair", action="store_true", help="rewrite a file that was not closed cleanly"
    )
    info.set_defaults(func=cmd_info)

    rep = sub.add_parser("replay", help="replay a recording into a graph")
    rep.add_argument("path", help="session folder or .mcap file")
    rep.add_argument("--graph", help="run this graph, recorded streams replacing its sources")
    rep.add_argument(
        "--rate", type=positive_float_arg, default=1.0, help="playback speed (default 1.0)"
    )
    rep.add_argument("--loop", action="store_true", help="start over at the end")
    rep.add_argument("--start", type=seconds_arg, default=0.0, metavar="T", help="e.g. 10s")
    rep.add_argument("--topics", metavar="PATTERNS", help="streams to replay (default all)")
    rep.add_argument(
        "--trust-graph",
        action="store_true",
        help="run the graph stored in the recording (it imports the modules it names: only "
        "for recordings you trust); default: the recorded streams alone, or --graph",
    )
    rep.add_argument(
        "--deterministic",
        action="store_true",
        help="re-execute every recorded activation on recorded time, as fast as the CPU allows "
        "(a flowrt record --deterministic session; needs --graph or --trust-graph)",
    )
    rep.add_argument(
        "--inline",
        action="store_true",
        help="with --deterministic: every node on the event loop, whatever its placement",
    )
    add_run_options(rep)  # --duration, --no-ui, --stats-json, --control, --display-port ...
    rep._option_string_actions["--json"].help = (
        "print one JSON document on stdout at the end: the final statistics, or with "
        "--deterministic the replay's result"
    )
    rep._option_string_actions["--check"].help = (
        "with --deterministic: compare every output with its recorded digest, exit 1 at the "
        "first that differs; else refuse to start when flowrt check shows a missed deadline"
    )
    rep.set_defaults(func=cmd_replay)
