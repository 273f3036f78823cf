"""How the runtime's own cost grows with the graph: nodes, workers, readers, recorded streams.

    python -m benchmarks.bench_scale [--seconds 4] [--rounds 3] [--out FILE.json] [--plot FILE.png]
    python -m benchmarks.bench_scale --only inline        # or workers, readers, record

Every point runs in a subprocess of its own (a clean heap, its own RSS), all points in one
run, neighbours back to back, so that they share the machine's state:

- ``inline``: 10 / 100 / 1000 inline nodes in four shapes: a chain (a timer source and N-1
  input-triggered relays), a fan-out (one timer source, N input-triggered readers), timers
  (N timer nodes, same period and phase) and frame ticks (a frame source, N frame-triggered
  readers, period 1). The rate is 100 Hz while the N nodes stay within 10 000 activations
  per second, lower beyond (1000 nodes: 10 Hz), so that the loop is never saturated and the
  per-activation figure is the runtime's cost, not a backlog's. Reported: the runtime process's
  CPU per activation (``time.process_time`` over the steady window / activations in it: every
  thread of the process, so the recorder's writer too; "net" takes off what an idle runtime
  uses per second, measured as its own point), the
  tick-to-last-activation latency (the source's stamp, or the timer's nominal release, to the
  last node's activation in that tick), start-up (validate: the graph model and its kinds;
  build: ``Runtime.start``; first: from the start to the first activation of the last node),
  teardown (``Runtime.stop``) and RSS.
- ``workers``: 1 / 8 / 32 ``process`` nodes on a 20 Hz timer each (an empty ``process``):
  start-up, PSS of the whole tree (the runtime, its forkserver, the workers), the per-call
  overhead (response time release -> finish, median over the workers, of an empty call), and
  what a dead worker costs the rest: one worker is SIGKILLed mid-run; the others' response
  p99 in the second after the kill against the second before, and how long the dead one
  takes to come back.
- ``readers``: 1 / 10 / 100 inline readers (``latest`` edges, frame-triggered) of one
  1920x1080x3 frame at 20 Hz: what a publication costs the source (``ctx.publish``, the
  frame links and the readers' wake-ups) and the loop CPU per frame.
- ``record``: a ``recorder`` node recording 1 / 4 / 16 streams of 320x240x3 frames at 20 Hz
  (raw, no compression): loop CPU per recorded frame, what was written and lost.

The O(1) claim is that the CPU per activation does not grow with N; the plot shows it.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from pydantic import BaseModel, ConfigDict

import flowrt
from flowrt import Frame, GraphBuilder, Input, Node, Output, Runtime, TimerTrigger

NS = (10, 100, 1000)
SHAPES = ("chain", "fanout", "timers", "frames")
BUDGET = 10_000.0  # activations per second the inline points stay within
SEEN: dict[int, float] = {}  # tick -> the latest activation of any node in it (perf_counter)
STAMP: dict[int, float] = {}  # tick -> its start (perf_counter)


def rate_for(n: int) -> float:
    return min(100.0, BUDGET / n)


class _P(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rate: float = 100.0


class Source(Node):
    """Publishes (tick, perf_counter stamp) on its timer."""

    Params = _P
    out = Output(object)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> Any:
        self.n += 1
        t = time.perf_counter()
        STAMP[self.n] = t
        return (self.n, t)


class Relay(Node):
    """Passes its input on and notes when the tick reached it."""

    value = Input(object)
    out = Output(object)

    def process(self, value: Any) -> Any:
        SEEN[value[0]] = time.perf_counter()
        return value


class Reader(Node):
    value = Input(object)

    def process(self, value: Any) -> None:
        SEEN[value[0]] = time.perf_counter()


class TimerNode(Node):
    """One of N timer nodes of the same period and phase: notes its tick's last activation."""

    Params = _P

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate)

    def setup(self) -> None:
        self.period = 1.0 / self.params.rate

    def process(self) -> None:
        now = self.ctx.now()
        k = round((now - ORIGIN[0]) / self.period)
        SEEN[k] = max(SEEN.get(k, 0.0), now)


ORIGIN = [0.0]


