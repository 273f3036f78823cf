"""A 1 ms timer node: ``timing: precise`` (its own release thread) against the loop's timer.

    python benchmarks/bench_precise.py [--duration 5] [--rounds 3] [--burners 0]

Each configuration runs in a subprocess of its own for ``--duration`` seconds, in
interleaved rounds (normal, precise, precise-spin, normal, ...: the machine's load moves
between rounds, and each round compares what ran within the same minute):

- ``normal``: a node on a 1 ms timer (``trigger: {timer: 1ms}``), released by the loop's
  timerfd (flowrt/clock.py);
- ``precise``: the same with ``timing: precise`` (flowrt/kernel/precise.py: a thread sleeping
  to each instant with an absolute clock_nanosleep, the call run in that thread);
- ``precise-spin``: the same with ``spin: 50us`` (the thread spins the last 50 us);
- ``normal-rt``, ``precise-rt``: ``normal`` and ``precise`` with ``Runtime(realtime=True)``
  (``flowrt run --realtime``: SCHED_FIFO where permitted; the release thread inherits it).

The node keeps ``time.monotonic()`` at the start of each call (what a device would see);
reported per run: the interval's p50, p99, max and std, |interval - 1 ms| p99, and the
activations skipped (late releases). A loop beside it stays busy the way a graph's is: a
second node on a 3 ms timer burns 0.3 ms per call on the loop, ``--busy-phase`` ms into each
period (default 0.9: its call straddles every third release of the 1 ms node; 0: it starts
with that release, after it in priority order, and never delays the loop's own timer). The
load average is printed with every row: on a shared machine the figures are "measured under
load".
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import time
from typing import Any

KINDS = ["normal", "precise", "precise-spin", "normal-rt", "precise-rt"]


def _spin() -> None:
    while True:
        pass


def one(kind: str, duration: float, busy_phase: float) -> dict[str, Any]:
    import flowrt
    from flowrt import GraphBuilder, Node, Output, Runtime

    stamps: list[float] = []

    class Stamp(Node):
        value = Output(int)

        def process(self) -> int:
            stamps.append(time.monotonic())
            return len(stamps)

    g = GraphBuilder("bench-precise")
    extra: dict[str, Any] = {}
    if kind.startswith("precise"):
        extra["timing"] = "precise"
    if kind == "precise-spin":
        extra["spin"] = "50us"
    g.add("stamp", Stamp, trigger={"timer": "1ms"}, priority=50, **extra)
    busy = {"timer": "3ms", "phase": f"{busy_phase}ms"}
    g.add("busy", "burn", params={"ms": 0.3}, trigger=busy, priority=10)
    out: dict[str, Any] = {}

    async def main() -> None:
        async with Runtime(g.build(), realtime=kind.endswith("-rt")) as rt:
            await asyncio.sleep(duration)
            st = rt.stats().node("stamp")
            out["activations"], out["skipped"] = st.activations, st.skipped
            out["flowrt_interval_std_ms"] = st.interval.std

    flowrt.run(main())
    gaps = [(b - a) * 1000 for a, b in itertools.pairwise(stamps[10:])]  # start-up left out
    gaps.sort()
    errs = sorted(abs(x - 1.0) for x in gaps)
    return {
        **out,
        "intervals": len(gaps),
        "p50_ms": statistics.median(gaps),
        "p99_ms": gaps[int(0.99 * (len(gaps) - 1))],
        "max_ms": gaps[-1],
        "std_ms": statistics.pstdev(gaps),
        "err_p99_ms": errs[int(0.99 * (len(errs) - 1))],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--burners", type=int, default=0, help="processes spinning meanwhile")
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=KINDS[:3])
    ap.add_argument("--busy-phase", type=float, default=0.9)
    ap.add_argument("--one", choices=KINDS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.duration, args.busy_phase)))
        return
    burners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.burners)]
    for b in burners:
        b.start()
    rows = []
    try:
        for rnd in range(1, args.rounds + 1):
            for kind in args.kinds:
                la = os.getloadavg()[0]
                res = subprocess.run(
                    [
                        *(sys.executable, __file__, "--one", kind),
                        *("--duration", str(args.duration), "--busy-phase", str(args.busy_phase)),
                    ],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                r = json.loads(res.stdout.strip().splitlines()[-1])
                r.update(round=rnd, kind=kind, loadavg=la)
                rows.append(r)
                print(json.dumps(r), flush=True)
    finally:
        for b in burners:
            b.terminate()
            b.join()
    print(
        f"\nburners: {args.burners}, busy phase {args.busy_phase} ms; "
        "load average (1 min) at the start of each run\n"
    )
    print(
        "| round | release | intervals | skipped | p50 ms | p99 ms | max ms | std ms "
        "| abs(interval - 1 ms) p99 | load avg |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['round']} | {r['kind']} | {r['intervals']} | {r['skipped']} | "
            f"{r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['max_ms']:.3f} | {r['std_ms']:.3f} | "
            f"{r['err_p99_ms']:.3f} | {r['loadavg']:.2f} |"
        )
    print("\nMedian over rounds:\n")
    for kind in args.kinds:
        mine = [r for r in rows if r["kind"] == kind]
        p99 = statistics.median(r["p99_ms"] for r in mine)
        std = statistics.median(r["std_ms"] for r in mine)
        print(f"- {kind}: interval p99 {p99:.3f} ms, std {std:.3f} ms")


if __name__ == "__main__":
    main()
