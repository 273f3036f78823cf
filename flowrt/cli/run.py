"""``flowrt run``: a graph with a live status table, until Ctrl-C or ``--duration``."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console

from ..graph._resolve import Graph
from ..remote._bridge import RemoteError
from ..system._eventloop import new_event_loop
from .common import (
    EXIT_BAD_GRAPH,
    EXIT_FAILED,
    EXIT_OK,
    load,
    output_file_arg,
    plain_handler,
    port_arg,
    positive_float_arg,
    positive_seconds_arg,
    setup_logging,
    stdout_console,
)
from .signals import StopSignals
from .zenoh_options import add_zenoh_options, apply_zenoh_options


def _warm_forkserver(path: str) -> None:
    """Start the workers' forkserver now if the file places any node in a worker.

    The forkserver imports numpy and OpenCV before it can fork the first worker (~0.5 s,
    more on a loaded machine); started here, before the graph is validated and its node
    modules imported, that runs on another CPU while this process does the rest of its
    start-up, instead of after it. A plain text search: a false positive costs an idle
    process, a miss only the overlap (the runtime starts it anyway).
    """
    import re
    import threading

    from ..files import read_bytes
    from ..graph._loading import MAX_FILE_BYTES

    try:  # the same limits as the graph file's reading: a device, a FIFO, 1 GiB: not read
        text = read_bytes(path, MAX_FILE_BYTES).decode(errors="replace")
    except OSError:
        return
    if re.search(r"placement\s*:\s*[\"']?(process|pool)\b", text):
        from ..workers import start_forkserver

        threading.Thread(target=start_forkserver, name="forkserver-warm", daemon=True).start()


def cmd_run(args: argparse.Namespace) -> int:
    from .. import _startup

    _warm_forkserver(args.file)
    err = Console(stderr=True, soft_wrap=True)
    _startup.phase = "loading the graph"
    graph = load(args.file, err)
    if graph is None:
        return EXIT_BAD_GRAPH
    if args.recordings is not None:
        problem = _with_recordings(graph, args.recordings)
        if isinstance(problem, str):
            err.print(f"flowrt run: --recordings: {problem}", markup=False, soft_wrap=True)
            return EXIT_BAD_GRAPH
        graph = problem
    return run_graph(graph, args, err)


def _with_recordings(graph: Graph, folder: str) -> Graph | str:
    """The graph with a recorder on every output that waits to be told to start (the live
    view's record panel, ``flowrt ctl record start``), and its display nodes reviewing the
    sessions of ``folder``; or why not, in one line."""
    from ..graph._resolve import resolve
    from ..recording import check_writable
    from .recorders import graph_outputs, with_recorder

    problem = check_writable(folder)
    if problem is not None:
        return problem
    root = str(Path(folder).resolve())  # relative to where the command runs, as -o is
    params = {
        "path": root,
        "start": False,
        "graph_file": str(Path(graph.file).resolve()) if graph.file else None,
    }
    try:
        base_dir = Path(graph.file).resolve().parent if graph.file else None
        out = resolve(with_recorder(graph.spec, graph_outputs(graph), params), base_dir=base_dir)
    except Exception as e:  # a recorder the graph cannot take
        return _one_line(e)
    out.file = graph.file
    for name in _display_nodes(out):
        n = out.nodes[name]
        n.params = n.params.model_validate({**n.params.model_dump(), "recordings": root})
    return out


def run_graph(
    graph: Graph,
    args: argparse.Namespace,
    err: Console,
    *,
    prog: str = "flowrt run",
    settle: Callable[[], None] | None = None,
    after: Callable[[Any], int] | None = None,
    kinds: dict[str, Any] | None = None,
    result: dict[str, Any] | None = None,
    measuring: bool = False,
    started: Callable[[Console], None] | None = None,
) -> int:
    """Run a loaded graph with every option of ``flowrt run`` (see :func:`add_run_options`).

    ``flowrt record`` is this with a recorder added to the graph, so a recording runs with
    the same real-time, control, display and failure options as a run. ``after`` is called
    with the runtime once it has stopped and the final table is printed; its exit code
    counts when it is worse than the run's own. ``settle`` runs first, before the final
    statistics are taken (a recorder's files finished, so its report is in them).
    With ``--json`` the final statistics are the document, ``result`` (which ``after`` may
    fill in) beside them. ``measuring`` (``check --measure``): no start-up timing check and
    no table at the end; the check's own report follows.
    ``started`` is called with the run's console once every node is set up and none has
    failed: what a command says only when it is true (``recording ... into ...``).
    """
    from ..runtime._runtime import Runtime

    console = stdout_console()
    as_json = getattr(args, "json", False)
    if as_json:
        args.no_ui = True  # a live table on stderr would be noise around the log lines
    if not measuring and not _timing_holds(graph, args, err, prog):
        return EXIT_FAILED
    problem = _display_options(graph, args) or apply_zenoh_options(graph, args)
    if problem:
        err.print(f"{prog}: {problem}", markup=False, soft_wrap=True)
        return EXIT_BAD_GRAPH
    control = _control_config(args, err, prog, graph.spec.zenoh)
    # Every address is checked before anything starts: a taken port is one line and exit 1.
    problem = _check_addresses(graph)
    if problem:
        err.print(f"{prog}: {problem}", markup=False, soft_wrap=True)
        return EXIT_FAILED
    rt = Runtime(
        graph,
        realtime=args.realtime,
        spin=args.spin / 1000,
        cpu_latency=None if args.cpu_latency is None else args.cpu_latency / 1000,
        drain_timeout=args.drain_timeout,
        stop_on_failure=not args.keep_going,
        kinds=kinds,
    )
    bound, server = _bind_control(rt, control, err, prog)
    if not bound:
        return EXIT_FAILED
    if _add_monitors(rt, args, console, err, prog) is not None:
        return EXIT_FAILED

    stop_signals = StopSignals(rt.interruption, rt.interrupt, prog, rt.mark_stop)
    stop_signals.install()
    cut = _run_on_loop(rt, server, graph, args, stop_signals, started, console, err, prog)
    if cut is None:
        cut = _cut_short(stop_signals, measuring, err, prog)
    if cut is not None:
        return cut
    if settle is not None:
        settle()
    return _ended(rt, args, console, err, prog, after=after, result=result, measuring=measuring)


def _run_on_loop(
    rt: Any,
    server: Any,
    graph: Graph,
    args: argparse.Namespace,
    stop_signals: StopSignals,
    started: Callable[[Console], None] | None,
    console: Console,
    err: Console,
    prog: str,
) -> int | None:
    """Start, run and stop ``rt`` on a new loop; an exit code when the run could not be
    had (a Zenoh endpoint taken, the control endpoint that never served), else None."""
    endpoint_failed: str | None = None

    async def main() -> None:
        nonlocal endpoint_failed
        stop_signals.loop = asyncio.get_running_loop()
        stop_signals.ran = True
        if stop_signals.before_start is not None:
            return  # a signal while loading: nothing starts
        try:
            async with rt:
                if started is not None and not rt.failures():
                    started(console)
                endpoint_failed = await _serve_run(rt, server, graph, args.duration)
        except asyncio.CancelledError:
            if stop_signals.in_setup is None:
                raise  # not ours
        finally:
            stop_signals.loop = None

    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        try:
            runner.run(main())
        except RemoteError as e:  # a Zenoh endpoint in use or unreachable: nothing ran
            err.print(f"{prog}: {e}", markup=False, soft_wrap=True)
            return 1
    if endpoint_failed is not None:  # the run was stopped for it
        err.print(f"{prog}: {endpoint_failed}", markup=False, soft_wrap=True)
        return EXIT_FAILED
    return None


def _bind_control(rt: Any, control: Any, err: Console, prog: str) -> tuple[bool, Any]:
    """The control endpoint's server, its port bound now (held from then on: nothing can take
    it before the runtime starts); (False, None) when it cannot be bound, said in one line."""
    if control is None:
        return True, None
    from ..control.server import ControlServer

    server = ControlServer(rt, control)
    try:
        server.bind()
    except OSError as e:
        err.print(
            f"{prog}: control endpoint: {e.strerror or e} (choose another with --control PORT)",
            markup=False,
            soft_wrap=True,
        )
        return False, None
    return True, server


def _cut_short(stop_signals: StopSignals, measuring: bool, err: Console, prog: str) -> int | None:
    """128 + N when a signal leaves nothing to report: it came before the run (undone, no
    table), or it cut a measuring run (``check --measure``: budgets of a part, no verdict)."""
    if stop_signals.exit_code is not None:
        return stop_signals.exit_code
    if measuring and stop_signals.received:
        err.print(f"{prog}: the measuring run was interrupted: no verdict from a cut run")
        return 128 + stop_signals.received[0]
    return None


def _ended(
    rt: Any,
    args: argparse.Namespace,
    console: Console,
    err: Console,
    prog: str,
    *,
    after: Callable[[Any], int] | None,
    result: dict[str, Any] | None,
    measuring: bool,
) -> int:
    """After the run: the final table, --stats-json, the verdict, ``after``'s code and the
    --json document; the worst exit code of them."""
    from ..monitors.status import render

    stats = rt.stats()
    with contextlib.suppress(OSError):  # a terminal that hung up (SIGHUP) cannot show it
        if not measuring:
            console.print(render(stats, list(rt.events)[-5:], rt.qos_status(), width=console.width))
    code = _write_stats(args.stats_json, stats, console, err, prog) if args.stats_json else 0
    code = max(code, _verdict(rt.failures(), err, prog))
    code = code if after is None else max(code, after(rt))
    if getattr(args, "json", False):
        from .json_output import emit

        emit({**(result or {}), "exit_code": code, "stats": stats.model_dump(mode="json")})
    return code


def _add_monitors(
    rt: Any, args: argparse.Namespace, console: Console, err: Console, prog: str
) -> int | None:
    """The run's monitors: the live table (or log lines) and the Foxglove server, started now
    so that a taken port is one line before anything runs (EXIT_FAILED; None: all there)."""
    from ..monitors.status import LiveTable, LogLines

    monitor: LogLines | LiveTable
    if args.no_ui:
        monitor = LogLines(args.log_every)
        setup_logging(plain_handler())
    else:
        monitor = LiveTable(console, hz=args.refresh)
        setup_logging(monitor.log_handler())
    rt.monitors.append(monitor)
    if args.foxglove is not None:  # the live Foxglove server: started now, so a taken port
        from ..recording.live import FoxgloveLive  # is one line before anything runs

        live = FoxgloveLive(port=args.foxglove)
        try:
            live.open()
        except OSError as e:
            err.print(
                f"{prog}: {e} (choose another with --foxglove PORT)", markup=False, soft_wrap=True
            )
            return EXIT_FAILED
        logging.getLogger("flowrt").info("foxglove: open %s in the Foxglove app", live.url)
        rt.monitors.append(live)
    return None


def _write_stats(path: str, stats: Any, console: Console, err: Console, prog: str) -> int:
    """``--stats-json``: checked as the option is parsed, but a disk may still fill up or the
    folder go during the run; then one line and exit 1, not a traceback."""
    target = Path(path)
    regular = not target.exists() or target.is_file()
    try:
        target.write_text(stats.model_dump_json(indent=2) + ("" if regular else "\n"))
    except OSError as e:
        err.print(f"{prog}: --stats-json {path}: {e.strerror or e}", markup=False)
        return EXIT_FAILED
    if regular:  # not /dev/stdout or a pipe, where the line would follow the document
        console.print(f"statistics written to {path}")
    return EXIT_OK


def startup_check(graph: Any) -> tuple[bool, list[str]]:
    """For ``flowrt run``: (no node shown to miss, lines to print) with the declared wcets,
    in the graph's initial mode.

    Nodes without a declared ``wcet`` are not judged (one line says which); a node whose
    bound exceeds its deadline makes the graph unschedulable.
    """
    from ..analysis.schedulability import analyse
    from ..analysis.timing import graph_timing, with_mode

    timing = graph_timing(graph)
    if graph.spec.initial_mode in graph.spec.modes:
        timing = with_mode(timing, graph, graph.spec.initial_mode)
    verdict = analyse(timing, os.cpu_count() or 1)
    misses = [v for v in verdict.nodes if v.schedulable is False]
    unknown = [v.name for v in verdict.nodes if v.schedulable is None]
    lines = [
        f"{v.name}: worst-case response {_ms(v.response_ms)} ms > "
        f"{'deadline' if v.has_deadline else 'period'} {_ms(v.deadline_ms)} ms"
        for v in misses
    ]
    if unknown and len(unknown) < len(verdict.nodes):
        lines.append(f"not checked (no wcet:): {', '.join(unknown)}")
    return not misses, lines


def _ms(x: float | None) -> str:
    """As ``flowrt check`` prints a time: ``2.5``, ``inf``, ``-``."""
    import math

    if x is None:
        return "-"
    return "inf" if not math.isfinite(x) else f"{x:.3f}".rstrip("0").rstrip(".")


def _timing_holds(graph: Graph, args: argparse.Namespace, err: Console, prog: str) -> bool:
    """The start-up timing check: a warning, or with ``--check`` a refusal (False)."""
    timing_ok, timing_lines = startup_check(graph)
    if not timing_ok:
        word = "refusing to start" if args.check else "warning"
        err.print(f"{prog}: {word}: the timing may not hold (flowrt check)", markup=False)
        for line in timing_lines:
            err.print(f"  {line}", markup=False)
    return timing_ok or not args.check


async def _serve_run(rt: Any, server: Any, graph: Graph, duration: float | None) -> str | None:
    """Run, with the control endpoint said and, when the graph asks, forwarded over Zenoh.

    The endpoint's process starts beside the run, not before it: at its low priority on a
    machine the graph keeps busy its start took 15 s, which ``--duration`` did not count and
    a signal waited for (its clients wait in the bound port's backlog meanwhile). If it does
    not start, the run stops: returns why (None: it served, or was not asked for)."""
    if server is None:
        await rt.run(duration, then_stop=True)
        return None
    await server.spawn()
    up = asyncio.create_task(_endpoint_up(rt, server))
    forwarder = None
    zenoh = graph.spec.zenoh
    try:
        if zenoh is not None and zenoh.control is not None:
            from ..remote.control import ZenohControl

            forwarder = ZenohControl(rt.remote_session, zenoh.control, server.url)
            forwarder.start()
            logging.getLogger("flowrt").info("control through zenoh: %s", zenoh.control)
        await rt.run(duration, then_stop=True)
    finally:
        up.cancel()  # (none when it is done)
        await asyncio.wait([up])
        if forwarder is not None:
            await asyncio.to_thread(forwarder.stop)
        await server.stop()
    failed = None if up.cancelled() else up.exception()
    return None if failed is None else str(failed)


async def _endpoint_up(rt: Any, server: Any) -> None:
    """Say the endpoint's address once it serves; if it never does, stop the run."""
    try:
        await server.wait_ready()
    except RuntimeError:
        rt.request_stop()
        raise
    logging.getLogger("flowrt").info("control endpoint %s", server.url)


def _verdict(failures: list[Any], err: Console, prog: str = "flowrt run") -> int:
    """Exit 1 when the run ends with a node failed or in error, one line per node."""
    for n in failures:
        what = {"failed": "failed", "backoff": "never completed an activation"}.get(
            n.state, "in error"
        )
        err.print(
            f"{prog}: node {n.name} {what}: {n.reason}",
            markup=False,
            style="red",
            soft_wrap=True,
        )
    return EXIT_FAILED if failures else EXIT_OK


def _display_nodes(graph: Graph) -> list[str]:
    """The nodes that serve a web view (their class says ``listens``: params host and port)."""
    return [name for name, n in graph.nodes.items() if getattr(n.cls, "listens", False)]


def _display_options(graph: Graph, args: argparse.Namespace) -> str | None:
    """Apply ``--no-display`` and ``--display-host/-port/-token`` to the graph's views."""
    names = _display_nodes(graph)
    if args.no_display:
        _remove_nodes(graph, set(names))
        return None
    token = args.display_token or os.environ.get("FLOWRT_DISPLAY_TOKEN")
    options = (("host", args.display_host), ("port", args.display_port), ("token", token))
    update = {k: v for k, v in options if v is not None}
    if not update:
        return None
    if not names:
        return "--display-host/--display-port/--display-token: the graph has no display node"
    if "port" in update and len(names) > 1 and update["port"] != 0:
        return f"--display-port: the graph has {len(names)} display nodes ({', '.join(names)})"
    made = args.display_host and not token and not _loopback(args.display_host)
    if made:
        import secrets

        update["token"] = secrets.token_urlsafe(18)
    for name in names:
        n = graph.nodes[name]
        try:
            n.params = n.params.model_validate({**n.params.model_dump(), **update})
        except ValueError as e:
            return f"--display-host/--display-port/--display-token: {_one_line(e)}"
    if made:  # said once the address is taken: never a token for a run that does not start
        print(f"live view token (open the view as /?token=...): {update['token']}", flush=True)
    return None


def _loopback(host: str) -> bool:
    from ..control.serving import is_loopback

    return is_loopback(host)


def _one_line(e: Exception) -> str:
    errors = getattr(e, "errors", None)
    if callable(errors):
        return "; ".join(
            f"{'.'.join(str(x) for x in err.get('loc', ())) or 'params'}: {err.get('msg')}"
            for err in errors()
        )
    return str(e).splitlines()[0]


def _remove_nodes(graph: Graph, names: set[str]) -> None:
    """Take nodes that nothing reads from out of the graph (and out of its modes)."""
    if not names:
        return
    for name in names:
        graph.nodes.pop(name)
    graph.edges = [e for e in graph.edges if e.src not in names and e.dst not in names]
    modes = {
        mode: spec.model_copy(
            update={"nodes": {k: v for k, v in spec.nodes.items() if k not in names}}
        )
        for mode, spec in graph.spec.modes.items()
    }
    nodes = {k: v for k, v in graph.spec.nodes.items() if k not in names}
    graph.spec = graph.spec.model_copy(update={"nodes": nodes, "modes": modes})


def _check_addresses(graph: Graph) -> str | None:
    """Try to bind every display node's address; the first that fails, in one line."""
    from ..control.server import listen

    for name in _display_nodes(graph):
        params = graph.nodes[name].params
        host, port = getattr(params, "host", "127.0.0.1"), getattr(params, "port", 0)
        try:  # port 0 too: the host must resolve to an address of this machine
            listen(host, port).close()
        except OSError as e:
            return (
                f"display {name!r}: {e.strerror or e} "
                "(choose another with --display-port PORT or --display-host HOST, "
                "or run with --no-display)"
            )
    return None


def _control_config(
    args: argparse.Namespace, err: Console, prog: str = "flowrt run", zenoh: Any = None
) -> Any:
    """``--control [HOST:]PORT``: a token is generated (and printed) if one is needed.

    A graph with ``zenoh: {control: KEY}`` gets a control endpoint (on a free loopback port
    unless ``--control`` says where) for its queryable to forward to; when its Zenoh session
    is reachable beyond loopback, the token is required on loopback too.
    """
    via_zenoh = zenoh is not None and zenoh.control is not None
    if args.control is None and not via_zenoh:
        if args.control_token_required:
            err.print(f"{prog}: --control-token-required needs --control", markup=False)
            raise SystemExit(EXIT_BAD_GRAPH)
        return None
    import secrets

    from ..control.server import ControlConfig

    required = args.control_token_required or (via_zenoh and zenoh.beyond_loopback())
    try:
        config = ControlConfig.parse(
            args.control or "127.0.0.1:0",
            args.token or os.environ.get("FLOWRT_TOKEN"),
            token_required=required,
        )
    except ValueError as e:
        err.print(f"{prog}: {e}", markup=False)
        raise SystemExit(EXIT_BAD_GRAPH) from None
    allow = getattr(args, "control_allow_kinds", "") or ""
    kinds = tuple(k.strip() for k in allow.split(",") if k.strip())
    config = dataclasses.replace(config, allow_kinds=kinds)
    if config.needs_token and not config.token:
        config = dataclasses.replace(config, token=secrets.token_urlsafe(24))
        err.print(f"control token (give it to flowrt ctl --token): {config.token}", markup=False)
    return config


def _up_to_10ms(text: str) -> float:
    """A duration of 0 to 10 ms (``--spin``, ``--cpu-latency``), in milliseconds."""
    from ..graph.spec import parse_duration_ms

    try:
        ms = parse_duration_ms(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a duration from 0 to 10 ms such as 0us or 300us, got {text!r}"
        ) from None
    if not 0 <= ms <= 10:
        raise argparse.ArgumentTypeError(f"must be between 0 and 10 ms, got {ms:g} ms")
    return ms


def _drain_s(text: str) -> float:
    try:
        s = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not 0 <= s <= 3600:
        raise argparse.ArgumentTypeError(f"must be between 0 and 3600 s, got {text}")
    return s


def add_parsers(sub: Any) -> None:
    run = sub.add_parser("run", help="run a graph with a live status table")
    run.add_argument("file", help="graph file")
    run.add_argument(
        "--recordings",
        metavar="DIR",
        help="add a recorder on every output that waits for Start (the live view's record "
        "panel, or flowrt ctl record start); sessions go in DIR/NAME_NNN and are reviewed "
        "in the live view",
    )
    add_run_options(run)
    run.set_defaults(func=cmd_run)


def add_run_options(parser: argparse.ArgumentParser, *, measuring: bool = False) -> None:
    """The options of a run, defined here once for every command that runs a graph:
    ``flowrt run``, ``record``, ``replay`` and the measuring run of ``check --measure``
    (``measuring``: its length is ``--measure``'s, and there is no ``--check`` or ``--json``
    of a run). All go through :func:`run_graph`, so each command honours every one of them.
    A new run option goes here, in the "run options" group (``check`` refuses those given
    without ``--measure``; tests/test_cli_paths.py checks the four commands agree).
    """
    run = parser.add_argument_group("run options")
    if not measuring:
        run.add_argument(
            "--duration",
            type=positive_seconds_arg,
            metavar="S",
            help="stop after S seconds of running, counted once every node is set up "
            "(start-up, e.g. starting worker processes, and teardown come on top)",
        )
        run.add_argument(
            "--json",
            action="store_true",
            help="print one JSON document on stdout at the end (the final statistics; "
            "everything else goes to stderr); implies --no-ui",
        )
    run.add_argument(
        "--no-ui", action="store_true", help="periodic log lines instead of the live table"
    )
    run.add_argument(
        "--stats-json",
        metavar="PATH",
        type=output_file_arg,
        help="write final statistics (flowrt schema stats)",
    )
    run.add_argument(
        "--realtime", action="store_true", help="SCHED_FIFO for the loop process where permitted"
    )
    run.add_argument(
        "--spin",
        type=_up_to_10ms,
        default=0.0,
        metavar="DURATION",
        help="the loop busy-waits this long before each timer release (0 to 10 ms, e.g. 300us; "
        "a bare number is ms; default 0)",
    )
    run.add_argument(
        "--cpu-latency",
        type=_up_to_10ms,
        default=None,
        metavar="DURATION",
        help="while running, no CPU may take longer to wake (a PM QoS request, 0 to 10 ms, "
        "e.g. 0us: idle CPUs poll; a bare number is ms; needs root)",
    )
    run.add_argument(
        "--drain-timeout",
        type=_drain_s,
        default=5.0,
        metavar="S",
        help="at stop, let lossless edges and running activations finish for at most S seconds "
        "(default 5; reported when hit)",
    )
    run.add_argument(
        "--refresh", type=positive_float_arg, default=4.0, metavar="HZ", help="table refresh rate"
    )
    run.add_argument(
        "--log-every",
        type=positive_float_arg,
        default=2.0,
        metavar="S",
        help="--no-ui summary period",
    )
    _add_serving_options(run)
    if not measuring:
        run.add_argument(
            "--check",
            action="store_true",
            help="refuse to start when flowrt check shows a node missing its deadline "
            "(declared wcet:)",
        )
    run.add_argument(
        "--keep-going",
        action="store_true",
        help="keep the rest of the graph running when a node fails for good (default: stop at"
        " once); the exit code is 1 either way",
    )
    add_zenoh_options(run)


def _add_serving_options(run: argparse._ArgumentGroup) -> None:
    """The run options of what a run serves: the control endpoint, Foxglove, the live view."""
    run.add_argument(
        "--control",
        nargs="?",
        const="127.0.0.1:8766",
        metavar="[HOST:]PORT",
        help="serve the control endpoint (default 127.0.0.1:8766); see flowrt ctl",
    )
    run.add_argument("--token", help="bearer token of the control endpoint (default $FLOWRT_TOKEN)")
    run.add_argument(
        "--control-allow-kinds",
        metavar="KINDS",
        default="",
        help="comma-separated node kinds POST /swap may name besides those the graph uses",
    )
    run.add_argument(
        "--foxglove",
        nargs="?",
        type=port_arg,
        const=8765,
        metavar="PORT",
        help="serve the graph live to Foxglove on ws://127.0.0.1:PORT (default 8765)",
    )
    run.add_argument(
        "--control-token-required",
        action="store_true",
        help="require the token on loopback too (one is generated and printed if none is given)",
    )
    run.add_argument(
        "--display-host",
        metavar="HOST",
        help="address of the graph's live view (overrides its display nodes' host)",
    )
    run.add_argument(
        "--display-port",
        type=int,
        metavar="PORT",
        help="port of the graph's live view (overrides its display node's port; 0: any free)",
    )
    run.add_argument(
        "--display-token",
        metavar="TOKEN",
        help="token the live view requires (default $FLOWRT_DISPLAY_TOKEN; generated and "
        "printed when --display-host is not loopback)",
    )
    run.add_argument(
        "--no-display", action="store_true", help="run without the graph's display nodes"
    )