class FrameSource(Node):
    """A frame source: a new pool frame per tick (tiny, or 1080p for the readers' points)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        rate: float = 100.0
        shape: tuple[int, ...] = (8, 8, 3)
        publish: bool = False  # ctx.publish (timed) instead of returning the frame

    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate)

    def setup(self) -> None:
        self.n = 0
        self.cost: list[float] = []

    def process(self) -> Any:
        self.n += 1
        f = self.ctx.new_frame(tuple(self.params.shape))
        f.seq = self.n
        t = time.perf_counter()
        STAMP[self.n] = t
        f.timestamp = self.ctx.now()
        if not self.params.publish:
            return f
        self.ctx.publish("frame", f)  # takes the creator's link
        self.cost.append(time.perf_counter() - t)
        return None


class FrameReader(Node):
    frame = Input(Frame)

    def process(self, frame: Frame) -> None:
        SEEN[frame.seq] = time.perf_counter()


class Empty(Node):
    """A worker node doing nothing but return a small value: the call's cost is the runtime's."""

    Params = _P
    done = Output(int)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate)

    def process(self) -> int:
        return 1


DONE: list[tuple[str, float]] = []  # (worker, when its result reached the loop)


class Collector(Node):
    """Inline, one per worker: when the worker's result arrived (the runtime's clock)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        worker: str

    value = Input(object)

    def process(self, value: Any) -> None:
        DONE.append((self.params.worker, self.ctx.now()))


# --- the points ------------------------------------------------------------------------------


def inline_graph(shape: str, n: int) -> flowrt.Graph:
    rate = rate_for(n)
    g = GraphBuilder(f"{shape}-{n}")
    if shape == "idle":  # the runtime's own background (its lag probe...): one 1 Hz node
        g.add("n0", Source, params={"rate": 1.0})
    elif shape == "chain":
        g.add("n0", Source, params={"rate": rate})
        for i in range(1, n):
            g.add(f"n{i}", Relay, inputs={"value": f"n{i - 1}.out"}, trigger="input")
    elif shape == "fanout":
        g.add("n0", Source, params={"rate": rate})
        for i in range(1, n):
            g.add(f"n{i}", Reader, inputs={"value": "n0.out"}, trigger="input")
    elif shape == "timers":
        for i in range(n):
            g.add(f"n{i}", TimerNode, params={"rate": rate})
    else:
        g.add("n0", FrameSource, params={"rate": rate})
        for i in range(1, n):
            g.add(f"n{i}", FrameReader, inputs={"frame": "n0.frame"}, trigger={"frame": "n0"})
    return g.build()


def _rss_mb() -> float:
    return float(psutil.Process().memory_info().rss / 2**20)


def _tree_pss_mb() -> float:
    total = 0.0
    me = psutil.Process()
    for p in [me, *me.children(recursive=True)]:
        try:
            m = p.memory_full_info()
        except (psutil.Error, OSError):
            continue
        total += getattr(m, "pss", m.rss)
    return total / 2**20


def _activations(rt: Runtime) -> int:
    return sum(n.activations for n in rt.stats().nodes)


async def _inline(shape: str, n: int, seconds: float) -> dict[str, Any]:
    rss0 = _rss_mb()
    t0 = time.perf_counter()
    graph = inline_graph(shape, n)
    t_validate = time.perf_counter() - t0
    rt = Runtime(graph)
    SEEN.clear()
    STAMP.clear()
    t1 = time.perf_counter()
    await rt.start()
    t_build = time.perf_counter() - t1
    ORIGIN[0] = rt.clock.origin
    # the first activation of the last node
    first_tick = None
    t_end = time.perf_counter() + 10
    while first_tick is None and time.perf_counter() < t_end:
        await asyncio.sleep(0.0005)
        if SEEN:
            first_tick = time.perf_counter()
    t_first = (first_tick or math.nan) - t1
    await asyncio.sleep(0.5)  # settle
    a0, c0 = _activations(rt), time.process_time()
    seen0 = max(SEEN, default=0)
    await asyncio.sleep(seconds)
    c1 = time.process_time()
    a1 = _activations(rt)
    seen1 = max(SEEN, default=0)
    stats = rt.stats()
    rss = _rss_mb()
    t2 = time.perf_counter()
    await rt.stop()
    t_stop = time.perf_counter() - t2
    if shape == "timers":
        period = 1.0 / rate_for(n)
        lat = [SEEN[k] - (ORIGIN[0] + k * period) for k in range(seen0 + 1, seen1) if k in SEEN]
    else:
        lat = [SEEN[k] - STAMP[k] for k in range(seen0 + 1, seen1) if k in SEEN and k in STAMP]
    skipped = sum(x.skipped for x in stats.nodes)
    dropped = sum(e.dropped for e in stats.edges)
    la = np.array(lat) * 1000 if lat else np.array([math.nan])
    return {
        "case": "inline",
        "shape": shape,
        "n": n,
        "rate_hz": rate_for(n),
        "activations": a1 - a0,
        "cpu_s_per_s": (c1 - c0) / seconds,
        "activations_per_s": (a1 - a0) / seconds,
        "cpu_us_per_activation": (c1 - c0) / max(1, a1 - a0) * 1e6,
        "latency_p50_ms": float(np.percentile(la, 50)),
        "latency_p99_ms": float(np.percentile(la, 99)),
        "validate_s": t_validate,
        "build_s": t_build,
        "first_s": t_first,
        "teardown_s": t_stop,
        "rss_mb": rss,
        "rss_delta_mb": rss - rss0,
        "skipped": skipped,
        "dropped": dropped,
        "loop_lag_p99_ms": stats.loop.lag.p99,
    }


