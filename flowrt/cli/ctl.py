"""``flowrt ctl``: talk to a running runtime's control endpoint (see :mod:`flowrt.control`)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from ..control import DEFAULT_URL, ControlClient, ControlError
from .common import stdout_console


def add_parsers(sub: Any) -> None:
    """Register ``flowrt ctl`` on the CLI's subcommands."""
    ctl = sub.add_parser("ctl", help="talk to a running runtime's control endpoint")
    ctl.add_argument(
        "--url",
        default=os.environ.get("FLOWRT_URL", DEFAULT_URL),
        help="default $FLOWRT_URL or %(default)s",
    )
    ctl.add_argument(
        "--token",
        default=os.environ.get("FLOWRT_TOKEN"),
        help="bearer token (default $FLOWRT_TOKEN)",
    )
    what = ctl.add_subparsers(dest="ctl_command", required=True)
    st = what.add_parser("stats", help="the status table of the running graph")
    st.add_argument("--json", action="store_true", help="raw RuntimeStats JSON")
    tm = what.add_parser("timing", help="change a node's timing between ticks")
    tm.add_argument("node")
    tm.add_argument("--period", type=int, help="frames (frame-triggered nodes)")
    tm.add_argument("--phase", type=int, help="frames (frame-triggered nodes)")
    tm.add_argument(
        "--timer", type=float, metavar="MS", help="period of a timer-triggered node, ms"
    )
    tm.add_argument("--deadline", type=float, metavar="MS")
    tm.add_argument("--priority", type=int)
    on = tm.add_mutually_exclusive_group()
    on.add_argument("--enable", dest="enabled", action="store_const", const=True)
    on.add_argument("--disable", dest="enabled", action="store_const", const=False)
    tm.add_argument(
        "--force", action="store_true", help="apply even if admission control refuses it"
    )
    md = what.add_parser("mode", help="switch to a mode of the graph file")
    md.add_argument("name")
    md.add_argument(
        "--force", action="store_true", help="apply even if admission control refuses it"
    )
    what.add_parser("modes", help="list the graph's modes and the current one")
    ev = what.add_parser("events", help="recent events")
    ev.add_argument("-n", type=int, default=20)
    what.add_parser("qos", help="mode, overload state and shed nodes")
    db = what.add_parser("rtdb", help="RTDB records (all, or the history of one)")
    db.add_argument("name", nargs="?")
    db.add_argument("-n", type=int, default=8, help="history length for one record")
    ctl.set_defaults(func=ctl_main)


def ctl_main(args: argparse.Namespace) -> int:
    """``flowrt ctl``: exit 0 on success, 1 when the runtime is unreachable or refuses."""
    client = ControlClient(args.url, args.token)
    try:
        return _ctl(client, args)
    except ControlError as e:
        print(f"flowrt ctl: {e}", file=sys.stderr)
        return 1


def _ctl(client: ControlClient, args: argparse.Namespace) -> int:
    cmd = args.ctl_command
    if cmd == "stats":
        data = client.get("/stats")
        if args.json:
            print(json.dumps(data, indent=2))
            return 0
        from ..stats import RuntimeStats
        from ..status import render

        console = stdout_console()
        console.print(render(RuntimeStats.model_validate(data), width=console.width))
        console.print(client.get("/qos")["summary"], markup=False, highlight=False)
    elif cmd == "timing":
        body = {"node": args.node}
        for key in ("period", "phase", "timer", "deadline", "priority", "enabled"):
            if getattr(args, key) is not None:
                body[key] = getattr(args, key)
        if args.force:
            body["force"] = True
        reply = client.post("/timing", body)
        print(f"{reply['node']}: {reply['change']}")
    elif cmd == "mode":
        reply = client.post("/mode", {"mode": args.name, **({"force": True} if args.force else {})})
        print(f"mode {reply['mode']}")
    elif cmd == "modes":
        reply = client.get("/modes")
        for name in reply["modes"]:
            print(f"{'*' if name == reply['current'] else ' '} {name}")
        if not reply["modes"]:
            print("(the graph defines no modes)")
    elif cmd == "events":
        events = client.get(f"/events?n={args.n}")
        for e in events:
            detail = {k: v for k, v in e.items() if k not in ("kind", "t", "node")}
            print(f"{e['t']:9.3f}s {e['kind']} {e.get('node') or ''} {json.dumps(detail)}")
        if not events:
            print("none (no event since the start: misses, failures, restarts, changes)")
    elif cmd == "qos":
        print(client.get("/qos")["summary"])
    elif cmd == "rtdb":
        path = f"/rtdb/{args.name}?n={args.n}" if args.name else "/rtdb"
        records = client.get(path)
        for r in records:
            flag = " STALE" if r["stale"] else ""
            when = f"t={r['timestamp']:.3f}s age={r['age'] * 1000:.1f}ms{flag}"
            print(f"{r['name']} #{r['seq']} {when}: {json.dumps(r['value'])}")
        if not records:
            print("none (no RTDB record yet)")  # an unknown NAME is an error (404)
    return 0
