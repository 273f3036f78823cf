"""Drive every configuration of the CAMBADA experiment, then write tables and figures.

    python -m benchmarks.cambada                 # 16 runs x 30 s + the mode change (~11 min)
    python -m benchmarks.cambada --quick         # 6 s runs, results in the output dir only
    python -m benchmarks.cambada --only calibrated/idle --duration 10
    python -m benchmarks.cambada --report-from DIR   # tables and figures again, no run

Configurations: {monolithic loop with every tracker on every frame (the paper's original),
monolithic loop with each tracker's period/phase, flowrt, flowrt --realtime} x {idle, 2 CPU
burners} x {real trackers, paper-calibrated}; each in subprocesses of its own, so SCHED_FIFO
never leaks. The burners are ``while True: pass`` processes at normal priority, started before
and killed after each run. Then the paper's mode change in an embedded Runtime
(paper-calibrated, idle, --realtime where permitted). Outputs: a section of
benchmarks/RESULTS.md, PNGs in benchmarks/results/, and every raw record under the output
directory (printed first).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from . import analysis, graph, report

ROOT = graph.ROOT
REGIMES = ("calibrated", "real")
LOADS = ("idle", "load")
SYSTEMS = ("monolithic-all", "monolithic", "flowrt", "flowrt-rt")
LOG_EVERY = 3600.0  # flowrt run --no-ui summary lines: off (each one holds the loop ~1 ms)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


@contextlib.contextmanager
def burners(n: int) -> Iterator[list[int]]:
    """``n`` processes spinning at normal priority for the duration of the block."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        time.sleep(0.5)  # let them reach full speed
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def _run_logged(cmd: list[str], log_path: Path, timeout: float) -> None:
    """Run a flowrt process of the benchmark from the repository root, its output to a log."""
    with open(log_path, "w") as log:
        subprocess.run(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=_env(),
            cwd=ROOT,
            timeout=timeout,
            check=True,
        )


