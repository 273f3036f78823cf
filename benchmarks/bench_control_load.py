"""Do 200 local HTTP clients disturb the cameras? The control endpoint and the live view.

    python benchmarks/bench_control_load.py                      # 200 clients, 20 s a run
    python benchmarks/bench_control_load.py --clients 200 --seconds 20 --scenarios baseline,control,view

Runs graphs/cambada.yaml (two 20 Hz cameras, nine tracker processes, the display) embedded,
with its control endpoint on a free loopback port, once per scenario:

- ``baseline``: nobody connected;
- ``control``: ``--clients`` clients, each its own connection, polling ``GET /stats`` of the
  control endpoint as fast as it answers;
- ``view``: as many clients of the live view, each looping over ``/frame/front_cam.jpg``,
  ``/frame/omni_cam.jpg`` and ``/stats.json``.

The clients run in a process of their own (at the shell's priority). After a warm-up the
interval statistics are reset, the clients start, and after ``--seconds`` the table gives,
per critical node (the cameras, Avoid_*, Ball_Om), the inter-activation interval mean and
std, skipped activations and deadline misses, the std's ratio to the baseline run, and how
many requests the clients got answered (and refused or failed). Target (issue 19): 200
clients change the critical nodes' interval std by less than 10 %.
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
        await asyncio.gather(*(one(i, counts, end) for i in range(n)))
        return counts

    out.send(asyncio.run(main()))


async def scenario(name: str, n: int, seconds: float, warmup: float) -> dict[str, Any]:
    import flowrt
    from flowrt.stats import Running

    graph = flowrt.Graph.from_file(ROOT / "graphs" / "cambada.yaml")
    view_port = free_port()
    view = graph.nodes["display"]
    view.params = view.params.model_validate({**view.params.model_dump(), "port": view_port})
    async with (
        flowrt.Runtime(graph) as rt,
        flowrt.ControlServer(rt, f"127.0.0.1:{free_port()}") as server,
    ):
        await asyncio.sleep(warmup)
        for r in rt.scheduler.runners.values():
            r.interval = Running()
        before = {c: (rt.stats().node(c).skipped, rt.stats().node(c).deadline_misses) for c in CRITICAL}
        proc = None
        if name != "baseline":
            base = server.url if name == "control" else f"http://127.0.0.1:{view_port}"
            ctx = multiprocessing.get_context("spawn")
            ours, theirs = ctx.Pipe()
            proc = ctx.Process(target=clients, args=(base, PATHS[name], n, seconds, theirs))
            proc.start()
        await asyncio.sleep(seconds)
        stats = rt.stats()
        counts: dict[str, int] = {}
        if proc is not None:
            counts = await asyncio.to_thread(ours.recv)
            await asyncio.to_thread(proc.join, 10)
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
            "answered": server.answered,
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--scenarios", default="baseline,control,view")
    args = ap.parse_args()
    import flowrt

    results = {}
    for name in args.scenarios.split(","):
        print(f"running {name} ({args.seconds:g} s)...", file=sys.stderr, flush=True)
        results[name] = flowrt.run(scenario(name, args.clients, args.seconds, args.warmup))
    base = results.get("baseline")
    print(f"\n{args.clients} clients, {args.seconds:g} s per run, graphs/cambada.yaml\n")
    print("| run | node | interval mean ms | std ms | std / baseline | max ms | skipped | misses |")
    print("|---|---|---|---|---|---|---|---|")
    for name, res in results.items():
        for c, row in res["rows"].items():
            ratio = f"{row['std'] / base['rows'][c]['std']:.2f}" if base else "-"
            print(
                f"| {name} | {c} | {row['mean']:.3f} | {row['std']:.3f} | {ratio} | "
                f"{row['max']:.2f} | {row['skipped']} | {row['misses']} |"
            )
    print("\n| run | loop lag p99 ms | client requests (by outcome) | answered by the runtime |")
    print("|---|---|---|---|")
    for name, res in results.items():
        outcome = ", ".join(f"{k} {v}" for k, v in sorted(res["counts"].items())) or "-"
        print(f"| {name} | {res['lag_p99']:.3f} | {outcome} | {res['answered']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
