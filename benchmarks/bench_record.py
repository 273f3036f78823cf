"""Recording: throughput at the acquisition paper's resolution, timing disturbance, rate fidelity.

    python benchmarks/bench_record.py throughput --seconds 15   # 2 (and 3) x 1936x1216 @ 20 fps
    python benchmarks/bench_record.py throughput --streams 3 --fps 30 --seconds 60 --crc yes
    python benchmarks/bench_record.py throughput --streams 3 --fps 100 --seconds 20  # > the disk
    python benchmarks/bench_record.py cambada --seconds 15 --rounds 3 --realtime  # with/without
    python benchmarks/bench_record.py fidelity --seconds 5      # reduced Table 5 + PNG plot
    python benchmarks/bench_record.py lateness --seconds 5 --rounds 3  # event-loop lateness
    python benchmarks/bench_record.py all                       # the three, as in RESULTS.md
    python benchmarks/bench_record.py vsdd --rounds 3 --fps 30 100 --seconds 10  # writer vs dd

What runs:

Every comparison names the recorder's writer: ``process`` (the default: a writer process
reading the frames from shared memory) or ``thread`` (writer threads in the runtime's process);
``--writers`` picks them (throughput, cambada), ``--conditions`` the lateness conditions.

1. throughput: N synthetic BGR streams of 1936x1216 at ``--fps`` (a source node copying one of
   eight pre-rendered scene frames into a shared-memory pool slot per tick, so the scene's
   renderer is not what is measured), each timer-phased 50/N ms apart, recorded by a
   ``recorder`` node over lossless edges (RawImage, no compression). Reported from the
   session's own report: expected/received/written/lost per stream, the writer's MB/s over the
   recording (bytes written / recording time; the close is timed), the CPU (user+sys of this
   process, every thread, and its descendants: the writer process) with and without the
   recorder in the same run, and the raw disk write speed in the same run, before and after:
   ``dd if=/dev/zero bs=8M oflag=direct`` into the same folder; each writer's rate as a share
   of it.
   ``vsdd``: the writer against ``dd`` in interleaved rounds (dd, writer at each ``--fps``,
   dd, writer ..., dd), each writer run's rate as a share of the mean of the two ``dd`` runs
   beside it. ``dd`` writes the same bytes to the same file system: the Frames node's
   pre-rendered images (what the writer writes, less ~100 bytes of headers per 7 MB frame),
   ``--dd-mib`` of them from a file in /dev/shm, ``bs=8M oflag=direct`` into ``--dir`` as the
   writer writes (direct I/O, 8 MiB writes, no fsync: the writer does not sync either).
2. cambada: ``flowrt run graphs/cambada.yaml`` and ``flowrt record graphs/cambada.yaml --writer
   W`` (every output) for the same time, interleaved: inter-activation std of the critical tasks
   (avoid_fr, avoid_om), skipped activations, edge drops, frame-pool drops.
3. fidelity: 640x480, 1280x720, 1936x1216 at 5, 10, 20, 30 fps, 1 and 2 streams: recorded fps
   (written-1 over the span of their log times, read back from the file) vs requested, lost.
   Writes benchmarks/results/record_fidelity.png.
4. lateness: in one process, a 1 kHz uvloop timer measuring its own lateness (due -> callback)
   while cambada-like traffic (2 x 640x480 BGR frames at 20 Hz in shared-memory pool slots, 11
   detection streams) is fed to a writer or not: ``none``; ``thread``: the writer threads with
   their GIL-free copies (flowrt.recording.gilfree); ``process``: the writer process (the
   recorder's default); older conditions on request: ``mcap`` (the threads with mcap's own
   buffers), ``*-switch`` (sys.setswitchinterval(0.5 ms)), ``forked`` (the thread writer and
   its traffic in a forked process). Conditions interleaved, rounds repeated;
   p50/p99/p99.9/max lateness, and the on-loop cost of submit and of giving frames' links back.

The machine is shared (2 cores, other engineers' test runs): every comparison is made within
one run, and RESULTS.md says when it was noisy.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from pydantic import BaseModel, ConfigDict

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import flowrt  # noqa: E402
from flowrt import Frame, Node, Output  # noqa: E402


class Frames(Node):
    """A synthetic camera: one of eight pre-rendered scene frames per tick, into the pool."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        width: int = 1936
        height: int = 1216
        seed: int = 1

    frame = Output(Frame)

    def setup(self) -> None:
        from flowrt.nodes.scene import SoccerScene

        scene = SoccerScene(self.params.width, self.params.height, seed=self.params.seed)
        self.images = [scene.render(i)[0] for i in range(8)]
        self.seq = 0

    def process(self) -> Frame:
        img = self.images[self.seq % len(self.images)]
        frame = self.ctx.new_frame(img.shape, np.uint8, "BGR")
        np.copyto(frame.data, img)
        frame.seq, frame.timestamp = self.seq, self.ctx.now()
        self.seq += 1
        return frame