def host_steal() -> float:
    """Seconds of CPU the hypervisor has taken from this machine since boot (all CPUs)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def run_flowrt(
    graph_file: Path, duration: float, realtime: bool, out: Path, spin: str = "0"
) -> tuple[dict[str, Any], str]:
    cmd = [
        sys.executable,
        "-m",
        "flowrt.cli",
        "run",
        str(graph_file),
        "--duration",
        f"{duration:g}",
        "--no-ui",
        "--log-every",
        f"{LOG_EVERY:g}",
        "--stats-json",
        str(out / "stats.json"),
    ]
    if realtime:
        cmd.append("--realtime")
    if spin not in ("0", ""):
        cmd += ["--spin", spin]
    _run_logged(cmd, out / "flowrt.log", duration + 120)
    stats = json.loads((out / "stats.json").read_text())
    return stats, stats.get("loop_scheduling") or stats.get("realtime", "")


def run_monolithic(
    graph_file: Path, duration: float, out: Path, every_frame: bool
) -> dict[str, Any]:
    """The Frontvision and Omnivision loops, one process per camera, started together."""
    cams, _ = graph.load(graph_file)
    start = time.monotonic() + 2.0  # both processes set up their trackers before frame 0
    extra = ["--every-frame"] if every_frame else []
    with contextlib.ExitStack() as stack:
        procs = []
        for cam in cams:
            log = stack.enter_context(open(out / f"{cam}.log", "w"))
            cmd = [
                sys.executable,
                "-m",
                "benchmarks.cambada.monolithic",
                "--graph",
                str(graph_file),
            ]
            cmd += ["--camera", cam, "--start", repr(start), "--duration", f"{duration:g}"]
            cmd += ["--out", str(out), *extra]
            procs.append(
                subprocess.Popen(cmd, env=_env(), cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
            )
        for p in procs:
            if p.wait(timeout=duration + 60) != 0:
                raise RuntimeError(f"monolithic loop failed: see {out}/*.log")
    return {cam: json.loads((out / f"{cam}.loop.json").read_text()) for cam in cams}


def run_config(
    regime: str, load: str, system: str, args: argparse.Namespace, base: Path
) -> dict[str, Any]:
    out = base / f"{regime}-{load}-{system}"
    rec = out / "records"
    rec.mkdir(parents=True, exist_ok=True)
    g = graph.derive(regime, rec, out / "graph.yaml", seed=args.seed, capture=args.capture)
    cams, tasks = graph.load(g)
    n_burn = args.burners if load == "load" else 0
    result: dict[str, Any] = {"regime": regime, "load": load, "system": system, "burners": n_burn}
    with burners(n_burn):
        t0, steal0 = time.monotonic(), host_steal()
        if system.startswith("monolithic"):
            result["loops"] = run_monolithic(g, args.duration, out, system == "monolithic-all")
            stats = None
        else:
            stats, result["granted"] = run_flowrt(
                g, args.duration, system == "flowrt-rt", out, args.spin
            )
        result["wall"] = time.monotonic() - t0
        result["steal_ms"] = (host_steal() - steal0) * 1000
    records = analysis.load_records(rec)
    every = system == "monolithic-all"
    rows = analysis.rows(records, tasks, cams, args.trim, stats, every)
    result["rows"] = [r.as_dict() for r in rows]
    if stats is not None:
        result["loop_lag"] = stats["loop"]["lag"]
        result["workers"] = {n["name"]: n.get("granted", "") for n in stats["nodes"]}
    (out / "result.json").write_text(json.dumps(result))
    return result


def run_mode_change(args: argparse.Namespace, base: Path) -> dict[str, Any]:
    out = base / "mode-change"
    rec = out / "records"
    rec.mkdir(parents=True, exist_ok=True)
    g = graph.derive("calibrated", rec, out / "graph.yaml", seed=args.seed, capture=args.capture)
    cmd = [
        sys.executable,
        "-m",
        "benchmarks.cambada.modechange",
        "--graph",
        str(g),
        "--duration",
        f"{args.mode_duration:g}",
        "--switch-at",
        f"{args.mode_duration / 2:g}",
        "--out",
        str(out),
        "--realtime",
    ]
    _run_logged(cmd, out / "flowrt.log", args.mode_duration + 120)
    mode = json.loads((out / "mode.json").read_text())
    records = analysis.load_records(rec)
    series = {}
    for node in ("ball_fr", "line", "ball_om"):
        t, iv = analysis.activation_series(records, node, mode["start"])
        series[node] = {"t": t.tolist(), "interval": iv.tolist()}
    result = {
        "switch": mode["switch"] - mode["start"],
        "granted": mode["realtime"],
        "series": series,
        "command": " ".join(shlex.quote(c) for c in cmd),
    }
    (out / "result.json").write_text(json.dumps(result))
    return result


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    py = platform.python_version()
    return f"{os.cpu_count()} CPUs ({cpu}), Linux {platform.release()}, Python {py}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.cambada", description=__doc__.splitlines()[0]
    )
    ap.add_argument(
        "--duration", type=float, default=30.0, metavar="S", help="seconds per run (30)"
    )
    ap.add_argument("--quick", action="store_true", help="6 s runs; write only to the output dir")
    ap.add_argument(
        "--only",
        action="append",
        metavar="PATTERN",
        help="run configurations whose regime/load/system contains PATTERN (repeatable)",
    )
    ap.add_argument("--burners", type=int, default=2, help="CPU burners of the loaded runs (2)")
    ap.add_argument(
        "--trim",
        type=float,
        default=1.0,
        metavar="S",
        help="start-up excluded from the record-based statistics (1 s)",
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the calibrated execution times")
    ap.add_argument(
        "--mode-duration",
        type=float,
        default=None,
        metavar="S",
        help="mode-change run (20 s; switch half-way)",
    )
    ap.add_argument("--no-mode-change", action="store_true")
    ap.add_argument(
        "--spin",
        default="300us",
        metavar="DURATION",
        help="flowrt run --spin: the loop busy-waits this long before each frame tick (300us)",
    )
    ap.add_argument(
        "--capture",
        choices=("ahead", "warm", "builtin"),
        default="ahead",
        help="camera node: the built-in capture, warm (scene motion simulated at setup), or "
        "ahead (warm + each frame rendered ahead of its timer; default)",
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="raw records and results (default: a new temp dir)"
    )
    ap.add_argument(
        "--write",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="update benchmarks/RESULTS.md and benchmarks/results/*.png (default: unless --quick)",
    )
    ap.add_argument(
        "--report-from",
        type=Path,
        metavar="DIR",
        help="run nothing: rebuild the report and figures from DIR/results.json of an earlier run",
    )
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    if args.report_from is not None:
        data = json.loads((args.report_from / "results.json").read_text())
        publish(
            data, args.report_from, data["meta"]["complete"] if args.write is None else args.write
        )
        return 0
    if args.quick and args.duration == 30.0:
        args.duration = 6.0
    if args.mode_duration is None:
        args.mode_duration = 8.0 if args.quick else 20.0
    complete = not args.quick and not args.only and not args.no_mode_change
    base = args.out or Path(tempfile.mkdtemp(prefix="flowrt-cambada-"))
    base.mkdir(parents=True, exist_ok=True)
    print(f"output: {base}", flush=True)

    configs = [(r, lo, s) for r in REGIMES for lo in LOADS for s in SYSTEMS]
    if args.only:
        configs = [c for c in configs if any(p in "/".join(c) for p in args.only)]
    results = []
    for regime, load, system in configs:
        print(
            f"[{time.strftime('%H:%M:%S')}] {regime}/{load}/{system} ({args.duration:g} s)...",
            flush=True,
        )
        res = run_config(regime, load, system, args, base)
        results.append(res)
        print(report.one_line(res), flush=True)
    mode = None
    if not args.no_mode_change:
        print(
            f"[{time.strftime('%H:%M:%S')}] mode change ({args.mode_duration:g} s)...", flush=True
        )
        mode = run_mode_change(args, base)
    meta = {
        "command": _command(argv),
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "duration": args.duration,
        "mode_duration": args.mode_duration if mode else None,
        "complete": complete,
    }
    data = {"results": results, "mode": mode, "meta": meta}
    (base / "results.json").write_text(json.dumps(data))
    publish(data, base, complete if args.write is None else args.write)
    return 0


def _command(argv: list[str]) -> str:
    """The command line, without the options that only say where outputs go."""
    kept: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a == "--out":
            skip = True
        elif not a.startswith(("--out=", "--write", "--no-write")):
            kept.append(a)
    return " ".join(["python -m benchmarks.cambada", *map(shlex.quote, kept)])


def publish(data: dict[str, Any], base: Path, write: bool) -> None:
    """Figures and the markdown section: into the repository when ``write``, else into ``base``."""
    results, mode = data["results"], data["mode"]
    fig_dir = ROOT / "benchmarks" / "results" if write else base
    figures = report.figures(results, mode, fig_dir)
    md = report.markdown(results, mode, figures, data["meta"], fig_base=ROOT / "benchmarks")
    (base / "report.md").write_text(md)
    if write:
        report.update_results(ROOT / "benchmarks" / "RESULTS.md", md)
        print("updated benchmarks/RESULTS.md and benchmarks/results/")
    print(report.summary(results))
    print(f"report: {base / 'report.md'}")
