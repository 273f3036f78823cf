"""Inter-activation jitter of a 20 Hz frame clock: idle and loaded, with and without --realtime.

    python benchmarks/bench_jitter.py               # 4 configurations x 20 s x 3 runs + 3 (~6 min)
    python benchmarks/bench_jitter.py --duration 5  # quicker, fewer samples

What runs, for each configuration (idle / N CPU burners) x (normal priority / --realtime):

- flowrt: ``flowrt run benchmarks/jitter_graph.yaml --no-ui --duration S --stats-json ...
  [--realtime]`` in a subprocess (PYTHONPATH=benchmarks so the graph can name the node classes
  below). ``source`` is a 20 Hz timer-triggered node (a timerfd on the loop) that fills and
  publishes a 320x240x3 uint8 ``flowrt.Frame``; ``reader`` is frame-triggered (period 1). The
  inter-activation interval (start to start) comes from flowrt's own statistics.
- baselines, in the same conditions (same event loop as ``flowrt run``, the same SCHED_FIFO
  when --realtime, the same frame-sized fill each iteration), each in its own subprocess:
  ``asyncio.sleep(50 ms)`` after the work (the naive loop, drifts), and ``asyncio.sleep`` to
  an absolute next release time (drift-free, but loop-timer granularity).

Two flowrt-only configurations, ``idle+spin`` and ``idle+rt+spin``, add ``--spin 300us`` (the
loop busy-waits the last 300 us before each release). A further one, ``ui+rt``, runs flowrt
alone, idle with --realtime, but with the live status table (no --no-ui) on a pseudo-terminal
(util-linux ``script``): what a user typing ``flowrt run graph.yaml --realtime`` gets.

Load: ``--burners`` (default: one per CPU) ``multiprocessing`` processes spinning
``while True: pass`` at normal priority, started before and killed after each loaded
configuration. Realtime runs are subprocesses, so SCHED_FIFO never leaks into other runs.

The machine may be shared and noisy: compare flowrt against the baselines of the same run.
Targets: inter-activation std <= 0.1 ms idle, and <= 0.1 ms under full load with --realtime.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import math
import multiprocessing
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from flowrt import Frame, Input, Node, Output

HERE = Path(__file__).resolve().parent
GRAPH = HERE / "jitter_graph.yaml"
PERIOD = 0.050  # s, must match jitter_graph.yaml
TARGET_STD_MS = 0.1


# --- the benchmark's nodes (public flowrt API only) ------------------------------------------


class FrameSource(Node):
    """Fills and publishes one width x height x 3 uint8 frame per activation (a camera stand-in)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        width: int = 320
        height: int = 240

    frame = Output(Frame)

    def setup(self) -> None:
        self.seq = 0
        # Allocate the frame pool's slots now, as a camera node should: the first reserve
        # creates the shared-memory segments (~1 ms), which would otherwise delay the first
        # activation and show up as one short reader interval. The runtime releases this
        # frame after the first activation.
        self.ctx.new_frame((self.params.height, self.params.width, 3))

    def process(self) -> Frame:
        frame = self.ctx.new_frame((self.params.height, self.params.width, 3))
        frame.data[...] = self.seq & 0xFF
        frame.seq = self.seq
        frame.timestamp = self.ctx.now()
        self.seq += 1
        return frame


class FrameReader(Node):
    """Touches each new frame (the work of a tracker is not what is measured here)."""

    frame = Input(Frame)

    def setup(self) -> None:
        self.checksum = 0

    def process(self, frame: Frame) -> None:
        self.checksum += int(frame.data[0, 0, 0])


# --- statistics ------------------------------------------------------------------------------


@dataclass
class Row:
    config: str
    subject: str
    n: int
    mean: float
    std: float
    min: float
    max: float
    p99: float
    skipped: int | None = None
    realtime: str = ""
    busy: float = math.nan  # whole-machine CPU busy % during the run (all processes)


