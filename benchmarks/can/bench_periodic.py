"""Periodic CAN transmission jitter: flowrt's timer scheduler against python-can's send_periodic.

    python benchmarks/can/bench_periodic.py [--duration 15] [--burners 2]

8 messages (periodic.dbc: 2 each at 10, 20, 30 and 100 ms, 8 data bytes) on a python-can
virtual bus, for ``--duration`` seconds per configuration (the issue asks 60 s; 15 s here to
keep the shared machine usable: ~3000 intervals per configuration):

- ``flowrt``: one ``can`` node transmitting all 8 from its default timer trigger (the gcd of
  the cycles, 10 ms; each message on the ticks of its cycle), the values from ``can-signals``
  nodes; ``flowrt --realtime``: the same with SCHED_FIFO/nice for the loop where permitted;
- ``send_periodic``: python-can's ``bus.send_periodic(msg, period)`` for each message (its
  thread-based cyclic tasks), the way python-can users do it;
- ``flowrt-precise`` (``-rt``): the ``can`` node with ``timing: precise`` (its ticks released
  by a thread of its own sleeping to each instant, the node's ``process`` run there;
  flowrt/kernel/precise.py), at normal priority and with ``--realtime``;
  ``flowrt-precise-offsets-rt``: with the offsets of ``flowrt-offsets`` too (the signal
  nodes off the bus's instants: their work on the loop holds the GIL the thread needs);
  ``flowrt-precise-spin-rt``: the same with ``spin: 50us`` on the ``can`` node (its thread
  wakes 50 us early and spins to the instant: the wake-up's own latency taken off);
- with ``--kinds``, also ``flowrt-spin`` (``--spin 0.3ms``) and ``bare-loop`` /
  ``bare-thread``: no node at all, one sender of pre-built frames on flowrt's timerfd clock
  or in one thread sleeping to absolute deadlines (what a single sender per bus costs).

Each configuration runs in its own subprocess; a passive monitor bus in that process (read
only after the run, so it wakes no thread meanwhile) keeps the virtual bus's send timestamp
of every frame (stamped inside ``bus.send``): the measure is the send instant. Reported per
configuration: |interval - period| over all intervals of all 8 messages (p50, p99, max),
and the mean period error (drift).
Idle, then with ``--burners`` processes spinning ``while True: pass``.
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
from pathlib import Path
from typing import Any

KINDS = [
    "flowrt",
    "flowrt-rt",
    "flowrt-spin",
    "flowrt-offsets",
    "flowrt-precise",
    "flowrt-precise-rt",
    "flowrt-precise-offsets-rt",
    "flowrt-precise-spin-rt",
    "send_periodic",
    "bare-loop",
    "bare-thread",
]
HERE = Path(__file__).resolve().parent
DBC = HERE / "periodic.dbc"


SPIN = {"flowrt-spin": 0.0003}
"""``flowrt --spin 0.3ms``: the loop wakes 0.3 ms early and busy-waits to the release."""


def _spin() -> None:
    while True:
        pass


class Monitor:
    """A passive listener: a virtual bus nobody reads during the run (its queue is unbounded),
    drained afterwards. A reading thread would wake per frame and take the GIL from the
    sender right when it sends: the measure would disturb what it measures."""

    def __init__(self, channel: str) -> None:
        import can

        self.bus = can.Bus(interface="virtual", channel=channel)

    def drain(self) -> dict[int, list[float]]:
        out: dict[int, list[float]] = {}
        while (m := self.bus.recv(0)) is not None:
            out.setdefault(m.arbitration_id, []).append(m.timestamp)
        self.bus.shutdown()
        return out


def run_flowrt(
    duration: float,
    realtime: bool,
    spin: float = 0.0,
    offsets: bool = False,
    precise: bool = False,
    node_spin: str | None = None,
) -> dict[int, list[float]]:
    import cantools

    import flowrt
    from flowrt import GraphBuilder, Runtime

    db = cantools.database.load_file(str(DBC))
    channel = f"periodic-{os.getpid()}"
    g = GraphBuilder()
    inputs = {}
    for i, m in enumerate(db.messages):
        g.add(
            f"v{i}",
            "can-signals",
            params={"rate_ms": 100, "signals": {f"Value{i}": {}}},
            **({"trigger": {"timer": "100ms", "phase": "8.5ms"}} if offsets else {}),
        )
        inputs[m.name] = f"v{i}.values"
    g.add(
        "bus",
        "can",
        params={
            "interface": "virtual",
            "channel": channel,
            "dbc": str(DBC),
            # each message 1 ms after the one before in the 10 ms grid: one send per tick
            **(
                {"messages": {m.name: {"phase_ms": float(i)} for i, m in enumerate(db.messages)}}
                if offsets
                else {}
            ),
        },
        inputs=inputs,
        priority=50,
        **({"timing": "precise"} if precise else {}),
        **({"spin": node_spin} if node_spin else {}),
    )
    mon = Monitor(channel)

    async def main() -> None:
        async with Runtime(g.build(), realtime=realtime, spin=spin):
            await asyncio.sleep(duration)

    flowrt.run(main())
    return mon.drain()


def _messages(channel: str) -> tuple[Any, list[tuple[Any, float]]]:
    """A virtual bus on ``channel`` and the DBC's 8 frames, pre-built, with their cycles in ms:
    what python-can's users and the bare senders send."""
    import can
    import cantools

    db = cantools.database.load_file(str(DBC))
    bus = can.Bus(interface="virtual", channel=channel)
    msgs = [
        (
            can.Message(
                arbitration_id=m.frame_id, data=m.encode({f"Value{i}": 0}), is_extended_id=False
            ),
            float(m.cycle_time),
        )
        for i, m in enumerate(db.messages)
    ]
    return bus, msgs