async def _workers(n: int, seconds: float) -> dict[str, Any]:
    rate = 20.0
    g = GraphBuilder(f"workers-{n}")
    for i in range(n):
        g.add(f"w{i}", Empty, params={"rate": rate}, placement="process")
        g.add(f"c{i}", Collector, params={"worker": f"w{i}"}, inputs={"value": f"w{i}.done"})
    graph = g.build()
    rt = Runtime(graph)
    t0 = time.perf_counter()
    await rt.start()
    t_start = time.perf_counter() - t0
    # ready: every worker has completed a call
    end = time.perf_counter() + 60
    while time.perf_counter() < end:
        if all(x.completions > 0 for x in rt.stats().nodes):
            break
        await asyncio.sleep(0.02)
    t_ready = time.perf_counter() - t0
    await asyncio.sleep(1.0)
    pss = _tree_pss_mb()
    c0, a0 = time.process_time(), sum(x.completions for x in rt.stats().nodes if x.name[0] == "w")
    DONE.clear()
    await asyncio.sleep(seconds)
    c1, a1 = time.process_time(), sum(x.completions for x in rt.stats().nodes if x.name[0] == "w")
    period, origin = 1.0 / rate, rt.clock.origin

    def late(since: float, until: float, skip: str) -> list[float]:
        """Release (the timer's grid) to the result on the loop, ms, of the workers but one."""
        return [((t - origin) % period) * 1000 for w, t in DONE if w != skip and since <= t < until]

    steady = late(-math.inf, math.inf, "")
    # a dead worker: the others' release -> result in the second before and after the kill
    victim = rt._sched.runners["w0"].executor._inner  # type: ignore[union-attr]
    restarts0 = rt.stats().node("w0").restarts
    DONE.clear()
    await asyncio.sleep(1.0)
    t_kill = rt.clock.now()
    os.kill(victim.pid, signal.SIGKILL)
    lag_after = await _loop_lateness(1.0)  # is it the loop that is held, or the CPUs?
    skip = "w0" if n > 1 else ""
    before = late(t_kill - 1.0, t_kill, skip)
    after = late(t_kill, t_kill + 1.0, skip)
    back = math.nan
    end = time.perf_counter() + 30
    restarted: float | None = None  # a result after the restart: the successor's
    while time.perf_counter() < end:
        if restarted is None and rt.stats().node("w0").restarts > restarts0:
            restarted = rt.clock.now()
        back_at = [t for w, t in DONE if w == "w0" and restarted is not None and t > restarted]
        if back_at:
            back = back_at[0] - t_kill
            break
        await asyncio.sleep(0.005)
    t1 = time.perf_counter()
    await rt.stop()

    def p(xs: list[float], q: float) -> float:
        return float(np.percentile(xs, q)) if xs else math.nan

    return {
        "case": "workers",
        "n": n,
        "start_s": t_start,
        "ready_s": t_ready,
        "pss_mb": pss,
        "pss_per_worker_mb": pss / n,
        "call_ms_p50": p(steady, 50),
        "call_ms_p99": p(steady, 99),
        "loop_cpu_us_per_call": (c1 - c0) / max(1, a1 - a0) * 1e6,
        "cpu_s_per_s": (c1 - c0) / seconds,
        "calls_per_s": (a1 - a0) / seconds,
        "others_p99_before_ms": p(before, 99),
        "others_p99_after_kill_ms": p(after, 99),
        "others_max_after_kill_ms": max(after, default=math.nan),
        "loop_lateness_max_after_kill_ms": lag_after,
        "dead_back_s": back,
        "teardown_s": time.perf_counter() - t1,
    }


