"""Per-hop latency of an inline chain: flowrt vs a plain asyncio.Queue chain, on uvloop and asyncio.

    python benchmarks/bench_hops.py                        # 10 hops, 20000 messages per subject
    python benchmarks/bench_hops.py --hops 10 --messages 20000 --burst 1000 --rounds 4

The chain: ``source -> relay1 -> ... -> relay{H-1} -> sink``, ``H`` hops (H edges and H node
activations: H-1 ``relay`` built-ins, input-triggered, and the sink). The host program stamps
``t0 = perf_counter()`` and injects it with ``rt.publish("source.value", t0)`` (``source`` is
disabled: it only gives the host an output to publish on); the sink (a node of this module)
computes ``perf_counter() - t0`` when it is activated and returns it, and the host reads it
through ``rt.subscribe("sink.latency")`` before sending the next message (one in flight at a
time). Per-hop latency = end-to-end / H; the host's own wake-up is outside the measured span.

Baselines, in the same run and on the same loops:
- asyncio.Queue: ``H`` queues and ``H`` tasks (H-1 relays ``q[i+1].put_nowait(await q[i].get())``
  and a sink that computes the same latency), read by the host through one more queue;
- bare call_soon: each hop one ``loop.call_soon`` of a plain function, nothing else: the
  event loop's own dispatch cost, the floor for any design that yields to the loop per hop.

Subjects: flowrt+uvloop (``flowrt.cli.new_event_loop``, what ``flowrt run`` uses),
flowrt+asyncio (``asyncio.new_event_loop``), and each baseline on both loops. The messages
are split into ``--rounds`` rounds and the subjects interleaved round by round (order reversed
every other round), so background noise on a shared machine hits them alike.

Throughput (``--burst`` messages in flight): the host publishes a burst back to back, then
reads every result; reported as time per message per hop and messages per second. Edge
queues are sized to the burst, so nothing is dropped (checked, ``dropped`` column). Note that
an asyncio.Queue relay task drains its whole queue without returning to the loop (``get`` on a
non-empty queue does not suspend), so in a burst it moves messages in batches; flowrt
activates a node once per message and per loop turn, so that timers and other nodes interleave.

Target: inline per-hop overhead <= 20 us.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict

from flowrt import GraphBuilder, Input, InputTrigger, Node, Output, Runtime, TimerTrigger

TARGET_US = 20.0


class StampSink(Node):
    """End of the chain: returns how long ago (perf_counter seconds) the value was stamped."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

    input = Input(float)
    latency = Output(float)

    def process(self, input: float) -> float:
        return time.perf_counter() - input


class HostSource(Node):
    """Start of the chain; never activated (disabled): the host publishes on its output."""

    value = Output(float)

    def process(self) -> None:
        return None


def build_chain(hops: int, size: int) -> Any:
    g = GraphBuilder(f"hops-{hops}")
    g.add("source", HostSource, trigger=TimerTrigger(timer=3_600_000), enabled=False)
    prev = "source.value"
    for i in range(1, hops):
        g.add(
            f"relay{i}",
            "relay",
            trigger=InputTrigger(),
            inputs={"input": {"from": prev, "size": size}},
        )
        prev = f"relay{i}.output"
    g.add("sink", StampSink, trigger=InputTrigger(), inputs={"input": {"from": prev, "size": size}})
    return g.build()


# --- one subject = one (chain implementation, event loop) ---------------------------------------


@dataclass
class Samples:
    latency: list[float] = field(default_factory=list)  # end-to-end, seconds
    burst_time: list[float] = field(default_factory=list)  # seconds per burst
    dropped: int = 0


async def flowrt_run(
    hops: int, messages: int, burst: int, bursts: int, warmup: int, out: Samples
) -> None:
    size = max(8, burst)
    rt = Runtime(build_chain(hops, size))
    async with rt:
        sub = rt.subscribe("sink.latency", size=size)
        publish, get, now = rt.publish, sub.get, time.perf_counter
        for _ in range(warmup):
            publish("source.value", now())
            await get()
        gc.collect()
        lat = out.latency
        for _ in range(messages):
            publish("source.value", now())
            lat.append(await get())
        if burst:
            for _ in range(bursts):
                t0 = now()
                for _ in range(burst):
                    publish("source.value", now())
                for _ in range(burst):
                    await get()
                out.burst_time.append(now() - t0)
        out.dropped += sum(e.dropped for e in rt.stats().edges) + sub.dropped


