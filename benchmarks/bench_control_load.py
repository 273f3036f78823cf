"""Do 200 local HTTP clients disturb the cameras? The control endpoint and the live view.

    python benchmarks/bench_control_load.py                  # 200 clients, 20 s a run
    python benchmarks/bench_control_load.py --seconds 10 --repeat 3 --scenarios baseline,view

Runs graphs/cambada.yaml (two 20 Hz cameras, nine tracker processes, the display) embedded,
with its control endpoint on a free loopback port, once per scenario:

- ``baseline``: nobody connected;
- ``control``: ``--clients`` clients, each its own connection, polling ``GET /stats`` of the
  control endpoint as fast as it answers;
- ``view``: as many clients of the live view, each looping over ``/frame/front_cam.jpg``,
  ``/frame/omni_cam.jpg`` and ``/stats.json``;
- ``echo`` (with ``--scenarios``): the ``control`` clients against a server with nothing
  behind it (the same answer, pacing and priority): what the clients' own CPU load does to
  the graph on this machine, whatever serves them.

The clients run in a process of their own (at the shell's priority). After a warm-up the
interval statistics are reset, the clients start, and after ``--seconds`` the table gives,
per critical node (the cameras, Avoid_*, Ball_Om), the inter-activation interval mean and
std, skipped activations and deadline misses, the std's ratio to the baseline run, and how
many requests the clients got answered (and refused or failed), with the CPU time the
runtime's own process (the event loop, and its threads) used per second of the run: the work
the clients cost the scheduler's process, which the machine's other load does not change
much. Target (issue 19): 200 clients change the critical nodes' interval std by less than
10 %.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import socket
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
CRITICAL = ["front_cam", "omni_cam", "avoid_fr", "avoid_om", "ball_om"]
PATHS = {
    "control": ["/stats"],
    "echo": ["/stats"],
    "view": ["/frame/front_cam.jpg", "/frame/omni_cam.jpg", "/stats.json"],
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def clients(base: str, paths: list[str], n: int, seconds: float, out: Any) -> None:
    """The load: ``n`` clients, one connection each, requesting ``paths`` in turn."""
    import aiohttp

    async def one(i: int, counts: dict[str, int], end: float) -> None:
        connector = aiohttp.TCPConnector(limit=1)
        timeout = aiohttp.ClientTimeout(total=10)
        async with aiohttp.ClientSession(connector=connector, timeout=timeout) as s:
            k = i
            while time.monotonic() < end:
                path = paths[k % len(paths)]
                k += 1
                try:
                    async with s.get(base + path) as r:
                        await r.read()
                        key = "ok" if r.status == 200 else f"http {r.status}"
                except (aiohttp.ClientError, OSError, TimeoutError) as e:
                    key = type(e).__name__
                    await asyncio.sleep(0.05)  # a refused client comes back, not in a spin
                counts[key] = counts.get(key, 0) + 1

    async def main() -> dict[str, int]:
        counts: dict[str, int] = {}
        end = time.monotonic() + seconds
        cpu = time.process_time()
        await asyncio.gather(*(one(i, counts, end) for i in range(n)))
        counts["cpu"] = round((time.process_time() - cpu) / seconds * 1000)
        return counts

    out.send(asyncio.run(main()))


def echo(sock: socket.socket, body: bytes, pace: float) -> None:
    """The ``echo`` scenario's server: the same answer and pacing as the control endpoint's
    server (one answer per connection per ``pace`` s, nice 19), but nothing behind it, so
    the run shows what the clients' load alone does to the graph."""
    import os

    from aiohttp import web

    os.setpriority(os.PRIO_PROCESS, 0, 19)
    due: dict[Any, float] = {}

    async def stats(request: web.Request) -> web.Response:
        now = time.monotonic()
        wait = due.get(request.transport, 0.0) - now
        if wait > 0:
            await asyncio.sleep(wait)
        due[request.transport] = max(now, due.get(request.transport, 0.0)) + pace
        return web.Response(body=body, content_type="application/json")

    async def main() -> None:
        app = web.Application()
        app.add_routes([web.get("/stats", stats)])
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        await web.SockSite(runner, sock).start()
        await asyncio.Event().wait()

    asyncio.run(main())