async def _loop_lateness(seconds: float) -> float:
    """The loop's worst lateness (ms) of a 1 ms sleep over ``seconds``."""
    end = time.monotonic() + seconds  # not loop.time(): uvloop's is cached per iteration
    worst = 0.0
    while (t := time.monotonic()) < end:
        await asyncio.sleep(0.001)
        worst = max(worst, time.monotonic() - t - 0.001)
    return worst * 1000


async def _readers(n: int, seconds: float) -> dict[str, Any]:
    g = GraphBuilder(f"readers-{n}")
    g.add("src", FrameSource, params={"rate": 20.0, "shape": (1080, 1920, 3), "publish": True})
    for i in range(n):
        g.add(f"r{i}", FrameReader, inputs={"frame": "src.frame"}, trigger={"frame": "src"})
    rt = Runtime(g.build())
    await rt.start()
    await asyncio.sleep(0.5)
    src = rt._sched.runners["src"].executor.node  # type: ignore[union-attr]
    src.cost.clear()
    c0, f0 = time.process_time(), src.n
    await asyncio.sleep(seconds)
    c1, f1 = time.process_time(), src.n
    cost = np.array(src.cost) * 1e6
    st = rt.stats()
    await rt.stop()
    return {
        "case": "readers",
        "n": n,
        "publish_us_p50": float(np.percentile(cost, 50)),
        "publish_us_p99": float(np.percentile(cost, 99)),
        "publish_us_per_reader": float(np.percentile(cost, 50)) / n,
        "loop_cpu_us_per_frame": (c1 - c0) / max(1, f1 - f0) * 1e6,
        "cpu_s_per_s": (c1 - c0) / seconds,
        "frames_per_s": (f1 - f0) / seconds,
        "skipped": sum(x.skipped for x in st.nodes),
    }


def _mcap_bytes(folder: str) -> int:
    """The recording's size, and the folder removed."""
    import shutil

    size = sum(p.stat().st_size for p in Path(folder).rglob("*.mcap"))
    shutil.rmtree(folder, ignore_errors=True)
    return size


async def _record(n: int, seconds: float) -> dict[str, Any]:
    tmp = tempfile.mkdtemp(prefix="flowrt_scale_")
    g = GraphBuilder(f"record-{n}")
    inputs = {}
    for i in range(n):
        g.add(f"cam{i}", FrameSource, params={"rate": 20.0, "shape": (240, 320, 3)})
        inputs[f"cam{i}"] = f"cam{i}.frame"
    g.add("rec", "recorder", params={"path": tmp, "name": "scale"}, inputs=inputs)
    rt = Runtime(g.build())
    await rt.start()
    await asyncio.sleep(0.5)
    c0, a0 = time.process_time(), _activations(rt)
    await asyncio.sleep(seconds)
    c1, a1 = time.process_time(), _activations(rt)
    await rt.stop()
    st = rt.stats()
    published = sum(e.published for e in st.edges if e.name.endswith(tuple(inputs)))
    dropped = sum(e.dropped for e in st.edges)
    frames = max(1, (a1 - a0) // 2)  # each frame: its source's and the recorder's activation
    size = await asyncio.to_thread(_mcap_bytes, tmp)
    return {
        "case": "record",
        "n": n,
        "loop_cpu_us_per_frame": (c1 - c0) / frames * 1e6,
        "cpu_s_per_s": (c1 - c0) / seconds,
        "frames_per_s": frames / seconds,
        "published": published,
        "dropped": dropped,
        "mcap_mb": size / 2**20,
    }


def point(case: str, shape: str, n: int, seconds: float) -> dict[str, Any]:
    gc.collect()
    if case == "inline":
        coro = _inline(shape, n, seconds)
    elif case == "workers":
        coro = _workers(n, seconds)
    elif case == "readers":
        coro = _readers(n, seconds)
    else:
        coro = _record(n, seconds)
    result: dict[str, Any] = flowrt.run(coro)
    return result


# --- the run ---------------------------------------------------------------------------------


def _child(case: str, shape: str, n: int, seconds: float) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "benchmarks.bench_scale", "--point", case, shape, str(n)]
    cmd += ["--seconds", str(seconds)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=600)
    if res.returncode != 0:
        return {"case": case, "shape": shape, "n": n, "error": res.stderr.strip()[-400:]}
    out: dict[str, Any] = json.loads(res.stdout.strip().splitlines()[-1])
    return out


