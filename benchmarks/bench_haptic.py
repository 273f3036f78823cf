"""The haptic loop (issue 42): 1 kHz timing, force age at the device, virtual-wall energy.

    python benchmarks/bench_haptic.py                 # 4 loop configurations x 5 s + walls
    python benchmarks/bench_haptic.py --duration 10   # longer runs
    python benchmarks/bench_haptic.py --walls-only    # the energy table alone (virtual time)
    python benchmarks/bench_haptic.py --precise       # each row also with timing: precise

1. **Loop timing and force age** (real time): ``flowrt run graphs/haptic.yaml --no-ui
   --no-display --duration S --stats-json F [--realtime]`` in a subprocess, idle and with
   ``--burners`` (default 2) processes spinning ``while True: pass`` at normal priority. From
   the statistics ("no burners" is idle only on a machine nobody else uses: the load
   average is printed before and after): the haptic node's activations, completions,
   inter-activation std and p99, deadline misses (its deadline: 1 ms), and its report's
   ``force_age_ms`` (the camera frame's time to the force given to the device: capture,
   tracker in a worker, vision_force, the newest wall taken by the loop).
2. **Virtual wall energy** (virtual time, deterministic): the simulated handle (0.2 kg,
   1 N·s/m, nobody holding it) thrown at 0.2 m/s against a vision wall at x = 0 rendered by
   the haptic node at 1 kHz with the graph's max_force (3 N) and max_rate (200 N/s). The
   energy ½mv² + ½kd² (d = depth behind the wall) must not grow: per stiffness, the worst
   contact's energy leaving the wall over the energy it came in with (> 1: the wall gave
   energy, the sampled wall's known failure), and the peak and final energy over the energy
   at the first contact. The README's value is 300 N/m.
"""

from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
GRAPH = HERE.parent / "graphs" / "haptic.yaml"


def _spin() -> None:
    while True:
        pass


def _precise_graph(tmp: str) -> Path:
    """graphs/haptic.yaml with ``timing: precise`` on the haptic node (same folder: its
    relative paths resolve the same)."""
    import yaml

    data = yaml.safe_load(GRAPH.read_text())
    data["nodes"]["haptic"]["timing"] = "precise"
    path = GRAPH.parent / f".haptic-precise-{os.getpid()}-{Path(tmp).name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_graph(duration: float, realtime: bool, precise: bool = False) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        stats = Path(tmp) / "stats.json"
        graph = _precise_graph(tmp) if precise else GRAPH
        cmd = [sys.executable, "-m", "flowrt.cli", "run", str(graph), "--no-ui", "--no-display"]
        cmd += ["--duration", str(duration), "--stats-json", str(stats)]
        if realtime:
            cmd.append("--realtime")
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=duration + 120)
        finally:
            if precise:
                graph.unlink()
        if r.returncode != 0:
            raise SystemExit(f"flowrt run failed ({r.returncode}): {r.stderr[-500:]}")
        s = json.loads(stats.read_text())
    node = next(n for n in s["nodes"] if n["name"] == "haptic")
    age = s["reports"]["haptic"]["force_age_ms"]
    return {
        "activations": node["activations"],
        "completions": node["completions"],
        "std_ms": node["interval"]["std"],
        "p99_ms": node["interval"]["p99"],
        "max_ms": node["interval"]["max"],
        "misses": node["deadline_misses"],
        "age_p50_ms": age["p50"],
        "age_p99_ms": age["p99"],
        "granted": node.get("granted", ""),
    }


def loop_table(
    duration: float, burners: int, precise: bool = False
) -> list[tuple[str, dict[str, Any]]]:
    rows = []
    for load in (0, burners) if burners else (0,):
        procs = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(load)]
        for p in procs:
            p.start()
        try:
            for realtime, exact in itertools.product((False, True), (False, True)[: 1 + precise]):
                name = (f"{load} burners" if load else "no burners") + (" --realtime" * realtime)
                name += ", timing: precise" * exact
                la = os.getloadavg()[0]
                rows.append((name, {**run_graph(duration, realtime, exact), "loadavg": la}))
                print(f"  {name}: {rows[-1][1]}", file=sys.stderr)
        finally:
            for p in procs:
                p.kill()
                p.join()
    return rows