def writer_params(writer: str) -> dict[str, str]:
    """``process-idle``: the writer process at the idle priority (``writer_priority: idle``)."""
    if writer == "process-idle":
        return {"writer": "process", "writer_priority": "idle"}
    return {"writer": writer}


def writer_flags(writer: str) -> list[str]:
    return [f"--{k.replace('_', '-')}={v}" for k, v in writer_params(writer).items()]


def streams_graph(
    n: int,
    fps: float,
    size: tuple[int, int],
    out: Path | None,
    crc: bool = True,
    writer: str = "process",
) -> flowrt.Graph:
    g = flowrt.GraphBuilder(f"{n}x{size[0]}x{size[1]}@{fps:g}")
    period = 1000.0 / fps
    for i in range(n):
        g.add(
            f"cam{i}",
            Frames,
            params={"width": size[0], "height": size[1], "seed": i + 1},
            trigger={"timer": f"{period}ms", "phase": f"{period * i / n}ms"},
            priority=50,
        )
    if out is not None:
        g.add(
            "rec",
            "recorder",
            params={"path": str(out), "name": "bench", "crc": crc, **writer_params(writer)},
            inputs={
                f"cam{i}.frame": {"from": f"cam{i}.frame", "policy": "lossless", "size": 16}
                for i in range(n)
            },
        )
    return g.build()


def cpu_seconds() -> float:
    """This process (every thread) and its live descendants (the writer process, workers)."""
    total = 0.0
    me = psutil.Process()
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


async def run_streams(
    n: int,
    fps: float,
    size: tuple[int, int],
    seconds: float,
    out: Path | None,
    crc: bool = True,
    writer: str = "process",
) -> dict[str, Any]:
    graph = streams_graph(n, fps, size, out, crc, writer)
    c0 = cpu_seconds()
    t0 = time.perf_counter()
    async with flowrt.Runtime(graph) as rt:
        await rt.run(seconds)
        t_stop = time.perf_counter()
        cpu = cpu_seconds() - c0  # before the stop: the writer process is still there
        stats = rt.stats()
    from flowrt.cli.record import wait_for_writers

    await asyncio.to_thread(wait_for_writers)
    t_closed = time.perf_counter()
    result: dict[str, Any] = {
        "cpu_percent": 100 * cpu / (t_stop - t0),
        "close_s": t_closed - t_stop,
        "pool_dropped": sum(p.dropped for p in stats.frames),
        "skipped": sum(x.skipped for x in stats.nodes if x.name.startswith("cam")),
    }
    if out is not None:
        (name,) = [n for n in os.listdir(out) if n.startswith("bench_")]
        session = out / name
        report = json.loads((session / "streams.json").read_text())
        result["report"] = report
        result["session"] = session
    return result


def disk_speed(folder: Path, mib: int = 512, direct: bool = True) -> float:
    """MB/s of ``dd`` into ``folder``, direct I/O or through the page cache (file removed)."""
    target = folder / "dd.tmp"
    flags = ["oflag=direct", "conv=fsync"] if direct else []
    r = subprocess.run(
        ["dd", "if=/dev/zero", f"of={target}", "bs=8M", f"count={mib // 8}", *flags],
        capture_output=True,
        text=True,
    )
    target.unlink(missing_ok=True)
    m = re.search(r"copied, ([0-9.]+) s", r.stderr)
    if not m:
        raise RuntimeError(f"dd: {r.stderr}")
    return mib * 1024 * 1024 / float(m.group(1)) / 1e6