def median_rows(runs: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Each point's figures: the median over the rounds (a failed round is left out)."""
    out = []
    for row in runs[0]:
        key = (row["case"], row.get("shape", "-"), row["n"])
        same = [
            r
            for rows in runs
            for r in rows
            if (r["case"], r.get("shape", "-"), r["n"]) == key and "error" not in r
        ]
        if not same:
            out.append(row)
            continue
        merged = dict(same[0])
        for k, v in same[0].items():
            if isinstance(v, int | float) and not isinstance(v, bool) and k != "n":
                merged[k] = float(np.median([r[k] for r in same]))
        out.append(merged)
    return out


def plan(only: str | None) -> list[tuple[str, str, int]]:
    points: list[tuple[str, str, int]] = []
    if only in (None, "inline"):
        points += [("inline", "idle", 1)]
        points += [("inline", s, n) for s in SHAPES for n in NS]
    if only in (None, "workers"):
        points += [("workers", "-", n) for n in (1, 8, 32)]
    if only in (None, "readers"):
        points += [("readers", "-", n) for n in (1, 10, 100)]
    if only in (None, "record"):
        points += [("record", "-", n) for n in (1, 4, 16)]
    return points


def net_us(r: dict[str, Any], idle: float) -> float:
    """CPU per activation without the runtime's background (the idle point's CPU per s)."""
    return float((r["cpu_s_per_s"] - idle) / max(r["activations_per_s"], 1e-9) * 1e6)


def idle_cpu(rows: list[dict[str, Any]]) -> float:
    return next(
        (r["cpu_s_per_s"] for r in rows if r.get("shape") == "idle" and "error" not in r), 0.0
    )


def table(rows: list[dict[str, Any]]) -> str:
    out: list[str] = []
    idle = idle_cpu(rows)
    inl = [r for r in rows if r["case"] == "inline" and "error" not in r and r["shape"] != "idle"]
    if inl:
        out += [
            f"Idle runtime (one 1 Hz node): {idle * 1000:.1f} ms of CPU per second, "
            "subtracted in the net column.",
            "",
            "| shape | N | rate Hz | process CPU us / activation (net) | tick -> last p50 / p99 ms "
            "| validate s | build s | first s | teardown s | RSS MB (+ graph) | skipped |",
            "|---|---:|---:|---|---|---:|---:|---:|---:|---|---:|",
        ]
        for r in inl:
            out.append(
                f"| {r['shape']} | {r['n']} | {r['rate_hz']:g} | "
                f"{r['cpu_us_per_activation']:.1f} ({net_us(r, idle):.1f}) | "
                f"{r['latency_p50_ms']:.3f} / "
                f"{r['latency_p99_ms']:.3f} | {r['validate_s']:.3f} | {r['build_s']:.3f} | "
                f"{r['first_s']:.3f} | {r['teardown_s']:.3f} | {r['rss_mb']:.0f} "
                f"(+{r['rss_delta_mb']:.0f}) | {r['skipped']:.0f} |"
            )
    wk = [r for r in rows if r["case"] == "workers" and "error" not in r]
    if wk:
        out += [
            "",
            "| workers | start s | all called s | PSS MB (per worker) | release -> result p50 / "
            "p99 ms | process CPU us / call (net) | others' p99 before / after a kill (max) ms "
            "| loop's worst lateness after the kill ms | dead one back s | teardown s |",
            "|---:|---:|---:|---|---|---:|---|---:|---:|---:|",
        ]
        for r in wk:
            out.append(
                f"| {r['n']} | {r['start_s']:.2f} | {r['ready_s']:.2f} | {r['pss_mb']:.0f} "
                f"({r['pss_per_worker_mb']:.1f}) | {r['call_ms_p50']:.3f} / "
                f"{r['call_ms_p99']:.3f} | "
                f"{(r['cpu_s_per_s'] - idle) / max(r['calls_per_s'], 1e-9) * 1e6:.0f} | "
                f"{r['others_p99_before_ms']:.2f} / {r['others_p99_after_kill_ms']:.2f} "
                f"({r['others_max_after_kill_ms']:.1f}) | "
                f"{r['loop_lateness_max_after_kill_ms']:.1f} | {r['dead_back_s']:.2f} | "
                f"{r['teardown_s']:.2f} |"
            )
    rd = [r for r in rows if r["case"] == "readers" and "error" not in r]
    if rd:
        out += [
            "",
            "| readers of one 1080p frame | publish p50 / p99 us | per reader us "
            "| process CPU us / frame (net) | skipped |",
            "|---:|---|---:|---|---:|",
        ]
        for r in rd:
            out.append(
                f"| {r['n']} | {r['publish_us_p50']:.0f} / {r['publish_us_p99']:.0f} | "
                f"{r['publish_us_per_reader']:.1f} | {r['loop_cpu_us_per_frame']:.0f} "
                f"({(r['cpu_s_per_s'] - idle) / max(r['frames_per_s'], 1e-9) * 1e6:.0f}) | "
                f"{r['skipped']:.0f} |"
            )
    rc = [r for r in rows if r["case"] == "record" and "error" not in r]
    if rc:
        out += [
            "",
            "| recorded streams (320x240x3 @ 20 Hz) | process CPU us / frame (net) | published "
            "| dropped | MCAP MB |",
            "|---:|---|---:|---:|---:|",
        ]
        for r in rc:
            out.append(
                f"| {r['n']} | {r['loop_cpu_us_per_frame']:.0f} "
                f"({(r['cpu_s_per_s'] - idle) / max(r['frames_per_s'], 1e-9) * 1e6:.0f}) | "
                f"{r['published']:.0f} | "
                f"{r['dropped']:.0f} | {r['mcap_mb']:.1f} |"
            )
    for r in rows:
        if "error" in r:
            out.append(f"\n{r['case']} {r['shape']} {r['n']}: FAILED {r['error']}")
    return "\n".join(out)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    inl = [r for r in rows if r["case"] == "inline" and "error" not in r]
    idle = idle_cpu(rows)
    for shape in SHAPES:
        pts = sorted(((r["n"], r) for r in inl if r["shape"] == shape), key=lambda x: x[0])
        if not pts:
            continue
        xs = [n for n, _ in pts]
        axes[0].plot(xs, [net_us(r, idle) for _, r in pts], "o-", label=shape)
        axes[1].plot(xs, [r["validate_s"] + r["first_s"] for _, r in pts], "o-", label=shape)
    axes[0].set(
        xscale="log",
        xlabel="inline nodes",
        ylabel="process CPU per activation, net of idle (us)",
        title="per activation: flat is O(1)",
    )
    axes[0].set_ylim(bottom=0)
    axes[1].axhline(1.0, color="grey", ls="--", lw=1, label="goal: 1 s")
    axes[1].set(xscale="log", yscale="log", xlabel="inline nodes", ylabel="s")
    axes[1].set_title("start-up: validate, build, first activation")
    rd = sorted(
        ((r["n"], r) for r in rows if r["case"] == "readers" and "error" not in r),
        key=lambda x: x[0],
    )
    if rd:
        axes[2].plot(
            [n for n, _ in rd], [r["publish_us_per_reader"] for _, r in rd], "o-", label="readers"
        )
        axes[2].set(
            xscale="log",
            xlabel="readers of one 1080p frame",
            ylabel="publish cost per reader (us)",
            title="frame publication",
        )
        axes[2].set_ylim(bottom=0)
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--rounds", type=int, default=1, help="rounds, alternating order; medians")
    ap.add_argument("--only", choices=["inline", "workers", "readers", "record"])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--point", nargs=3, metavar=("CASE", "SHAPE", "N"))
    ap.add_argument("--replot", type=Path, help="table and plot again from an --out file")
    args = ap.parse_args()
    if args.replot:
        rows = json.loads(args.replot.read_text())["medians"]
        print(table(rows))
        if args.plot:
            plot(rows, args.plot)
        return
    if args.point:
        case, shape, n = args.point
        print(json.dumps(point(case, shape, int(n), args.seconds)))
        return
    start_load = os.getloadavg()
    runs: list[list[dict[str, Any]]] = []
    for k in range(args.rounds):
        points = plan(args.only)
        rows = []
        for case, shape, n in points if k % 2 == 0 else points[::-1]:
            r = _child(case, shape, n, args.seconds)
            print(json.dumps(r), flush=True)
            rows.append(r)
        runs.append(rows)
    rows = median_rows(runs)
    print(
        f"\n{args.rounds} round(s), medians; load average {start_load} at the start, "
        f"{os.getloadavg()} at the end\n"
    )
    print(table(rows))
    if args.out:
        args.out.write_text(json.dumps({"medians": rows, "rounds": runs}, indent=1))
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