async def queue_run(
    hops: int, messages: int, burst: int, bursts: int, warmup: int, out: Samples
) -> None:
    qs: list[asyncio.Queue[float]] = [asyncio.Queue() for _ in range(hops)]
    result: asyncio.Queue[float] = asyncio.Queue()

    async def relay(src: asyncio.Queue[float], dst: asyncio.Queue[float]) -> None:
        while True:
            dst.put_nowait(await src.get())

    async def sink(src: asyncio.Queue[float]) -> None:
        while True:
            v = await src.get()
            result.put_nowait(time.perf_counter() - v)

    tasks = [asyncio.create_task(relay(qs[i], qs[i + 1])) for i in range(hops - 1)]
    tasks.append(asyncio.create_task(sink(qs[-1])))
    await asyncio.sleep(0)
    put, get, now = qs[0].put_nowait, result.get, time.perf_counter
    try:
        for _ in range(warmup):
            put(now())
            await get()
        gc.collect()
        lat = out.latency
        for _ in range(messages):
            put(now())
            lat.append(await get())
        if burst:
            for _ in range(bursts):
                t0 = now()
                for _ in range(burst):
                    put(now())
                for _ in range(burst):
                    await get()
                out.burst_time.append(now() - t0)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def callsoon_run(
    hops: int, messages: int, burst: int, bursts: int, warmup: int, out: Samples
) -> None:
    """The floor: each hop is one bare ``loop.call_soon`` (no queue, no task, no bookkeeping)."""
    loop = asyncio.get_running_loop()
    result: asyncio.Queue[float] = asyncio.Queue()
    call_soon, now = loop.call_soon, time.perf_counter

    def hop(k: int, t0: float) -> None:
        if k == 1:
            result.put_nowait(now() - t0)
        else:
            call_soon(hop, k - 1, t0)

    get = result.get
    for _ in range(warmup):
        call_soon(hop, hops, now())
        await get()
    gc.collect()
    lat = out.latency
    for _ in range(messages):
        call_soon(hop, hops, now())
        lat.append(await get())
    if burst:
        for _ in range(bursts):
            t0 = now()
            for _ in range(burst):
                call_soon(hop, hops, now())
            for _ in range(burst):
                await get()
            out.burst_time.append(now() - t0)


def uvloop_factory() -> asyncio.AbstractEventLoop:
    from flowrt.system._eventloop import new_event_loop

    loop = new_event_loop()
    if type(loop).__module__.split(".")[0] != "uvloop":
        raise SystemExit("uvloop is not installed: pip install uvloop")
    return loop


SUBJECTS: dict[str, tuple[Callable[..., Any], Callable[[], asyncio.AbstractEventLoop]]] = {
    "flowrt + uvloop": (flowrt_run, uvloop_factory),
    "flowrt + asyncio": (flowrt_run, asyncio.new_event_loop),
    "asyncio.Queue + uvloop": (queue_run, uvloop_factory),
    "asyncio.Queue + asyncio": (queue_run, asyncio.new_event_loop),
    "bare call_soon + uvloop": (callsoon_run, uvloop_factory),
    "bare call_soon + asyncio": (callsoon_run, asyncio.new_event_loop),
}


