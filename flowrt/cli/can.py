"""``flowrt can analyse`` and ``flowrt can stats``: a CAN bus on paper and in a trace.

``analyse`` reads a CAN database (DBC, KCD, ARXML, SYM: whatever cantools reads, loaded
non-strictly: :mod:`flowrt.analysis.can_database`) and prints the analysis of
:mod:`flowrt.analysis.can` (worst-case frame lengths, classic and FD, utilisation,
worst-case response times after Davis et al. 2007); exit 1 unless the bus is shown
schedulable (a message can miss its deadline, the utilisation is over 100 %, or the
verdict is unknown: nothing could be analysed), 2 when the database does not load or an
argument is out of range. ``stats`` reads
a trace in any format python-can reads (.asc, .blf, .log, .trc, .csv, .mf4, ...) and prints
per channel and identifier the count, mean period and inter-arrival spread, and the bus
load per second (:mod:`flowrt.analysis.can_trace`).
"""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path
from typing import Any

from rich.console import Console

from ..analysis.can_database import CanDatabaseError
from ..analysis.can_database import load_database as _load
from ..analysis.can_frames import bit_rate
from ..analysis.can_trace import TraceError, trace_stats
from ..graph._registry import KindError, resolve_kind
from ..graph.spec import parse_duration_ms
from ..monitors._columns import Column, fit_table
from .common import EXIT_BAD_GRAPH, EXIT_FAILED, EXIT_OK, stdout_console
from .json_output import emit

__all__ = ["CanDatabaseError", "load_database", "parse_bitrate", "trace_stats"]

#: Names (and strict-loading warnings) shown in a long list; ``--json`` has them all.
SHOWN = 5

#: Longest period, deadline, jitter or inter-arrival time taken (an hour): past it a busy
#: period is not worth computing (``--jitter X=1e9`` took hours).
MAX_MS = 3_600_000.0


def load_database(path: str, strict: bool = False) -> Any:
    """A cantools database (non-strict unless ``strict``), or a one-line CanDatabaseError."""
    return _load(database_path(path), strict)[0]


def database_path(path: str) -> str:
    """``path`` as given (relative to the working directory), else a database shipped with the
    ``can`` node kind's package (``robot.dbc``), where the node's ``dbc:`` param looks too: the
    README's example runs from an installed wheel as well as from the repository, and so does
    its path in the repository (``nodes/robot.dbc``: ``nodes/`` installs as flowrt.nodes)."""
    p = Path(path)
    if p.exists() or p.is_absolute():
        return path
    inside = Path(*p.parts[1:]) if p.parts[:1] == ("nodes",) and len(p.parts) > 1 else p
    try:
        kind = resolve_kind("can")  # through the entry points, as a graph's kinds are
        shipped = Path(inspect.getfile(kind)).resolve().parent.parent / inside
    except (KindError, TypeError, OSError):
        return path
    return str(shipped) if shipped.is_file() else path


def parse_bitrate(text: str, flag: str = "--bitrate") -> int:
    """``500000``, ``500k``, ``1e6``, ``1M``, ``2Mbit/s`` as bit/s, range-checked."""
    try:
        return bit_rate(text)
    except ValueError as e:
        raise CanDatabaseError(f"{flag} {text!r}: {e}") from None


def _pairs(items: list[str] | None, flag: str, zero_ok: bool = False) -> dict[str, float]:
    """``NAME=10ms`` (a bare number is ms) items, finite and within 0..an hour."""
    out: dict[str, float] = {}
    for item in items or []:
        name, sep, value = item.rpartition("=")
        try:
            if not sep or not name:
                raise ValueError
            ms = parse_duration_ms(value.strip())
        except ValueError:
            raise CanDatabaseError(f"{flag} {item!r}: expected NAME=MS, e.g. Foo=20ms") from None
        low_ok = ms >= 0 if zero_ok else ms > 0
        if not low_ok or ms > MAX_MS:
            least = "0" if zero_ok else "more than 0"
            raise CanDatabaseError(f"{flag} {item!r}: must be {least} and at most 1 h")
        out[name] = ms
    return out