def wall_energy(stiffness: float, seconds: float = 2.0) -> dict[str, float]:
    """Peak energy after the first contact over the start energy (<= 1: the wall is stable)."""
    from flowrt.nodes.haptic import Fixture, Haptic

    from flowrt.testing import NodeHarness

    sim = {"hand": {"mode": "none"}, "start": [-20, 0, 0], "velocity": [200, 0, 0]}
    params = {"sim": sim, "max_force": 3.0, "max_rate": 200.0, "timeout": "10s"}
    h = NodeHarness(Haptic, params, name="haptic")
    wall = Fixture("wall", ("x", "y"), (0.0, 0.0), (-1.0, 0.0), stiffness, 0.0, True, 0.0)
    device = h.node.device

    def energy() -> float:
        depth = max(0.0, device.pos[0])  # metres behind the wall at x = 0
        return device.kinetic_energy() + 0.5 * stiffness * depth * depth

    h.publish("force", wall, 0.0)
    gains: list[float] = []  # per contact: energy leaving the wall over energy entering it
    entered: float | None = None
    first: float | None = None
    peak = 0.0
    for i in range(int(seconds * 1000)):
        h.ctx.time = i / 1000
        h.process(force=wall)
        behind = device.pos[0] > 0
        e = energy()
        if behind and entered is None:
            entered = e
            first = e if first is None else first
        elif not behind and entered is not None:
            gains.append(e / entered)
            entered = None
        if first is not None:
            peak = max(peak, e)
    assert first is not None, "the handle never reached the wall"
    return {"k": stiffness, "contacts": len(gains), "gain": max(gains, default=1.0),
            "peak": peak / first, "end": energy() / first}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--burners", type=int, default=2)
    ap.add_argument("--walls-only", action="store_true")
    ap.add_argument("--precise", action="store_true", help="each row also with timing: precise")
    args = ap.parse_args()
    load = Path("/proc/loadavg").read_text().split()[:3] if os.path.exists("/proc/loadavg") else []
    print(f"load average before: {' '.join(load)}")
    if not args.walls_only:
        print(f"\n### graphs/haptic.yaml, {args.duration:g} s per row (haptic node, 1 kHz)\n")
        print("| configuration | activations | done | std ms | p99 ms | max ms | misses "
              "| force age p50 / p99 ms | load avg |")  # fmt: skip
        print("|---|---|---|---|---|---|---|---|---|")
        for name, r in loop_table(args.duration, args.burners, args.precise):
            print(
                f"| {name} | {r['activations']} | {r['completions']} | {r['std_ms']:.3f} "
                f"| {r['p99_ms']:.3f} | {r['max_ms']:.2f} | {r['misses']} "
                f"| {r['age_p50_ms']} / {r['age_p99_ms']} | {r['loadavg']:.2f} |"
            )
    print("\n### Virtual wall, simulated handle thrown at 0.2 m/s (virtual time, 1 kHz)\n")
    print("| stiffness N/m | contacts | energy out / in, worst contact | peak / at contact "
          "| end / at contact |")  # fmt: skip
    print("|---|---|---|---|---|")
    for k in (100, 300, 1000, 2000, 3000, 10_000, 30_000):
        w = wall_energy(k)
        print(f"| {k:g} | {w['contacts']:g} | {w['gain']:.3f} | {w['peak']:.3f} "
              f"| {w['end']:.3f} |")  # fmt: skip
    load = Path("/proc/loadavg").read_text().split()[:3] if os.path.exists("/proc/loadavg") else []
    print(f"\nload average after: {' '.join(load)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