def dd_source(mib: int) -> Path:
    """``mib`` MiB of the Frames node's images in /dev/shm: what ``dd`` writes (not zeros)."""
    from flowrt.nodes.scene import SoccerScene

    scene = SoccerScene(1936, 1216, seed=1)
    images = [scene.render(i)[0].tobytes() for i in range(8)]
    src = Path("/dev/shm") / f"flowrt_dd_{os.getpid()}"
    left = mib << 20
    with open(src, "wb") as f:
        while left > 0:
            for img in images:
                f.write(img[:left])
                left -= min(left, len(img))
    return src


def dd_same_bytes(src: Path, folder: Path) -> float:
    """MB/s of ``dd`` copying ``src`` into ``folder`` as the writer writes (file removed)."""
    target = folder / "dd.tmp"
    r = subprocess.run(
        ["dd", f"if={src}", f"of={target}", "bs=8M", "oflag=direct"],
        capture_output=True,
        text=True,
    )
    target.unlink(missing_ok=True)
    m = re.search(r"^(\d+) bytes.*copied, ([0-9.]+) s", r.stderr, re.M)
    if not m:
        raise RuntimeError(f"dd: {r.stderr}")
    return int(m.group(1)) / float(m.group(2)) / 1e6


def vsdd(args: argparse.Namespace) -> None:
    """Interleaved rounds: dd, then the writer at each rate, ...; ratio per writer run."""
    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    n = args.streams[-1]
    print(
        f"### Writer against dd, {n} x 1936x1216 BGR at {' / '.join(f'{f:g}' for f in args.fps)}"
        f" fps ({args.seconds:g} s per run, {args.rounds} interleaved rounds, writer "
        f"{args.writers[0]}, CRC {args.crc[0]})\n"
    )
    print(machine() + "\n")
    src = dd_source(args.dd_mib)
    runs: list[tuple[int, float, dict[str, Any], float]] = []
    dds: list[float] = []
    try:
        dds.append(dd_same_bytes(src, base))
        for r in range(args.rounds):
            for fps in args.fps:
                folder = Path(tempfile.mkdtemp(dir=base))
                rec = flowrt.run(
                    run_streams(
                        n,
                        fps,
                        (1936, 1216),
                        args.seconds,
                        folder,
                        args.crc[0] == "yes",
                        args.writers[0],
                    )
                )
                shutil.rmtree(folder)
                runs.append((r, fps, rec, os.getloadavg()[0]))
            dds.append(dd_same_bytes(src, base))
    finally:
        src.unlink(missing_ok=True)
    print(
        "| round | fps | dd before MB/s | writer MB/s | dd after MB/s | writer / dd | expected |"
        " received | written | lost | source skips | pool drops | load |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    ratios: dict[float, list[float]] = {}
    for r, fps, rec, load in runs:
        rep = rec["report"]
        mbps = sum(s["bytes"] for s in rep["streams"]) / rep["duration"] / 1e6
        before, after = dds[r], dds[r + 1]
        ratio = mbps / ((before + after) / 2)
        ratios.setdefault(fps, []).append(ratio)
        total = {k: sum(s[k] for s in rep["streams"]) for k in ("expected", "received", "written")}
        lost = sum(s["lost"] for s in rep["streams"])
        print(
            f"| {r + 1} | {fps:g} | {before:.0f} | **{mbps:.0f}** | {after:.0f} | "
            f"**{100 * ratio:.0f} %** | {total['expected']} | {total['received']} | "
            f"{total['written']} | {lost} | {rec['skipped']} | {rec['pool_dropped']} | "
            f"{load:.2f} |"
        )
    print(
        "\nPer rate, writer / dd (median of rounds): "
        + "; ".join(
            f"{fps:g} fps {100 * float(np.median(v)):.0f} % "
            f"({', '.join(f'{100 * x:.0f}' for x in v)})"
            for fps, v in ratios.items()
        )
        + f". dd: {args.dd_mib} MiB of the scene's images per run, `dd bs=8M oflag=direct`. "
        f"Load average at the end: {os.getloadavg()[0]:.2f}.\n"
    )


def machine() -> str:
    import uvloop  # noqa: F401  (the runtime's loop)

    return (
        f"{platform.node()} · {platform.platform()} · {os.cpu_count()} CPUs · "
        f"Python {platform.python_version()} · load average {os.getloadavg()[0]:.2f} at start"
    )


def throughput(args: argparse.Namespace) -> None:
    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    size = (1936, 1216)
    fps = args.fps[0]
    print(
        f"### Recording throughput, {size[0]}x{size[1]} BGR at {fps:g} fps "
        f"({args.seconds:g} s per run; writers: {', '.join(args.writers)})\n"
    )
    print(machine() + "\n")
    dd_before = disk_speed(base)
    rows = []
    rates: dict[str, list[float]] = {}
    crcs = [c == "yes" for c in args.crc]
    for n in args.streams:
        base_run = flowrt.run(run_streams(n, fps, size, args.seconds, None))
        for crc in crcs:
            for writer in args.writers:
                folder = Path(tempfile.mkdtemp(dir=base))
                rec = flowrt.run(run_streams(n, fps, size, args.seconds, folder, crc, writer))
                rep = rec["report"]
                written = sum(s["bytes"] for s in rep["streams"])
                mbps = written / rep["duration"] / 1e6
                rates.setdefault(writer, []).append(mbps)
                lead = f"| {n} | {'yes' if crc else 'no'} | {writer} |"
                for s in rep["streams"]:
                    rows.append(
                        f"{lead} {s['topic']} | {s['expected']} | {s['received']} | "
                        f"{s['written']} | **{s['lost']}** | {s['rate_mean']:.2f} | "
                        f"{s['bytes'] / 1e6:.0f} MB |"
                    )
                rows.append(
                    f"{lead} *all* | | | | | | writer **{mbps:.0f} MB/s**; close "
                    f"{rec['close_s']:.2f} s; CPU {rec['cpu_percent']:.0f}% vs "
                    f"{base_run['cpu_percent']:.0f}% without recording; pool drops "
                    f"{rec['pool_dropped']}; source skips {rec['skipped']} |"
                )
                shutil.rmtree(folder)
    dd_after = disk_speed(base)
    print(
        "| streams | CRC | writer | stream | expected | received | written | lost | Hz mean | "
        "bytes |"
    )
    print("|---:|---|---|---|---:|---:|---:|---:|---:|---|")
    print("\n".join(rows))
    dd = (dd_before + dd_after) / 2
    print(
        f"\nRaw disk, same run: `dd if=/dev/zero bs=8M count=64 oflag=direct conv=fsync` "
        f"{dd_before:.0f} MB/s before, {dd_after:.0f} MB/s after (mean {dd:.0f}). Writer rate "
        "against it: "
        + "; ".join(
            f"{w} {', '.join(f'{r:.0f} MB/s ({100 * r / dd:.0f} %)' for r in v)}"
            for w, v in rates.items()
        )
        + f". Load average at the end: {os.getloadavg()[0]:.2f}.\n"
    )


def _stats_row(label: str, stats: dict[str, Any]) -> list[str]:
    rows = []
    edge_drops = sum(e["dropped"] for e in stats["edges"] if not e["sampled"])
    pool = sum(p["dropped"] for p in stats.get("frames", []))
    for n in stats["nodes"]:
        if n["name"] in ("avoid_fr", "avoid_om"):
            iv = n["interval"]
            rows.append(
                f"| {label} | {n['name']} | {iv['count']} | {iv['mean']:.3f} | {iv['std']:.3f} | "
                f"{iv['min']:.3f} | {iv['max']:.3f} | {n['skipped']} | {n['deadline_misses']} | "
                f"{edge_drops} | {pool} |"
            )
    return rows


def cambada(args: argparse.Namespace) -> None:
    """Interleaved rounds (run, record, run, record ...): the machine's drift hits both alike.

    Per task the median over the rounds of each run's std is the figure; every row is listed.
    """
    extra = ["--realtime"] if args.realtime else []
    print(
        f"### Timing with and without recording: cambada graph ({args.seconds:g} s each, "
        f"{args.rounds} interleaved rounds{', --realtime' if args.realtime else ''})\n"
    )
    print(machine() + "\n")
    rows = []
    stds: dict[tuple[str, str], list[float]] = {}
    written = lost = streams = 0
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for r in range(args.rounds):
            runs = [("run (no recording)", ["run", "graphs/cambada.yaml"])]
            runs += [
                (
                    f"record, writer {w}",
                    ["record", "graphs/cambada.yaml", "-o", tmp, *writer_flags(w)],
                )
                for w in args.writers
            ]
            for label, cmd in runs:
                out = Path(tmp) / "stats.json"
                out.unlink(missing_ok=True)
                subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "flowrt.cli",
                        *cmd,
                        *extra,
                        "--no-ui",
                        "--duration",
                        str(args.seconds),
                        "--stats-json",
                        str(out),
                    ],
                    cwd=REPO,
                    capture_output=True,
                    check=False,
                )
                if not out.exists():
                    print(f"round {r + 1} {label}: no statistics (the run failed)")
                    continue
                stats = json.loads(out.read_text())
                rows += _stats_row(f"{r + 1}: {label}", stats)
                for n in stats["nodes"]:
                    if n["name"] in ("avoid_fr", "avoid_om"):
                        stds.setdefault((label, n["name"]), []).append(n["interval"]["std"])
                for rep in stats.get("reports", {}).get("recorder", None) or []:
                    streams = len(rep["streams"])
                    written += sum(s["written"] for s in rep["streams"])
                    lost += sum(s["lost"] for s in rep["streams"])
    print(
        "| round: run | task | n | mean ms | std ms | min | max | skipped | misses | edge drops | "
        "pool drops |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print("\n".join(rows))
    print("\n| run | task | median std ms | stds ms |\n|---|---|---:|---|")
    for (label, task), v in sorted(stds.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        print(
            f"| {label} | {task} | {float(np.median(v)):.3f} | {', '.join(f'{x:.2f}' for x in v)} |"
        )
    print(
        f"\nThe recordings: {streams} streams each, {written} messages written in all, "
        f"{lost} lost. Load average at the end: {os.getloadavg()[0]:.2f}.\n"
    )


def fidelity(args: argparse.Namespace) -> None:
    from flowrt.recording.reader import scan

    print(f"### Rate fidelity (reduced Table 5, {args.seconds:g} s per cell)\n")
    print(machine() + "\n")
    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    results = []
    for size in ((640, 480), (1280, 720), (1936, 1216)):
        for fps in (5, 10, 20, 30):
            for n in (1, 2):
                folder = Path(tempfile.mkdtemp(dir=base))
                rec = flowrt.run(run_streams(n, fps, size, args.seconds, folder, crc=False))
                mcap = rec["session"] / "bench_001.mcap"
                info = scan(mcap)
                lost = sum(s["lost"] for s in rec["report"]["streams"])
                got = [s.rate_mean or 0.0 for s in info.streams]
                results.append((size, fps, n, min(got), max(got), lost))
                shutil.rmtree(folder)
                print(f"<!-- {size} {fps} {n}: {got} lost {lost} -->", flush=True)
    report_fidelity(results)


def report_fidelity(results: list[Any]) -> None:
    """The table and the plot of (size, fps, streams, lowest fps, highest fps, lost) rows."""
    print(
        "| resolution | requested fps | streams | recorded fps (min of streams) | "
        "error fps | lost |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for size, fps, n, lo, hi, lost in results:
        err = max(abs(lo - fps), abs(hi - fps))
        print(f"| {size[0]}x{size[1]} | {fps} | {n} | {lo:.3f} | {err:.3f} | {lost} |")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for size in ((640, 480), (1280, 720), (1936, 1216)):
            for n, marker in ((1, "o"), (2, "s")):
                pts = [(r[1], r[3]) for r in results if r[0] == size and r[2] == n]
                ax.plot(*zip(*pts, strict=True), marker=marker, label=f"{size[0]}x{size[1]} x{n}")
        ax.plot([0, 32], [0, 32], color="grey", lw=0.5, ls="--")
        ax.set_xlabel("requested fps")
        ax.set_ylabel("recorded fps")
        ax.legend(fontsize=7)
        png = REPO / "benchmarks" / "results" / "record_fidelity.png"
        png.parent.mkdir(exist_ok=True)
        fig.tight_layout()
        fig.savefig(png, dpi=100)
        print(f"\nPlot: benchmarks/results/{png.name}\n")
    except ImportError:
        print("\n(matplotlib not installed: no plot)\n")


# --- lateness: does the writer delay the event loop? ------------------------------------------


async def _lateness_once(
    writer_kind: str, seconds: float, folder: Path, shape: tuple[int, ...], probe: str = "timerfd"
) -> dict[str, Any]:
    """One condition: a 1 kHz timer measuring its own lateness while cambada-like traffic runs.

    The traffic (2 cameras at 20 Hz, half a period apart, 11 detection streams: 6 at 20 Hz, 5
    at 5 Hz) is made in every condition, frames copied into shared-memory pool slots as the
    runtime's cameras do; only whether it is handed to a writer (and which one) changes:
    ``mcap`` / ``gil-free``: a RecordingWriter's threads; ``process``: the writer process.
    """
    from flowrt.nodes.tracker import FrameDetection  # what the trackers publish

    from flowrt.frames import FrameStore

    loop = asyncio.get_running_loop()
    store = FrameStore()
    pools = [store.pool(f"cam{i}") for i in range(2)]
    late: list[float] = []
    submit_ns: list[int] = []
    release_ns: list[int] = []
    writer: Any = None

    def release_done() -> None:
        t0 = time.perf_counter_ns()
        while writer is not None and writer.done:
            writer.done.popleft().release()
        release_ns.append(time.perf_counter_ns() - t0)

    path = folder / f"late_{time.monotonic_ns()}.mcap"
    writer = await _bench_writer(writer_kind, path, release_done)
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 255, shape, np.uint8) for _ in range(2)]
    stop = time.monotonic() + seconds

    async def camera(i: int, phase: float) -> None:
        await asyncio.sleep(phase)
        seq, due = 0, time.monotonic()
        while time.monotonic() < stop:
            now = time.monotonic()
            f = pools[i].reserve(shape, np.uint8, source=f"cam{i}", seq=seq, timestamp=now)
            if f is None:  # every slot held (the writer is behind): a heap frame, counted
                f = Frame(np.empty(shape, np.uint8), source=f"cam{i}", seq=seq, timestamp=now)
            np.copyto(f.data, images[i])
            t0 = time.perf_counter_ns()
            if writer is not None:
                f.acquire()
                if not writer.submit(f"cam{i}.frame", f, f.timestamp, seq):
                    f.release()
                submit_ns.append(time.perf_counter_ns() - t0)
            f.release()
            seq, due = seq + 1, due + 0.05
            await asyncio.sleep(max(0.0, due - time.monotonic()))

    async def detections(k: int, rate: float) -> None:
        seq, due = 0, time.monotonic()
        while time.monotonic() < stop:
            d = FrameDetection(
                True, (1.5, 2.5), (1, 2, 3, 4), 12, 0.9, 1000, "ball", "cam0", seq, time.monotonic()
            )
            t0 = time.perf_counter_ns()
            if writer is not None:
                writer.submit(f"t{k}.detection", d, d.timestamp, seq)
                submit_ns.append(time.perf_counter_ns() - t0)
            seq, due = seq + 1, due + 1 / rate
            await asyncio.sleep(max(0.0, due - time.monotonic()))

    tasks = [loop.create_task(camera(0, 0.0)), loop.create_task(camera(1, 0.025))]
    tasks += [loop.create_task(detections(k, 20.0 if k < 6 else 5.0)) for k in range(11)]
    await _probe(probe, 0.001, stop, late)
    await asyncio.gather(*tasks)
    out: dict[str, Any] = {"late_ms": np.array(late) * 1e3}
    if writer is not None:
        writer.request_close()  # as the recorder closes either writer
        for frame in writer.detach_frames():
            frame.release()
        while writer.encoding_frame():
            release_done()
            await asyncio.sleep(0.005)
        await asyncio.to_thread(writer.join)
        release_done()
        out["written"] = sum(s.written for s in writer.streams.values())
        out["lost"] = sum(s.lost for s in writer.streams.values())
        out["submit_us"] = np.array(submit_ns) / 1e3
        out["release_us"] = np.array(release_ns) / 1e3
    store.close()
    return out


async def _bench_writer(kind: str, path: Path, release_done: Any) -> Any:
    """The writer of one lateness condition, opened (None: ``none``, no recording)."""
    from flowrt.recording import ProcessRecordingWriter, RecordingWriter

    loop = asyncio.get_running_loop()
    writer: Any = None
    if kind.startswith("process"):
        writer = ProcessRecordingWriter(
            path,
            loop=loop,
            direct_io=True,
            on_written=lambda: loop.call_soon(release_done),
            priority="idle" if kind == "process-idle" else "normal",
        )
        await asyncio.to_thread(writer.open, {"bench": {"what": "lateness"}}, [])
    elif kind != "none":
        writer = RecordingWriter(
            path,
            direct_io=True,
            gil_free=kind == "gil-free",
            on_written=lambda: loop.call_soon_threadsafe(release_done),
        )
        writer.open({"bench": {"what": "lateness"}}, [])
    return writer


async def _probe(probe: str, period: float, stop: float, late: list[float]) -> None:
    """A ``period`` timer noting its own lateness in ``late`` until ``stop`` (monotonic):
    ``timerfd`` (the runtime's periodic timers) or the loop's ``call_later``."""
    loop = asyncio.get_running_loop()
    finished = loop.create_future()
    if probe == "timerfd":  # the runtime's own periodic timers (flowrt.clock, one timerfd)
        from flowrt.clock import SystemClock

        timer: Any = None

        def on_tick(release: float, missed: int) -> None:
            now = time.monotonic()
            late.append(now - release)
            if now >= stop and not finished.done():
                timer.cancel()
                finished.set_result(None)

        timer = SystemClock().periodic(period, 0.0, on_tick)
    else:  # the loop's call_later: uvloop's timers have a resolution of 1 ms
        due = time.monotonic() + period

        def tick() -> None:
            nonlocal due
            now = time.monotonic()
            late.append(now - due)
            if now >= stop:
                finished.set_result(None)
                return
            due = max(due + period, now + period / 2)
            loop.call_later(due - time.monotonic(), tick)

        loop.call_later(period, tick)
    await finished


def _writer_elsewhere(seconds: float, folder: Path, shape: tuple[int, ...]) -> None:
    """The writer condition's work in another process: tells CPU contention from the GIL."""
    from flowrt.system._eventloop import new_event_loop

    loop = new_event_loop()
    try:
        loop.run_until_complete(_lateness_once("gil-free", seconds, folder, shape))
    finally:
        loop.close()


def lateness(args: argparse.Namespace) -> None:
    """Interleaved conditions in one process: no writer, mcap's buffers, GIL-free; intervals."""
    from flowrt.system._eventloop import new_event_loop

    shape = (args.height, args.width, 3)
    every = {
        "none": ("no recording", "none", 0.005),
        "mcap": ("writer thread, mcap's own buffers", "mcap", 0.005),
        "thread": ("writer thread (GIL-free copies)", "gil-free", 0.005),
        "mcap-switch": ("writer thread, mcap's own buffers, switch 0.5 ms", "mcap", 0.0005),
        "thread-switch": ("writer thread, GIL-free copies, switch 0.5 ms", "gil-free", 0.0005),
        "forked": ("writer thread in a forked process beside this one", "process-fork", 0.005),
        "process": ("writer process (the recorder's default)", "process", 0.005),
        "process-idle": ("writer process, writer_priority idle", "process-idle", 0.005),
    }
    conditions = [every[c] for c in args.conditions]
    print(
        f"### Event-loop lateness with and without the writer ({args.seconds:g} s per "
        f"condition, {args.rounds} interleaved rounds, frames {args.width}x{args.height} BGR, "
        f"probe: {args.probe})\n"
    )
    print(machine() + "\n")
    default_switch = sys.getswitchinterval()
    got: dict[str, list[dict[str, Any]]] = {c[0]: [] for c in conditions}
    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=base) as tmp:
        for _ in range(args.rounds):
            for label, kind, switch in conditions:
                sys.setswitchinterval(switch)
                other = None
                if kind == "process-fork":  # the same traffic and writer, in a forked process
                    other = multiprocessing.get_context("fork").Process(
                        target=_writer_elsewhere, args=(args.seconds + 0.5, Path(tmp), shape)
                    )
                    other.start()
                    kind = "none"
                loop = new_event_loop()
                try:
                    got[label].append(
                        loop.run_until_complete(
                            _lateness_once(kind, args.seconds, Path(tmp), shape, args.probe)
                        )
                    )
                finally:
                    loop.close()
                    sys.setswitchinterval(default_switch)
                    if other is not None:
                        other.join()
                for f in Path(tmp).iterdir():
                    f.unlink()
    print(
        "| condition | ticks | p50 ms | p99 ms | p99.9 ms | max ms (median of rounds) | "
        "> 2 ms | written | lost | submit us p50/p99 | link release us p50 |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for label, runs in got.items():
        late = np.concatenate([r["late_ms"] for r in runs])
        p = np.percentile(late, [50, 99, 99.9])
        worst = float(np.median([r["late_ms"].max() for r in runs]))
        row = (
            f"| {label} | {late.size} | {p[0]:.3f} | {p[1]:.3f} | {p[2]:.3f} | {worst:.2f} | "
            f"{int(np.sum(late > 2))} |"
        )
        if "written" in runs[0]:
            sub = np.concatenate([r["submit_us"] for r in runs])
            rel = np.concatenate([r["release_us"] for r in runs])
            row += (
                f" {sum(r['written'] for r in runs)} | {sum(r['lost'] for r in runs)} | "
                f"{np.median(sub):.1f} / {np.percentile(sub, 99):.1f} | {np.median(rel):.1f} |"
            )
        else:
            row += " - | - | - | - |"
        print(row)
    print(f"\nLoad average at the end: {os.getloadavg()[0]:.2f}.\n")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("throughput", "vsdd", "cambada", "fidelity", "lateness", "all"))
    p.add_argument("--seconds", type=float, default=None)
    p.add_argument("--streams", type=int, nargs="+", default=[2, 3])
    p.add_argument(
        "--fps", type=float, nargs="+", default=[20.0], help="throughput, vsdd: each source's rate"
    )
    p.add_argument("--dd-mib", type=int, default=2048, help="vsdd: MiB dd writes per run")
    p.add_argument(
        "--writers",
        nargs="+",
        choices=("process", "process-idle", "thread"),
        default=["process", "thread"],
        help="throughput, cambada: the recorder's writer(s) to measure",
    )
    p.add_argument(
        "--crc", nargs="+", choices=("yes", "no"), default=["yes", "no"], help="throughput"
    )
    p.add_argument("--rounds", type=int, default=3, help="cambada: interleaved rounds")
    p.add_argument("--realtime", action="store_true", help="cambada: runs with --realtime")
    p.add_argument(
        "--conditions",
        nargs="+",
        default=["none", "thread", "process"],
        help="lateness: none mcap thread mcap-switch thread-switch forked process process-idle",
    )
    p.add_argument(
        "--probe",
        choices=("timerfd", "loop"),
        default="timerfd",
        help="lateness: the 1 kHz probe on the runtime's timerfd clock, or the loop's call_later",
    )
    p.add_argument("--width", type=int, default=640, help="lateness: frame width")
    p.add_argument("--height", type=int, default=480, help="lateness: frame height")
    p.add_argument("--dir", default=str(REPO / "benchmarks" / "results" / "rec_tmp"))
    args = p.parse_args()
    Path(args.dir).mkdir(parents=True, exist_ok=True)
    todo = ("throughput", "cambada", "fidelity") if args.what == "all" else (args.what,)
    default = {"throughput": 15.0, "cambada": 15.0, "fidelity": 5.0, "lateness": 5.0, "vsdd": 10.0}
    given = args.seconds
    for what in todo:
        args.seconds = given or default[what]
        run = {"throughput": throughput, "cambada": cambada, "fidelity": fidelity}
        run["lateness"], run["vsdd"] = lateness, vsdd
        run[what](args)
    shutil.rmtree(args.dir, ignore_errors=True)


if __name__ == "__main__":
    main()