def summarise(intervals_s: list[float]) -> dict[str, float]:
    """Same definitions as flowrt.stats.Running: sample std, p99 = sorted[int(0.99 n)]."""
    n = len(intervals_s)
    if n < 2:
        return {
            "n": n,
            "mean": math.nan,
            "std": math.nan,
            "min": math.nan,
            "max": math.nan,
            "p99": math.nan,
        }
    ms = [x * 1000 for x in intervals_s]
    mean = sum(ms) / n
    std = math.sqrt(sum((x - mean) ** 2 for x in ms) / (n - 1))
    ordered = sorted(ms)
    return {
        "n": n,
        "mean": mean,
        "std": std,
        "min": ordered[0],
        "max": ordered[-1],
        "p99": ordered[min(n - 1, int(0.99 * n))],
    }


# --- baseline child: a plain asyncio.sleep-paced 20 Hz loop ------------------------------------


async def _baseline_loop(duration: float, mode: str) -> list[float]:
    data = np.empty((240, 320, 3), np.uint8)
    starts: list[float] = []
    seq = 0
    await asyncio.sleep(PERIOD)
    nxt = time.monotonic()
    end = nxt + duration
    while True:
        now = time.monotonic()
        starts.append(now)
        if now >= end:
            break
        data[...] = seq & 0xFF  # the same work as FrameSource
        seq += 1
        if mode == "naive":
            await asyncio.sleep(PERIOD)
        else:
            nxt += PERIOD
            while nxt <= now:  # skip missed releases, as a timerfd does
                nxt += PERIOD
            await asyncio.sleep(nxt - time.monotonic())
    return [b - a for a, b in itertools.pairwise(starts)]


def baseline_child(args: argparse.Namespace) -> int:
    from flowrt.system._eventloop import new_event_loop

    granted = ""
    if args.realtime:
        from flowrt.system._realtime import enable_realtime

        ok, granted = enable_realtime()
        if not ok:
            granted = "refused: " + granted
    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        intervals = runner.run(_baseline_loop(args.duration, args.baseline))
        loop_name = type(runner.get_loop()).__module__
    Path(args.out).write_text(
        json.dumps({"realtime": granted, "loop": loop_name, "intervals": intervals})
    )
    return 0


# --- the parent: configurations, load, tables ------------------------------------------------


def _spin() -> None:
    while True:
        pass


def start_burners(n: int) -> list[multiprocessing.Process]:
    procs = [
        multiprocessing.Process(target=_spin, daemon=True, name=f"burner{i}") for i in range(n)
    ]
    for p in procs:
        p.start()
    return procs


def stop_burners(procs: list[multiprocessing.Process]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.join()


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(HERE), env.get("PYTHONPATH", "")) if p)
    return env


def run_flowrt(
    config: str,
    duration: float,
    realtime: bool,
    tmp: Path,
    commands: list[str],
    ui: bool = False,
    spin: str = "",
) -> list[Row]:
    out = tmp / f"flowrt-{config.replace(' ', '_').replace('/', '_')}.json"
    cmd = [
        sys.executable,
        "-m",
        "flowrt.cli",
        "run",
        str(GRAPH),
        "--duration",
        f"{duration:g}",
        "--stats-json",
        str(out),
    ]
    if not ui:
        cmd.append("--no-ui")
    if realtime:
        cmd.append("--realtime")
    if spin:
        cmd += ["--spin", spin]
    shown = "PYTHONPATH=benchmarks " + shlex.join(["flowrt", *cmd[3:]]).replace(
        str(HERE.parent) + "/", ""
    )
    if ui:
        # The live table renders only on a terminal: give it a pseudo-terminal (util-linux script).
        cmd = ["script", "-qec", shlex.join(cmd), "/dev/null"]
        shown += "    # on a terminal (live table)"
    commands.append(shown)
    t0 = cpu_times()
    proc = subprocess.run(
        cmd, env=_env(), capture_output=True, text=True, check=False, stdin=subprocess.DEVNULL
    )
    busy = busy_since(t0)
    if proc.returncode != 0 or not out.exists():
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"flowrt run failed ({proc.returncode}) in configuration {config}")
    stats = json.loads(out.read_text())
    rows = []
    for node in stats["nodes"]:
        iv = node["interval"]
        rows.append(
            Row(
                config,
                f"flowrt {node['name']}",
                iv["count"],
                iv["mean"],
                iv["std"],
                iv["min"],
                iv["max"],
                iv["p99"],
                node["skipped"],
                stats.get("loop_scheduling") or stats.get("realtime", ""),
                busy,
            )
        )
    return rows


