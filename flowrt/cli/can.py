"""``flowrt can analyse`` and ``flowrt can stats``: a CAN bus on paper and in a trace.

``analyse`` reads a CAN database (DBC, KDC, ARXML: whatever cantools reads) and prints the
analysis of :mod:`flowrt.analysis.can` (worst-case frame lengths, utilisation, worst-case
response times after Davis et al. 2007); exit 1 when a message can miss its deadline, 2
when the database does not load. ``stats`` reads a trace in any format python-can reads
(.asc, .blf, .log, .trc, .csv, .mf4, ...) and prints per identifier the count, mean period
and inter-arrival spread, and the bus load per second.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
from pathlib import Path
from typing import Any

from rich.console import Console

from ..columns import Column, fit_table
from .common import EXIT_BAD_GRAPH, EXIT_FAILED, EXIT_OK, stdout_console


class CanDatabaseError(Exception):
    """A CAN database that does not load; the message is one line naming the file."""


def load_database(path: str) -> Any:
    """A cantools database, or CanDatabaseError with one clear line (never a traceback)."""
    import cantools

    if not Path(path).is_file():
        raise CanDatabaseError(f"{path}: no such file")
    try:
        return cantools.database.load_file(path, strict=True)
    except Exception as e:  # cantools raises parser, value and key errors of several kinds
        text = " ".join(str(e).split()) or type(e).__name__
        raise CanDatabaseError(f"{path}: not a valid CAN database: {text}") from None


def _pairs(items: list[str] | None, flag: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name] = float(value.removesuffix("ms"))
        except ValueError:
            raise CanDatabaseError(f"{flag} {item!r}: expected NAME=MS") from None
    return out


def cmd_analyse(args: argparse.Namespace) -> int:
    from ..analysis.can import analyse_bus, timings_from_dbc

    err = Console(stderr=True, highlight=False)
    try:
        db = load_database(args.dbc)
        timings = timings_from_dbc(
            db,
            periods=_pairs(args.period, "--period"),
            deadlines=_pairs(args.deadline, "--deadline"),
            jitters=_pairs(args.jitter, "--jitter"),
        )
        if args.bitrate <= 0:
            raise CanDatabaseError(f"--bitrate must be positive, got {args.bitrate}")
        result = analyse_bus(timings, args.bitrate)
    except (CanDatabaseError, KeyError, ValueError) as e:
        err.print(str(e).strip("'\""), style="red", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        console = stdout_console()
        console.print(
            f"{args.dbc}: {len(result.messages)} messages at {args.bitrate} bit/s "
            "(worst-case stuffing, 3-bit interframe space; Davis et al. 2007)",
            style="italic",
            highlight=False,
        )
        t = _message_table(result.messages, console.width)
        console.print(t)
        console.print(
            f"bus: {result.bits_per_s:,.0f} bit/s of {args.bitrate:,} = "
            f"utilisation {100 * result.utilisation:.2f} %; schedulable: "
            f"{'yes' if result.schedulable else 'NO'}"
        )
        event = [m.name for m in result.messages if m.timing.period_ms is None]
        if event:
            console.print(
                f"not analysed (no GenMsgCycleTime; give --period NAME=MS): {', '.join(event)}",
                style="yellow",
            )
    return EXIT_OK if result.schedulable else EXIT_FAILED


def _ident(r: dict[str, Any]) -> str:
    return f"0x{r['id']:08X}x" if r["extended"] else f"0x{r['id']:03X}"


def _message_table(messages: Any, width: int) -> Any:
    """The analysis per message; at 80 columns the derived terms (B, J, busy, Q) go first."""

    def ident(m: Any) -> str:
        tm = m.timing
        return f"0x{tm.id:08X}x" if tm.extended else f"0x{tm.id:03X}"

    def wcrt(m: Any) -> str:
        ok = m.wcrt_ms is not None or m.timing.period_ms is None
        return _ms(m.wcrt_ms) if ok else "unbounded"

    cols: tuple[Column[Any], ...] = (
        Column("message", lambda m: m.name, right=False),
        Column("id", ident, right=False),
        Column("dlc", lambda m: str(m.timing.dlc), drop=5),
        Column("period ms", lambda m: _ms(m.timing.period_ms)),
        Column("bits", lambda m: str(m.frame_bits), drop=6),
        Column("C ms", lambda m: f"{m.c_ms:.3f}"),
        Column("B ms", lambda m: f"{m.blocking_ms:.3f}", drop=3),
        Column("J ms", lambda m: f"{m.timing.jitter_ms:g}", drop=4),
        Column("busy ms", lambda m: _ms(m.busy_period_ms), drop=1),
        Column("Q", lambda m: "-" if m.instances is None else str(m.instances), drop=2),
        Column("WCRT ms", wcrt),
        Column("deadline ms", lambda m: _ms(m.deadline_ms)),
        Column(
            "ok",
            lambda m: "-" if m.schedulable is None else ("yes" if m.schedulable else "NO"),
            right=False,
        ),
    )
    return fit_table(
        cols, messages, width, row_style=lambda m: "red" if m.schedulable is False else None
    )


def _ms_of(key: str) -> Any:
    return lambda r: _ms(r[key])


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def trace_stats(path: str, bitrate: int, db: Any = None) -> dict[str, Any]:
    """Per identifier count, mean period and inter-arrival spread; bus load per second.

    The load counts each frame at its worst-case stuffed length (the analysis' figure), so
    it is an upper bound of the load on the wire and comparable with ``can analyse``.
    """
    import can

    from ..analysis.can import frame_bits

    arrivals: dict[tuple[int, bool], list[float]] = {}
    dlcs: dict[tuple[int, bool], int] = {}
    bins: dict[int, int] = {}
    errors = 0
    first = last = None
    with can.LogReader(path) as reader:
        for msg in reader:
            t = float(msg.timestamp)
            first = t if first is None else min(first, t)
            last = t if last is None else max(last, t)
            if msg.is_error_frame:
                errors += 1
                continue
            key = (int(msg.arbitration_id), bool(msg.is_extended_id))
            arrivals.setdefault(key, []).append(t)
            dlc = min(int(msg.dlc), 8)
            dlcs[key] = dlc
            bins.setdefault(int(t), 0)
            bins[int(t)] += frame_bits(dlc, key[1])
    names: dict[tuple[int, bool], str] = {}
    if db is not None:
        for m in db.messages:
            names[(int(m.frame_id), bool(m.is_extended_frame))] = m.name
    ids: list[dict[str, Any]] = []
    for key in sorted(arrivals):
        ts = sorted(arrivals[key])
        gaps = [(b - a) * 1000.0 for a, b in itertools.pairwise(ts)]
        ids.append(
            {
                "id": key[0],
                "extended": key[1],
                "name": names.get(key),
                "dlc": dlcs[key],
                "count": len(ts),
                "period_ms": statistics.fmean(gaps) if gaps else None,
                "std_ms": statistics.pstdev(gaps) if len(gaps) > 1 else (0.0 if gaps else None),
                "min_ms": min(gaps) if gaps else None,
                "max_ms": max(gaps) if gaps else None,
            }
        )
    duration = (last - first) if first is not None and last is not None else 0.0
    start = int(first) if first is not None else 0
    load = [
        {"t_s": float(sec - start), "bits": bins[sec], "load": bins[sec] / bitrate}
        for sec in sorted(bins)
    ]
    total_bits = sum(bins.values())
    return {
        "file": path,
        "bitrate": bitrate,
        "duration_s": duration,
        "frames": sum(len(v) for v in arrivals.values()),
        "error_frames": errors,
        "mean_load": (total_bits / duration / bitrate) if duration > 0 else None,
        "ids": ids,
        "load": load,
    }


def cmd_stats(args: argparse.Namespace) -> int:
    err = Console(stderr=True, highlight=False)
    if not Path(args.trace).is_file():
        err.print(f"{args.trace}: no such file", style="red", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    try:
        db = load_database(args.dbc) if args.dbc else None
        if args.bitrate <= 0:
            raise CanDatabaseError(f"--bitrate must be positive, got {args.bitrate}")
        doc = trace_stats(args.trace, args.bitrate, db)
    except CanDatabaseError as e:
        err.print(str(e), style="red", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    except Exception as e:  # python-can's readers raise many kinds on unknown/bad files
        err.print(
            f"{args.trace}: cannot read the trace: {e}", style="red", markup=False, soft_wrap=True
        )
        return EXIT_BAD_GRAPH
    if args.json:
        print(json.dumps(doc, indent=2))
        return EXIT_OK
    console = stdout_console()
    console.print(
        f"{args.trace}: {doc['frames']} frames over {doc['duration_s']:.3f} s"
        + (f", {doc['error_frames']} error frames" if doc["error_frames"] else ""),
        style="italic",
        highlight=False,
    )
    cols: tuple[Column[Any], ...] = (
        Column("id", _ident, right=False),
        Column("name", lambda r: r["name"] or "", drop=2, right=False),
        Column("dlc", lambda r: str(r["dlc"]), drop=1),
        Column("frames", lambda r: str(r["count"])),
        *(
            Column(h, _ms_of(k))
            for h, k in (
                ("period ms", "period_ms"),
                ("std ms", "std_ms"),
                ("min ms", "min_ms"),
                ("max ms", "max_ms"),
            )
        ),
    )
    t = fit_table(cols, doc["ids"], console.width)
    console.print(t)
    if doc["load"]:
        peak = max(b["load"] for b in doc["load"])
        mean = doc["mean_load"]
        head = f"mean {100 * mean:.2f} %, " if mean is not None else ""
        console.print(
            f"bus load at {args.bitrate:,} bit/s (worst-case stuffing): {head}"
            f"busiest second {100 * peak:.2f} % ({len(doc['load'])} s)"
        )
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    can_p = sub.add_parser("can", help="CAN bus analysis and trace statistics")
    can_sub = can_p.add_subparsers(dest="can_command", required=True)
    an = can_sub.add_parser(
        "analyse",
        aliases=["analyze"],
        help="worst-case frame lengths, utilisation and response times of a DBC's messages",
    )
    an.add_argument("dbc", help="CAN database (.dbc, .kcd, .arxml, .sym)")
    an.add_argument("--bitrate", type=int, default=500000, help="bit/s (default 500000)")
    an.add_argument(
        "--period",
        action="append",
        metavar="NAME=MS",
        help="period of a message (overrides GenMsgCycleTime); repeatable",
    )
    an.add_argument(
        "--deadline",
        action="append",
        metavar="NAME=MS",
        help="deadline of a message (default: its period); repeatable",
    )
    an.add_argument(
        "--jitter",
        action="append",
        metavar="NAME=MS",
        help="queuing jitter of a message (default 0); repeatable",
    )
    an.add_argument("--json", action="store_true", help="print JSON for scripts")
    an.set_defaults(func=cmd_analyse)
    st = can_sub.add_parser("stats", help="per-identifier timing and bus load of a CAN trace")
    st.add_argument("trace", help="a trace python-can reads: .asc .blf .log .trc .csv .mf4 ...")
    st.add_argument("--dbc", help="name the identifiers from this database")
    st.add_argument("--bitrate", type=int, default=500000, help="for the load (default 500000)")
    st.add_argument("--json", action="store_true", help="print JSON for scripts")
    st.set_defaults(func=cmd_stats)