def run_send_periodic(duration: float) -> dict[int, list[float]]:
    channel = f"periodic-{os.getpid()}"
    mon = Monitor(channel)
    bus, msgs = _messages(channel)
    tasks = [bus.send_periodic(msg, cycle_ms / 1000) for msg, cycle_ms in msgs]
    time.sleep(duration)
    for t in tasks:
        t.stop()
    bus.shutdown()
    return mon.drain()


def run_bare(duration: float, on_loop: bool) -> dict[int, list[float]]:
    """One sender, no flowrt node: the pre-built frames sent on a 10 ms grid, in DBC order,
    from flowrt's timerfd clock on the event loop (``bare-loop``) or from one thread sleeping
    to absolute deadlines (``bare-thread``). What a single sender per bus costs by itself."""
    channel = f"periodic-{os.getpid()}"
    mon = Monitor(channel)
    bus, msgs = _messages(channel)
    every = [(msg, round(cycle_ms / 10)) for msg, cycle_ms in msgs]  # in 10 ms ticks

    def tick(k: int) -> None:
        for msg, n in every:
            if k % n == 0:
                bus.send(msg)

    if on_loop:
        import flowrt
        from flowrt.clock import SystemClock

        async def main() -> None:
            k = itertools.count(1)
            timer = SystemClock().periodic(0.01, 0.0, lambda t, missed: tick(next(k)))
            await asyncio.sleep(duration)
            timer.cancel()

        flowrt.run(main())
    else:
        t0 = time.monotonic()
        for k in range(1, int(duration / 0.01)):
            delay = t0 + k * 0.01 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            tick(k)
    bus.shutdown()
    return mon.drain()


def per_message(stamps: dict[int, list[float]], periods: dict[int, float]) -> str:
    """p50 / p99 of |interval - period| per message, ms: where in a tick the error grows."""
    out = []
    for ident, ts in sorted(stamps.items()):
        ts = sorted(ts)[1:]
        errs = sorted(abs((b - a) * 1000 - periods[ident]) for a, b in itertools.pairwise(ts))
        out.append(
            f"{ident:#x} {statistics.median(errs):.3f}/{errs[int(0.99 * (len(errs) - 1))]:.3f}"
        )
    return ", ".join(out)