def cmd_analyse(args: argparse.Namespace) -> int:
    from ..analysis.can import analyse_bus, timings_from_dbc
    from ..analysis.can_database import data_bitrate_of

    err = Console(stderr=True, highlight=False, soft_wrap=True)
    try:
        bitrate = parse_bitrate(args.bitrate)
        data_rate = (
            parse_bitrate(args.data_bitrate, "--data-bitrate") if args.data_bitrate else None
        )
        db, warnings = _load(database_path(args.dbc), args.strict)
        source = "--data-bitrate"
        if data_rate is None:
            data_rate, source = data_bitrate_of(db), "the DBC's BaudrateCANFD"
        timings = timings_from_dbc(
            db,
            periods=_pairs(args.period, "--period"),
            deadlines=_pairs(args.deadline, "--deadline"),
            jitters=_pairs(args.jitter, "--jitter", zero_ok=True),
            sporadic=_pairs(args.sporadic, "--sporadic"),
        )
        if data_rate is not None and data_rate < bitrate:
            raise CanDatabaseError(f"{source} {data_rate} is below --bitrate {bitrate}")
        result = analyse_bus(timings, bitrate, data_rate)
    except (CanDatabaseError, KeyError, ValueError) as e:
        # a KeyError's str() is quoted; stripping quotes off any message cut "got 'yaml'"
        why = e.args[0] if isinstance(e, KeyError) and e.args else e
        err.print(f"flowrt can analyse: {why}", style="red", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    if args.json:
        doc = result.to_json()
        doc["warnings"] = [
            {"message": w.message, "signal": w.signal, "reason": w.reason} for w in warnings
        ]
        emit(doc)
        return EXIT_OK if result.schedulable is True else EXIT_FAILED
    for w in warnings[:SHOWN]:  # on stderr: the analysis itself is on stdout
        err.print(f"warning: {args.dbc}: {w}", style="yellow", markup=False, soft_wrap=True)
    if len(warnings) > SHOWN:
        err.print(
            f"warning: {args.dbc}: {len(warnings) - SHOWN} more that strict loading would "
            "refuse (--json lists them all)",
            style="yellow",
            markup=False,
            soft_wrap=True,
        )
    _print_analysis(args.dbc, result)
    return EXIT_OK if result.schedulable is True else EXIT_FAILED


def _names(messages: list[Any]) -> str:
    """``N: A, B, C, D, E, ... (--json lists them all)`` (the first SHOWN of a long list)."""
    names = ", ".join(m.name for m in messages[:SHOWN])
    if len(messages) <= SHOWN:
        return names
    return f"{len(messages)} messages: {names}, ... (--json lists them all)"


def _verdict(result: Any) -> str:
    """The bus line: load (in nominal bit times, the FD data phase at its own rate), the
    utilisation (a range when an FD data phase has no known rate) and the verdict."""
    load = f"bus: {result.bits_per_s:,.0f} bit/s"
    if result.data_bitrate is not None and result.data_bits_per_s:
        load += (
            f" in nominal bit times ({result.arbitration_bits_per_s:,.0f} at the nominal rate "
            f"+ {result.data_bits_per_s:,.0f} FD data-phase bit/s at {result.data_bitrate:,})"
        )
    if result.utilisation_min is None:
        util = f"utilisation {100 * result.utilisation:.2f} %"
    else:
        util = (
            f"utilisation {100 * result.utilisation_min:.2f} to {100 * result.utilisation:.2f} %"
            " (FD data phase at an unknown rate)"
        )
    verdict = {True: "yes", False: "NO", None: "unknown"}[result.schedulable]
    reason = result.verdict_reason
    return f"{load}, {util}; schedulable: {verdict}" + (f" ({reason})" if reason else "")


def _print_analysis(path: str, result: Any) -> None:
    console = stdout_console()
    rates = f"{result.bitrate} bit/s"
    if result.data_bitrate is not None:
        rates += f", FD data phase {result.data_bitrate} bit/s"
    console.print(
        f"{path}: {len(result.messages)} messages at {rates} "
        "(worst-case stuffing, 3-bit interframe space; Davis et al. 2007, FD after "
        "ISO 11898-1:2015)",
        style="italic",
        highlight=False,
        markup=False,
    )
    console.print(_message_table(result.messages, console.width))
    console.print(_verdict(result), markup=False)
    left = result.not_analysed
    event = [m for m in left if m.timing.period_ms is None]
    fd = [m for m in left if m.timing.period_ms is not None]
    if fd:
        console.print(
            "not analysed (CAN FD with bit-rate switch, no data bit rate; give --data-bitrate "
            f"or the DBC's BaudrateCANFD): {_names(fd)}; their no-BRS "
            "length counts as interference and blocking for the others",
            style="yellow",
            markup=False,
        )
    if event:
        console.print(
            "not analysed (no cycle time; give --period NAME=MS, or --sporadic NAME=MS for a "
            f"minimum inter-arrival time): {_names(event)}",
            style="yellow",
            markup=False,
        )
        below = {d for m in event for d in m.delays}
        worst = max(m.c_ms for m in event)
        console.print(
            f"  each can still delay others: it blocks higher-priority messages by at most "
            f"its frame time (<= {worst:.3f} ms, included in their B), and it delays "
            f"lower-priority messages without bound: {len(below)} analysed message"
            f"{'s are' if len(below) != 1 else ' is'} below at least one of them (their "
            "WCRT assumes these stay silent)",
            markup=False,
        )
        if len(event) <= 10:
            for m in event:
                if m.delays:
                    shown = ", ".join(m.delays[:5]) + (", ..." if len(m.delays) > 5 else "")
                    console.print(f"  {m.name} is above {shown}", markup=False)


def _ident(r: dict[str, Any]) -> str:
    return f"0x{r['id']:08X}x" if r["extended"] else f"0x{r['id']:03X}"


def _message_table(messages: Any, width: int) -> Any:
    """The analysis per message; at 80 columns the derived terms (B, J, busy, Q) go first."""

    def ident(m: Any) -> str:
        tm = m.timing
        return f"0x{tm.id:08X}x" if tm.extended else f"0x{tm.id:03X}"

    def wcrt(m: Any) -> str:
        ok = m.wcrt_ms is not None or m.schedulable is None  # not analysed: "-"
        return _ms(m.wcrt_ms) if ok else "unbounded"

    cols: tuple[Column[Any], ...] = (
        Column("message", lambda m: m.name, right=False),
        Column("id", ident, right=False),
        Column("dlc", lambda m: str(m.timing.dlc) + (" FD" if m.timing.fd else ""), drop=5),
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


def cmd_stats(args: argparse.Namespace) -> int:
    err = Console(stderr=True, highlight=False, soft_wrap=True)
    try:
        bitrate = parse_bitrate(args.bitrate)
        data_rate = (
            parse_bitrate(args.data_bitrate, "--data-bitrate") if args.data_bitrate else None
        )
        db = load_database(args.dbc) if args.dbc else None
        doc = trace_stats(args.trace, bitrate, db, data_rate)
    except (CanDatabaseError, TraceError, OSError) as e:
        err.print(f"flowrt can stats: {e}", style="red", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    if args.json:
        emit(doc)
        return EXIT_OK
    console = stdout_console()
    console.print(
        f"{args.trace}: {doc['frames']} frames over {doc['duration_s']:.3f} s"
        + (f", {doc['error_frames']} error frames" if doc["error_frames"] else "")
        + (f", {len(doc['channels'])} channels" if len(doc["channels"]) > 1 else ""),
        style="italic",
        highlight=False,
        markup=False,
    )
    if doc["truncated"]:  # its figures are those of the part before the cut
        console.print(f"{doc['truncated']}: the figures are those before the cut", style="yellow")
    for ch in doc["channels"]:
        _print_channel(console, ch, bitrate, len(doc["channels"]) > 1)
    if doc["brs_at_nominal_rate"]:
        console.print(
            f"{doc['brs_at_nominal_rate']} FD frames with bit-rate switch counted at the "
            "nominal rate (give --data-bitrate)",
            style="yellow",
        )
    return EXIT_OK


def _print_channel(console: Console, ch: dict[str, Any], bitrate: int, head: bool) -> None:
    if head:
        console.print(f"channel {ch['channel'] or '-'}", style="bold", markup=False)
    cols: tuple[Column[Any], ...] = (
        Column("id", _ident, right=False),
        Column("name", lambda r: r["name"] or "", drop=2, right=False),
        Column("dlc", lambda r: str(r["dlc"]) + (" FD" if r["fd"] else ""), drop=1),
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
    console.print(fit_table(cols, ch["ids"], console.width))
    if ch["load"]:
        mean, peak, span = ch["mean_load"], ch["peak_load"], ch["duration_s"]
        if peak is not None:
            what = f"busiest second {100 * peak:.2f} % (of {span:.1f} s)"
            what = (f"mean {100 * mean:.2f} %, " if mean is not None else "") + what
        elif mean is not None:  # under 2 s: the mean is all there is
            what = (
                f"{100 * mean:.2f} % over the whole trace "
                f"({span:.3f} s: too short for a busiest second)"
            )
        else:
            what = "one instant only (a trace of one frame time)"
        console.print(f"bus load at {bitrate:,} bit/s (worst-case stuffing): {what}", markup=False)


def add_parsers(sub: Any) -> None:
    can_p = sub.add_parser("can", help="CAN bus analysis and trace statistics")
    can_sub = can_p.add_subparsers(dest="can_command", required=True)
    an = can_sub.add_parser(
        "analyse",
        aliases=["analyze"],
        help="worst-case frame lengths, utilisation and response times of a DBC's messages",
    )
    an.add_argument("dbc", help="CAN database (.dbc, .kcd, .arxml, .sym)")
    an.add_argument(
        "--bitrate", default="500k", help="nominal bit/s: 500000, 500k, 1e6, 1M (default 500k)"
    )
    an.add_argument(
        "--data-bitrate",
        help="CAN FD data-phase bit/s, e.g. 2M (default: the DBC's BaudrateCANFD; without "
        "either, FD messages with bit-rate switch are not analysed)",
    )
    an.add_argument(
        "--period",
        action="append",
        metavar="NAME=MS",
        help="period of a message (overrides GenMsgCycleTime), e.g. Foo=20ms; repeatable",
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
        help="queuing jitter of a message (default 0, at most 1 h); repeatable",
    )
    an.add_argument(
        "--sporadic",
        action="append",
        metavar="NAME=MS",
        help="minimum inter-arrival time of a message without a cycle time (default: the "
        "DBC's GenMsgDelayTime): analysed as sporadic interference; repeatable",
    )
    an.add_argument(
        "--strict",
        action="store_true",
        help="refuse the database where cantools' strict loading would (overlapping signals...)",
    )
    an.add_argument("--json", action="store_true", help="print JSON for scripts")
    an.set_defaults(func=cmd_analyse)
    st = can_sub.add_parser(
        "stats", help="per-channel, per-identifier timing and bus load of a CAN trace"
    )
    st.add_argument("trace", help="a trace python-can reads: .asc .blf .log .trc .csv .mf4 ...")
    st.add_argument("--dbc", help="name the identifiers from this database")
    st.add_argument("--bitrate", default="500k", help="nominal bit/s for the load (default 500k)")
    st.add_argument("--data-bitrate", help="CAN FD data-phase bit/s for BRS frames, e.g. 2M")
    st.add_argument("--json", action="store_true", help="print JSON for scripts")
    st.set_defaults(func=cmd_stats)