def pct(ordered: list[float], q: float) -> float:
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--hops",
        type=int,
        default=10,
        help="edges from publish to sink (default 10: 9 relays + sink)",
    )
    p.add_argument(
        "--messages",
        type=int,
        default=20000,
        help="sequential messages per subject (default 20000)",
    )
    p.add_argument(
        "--burst",
        type=int,
        default=1000,
        help="messages in flight for the throughput figure; 0: skip",
    )
    p.add_argument("--bursts", type=int, default=5, help="bursts per subject and round (default 5)")
    p.add_argument(
        "--rounds", type=int, default=4, help="interleave the subjects over this many rounds"
    )
    p.add_argument(
        "--warmup", type=int, default=500, help="messages discarded at the start of each round"
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="run this process SCHED_FIFO (as flowrt run --realtime): tails without other "
        "processes' noise",
    )
    args = p.parse_args(argv)
    if args.hops < 1:
        p.error("--hops must be >= 1")

    from importlib.metadata import version

    granted = "not requested (SCHED_OTHER)"
    if args.realtime:
        from flowrt.system._realtime import enable_realtime

        ok, granted = enable_realtime()
        if not ok:
            granted = "refused: " + granted
    print(f"# bench_hops: {args.hops} hops, {args.messages} sequential messages per subject")
    print(
        f"\n{platform.node()} · {platform.platform()} · "
        f"{os.cpu_count()} CPUs · Python {platform.python_version()} "
        f"· uvloop {version('uvloop')} · load average "
        f"{os.getloadavg()[0]:.2f} at start · scheduling: {granted}"
    )
    samples = {name: Samples() for name in SUBJECTS}
    per_round = math.ceil(args.messages / args.rounds)
    for r in range(args.rounds):
        order = list(SUBJECTS) if r % 2 == 0 else list(reversed(SUBJECTS))
        for name in order:
            print(f"  round {r + 1}/{args.rounds}: {name}", file=sys.stderr, flush=True)
            fn, factory = SUBJECTS[name]
            with asyncio.Runner(loop_factory=factory) as runner:
                runner.run(
                    fn(args.hops, per_round, args.burst, args.bursts, args.warmup, samples[name])
                )
    print(f"load average {os.getloadavg()[0]:.2f} at end")

    base = {
        "uvloop": samples["asyncio.Queue + uvloop"],
        "asyncio": samples["asyncio.Queue + asyncio"],
    }
    h = args.hops
    print(f"\n### Sequential (one message in flight): latency per hop, us (end-to-end / {h})\n")
    print(
        "| subject | messages | p50 / hop | p99 / hop "
        "| max / hop | end-to-end p50 | end-to-end p99 "
        "| p50 vs asyncio.Queue (same loop) | p50 <= 20 us |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|:---:|")
    medians = {}
    for name, s in samples.items():
        o = sorted(s.latency)
        p50, p99, mx = pct(o, 0.5) * 1e6, pct(o, 0.99) * 1e6, o[-1] * 1e6
        medians[name] = p50
        loop_name = name.split(" + ")[1]
        ref = sorted(base[loop_name].latency)
        ratio = p50 / (pct(ref, 0.5) * 1e6)
        print(
            f"| {name} | {len(o)} | {p50 / h:.1f} | {p99 / h:.1f} "
            f"| {mx / h:.1f} | {p50:.1f} | {p99:.1f} "
            f"| {ratio:.2f}x | {'yes' if p50 / h <= TARGET_US else 'no'} |"
        )
    if args.burst:
        print(f"\n### Throughput ({args.burst} messages in flight): time per message per hop\n")
        print(
            "| subject | bursts | us / message / hop (median "
            "burst) | messages / s through the chain "
            "| vs asyncio.Queue (same loop) | dropped |"
        )
        print("|---|---:|---:|---:|---:|---:|")
        for name, s in samples.items():
            o = sorted(s.burst_time)
            med = pct(o, 0.5)
            per = med / (args.burst * h) * 1e6
            loop_name = name.split(" + ")[1]
            ref_med = pct(sorted(base[loop_name].burst_time), 0.5)
            print(
                f"| {name} | {len(o)} | {per:.2f} | {args.burst / med:,.0f} "
                f"| {med / ref_med:.2f}x | {s.dropped} |"
            )
    print(
        f"\nflowrt overhead per hop over asyncio.Queue, median: uvloop "
        f"{(medians['flowrt + uvloop'] - medians['asyncio.Queue + uvloop']) / h:.1f} us, asyncio "
        f"{(medians['flowrt + asyncio'] - medians['asyncio.Queue + asyncio']) / h:.1f} us"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
