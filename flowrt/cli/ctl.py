"""``flowrt ctl``: talk to a running runtime's control endpoint.

See :mod:`flowrt.control.server`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

from ..control.server import DEFAULT_URL, ControlClient, ControlError
from ..rtdb import RECORDING_SESSION
from .common import stdout_console
from .json_output import emit, note


def duration_ms_arg(text: str) -> float:
    """``--timer 80ms`` / ``--deadline 0.02s`` as milliseconds (a bare number is ms, as in a
    graph file's timing)."""
    from ..graph.spec import parse_duration_ms

    try:
        return parse_duration_ms(text if not _is_number(text) else float(text))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _count(text: str) -> int:
    """``-n``: a whole number more than 0."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError("must be more than 0")
    return n


def _session_name(text: str) -> str:
    """``record start --name``: what ``POST /record`` takes (checked here: exit 2)."""
    from ..recording.session import SESSION_NAME

    if not SESSION_NAME.match(text):
        raise argparse.ArgumentTypeError(
            f"{text!r}: a session name is letters, digits, _ and - (at most 64)"
        )
    return text


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _connection_options(parser: argparse.ArgumentParser, after: bool = False) -> None:
    """Where the runtime is: before the command (``ctl --url U stats``) or, as the README's
    list and users write them, after it (``ctl stats --url U``; then not defaulted, so the
    one given before the command stands)."""

    def default(value: Any) -> Any:
        return argparse.SUPPRESS if after else value

    parser.add_argument(
        "--url",
        default=default(os.environ.get("FLOWRT_URL", DEFAULT_URL)),
        help=f"default $FLOWRT_URL or {DEFAULT_URL}",
    )
    parser.add_argument(
        "--token",
        default=default(os.environ.get("FLOWRT_TOKEN")),
        help="bearer token (default $FLOWRT_TOKEN)",
    )
    parser.add_argument(
        "--zenoh",
        metavar="ENDPOINT",
        action="append",
        default=default(None),
        help="reach the runtime through Zenoh at ENDPOINT (e.g. tcp/10.0.0.2:7447; repeat "
        "for more), on the key of its graph's zenoh.control (--key)",
    )
    parser.add_argument(
        "--key",
        default=default(os.environ.get("FLOWRT_CONTROL_KEY")),
        help="with --zenoh: the graph's zenoh.control key (default $FLOWRT_CONTROL_KEY)",
    )


def add_parsers(sub: Any) -> None:
    """Register ``flowrt ctl`` on the CLI's subcommands."""
    ctl = sub.add_parser("ctl", help="talk to a running runtime's control endpoint")
    _connection_options(ctl)
    # before the command too (``ctl --json stats``), as --url; the command's own, given after
    # it, is not defaulted so that this one stands
    ctl.add_argument("--json", action="store_true", help="the endpoint's reply as JSON")
    what = ctl.add_subparsers(dest="ctl_command", required=True)
    st = what.add_parser("stats", help="the status table of the running graph")
    st.add_argument(
        "--json", action="store_true", default=argparse.SUPPRESS, help="raw RuntimeStats JSON"
    )
    tm = what.add_parser("timing", help="change a node's timing between ticks")
    tm.add_argument("node", help="the node whose timing changes")
    tm.add_argument("--period", type=int, help="frames (frame-triggered nodes)")
    tm.add_argument("--phase", type=int, help="frames (frame-triggered nodes)")
    tm.add_argument(
        "--timer",
        type=duration_ms_arg,
        metavar="T",
        help="period of a timer-triggered node: 80ms, 0.1s, 500us (a bare number is ms)",
    )
    tm.add_argument(
        "--timer-phase",
        type=duration_ms_arg,
        metavar="T",
        help="phase of a timer-triggered node within its period: 5ms (a bare number is ms)",
    )
    tm.add_argument(
        "--deadline",
        type=duration_ms_arg,
        metavar="T",
        help="relative deadline: 5ms, 0.02s (a bare number is ms)",
    )
    tm.add_argument("--priority", type=int, help="1 to 99, higher runs first")
    on = tm.add_mutually_exclusive_group()
    on.add_argument(
        "--enable", dest="enabled", action="store_const", const=True, help="run it again"
    )
    on.add_argument(
        "--disable",
        dest="enabled",
        action="store_const",
        const=False,
        help="stop activating it (its state kept)",
    )
    tm.add_argument(
        "--force", action="store_true", help="apply even if admission control refuses it"
    )
    md = what.add_parser("mode", help="switch to a mode of the graph file")
    md.add_argument("name", help="a mode of the graph file (flowrt ctl modes lists them)")
    md.add_argument(
        "--force", action="store_true", help="apply even if admission control refuses it"
    )
    what.add_parser("modes", help="list the graph's modes and the current one")
    ev = what.add_parser("events", help="recent events")
    ev.add_argument("-n", type=_count, default=20, help="how many of the newest events")
    what.add_parser("qos", help="mode, overload state and shed nodes")
    db = what.add_parser("rtdb", help="RTDB records (all, or the history of one)")
    db.add_argument("name", nargs="?", help="one record: its history (default: every record)")
    db.add_argument("-n", type=_count, default=8, help="history length for one record")
    rc = what.add_parser("record", help="start or stop the graph's recorder node(s)")
    rc.add_argument("action", choices=("start", "stop"), help="start or stop recording")
    rc.add_argument("--node", help="one recorder (default: every recorder of the graph)")
    rc.add_argument(
        "--name",
        type=_session_name,
        help="with start: the session's name, NAME_NNN (default: the recorder's)",
    )
    sw = what.add_parser(
        "swap", help="replace a node's algorithm while running (set up beside, then take over)"
    )
    sw.add_argument("node", help="the node to give a new instance")
    sw.add_argument("kind", help="a node kind: an entry-point name or package.module:Class")
    sw.add_argument(
        "--params",
        metavar="JSON",
        help="params to change (a JSON object), merged into the running ones; only those "
        "`flowrt kinds KIND` lists as swappable",
    )
    rl = what.add_parser("reload", help="re-import a node's module from disk and swap to it")
    rl.add_argument("node", help="the node whose module is re-imported")
    for name, parser in what.choices.items():
        _connection_options(parser, after=True)
        if "--json" not in parser._option_string_actions:  # stats: its own help
            parser.add_argument(
                "--json",
                action="store_true",
                default=argparse.SUPPRESS,
                help=f"the endpoint's reply to {name} as JSON",
            )
    ctl.set_defaults(func=ctl_main)


def ctl_main(args: argparse.Namespace) -> int:
    """``flowrt ctl``: exit 0 on success, 1 when the runtime is unreachable or refuses."""
    if args.zenoh:
        from ..graph.spec import _endpoint, check_key_expr

        try:
            for endpoint in args.zenoh:
                _endpoint(endpoint)
            if not args.key:
                raise ValueError("--zenoh needs --key (the graph's zenoh.control key)")
            check_key_expr(args.key, wildcards=False)
        except ValueError as e:
            print(f"flowrt ctl: {e}", file=sys.stderr)
            return 2
    client = _client(args)
    try:
        return _ctl(client, args)
    except ControlError as e:
        print(f"flowrt ctl: {e}", file=sys.stderr)
        return 2 if e.malformed else 1  # a malformed argument is a bad argument (exit 2)
    finally:
        _close(client)


def _client(args: argparse.Namespace, timeout: float = 15.0) -> Any:
    # 15 s: longer than the endpoint takes to answer a change (a 503 after 5 s queued, a
    # 504 after 10 s sent), so that the answer says whether it was applied
    """HTTP (``--url``), or Zenoh queries (``--zenoh ENDPOINT --key KEY``): the same API."""
    if args.zenoh:
        from ..remote.control import ZenohControlClient

        return ZenohControlClient(args.zenoh, args.key, args.token, timeout=timeout)
    return ControlClient(args.url, args.token, timeout=timeout)


def _close(client: Any) -> None:
    close = getattr(client, "close", None)
    if close is not None:
        close()


def _ctl(client: Any, args: argparse.Namespace) -> int:
    cmd = args.ctl_command
    if args.json and cmd in _QUERIES:
        emit(client.get(_QUERIES[cmd](args)))
        return 0
    command = _COMMANDS.get(cmd)
    return 0 if command is None else command(client, args)


def _cmd_stats(client: Any, args: argparse.Namespace) -> int:
    data = client.get("/stats")
    from ..monitors.status import render
    from ..stats import RuntimeStats

    console = stdout_console()
    console.print(render(RuntimeStats.model_validate(data), width=console.width))
    console.print(client.get("/qos")["summary"], markup=False, highlight=False)
    return 0


def _cmd_timing(client: Any, args: argparse.Namespace) -> int:
    body = {"node": args.node}
    for key in ("period", "phase", "timer", "timer_phase", "deadline", "priority", "enabled"):
        if getattr(args, key) is not None:
            body[key] = getattr(args, key)
    if args.force:
        body["force"] = True
    reply = client.post("/timing", body)
    _say(args, reply, f"{reply['node']}: {reply['change']}")
    return 0


def _cmd_mode(client: Any, args: argparse.Namespace) -> int:
    reply = client.post("/mode", {"mode": args.name, **({"force": True} if args.force else {})})
    _say(args, reply, f"mode {reply['mode']}")
    return 0


def _cmd_modes(client: Any, args: argparse.Namespace) -> int:
    reply = client.get("/modes")
    for name in reply["modes"]:
        print(f"{'*' if name == reply['current'] else ' '} {name}")
    if not reply["modes"]:
        print("(the graph defines no modes)")
    return 0


def _cmd_events(client: Any, args: argparse.Namespace) -> int:
    events = client.get(f"/events?n={args.n}")
    for e in events:
        detail = {k: v for k, v in e.items() if k not in ("kind", "t", "node")}
        print(f"{e['t']:9.3f}s {e['kind']} {e.get('node') or ''} {json.dumps(detail)}")
    if not events:
        print("none (no event since the start: misses, failures, restarts, changes)")
    return 0


def _cmd_qos(client: Any, args: argparse.Namespace) -> int:
    print(client.get("/qos")["summary"])
    return 0


def _cmd_rtdb(client: Any, args: argparse.Namespace) -> int:
    path = f"/rtdb/{args.name}?n={args.n}" if args.name else "/rtdb"
    records = client.get(path)
    for r in records:
        flag = " STALE" if r["stale"] else ""
        when = f"t={r['timestamp']:.3f}s age={r['age'] * 1000:.1f}ms{flag}"
        print(f"{r['name']} #{r['seq']} {when}: {json.dumps(r['value'])}")
    if not records:
        print("none (no RTDB record yet)")  # an unknown NAME is an error (404)
    return 0


def _cmd_swap(client: Any, args: argparse.Namespace) -> int:
    """Swap or reload on a client of its own: setting up the new instance takes seconds."""
    slow = _client(args, timeout=60.0)
    try:
        return _swap(slow, args)
    finally:
        _close(slow)


def _swap(client: Any, args: argparse.Namespace) -> int:
    """Swap or reload: setting up the new instance (a worker process) may take seconds."""
    body: dict[str, Any] = {"node": args.node}
    if args.ctl_command == "swap":
        body["kind"] = args.kind
        if args.params is not None:
            try:
                params = json.loads(args.params)
            except ValueError as e:
                print(f"flowrt ctl swap: --params is not JSON: {e}", file=sys.stderr)
                return 2
            if not isinstance(params, dict):
                print("flowrt ctl swap: --params must be a JSON object", file=sys.stderr)
                return 2
            body["params"] = params
    reply = client.post(f"/{args.ctl_command}", body)
    _say(args, reply, f"{reply['node']}: now {reply['kind']} ({reply['op']})")
    return 0


def _say(args: argparse.Namespace, reply: Any, line: str) -> None:
    """A change's reply: the endpoint's own with ``--json``, else one line."""
    if args.json:
        emit(reply)
    else:
        print(line)


#: The queries: with ``--json`` each prints the endpoint's reply as it is.
_QUERIES: dict[str, Callable[[argparse.Namespace], str]] = {
    "stats": lambda a: "/stats",
    "modes": lambda a: "/modes",
    "events": lambda a: f"/events?n={a.n}",
    "qos": lambda a: "/qos",
    "rtdb": lambda a: f"/rtdb/{a.name}?n={a.n}" if a.name else "/rtdb",
}


def _sessions(client: Any, node: str | None) -> dict[str, str]:
    """Each recorder's session as it publishes it (``""``: stopped), by node; ``node``: that
    one only. A recorder that has said nothing yet is not in it (the endpoint decides)."""
    out: dict[str, str] = {}
    for r in client.get("/rtdb"):
        name = str(r.get("name", ""))
        if name.startswith(RECORDING_SESSION) and node in (None, name[len(RECORDING_SESSION) :]):
            out[name[len(RECORDING_SESSION) :]] = str(r.get("value") or "")
    return out


def _refused(message: str, sessions: dict[str, str]) -> int:
    """A start while recording, a stop while not: exit 1, as the operator page's API and the
    endpoint's POST /record answer 409 for them; said here first, with each recorder's
    session (``--json``), from the state the recorders publish."""
    print(f"flowrt ctl: {message}", file=sys.stderr)
    note(sessions={n: s or None for n, s in sessions.items()})
    return 1


def _record(client: Any, args: argparse.Namespace) -> int:
    """Ask, then wait (up to 5 s) for each recorder to say where it records, or that it stopped."""
    import time

    if args.name is not None and args.action != "start":  # a bad argument: exit 2
        print("flowrt ctl: --name names a new session (record start --name NAME)", file=sys.stderr)
        return 2
    before = _sessions(client, args.node)
    busy = {n: s for n, s in before.items() if s}
    if args.action == "start" and busy:
        where = ", ".join(f"{n} into {s}" for n, s in busy.items())
        return _refused(f"already recording: {where} (flowrt ctl record stop first)", before)
    if args.action == "stop" and before and not busy:
        return _refused(f"not recording ({', '.join(before)} stopped)", before)
    body: dict[str, Any] = {"action": args.action}
    if args.node:
        body["node"] = args.node
    if args.name is not None:
        body["name"] = args.name
    nodes = client.post("/record", body)["nodes"]
    said: dict[str, Any] = {}
    for node in nodes:
        end = time.monotonic() + 5.0
        session: Any = None
        while time.monotonic() < end:
            try:
                session = client.get(f"/rtdb/flowrt.recording.{node}?n=1")[-1]["value"]
            except ControlError:
                session = None
            if session is not None and bool(session) == (args.action == "start"):
                break
            time.sleep(0.1)
        else:
            print(f"flowrt ctl: {node} did not {args.action} within 5 s", file=sys.stderr)
            return 1
        said[node] = session or None
        if not args.json:
            print(f"{node}: recording into {session}" if session else f"{node}: stopped")
    if args.json:
        emit({"action": args.action, "nodes": said})
    return 0


#: The commands, one handler each: ``flowrt ctl CMD`` calls ``_COMMANDS[CMD](client, args)``
#: for its exit code (after the ``--json`` queries above, answered as they are).
_COMMANDS: dict[str, Callable[[Any, argparse.Namespace], int]] = {
    "stats": _cmd_stats,
    "timing": _cmd_timing,
    "mode": _cmd_mode,
    "modes": _cmd_modes,
    "events": _cmd_events,
    "qos": _cmd_qos,
    "rtdb": _cmd_rtdb,
    "record": _record,
    "swap": _cmd_swap,
    "reload": _cmd_swap,
}
