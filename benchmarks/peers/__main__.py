"""flowrt against dora-rs 1.1, the same payloads and nodes, interleaved: one command.

    pip install -e ".[bench]"                       # dora-rs + dora-rs-cli (optional extra)
    python -m benchmarks.peers                      # 3 rounds, ~4-5 min on 2 cores
    python -m benchmarks.peers --rounds 1 --only lat,fps   # a subset, quicker
    python -m benchmarks.peers --no-write           # print the table, leave RESULTS.md alone
    python -m benchmarks.peers --only pipe,fps-flat --sides "flowrt workers new,flowrt pipeline 1"
    python -m benchmarks.peers --pm-qos ...        # every side with a 0 us CPU wake-up bound (root)

Each scenario runs as ``flowrt run graph.yaml --no-ui`` and as ``dora run dataflow.yml``
(no daemon needed), one after the other, in every round; the ratio is taken within a round and
the table gives the median over rounds. Both sides run the same node code (``fnodes.py`` and
``dora_nodes/``: the same stamps, the same arithmetic, results written as JSON by the nodes).
The graphs are generated into a temporary directory; nothing is left behind.

Rows (ratios are dora / flowrt for times and flowrt / dora for rates: > 1 means flowrt ahead):

- ``lat``: a 10 ms timer source sends 8 B, 640x480x3, 1920x1080x3 and 40 MiB; an echo node in
  another process (flowrt: ``placement: process``; dora: every node is a process) takes a
  zero-copy view, measures one-way latency and answers 16 bytes; the source's process
  measures the round trip. ``flowrt spin``: the echo busy-polls 0.5 ms either side of the
  call it expects; ``flowrt pinned``: the loop on CPU 0 (``taskset``), the echo on CPU 1.
- ``timer``: a 20 Hz timer node records its activation instants; std of the intervals, idle and
  with two ``while True: pass`` burners.
- ``fps``: 640x480x3 frames into a receiver in another process that computes their mean,
  through a queue of 10: flat out for 3 s, and at 250/500/1000 Hz (the highest rate with 0
  drops is reported).
- ``pipe``: source -> 8 relays -> sink, 640x480x3 at 30 Hz: end-to-end latency, total PSS of
  every process, start-up (launch to the first frame at the sink) and exit (SIGINT to the
  runner's exit). flowrt runs it inline and with the 8 relays at ``placement: process``,
  passing the frame on (``workers``) or making a new one, a copy, as dora's relays do
  (``workers new``; ``workers new spin``: each relay busy-polls 0.5 ms either side of the
  call it expects); dora has one form (every node is a process).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import platform
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import yaml

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
DORA_NODES = HERE / "dora_nodes"
FN = "benchmarks.peers.fnodes"
RESULTS = REPO / "benchmarks" / "RESULTS.md"
BEGIN, END = "<!-- peers:begin -->", "<!-- peers:end -->"

SIZES = {"8 B": 8, "640x480x3": 640 * 480 * 3, "1920x1080x3": 1920 * 1080 * 3, "40 MiB": 40 << 20}
RATES = (250, 500, 1000)
BASELINE = " (baseline)"
TIMER_WARMUP = 10
BASELINED = {
    "flowrt",
    "flowrt inline",
    "flowrt workers",
    "flowrt workers new",
    "flowrt pipeline 1",
}  # + --baseline


# --- running one side --------------------------------------------------------------------------


@dataclass
class Run:
    """What one ``flowrt run`` / ``dora run`` produced."""

    files: dict[str, Any] = field(default_factory=dict)
    start: float = 0.0  # monotonic instant of the launch
    pss_mb: float = float("nan")
    exit_s: float = float("nan")
    returncode: int | None = None
    error: str = ""


def _tree_pss(pid: int) -> float:
    """Total PSS (MB) of a process and all its descendants."""
    total = 0
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return float("nan")
    for p in procs:
        with contextlib.suppress(psutil.Error):
            total += p.memory_full_info().pss
    return total / 1e6


def _wait_files(paths: list[str], deadline: float, proc: subprocess.Popen[bytes]) -> bool:
    while time.monotonic() < deadline:
        if all(os.path.exists(p) for p in paths):
            return True
        if proc.poll() is not None and not all(os.path.exists(p) for p in paths):
            return False
        time.sleep(0.02)
    return False


def run_side(
    cmd: list[str],
    env: dict[str, str],
    cwd: Path,
    log: Path,
    before_sigint: list[str],
    after_exit: list[str] = (),  # type: ignore[assignment]
    *,
    settle: float = 0.0,
    pss: bool = False,
    timeout: float = 60.0,
) -> Run:
    """Launch, wait for the files of ``before_sigint``, [measure PSS], SIGINT, time the exit."""
    run = Run()
    with open(log, "wb") as logf:
        run.start = time.monotonic()
        proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=logf, stderr=subprocess.STDOUT)
        try:
            ok = _wait_files(before_sigint, run.start + timeout, proc)
            if not ok:
                run.error = "no result" if proc.poll() is None else f"exited {proc.returncode}"
            time.sleep(settle)
            if pss and ok:
                run.pss_mb = _tree_pss(proc.pid)
            t = time.monotonic()
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=15)
                run.exit_s = time.monotonic() - t
            except subprocess.TimeoutExpired:
                run.error = run.error or "no exit within 15 s of SIGINT"
            run.returncode = proc.returncode
        finally:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL) if False else proc.kill()
                proc.wait()
    for p in [*before_sigint, *after_exit]:
        with contextlib.suppress(OSError, ValueError):
            run.files[Path(p).name] = json.loads(Path(p).read_text())
    missing = [Path(p).name for p in [*before_sigint, *after_exit] if Path(p).name not in run.files]
    if missing and not run.error:
        run.error = f"missing {missing}"
    if run.error:
        tail = log.read_bytes()[-600:].decode(errors="replace")
        run.error += " | " + " ".join(tail.split())[-300:]
    return run


class Bench:
    def __init__(
        self,
        tmp: Path,
        quiet_dora: bool,
        baseline: Path | None = None,
        keep: set[str] | None = None,
    ) -> None:
        self.tmp = tmp
        self.keep = keep  # the flowrt sides to run (None: all); dora always runs
        # Every other round the baseline runs first: the side that runs first after the
        # previous scenario (dora's teardown of ~700 MB) is the one the machine disturbs.
        self.flip = False
        self.n = 0
        self.env = dict(os.environ)
        self.env["PYTHONPATH"] = str(REPO) + os.pathsep + self.env.get("PYTHONPATH", "")
        self.bindir = Path(sys.executable).parent
        # dora spawns its Python nodes as `python` from PATH: this interpreter's, the one with
        # dora-rs installed (run as `.venv/bin/python -m benchmarks.peers`, PATH may not say so)
        self.env["PATH"] = str(self.bindir) + os.pathsep + self.env.get("PATH", "")
        self.flowrt = shutil.which("flowrt", path=str(self.bindir)) or "flowrt"
        self.dora = shutil.which("dora", path=str(self.bindir)) or shutil.which("dora") or "dora"
        self.quiet_dora = quiet_dora
        self.baseline_env: dict[str, str] | None = None
        self.baseline = baseline
        if baseline is not None:  # an older checkout of flowrt, run the same way (before/after)
            self.baseline_env = dict(self.env)
            self.baseline_env["PYTHONPATH"] = str(baseline) + os.pathsep + self.env["PYTHONPATH"]

    def sides(self, *names: str) -> list[str]:
        """The sides of a scenario: each flowrt side also as the baseline checkout, if any."""
        out: list[str] = []
        for n in names:
            if n.startswith("flowrt") and self.keep is not None and n not in self.keep:
                continue
            pair = [n]
            if n.startswith("flowrt") and self.baseline_env is not None and n in BASELINED:
                pair.append(n + BASELINE)
            out.extend(reversed(pair) if self.flip else pair)
        return out

    def path(self, name: str) -> str:
        self.n += 1
        return str(self.tmp / f"{self.n:04d}_{name}")

    def flowrt_run(
        self,
        side: str,
        nodes: dict[str, Any],
        before: list[str],
        after: list[str] = (),  # type: ignore[assignment]
        args: list[str] = (),  # type: ignore[assignment]
        prefix: list[str] = (),  # type: ignore[assignment]
        **kw: Any,
    ) -> Run:
        g = self.path("graph.yaml")
        Path(g).write_text(yaml.safe_dump({"name": "peers", "nodes": nodes}, sort_keys=False))
        cmd = [*prefix, self.flowrt, "run", g, "--no-ui", "--log-every", "3600", *args]
        env, cwd = self.env, REPO
        if side.endswith(BASELINE):  # cwd too: the forkserver's sys.path starts with it
            assert self.baseline_env is not None
            assert self.baseline is not None
            env, cwd = self.baseline_env, self.baseline
        return run_side(cmd, env, cwd, Path(g + ".log"), before, after, **kw)

    def dora_run(
        self,
        nodes: list[dict[str, Any]],
        before: list[str],
        after: list[str] = (),
        **kw: Any,  # type: ignore[assignment]
    ) -> Run:
        for n in nodes:
            n["path"] = str(DORA_NODES / n["path"])
            n.setdefault("env", {})
            n["env"] = {k: str(v) for k, v in n["env"].items()}
            if self.quiet_dora:
                n["env"].setdefault("RUST_LOG", "error")
        g = self.path("dataflow.yml")
        Path(g).write_text(yaml.safe_dump({"nodes": nodes}, sort_keys=False))
        cwd = Path(g).parent
        return run_side([self.dora, "run", g], self.env, cwd, Path(g + ".log"), before, after, **kw)


# --- scenarios ---------------------------------------------------------------------------------

Sample = dict[str, float]  # metric name -> value, for one side of one scenario in one round


def _us(xs: list[float]) -> tuple[float, float]:
    a = np.asarray(xs) * 1e6
    return float(np.median(a)), float(np.percentile(a, 99))


def lat(b: Bench, label: str, nbytes: int, count: int) -> dict[str, Sample]:
    out: dict[str, Sample] = {}
    pinned = (os.cpu_count() or 1) >= 2 and shutil.which("taskset") is not None
    for side in b.sides("flowrt", "flowrt spin", *(["flowrt pinned"] if pinned else []), "dora"):
        res = b.path("lat.json")
        if side.startswith("flowrt"):
            nodes = {
                "src": {
                    "kind": f"{FN}:LatSource",
                    "params": {"nbytes": nbytes},
                    "trigger": {"timer": "10ms"},
                    "priority": 40,
                },
                "echo": {
                    "kind": f"{FN}:Echo",
                    "placement": "process",
                    "priority": 40,
                    "inputs": {"x": "src.out"},
                    # The remedy for the worker's wake-up: it busy-polls 0.5 ms either side
                    # of the call it expects (the calls come every 10 ms).
                    **({"spin": "0.5ms"} if "spin" in side else {}),
                    # Another remedy: the worker on a CPU of its own, the loop on the other
                    # (taskset below), so that neither wakes up queued behind the other.
                    **({"cpus": [1]} if "pinned" in side else {}),
                },
                "sink": {
                    "kind": f"{FN}:LatSink",
                    "params": {"count": count, "out": res},
                    "priority": 40,
                    "inputs": {"back": "echo.back"},
                },
            }
            prefix = ["taskset", "-c", "0"] if "pinned" in side else []
            r = b.flowrt_run(side, nodes, [res], timeout=60, prefix=prefix)
        else:
            dnodes = [
                {
                    "id": "src",
                    "path": "lat_source.py",
                    "inputs": {"tick": "dora/timer/millis/10", "back": "echo/back"},
                    "outputs": ["out"],
                    "env": {"NBYTES": nbytes, "OUT": res, "COUNT": count},
                    # dora's default 8 MB pool holds one 1080p frame and no 40 MiB one: the
                    # messages leave its zero-copy path (see RESULTS.md). Sized to 4 messages.
                    "shared_memory_pool_size": max(8 << 20, 4 * nbytes + (1 << 20)),
                },
                {"id": "echo", "path": "echo.py", "inputs": {"x": "src/out"}, "outputs": ["back"]},
            ]
            r = b.dora_run(dnodes, [res], timeout=60)
        d = r.files.get(Path(res).name)
        if d is None:
            out[side] = {"error": r.error}  # type: ignore[dict-item]
            continue
        ow50, ow99 = _us(d["one_way"])
        rt50, rt99 = _us(d["rtt"])
        out[side] = {
            f"lat {label} one-way p50": ow50,
            f"lat {label} one-way p99": ow99,
            f"lat {label} round trip p50": rt50,
            f"lat {label} round trip p99": rt99,
        }
    return out


def _burners(n: int) -> list[multiprocessing.Process]:
    procs = [multiprocessing.Process(target=_burn, daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    return procs


def _burn() -> None:
    while True:
        pass


def timer(b: Bench, label: str, burners: int, count: int) -> dict[str, Sample]:
    out: dict[str, Sample] = {}
    procs = _burners(burners)
    try:
        for side in b.sides("flowrt", "flowrt --realtime", "dora"):
            res = b.path("timer.json")
            if side.startswith("flowrt"):
                nodes = {
                    "tick": {
                        "kind": f"{FN}:TimerRecorder",
                        "params": {"count": count, "out": res},
                        "trigger": {"timer": "50ms"},
                        "priority": 40,
                    }
                }
                extra = ["--realtime"] if "--realtime" in side else []
                r = b.flowrt_run(side, nodes, [res], timeout=60, args=extra)
            else:
                dnodes = [
                    {
                        "id": "tick",
                        "path": "timer_recorder.py",
                        "inputs": {"tick": "dora/timer/millis/50"},
                        "env": {"OUT": res, "COUNT": count},
                    }
                ]
                r = b.dora_run(dnodes, [res], timeout=60)
            d = r.files.get(Path(res).name)
            if d is None:
                out[side] = {"error": r.error}  # type: ignore[dict-item]
                continue
            # The first ticks queue behind start-up (dora delivers a burst of them): skipped.
            iv = np.diff(np.asarray(d["t"][TIMER_WARMUP:])) * 1000
            out[side] = {
                f"timer 20 Hz {label} std": float(np.std(iv, ddof=1)),
                f"timer 20 Hz {label} p99 abs. error": float(np.percentile(np.abs(iv - 50.0), 99)),
            }
    finally:
        for p in procs:
            p.kill()
            p.join()
    return out


def fps(b: Bench, rate: int | None, seconds: float) -> dict[str, Sample]:
    """640x480x3 into a receiver process through a queue of 10; rate None = flat out."""
    out: dict[str, Sample] = {}
    label = "flat out" if rate is None else f"{rate} Hz"
    sides = ("flowrt", "flowrt pipeline 1", "dora") if rate is None else ("flowrt", "dora")
    for side in b.sides(*sides):
        sent, got = b.path("sent.json"), b.path("got.json")
        if side.startswith("flowrt"):
            trig = {"loop": True} if rate is None else {"timer": f"{1000 / rate:g}ms"}
            # Flat out is "a video file as fast as possible": the producer waits for the
            # worker (lossless); dora has no such edge, its queue of 10 drops the oldest.
            policy = "lossless" if rate is None else "queue"
            nodes = {
                "src": {
                    "kind": f"{FN}:FrameSource",
                    "params": {"seconds": seconds, "out": sent},
                    "trigger": trig,
                    "priority": 40,
                },
                "mean": {
                    "kind": f"{FN}:Mean",
                    "placement": "process",
                    "priority": 40,
                    "trigger": {"input": "frame"},
                    "inputs": {"frame": {"from": "src.frame", "policy": policy, "size": 10}},
                    **({"pipeline": 1} if side.startswith("flowrt pipeline 1") else {}),
                },
                "count": {
                    "kind": f"{FN}:Count",
                    "params": {"out": got},
                    "priority": 40,
                    "inputs": {"result": {"from": "mean.result", "policy": "queue", "size": 64}},
                },
            }
            r = b.flowrt_run(side, nodes, [sent], [got], settle=0.5, timeout=60)
        else:
            env: dict[str, Any] = {"SECONDS": seconds, "OUT": sent}
            inputs: dict[str, Any] = {}
            if rate is None:
                env["FLAT_OUT"] = 1
            else:
                inputs["tick"] = f"dora/timer/millis/{1000 // rate}"
            dnodes = [
                {
                    "id": "src",
                    "path": "frame_source.py",
                    "inputs": inputs,
                    "outputs": ["frame"],
                    "env": env,
                },
                {
                    "id": "mean",
                    "path": "mean.py",
                    "inputs": {"frame": {"source": "src/frame", "queue_size": 10}},
                    "env": {"OUT": got},
                },
            ]
            if not inputs:
                del dnodes[0]["inputs"]
            r = b.dora_run(dnodes, [sent], [got], settle=0.5, timeout=60)
        s, g = r.files.get(Path(sent).name), r.files.get(Path(got).name)
        if s is None or g is None:
            out[side] = {"error": r.error}  # type: ignore[dict-item]
            continue
        span = max(g["last"] - g["first"], 1e-9)
        # Dropped: the gaps between the first and the last frame received. Frames sent before
        # the receiver was up (dora drops those while a node is starting) are not counted:
        # this is the sustained rate, not start-up.
        gaps = g["last_seq"] - g["first_seq"] + 1 - g["n"] if g["n"] else float(s["sent"])
        out[side] = {
            f"fps {label} delivered/s": (g["n"] - 1) / span if g["n"] > 1 else 0.0,
            f"fps {label} dropped": float(gaps),
            f"fps {label} sent": float(s["sent"]),
        }
    return out


def pipe(b: Bench, count: int) -> dict[str, Sample]:
    out: dict[str, Sample] = {}
    sides = ("flowrt inline", "flowrt workers", "flowrt workers new", "flowrt workers new spin")
    for side in b.sides(*sides, "dora"):
        res = b.path("pipe.json")
        if side.startswith("flowrt"):
            nodes: dict[str, Any] = {
                "src": {
                    "kind": f"{FN}:FrameSource",
                    "params": {"seconds": 3600},
                    "trigger": {"timer": "33.333ms"},
                    "priority": 40,
                }
            }
            prev = "src.frame"
            for i in range(8):
                # "new": each relay makes a new frame (a copy), as dora's relays do; else the
                # built-in relay passes the frame it got on.
                kind = f"{FN}:NewFrameRelay" if "new" in side else "relay"
                node: dict[str, Any] = {"kind": kind, "priority": 40, "inputs": {"input": prev}}
                if side.startswith("flowrt workers"):
                    node["placement"] = "process"
                if side.endswith("spin"):  # each relay busy-polls 0.5 ms around its call
                    node["spin"] = "0.5ms"
                nodes[f"r{i}"] = node
                prev = f"r{i}.output"
            nodes["sink"] = {
                "kind": f"{FN}:PipeSink",
                "params": {"count": count, "out": res},
                "priority": 40,
                "inputs": {"frame": prev},
            }
            r = b.flowrt_run(side, nodes, [res], settle=0.3, pss=True, timeout=60)
        else:
            dn: list[dict[str, Any]] = [
                {
                    "id": "src",
                    "path": "frame_source.py",
                    "inputs": {"tick": "dora/timer/millis/33"},
                    "outputs": ["frame"],
                    "env": {"SECONDS": 3600},
                }
            ]
            prev = "src/frame"
            for i in range(8):
                dn.append(
                    {"id": f"r{i}", "path": "relay.py", "inputs": {"x": prev}, "outputs": ["out"]}
                )
                prev = f"r{i}/out"
            dn.append(
                {
                    "id": "sink",
                    "path": "pipe_sink.py",
                    "inputs": {"frame": prev},
                    "env": {"OUT": res, "COUNT": count},
                }
            )
            r = b.dora_run(dn, [res], settle=0.3, pss=True, timeout=60)
        d = r.files.get(Path(res).name)
        if d is None:
            out[side] = {"error": r.error}  # type: ignore[dict-item]
            continue
        p50, p99 = _us(d["lat"])
        out[side] = {
            "pipe e2e p50": p50 / 1000,
            "pipe e2e p99": p99 / 1000,
            "pipe PSS": r.pss_mb,
            "start-up to first message": (d["first"] - r.start) * 1000,
            "SIGINT to exit": r.exit_s * 1000,
        }
    return out


# --- rows and the table -----------------------------------------------------------------------


@dataclass
class Row:
    """One line of the table: a metric, the flowrt configuration it comes from, its unit."""

    metric: str
    flowrt_side: str
    unit: str
    higher_better: bool = False
    values: dict[str, list[float]] = field(default_factory=dict)  # side -> per round
    ratios: list[float] = field(default_factory=list)
    note: str = ""


def collect(rows: dict[tuple[str, str], Row], result: dict[str, Sample], unit: str) -> None:
    dora = result.get("dora", {})
    for side, sample in result.items():
        if side == "dora":
            continue
        for metric, v in sample.items():
            paced = metric.startswith("fps") and "flat out" not in metric
            if (
                metric == "error"
                or metric.endswith(" sent")
                or metric == "fps flat out dropped"
                or (paced and metric.endswith("/s"))  # paced: the rate is the source's; drops count
            ):
                # flat out, a source outruns any receiver: the queue of 10 drops by design
                continue
            key = (metric, side)
            hb = metric.endswith("/s")
            u = unit_of(metric, unit)
            row = rows.setdefault(key, Row(metric, side, u, hb))
            row.values.setdefault("flowrt", []).append(v)
            dv = dora.get(metric)
            if dv is not None and not isinstance(dv, str):
                row.values.setdefault("dora", []).append(dv)
                if metric.endswith("dropped"):
                    continue
                if hb:
                    row.ratios.append(v / dv if dv else float("inf"))
                else:
                    row.ratios.append(dv / v if v else float("inf"))
    for side, sample in result.items():
        if "error" in sample:
            print(f"  {side}: FAILED {sample['error']}", file=sys.stderr)


def unit_of(metric: str, default: str) -> str:
    if metric.startswith("lat"):
        return "us"
    if metric.startswith("timer"):
        return "ms"
    if metric.endswith("/s"):
        return "frames/s"
    if metric.endswith("dropped"):
        return "frames"
    if metric == "pipe PSS":
        return "MB"
    return "ms"


def summarise_rate(
    rows: dict[tuple[str, str], Row], per_round: list[dict[str, dict[str, Sample]]]
) -> None:
    """The highest rate each side delivered with 0 drops, per round."""
    row = Row("fps highest rate with 0 drops", "flowrt", "Hz", True)
    for rnd in per_round:
        best: dict[str, float] = {}
        for side in ("flowrt", "dora"):
            ok = [
                rate
                for rate in RATES
                if rnd.get(f"fps {rate}", {}).get(side, {}).get(f"fps {rate} Hz dropped") == 0
            ]
            best[side] = float(max(ok)) if ok else 0.0
            row.values.setdefault(side, []).append(best[side])
        if best["dora"]:
            row.ratios.append(best["flowrt"] / best["dora"])
        elif best["flowrt"]:
            row.ratios.append(float("inf"))
    if row.values:
        rows[(row.metric, "flowrt")] = row


def fmt(x: float) -> str:
    if x != x:
        return "-"
    if x == float("inf"):
        return "inf"
    if abs(x) >= 100:
        return f"{x:,.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    return f"{x:.2f}"


def table(rows: dict[tuple[str, str], Row]) -> str:
    lines = [
        "| row | flowrt | unit | flowrt (median of rounds) | dora (median of rounds) | "
        "ratio (median) | rounds flowrt ahead | verdict |",
        "|---|---|---|---:|---:|---:|---:|---|",
    ]
    for row in rows.values():
        f = row.values.get("flowrt", [])
        d = row.values.get("dora", [])
        fm = statistics.median(f) if f else float("nan")
        dm = statistics.median(d) if d else float("nan")
        if row.metric.endswith("dropped"):
            ahead = sum(1 for a, c in zip(f, d, strict=False) if a <= c)
            ratio = "-"
            verdict = "ahead" if fm <= dm else "behind"
        else:
            ratio_v = statistics.median(row.ratios) if row.ratios else float("nan")
            ratio = fmt(ratio_v) + "x" if row.ratios else "-"
            ahead = sum(1 for r in row.ratios if r >= 1.0)
            verdict = "-" if not row.ratios else ("ahead" if ratio_v >= 1.0 else "**behind**")
        if not d:
            verdict = "dora: no result"
        lines.append(
            f"| {row.metric} | {row.flowrt_side} | {row.unit} | {fmt(fm)} | {fmt(dm)} | {ratio} | "
            f"{ahead}/{max(len(f), len(d))} | {verdict} |"
        )
    return "\n".join(lines)


# --- main --------------------------------------------------------------------------------------


def scenarios(
    only: set[str] | None, quick: bool
) -> Iterator[tuple[str, str, Callable[[Bench], dict[str, Sample]]]]:
    n_lat = 100 if quick else 150
    if not only or "lat" in only:
        for label, nbytes in SIZES.items():
            yield "lat", f"lat {label}", lambda b, lb=label, nb=nbytes: lat(b, lb, nb, n_lat)
    if not only or "timer" in only:
        n = 100 + TIMER_WARMUP
        yield "timer", "timer idle", lambda b: timer(b, "idle", 0, n)
        yield "timer", "timer 2 burners", lambda b: timer(b, "2 burners", 2, n)
    if not only or "fps" in only or "fps-flat" in only:
        yield "fps", "fps flat", lambda b: fps(b, None, 3.0)
    if not only or "fps" in only:
        for rate in RATES:
            yield "fps", f"fps {rate}", lambda b, r=rate: fps(b, r, 2.0)
    if not only or "pipe" in only:
        yield "pipe", "pipe", lambda b: pipe(b, 60)


def machine() -> str:
    import uvloop

    return (
        f"{platform.node()} · {platform.platform()} · {os.cpu_count()} CPUs (a shared 2-core VM) "
        f"· Python {platform.python_version()} · uvloop {uvloop.__version__} · "
        f"dora-rs {_version('dora-rs')} / dora-rs-cli {_version('dora-rs-cli')} · "
        f"load average {os.getloadavg()[0]:.2f} at start"
    )


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "not installed"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.peers", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--only", help="comma-separated groups: lat,timer,fps,pipe (fps-flat: fps flat out only)"
    )
    ap.add_argument(
        "--sides",
        help="comma-separated flowrt sides to run, e.g. 'flowrt workers new,flowrt pipeline 1' "
        "(default: all; dora and the --baseline copies of these always run)",
    )
    ap.add_argument("--quick", action="store_true", help="fewer messages per latency run")
    ap.add_argument("--no-write", action="store_true", help="do not touch RESULTS.md")
    ap.add_argument("--json", metavar="PATH", help="also write every per-round sample here")
    ap.add_argument(
        "--baseline",
        metavar="DIR",
        type=Path,
        help="also run every flowrt side with this checkout of flowrt first on PYTHONPATH "
        "(e.g. a `git worktree` of an older commit): before/after in the same run",
    )
    ap.add_argument(
        "--dora-logs", action="store_true", help="leave dora's per-message diagnostics on"
    )
    ap.add_argument(
        "--pm-qos",
        action="store_true",
        help="hold a CPU wake-up bound of 0 us (/dev/cpu_dma_latency, root) for the whole "
        "run, every side alike: what flowrt run --cpu-latency 0us gives, the software compared",
    )
    args = ap.parse_args(argv)
    if args.pm_qos:  # held until this process exits
        from flowrt.system._cpu_latency import CpuLatencyRequest

        qos = CpuLatencyRequest(0.0)
        if not qos.hold():
            print(f"--pm-qos: {qos.granted}", file=sys.stderr)
            return 2
        print(f"CPU wake-up bound {qos.granted} for every side (PM QoS)")
    only = set(args.only.split(",")) if args.only else None
    if shutil.which("dora", path=str(Path(sys.executable).parent)) is None and not shutil.which(
        "dora"
    ):
        print("dora not found: pip install -e '.[bench]'", file=sys.stderr)
        return 2
    header = machine()
    print(header)
    rows: dict[tuple[str, str], Row] = {}
    per_round: list[dict[str, dict[str, Sample]]] = []
    loads: list[float] = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="flowrt-peers-") as tmp:
        keep = set(args.sides.split(",")) if args.sides else None
        b = Bench(Path(tmp), quiet_dora=not args.dora_logs, baseline=args.baseline, keep=keep)
        for rnd in range(args.rounds):
            this: dict[str, dict[str, Sample]] = {}
            b.flip = rnd % 2 == 1
            loads.append(os.getloadavg()[0])
            print(f"round {rnd + 1}: load average {loads[-1]:.2f}", flush=True)
            for _group, name, fn in scenarios(only, args.quick):
                t = time.monotonic()
                result = fn(b)
                this[name] = result
                collect(rows, result, "")
                brief = {
                    s: {k: round(v, 1) for k, v in m.items() if not isinstance(v, str)} or m
                    for s, m in result.items()
                }
                print(f"round {rnd + 1} {name} ({time.monotonic() - t:.1f} s): {brief}", flush=True)
            per_round.append(this)
    if not only or "fps" in only:
        summarise_rate(rows, per_round)
    took = time.monotonic() - t0
    text = table(rows)
    print(text)
    print(f"took {took:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(per_round, indent=1))
    if not args.no_write:
        cmd = "python -m benchmarks.peers" + (" " + " ".join(argv or sys.argv[1:])).rstrip()
        section = (
            f"{BEGIN}\n### Measured table ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
            f"{args.rounds} rounds, {took:.0f} s)\n\nCommand: `{cmd}`  \n{header}; "
            f"load average at the start of each round: {', '.join(f'{x:.1f}' for x in loads)}"
            f"\n\n{text}\n{END}"
        )
        old = RESULTS.read_text()
        if BEGIN in old and END in old:
            new = re.sub(
                re.escape(BEGIN) + ".*?" + re.escape(END), lambda _m: section, old, flags=re.S
            )
        else:
            new = old.rstrip() + "\n\n" + section + "\n"
        RESULTS.write_text(new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