def summarise(stamps: dict[int, list[float]], periods: dict[int, float]) -> dict[str, Any]:
    errs: list[float] = []
    drift: list[float] = []
    for ident, ts in stamps.items():
        ts = sorted(ts)[1:]  # the first interval starts with the start-up
        p = periods[ident]
        gaps = [(b - a) * 1000 for a, b in itertools.pairwise(ts)]
        errs += [abs(g - p) for g in gaps]
        if gaps:
            drift.append(statistics.fmean(gaps) - p)
    errs.sort()
    return {
        "intervals": len(errs),
        "p50_ms": statistics.median(errs),
        "p99_ms": errs[int(0.99 * (len(errs) - 1))],
        "max_ms": errs[-1],
        "mean_period_error_ms": max(drift, key=abs),
        "frames": sum(len(v) for v in stamps.values()),
    }


def one(kind: str, duration: float) -> None:
    import cantools

    db = cantools.database.load_file(str(DBC))
    periods = {m.frame_id: float(m.cycle_time) for m in db.messages}
    if kind == "send_periodic":
        stamps = run_send_periodic(duration)
    elif kind.startswith("bare-"):
        stamps = run_bare(duration, on_loop=kind == "bare-loop")
    else:
        stamps = run_flowrt(
            duration,
            realtime=kind.endswith("-rt"),
            spin=SPIN.get(kind, 0.0),
            offsets="offsets" in kind or "spin-rt" in kind,
            precise=kind.startswith("flowrt-precise"),
            node_spin="50us" if kind == "flowrt-precise-spin-rt" else None,
        )
    print(json.dumps({**summarise(stamps, periods), "per_message": per_message(stamps, periods)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--burners", type=int, default=2)
    ap.add_argument("--one", choices=KINDS)
    ap.add_argument(
        "--kinds", nargs="+", choices=KINDS, default=["flowrt", "flowrt-rt", "send_periodic"]
    )
    ap.add_argument("--json", help="write all results here")
    ap.add_argument("--rounds", type=int, default=1, help="interleaved rounds of the kinds")
    args = ap.parse_args()
    if args.one:
        one(args.one, args.duration)
        return
    rows = []
    loads = ("idle", f"{args.burners} burners") if args.burners else ("idle",)
    for load in loads:
        burners = []
        if load != "idle":
            burners = [
                multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.burners)
            ]
            for b in burners:
                b.start()
            time.sleep(1.0)
        try:
            for kind in [k for _ in range(args.rounds) for k in args.kinds]:
                la = os.getloadavg()[0]
                res = subprocess.run(
                    [sys.executable, __file__, "--one", kind, "--duration", str(args.duration)],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                r = json.loads(res.stdout.strip().splitlines()[-1])
                r.update(load=load, kind=kind, loadavg=la)
                rows.append(r)
                print(json.dumps(r), flush=True)
        finally:
            for b in burners:
                b.terminate()
                b.join()
    print(
        "\n|load | sender | intervals | p50 ms | p99 ms | max ms | mean period error ms |"
        " load avg at start |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['load']} | {r['kind']} | {r['intervals']} | {r['p50_ms']:.3f} | "
            f"{r['p99_ms']:.3f} | {r['max_ms']:.3f} | {r['mean_period_error_ms']:+.4f} | "
            f"{r['loadavg']:.2f} |"
        )
    print("\nPer message, |interval - period| p50/p99 ms:\n")
    for r in rows:
        print(f"- {r['load']}, {r['kind']}: {r['per_message']}")
    for load in loads:
        by = {r["kind"]: r for r in rows if r["load"] == load}  # the last round
        if "send_periodic" in by:
            ratios = ", ".join(
                f"{k} {by['send_periodic']['p99_ms'] / by[k]['p99_ms']:.1f}x"
                for k in by
                if k != "send_periodic"
            )
            print(f"\n{load}: send_periodic p99 / p99 of {ratios}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