async def scenario(
    name: str, n: int, seconds: float, warmup: float, max_clients: int
) -> dict[str, Any]:
    import flowrt
    from flowrt.stats import Running

    graph = flowrt.Graph.from_file(ROOT / "graphs" / "cambada.yaml")
    view_port = free_port()
    view = graph.nodes["display"]
    update: dict[str, Any] = {"port": view_port}
    if "max_clients" in type(view.params).model_fields:  # (a display before its cap: as is)
        update["max_clients"] = max_clients
    view.params = view.params.model_validate({**view.params.model_dump(), **update})
    async with (
        flowrt.Runtime(graph) as rt,
        flowrt.ControlServer(rt, f"127.0.0.1:{free_port()}") as server,
    ):
        await asyncio.sleep(warmup)
        for r in rt.scheduler.runners.values():
            r.counts.interval = Running()
        first = rt.stats()
        before = {c: (first.node(c).skipped, first.node(c).deadline_misses) for c in CRITICAL}
        cpu0 = time.process_time()  # the runtime's process: the loop and its threads
        wall0 = time.monotonic()
        proc = echo_proc = None
        ctx = multiprocessing.get_context("spawn")
        if name == "echo":
            from flowrt.control.server import READ_MAX_AGE, listen

            sock = listen("127.0.0.1", 0)
            echo_port = sock.getsockname()[1]
            body = rt.stats().model_dump_json().encode()
            echo_proc = ctx.Process(target=echo, args=(sock, body, READ_MAX_AGE), daemon=True)
            echo_proc.start()
            sock.close()
        if name != "baseline":
            base = {
                "control": server.url,
                "view": f"http://127.0.0.1:{view_port}",
                "echo": f"http://127.0.0.1:{echo_port}" if name == "echo" else "",
            }[name]
            ours, theirs = ctx.Pipe()
            proc = ctx.Process(target=clients, args=(base, PATHS[name], n, seconds, theirs))
            proc.start()
        await asyncio.sleep(seconds)
        cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0) * 1000
        stats = rt.stats()
        counts: dict[str, int] = {}
        if proc is not None:
            counts = await asyncio.to_thread(ours.recv)
            await asyncio.to_thread(proc.join, 10)
        if echo_proc is not None:
            echo_proc.kill()
            await asyncio.to_thread(echo_proc.join, 5)
        rows = {}
        for c in CRITICAL:
            s = stats.node(c)
            rows[c] = {
                "mean": s.interval.mean,
                "std": s.interval.std,
                "max": s.interval.max,
                "skipped": s.skipped - before[c][0],
                "misses": s.deadline_misses - before[c][1],
            }
        return {
            "rows": rows,
            "counts": counts,
            "lag_p99": stats.loop.lag.p99,
            "cpu": cpu,
            "answered": server.answered,
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--scenarios", default="baseline,control,view")
    ap.add_argument(
        "--repeat", type=int, default=1, help="run the scenarios in turn this many times"
    )
    ap.add_argument(
        "--view-max-clients",
        type=int,
        default=256,
        help="the display's max_clients (default 256: every client is served)",
    )
    args = ap.parse_args()
    import flowrt

    names = args.scenarios.split(",")
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    for rep in range(args.repeat):
        for name in names:
            print(f"run {rep + 1}: {name} ({args.seconds:g} s)...", file=sys.stderr, flush=True)
            res = flowrt.run(
                scenario(name, args.clients, args.seconds, args.warmup, args.view_max_clients)
            )
            results[name].append(res)
    print(
        f"\n{args.clients} clients, {args.seconds:g} s per run, {args.repeat} run(s) per "
        "scenario in turn, graphs/cambada.yaml; std: the mean of the runs' std\n"
    )
    print(
        "| scenario | node | interval mean ms | std ms | std / baseline | max ms | skipped "
        "| misses |"
    )
    print("|---|---|---|---|---|---|---|---|")

    def avg(runs: list[dict[str, Any]], node: str, key: str) -> float:
        return sum(r["rows"][node][key] for r in runs) / len(runs)

    base = results.get("baseline")
    for name, runs in results.items():
        for c in CRITICAL:
            std = avg(runs, c, "std")
            ratio = f"{std / avg(base, c, 'std'):.2f}" if base else "-"
            print(
                f"| {name} | {c} | {avg(runs, c, 'mean'):.3f} | {std:.3f} | {ratio} | "
                f"{max(r['rows'][c]['max'] for r in runs):.2f} | "
                f"{sum(r['rows'][c]['skipped'] for r in runs)} | "
                f"{sum(r['rows'][c]['misses'] for r in runs)} |"
            )
        if base and name != "baseline":
            ratio = sum(avg(runs, c, "std") for c in CRITICAL) / sum(
                avg(base, c, "std") for c in CRITICAL
            )
            print(f"| {name} | **all critical** | | | **{ratio:.2f}** | | | |")
    print(
        "\n| scenario | runtime process CPU ms/s | clients' CPU ms/s | loop lag p99 ms "
        "| client requests (by outcome) | answered by the runtime |"
    )
    print("|---|---|---|---|---|---|")
    for name, runs in results.items():
        counts: dict[str, int] = {}
        client_cpu = sum(r["counts"].get("cpu", 0) for r in runs) / len(runs)
        for r in runs:
            for k, v in r["counts"].items():
                if k != "cpu":
                    counts[k] = counts.get(k, 0) + v
        outcome = ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "-"
        lag = max(r["lag_p99"] for r in runs)
        cpu = sum(r["cpu"] for r in runs) / len(runs)
        answered = sum(r["answered"] for r in runs)
        print(f"| {name} | {cpu:.0f} | {client_cpu:.0f} | {lag:.3f} | {outcome} | {answered} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