def run_baseline(config: str, mode: str, duration: float, realtime: bool, tmp: Path) -> Row:
    out = tmp / f"baseline-{mode}-{config.replace(' ', '_').replace('/', '_')}.json"
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--baseline",
        mode,
        "--duration",
        f"{duration:g}",
        "--out",
        str(out),
    ]
    if realtime:
        cmd.append("--realtime")
    t0 = cpu_times()
    proc = subprocess.run(cmd, env=_env(), capture_output=True, text=True, check=False)
    busy = busy_since(t0)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"baseline {mode} failed in configuration {config}")
    data = json.loads(out.read_text())
    s = summarise(data["intervals"])
    label = {"naive": "asyncio.sleep(50ms)", "absolute": "asyncio.sleep(until next)"}[mode]
    return Row(
        config,
        f"baseline {label}",
        int(s["n"]),
        s["mean"],
        s["std"],
        s["min"],
        s["max"],
        s["p99"],
        None,
        data["realtime"],
        busy,
    )


def cpu_times() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine, from /proc/stat."""
    with open("/proc/stat") as f:
        fields = [int(x) for x in f.readline().split()[1:]]
    idle = fields[3] + fields[4]
    return sum(fields) - idle, sum(fields)


def busy_since(start: tuple[int, int]) -> float:
    b, t = cpu_times()
    return 100.0 * (b - start[0]) / max(1, t - start[1])


def _fmt(x: float) -> str:
    return "nan" if math.isnan(x) else f"{x:.3f}"


def print_tables(rows: list[Row], burners: int) -> None:
    print("\n### Inter-activation interval at 20 Hz (50 ms), ms\n")
    print(
        "| configuration | subject | n | mean | std | min "
        "| max | p99 | skipped | std <= 0.1 ms | CPU busy |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|:---:|---:|")
    for r in rows:
        ok = "yes" if r.std <= TARGET_STD_MS else "no"
        skipped = "-" if r.skipped is None else str(r.skipped)
        print(
            f"| {r.config} | {r.subject} | {r.n} | {_fmt(r.mean)} "
            f"| {_fmt(r.std)} | {_fmt(r.min)} | {_fmt(r.max)} "
            f"| {_fmt(r.p99)} | {skipped} | {ok} | {r.busy:.0f}% |"
        )
    print(
        "\n### flowrt against the baselines of the same "
        "configuration (std ratio: baseline / flowrt)\n"
    )
    print(
        "| configuration | flowrt source std | flowrt "
        "reader std | naive sleep std | abs. sleep std "
        "| naive / source | abs. / source |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    configs = list(dict.fromkeys(r.config for r in rows))
    for c in configs:
        by = {r.subject: r for r in rows if r.config == c}
        if "baseline asyncio.sleep(50ms)" not in by:
            continue
        src, rd = by["flowrt source"], by["flowrt reader"]
        naive, ab = by["baseline asyncio.sleep(50ms)"], by["baseline asyncio.sleep(until next)"]
        print(
            f"| {c} | {_fmt(src.std)} | {_fmt(rd.std)} | {_fmt(naive.std)} | {_fmt(ab.std)} "
            f"| {naive.std / src.std:.1f}x | {ab.std / src.std:.1f}x |"
        )
    print("\n### Scheduling granted\n")
    print("| configuration | flowrt loop | baseline |")
    print("|---|---|---|")
    for c in configs:
        by = {r.subject: r for r in rows if r.config == c}
        base = by.get("baseline asyncio.sleep(50ms)")
        print(
            f"| {c} | {by['flowrt source'].realtime or '(not requested)'} "
            f"| {'-' if base is None else base.realtime or '(not requested)'} |"
        )
    print(
        f"\nLoad: {burners} x `while True: pass` processes "
        "at normal priority (SCHED_OTHER, nice 0). "
        "CPU busy: the whole machine during that run (all processes, all CPUs; on a shared machine "
        "an 'idle' run may not be idle). A mean above 50 "
        "ms with a small std is drift, not precision: "
        "the naive sleep loop falls behind the 20 Hz schedule by (mean - 50) ms every period."
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--duration", type=float, default=20.0, metavar="S", help="seconds per run (default 20)"
    )
    p.add_argument(
        "--burners", type=int, default=os.cpu_count() or 2, help="CPU-burning processes under load"
    )
    p.add_argument(
        "--configs",
        default="idle,idle+rt,load,load+rt,ui+rt,idle+spin,idle+rt+spin",
        help="comma-separated subset of idle,idle+rt,load,load+rt,ui+rt,idle+spin,idle+rt+spin "
        "(*spin: flowrt only, with --spin 300us; ui+rt: flowrt only, "
        "with the live status table on a pseudo-terminal instead of --no-ui)",
    )
    p.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    p.add_argument("--baseline", choices=["naive", "absolute"], help=argparse.SUPPRESS)
    p.add_argument("--realtime", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.baseline:
        return baseline_child(args)

    from importlib.metadata import version

    from flowrt.system._eventloop import new_event_loop

    loop = new_event_loop()
    loop_name = type(loop).__module__
    loop.close()
    print(f"# bench_jitter: 20 Hz frame clock, {args.duration:g} s per run")
    print(
        f"\n{platform.node()} · {platform.platform()} · "
        f"{os.cpu_count()} CPUs · Python {platform.python_version()} "
        f"· event loop {loop_name} (uvloop {version('uvloop')}) "
        f"· load average {os.getloadavg()[0]:.2f} at start"
    )
    labels = {
        "idle": ("idle", False, False),
        "idle+rt": ("idle / --realtime", False, True),
        "load": (f"{args.burners} burners", True, False),
        "load+rt": (f"{args.burners} burners / --realtime", True, True),
        "ui+rt": ("idle / --realtime / live table", False, True),
        "idle+spin": ("idle / --spin 300us", False, False),
        "idle+rt+spin": ("idle / --realtime / --spin 300us", False, True),
    }
    rows: list[Row] = []
    commands: list[str] = []
    with tempfile.TemporaryDirectory(prefix="flowrt-bench-jitter-") as tmpdir:
        tmp = Path(tmpdir)
        for key in args.configs.split(","):
            key = key.strip()
            config, load, realtime = labels[key]
            if key == "ui+rt" and shutil.which("script") is None:
                print(
                    "  skipping ui+rt: needs util-linux `script` for a pseudo-terminal",
                    file=sys.stderr,
                )
                continue
            print(f"  running {config} ...", file=sys.stderr, flush=True)
            burners = start_burners(args.burners) if load else []
            try:
                if burners:
                    time.sleep(1.0)
                spin = "300us" if key.endswith("spin") else ""
                rows += run_flowrt(
                    config, args.duration, realtime, tmp, commands, ui=key == "ui+rt", spin=spin
                )
                # the baselines have no status table and no spin: the same as their base config
                if key != "ui+rt" and not spin:
                    for mode in ("naive", "absolute"):
                        rows.append(run_baseline(config, mode, args.duration, realtime, tmp))
            finally:
                stop_burners(burners)
    print("\nflowrt commands (from the repository root):\n")
    for c in dict.fromkeys(commands):
        print(f"    {c}")
    print_tables(rows, args.burners)
    if args.json:
        Path(args.json).write_text(json.dumps([r.__dict__ for r in rows], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
