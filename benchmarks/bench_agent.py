"""The agent experiment: stopping, restarting and swapping one behaviour mid-run must leave the
others' timing untouched (the flexible real-time control system's mixed-rate agents).

Runs graphs/agent.yaml (without the live view) on the real clock in four phases of ``--phase``
seconds: nominal; ``wall`` disabled (as ``flowrt ctl timing wall --disable``); ``wall``
enabled again; ``track`` swapped for a new instance of itself (``flowrt ctl swap``). For every
other node and phase: activations against the expected count, inter-activation mean and std,
deadline misses, skips. Statistics per phase are the differences of the cumulative ones.

    python -m benchmarks.bench_agent [--phase 10] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import flowrt
from flowrt.graph._resolve import resolve

REPO = Path(__file__).resolve().parents[1]
PHASES = ("nominal", "wall disabled", "wall enabled", "track swapped")


def _moments(rt: flowrt.Runtime) -> dict[str, tuple[int, float, float, int, int, int]]:
    out = {}
    for n in rt.stats().nodes:
        s = n.interval
        count = s.count
        mean = s.mean or 0.0
        m2 = (s.std or 0.0) ** 2 * max(0, count - 1)
        out[n.name] = (
            count,
            count * mean,
            m2 + count * mean * mean,
            n.activations,
            n.deadline_misses,
            n.skipped,
        )
    return out


def _phase(a: tuple[Any, ...], b: tuple[Any, ...]) -> dict[str, float]:
    n = b[0] - a[0]
    total, sq = b[1] - a[1], b[2] - a[2]
    mean = total / n if n else math.nan
    var = (sq - n * mean * mean) / (n - 1) if n > 1 else math.nan
    return {
        "activations": b[3] - a[3],
        "mean_ms": mean,
        "std_ms": math.sqrt(max(0.0, var)),
        "misses": b[4] - a[4],
        "skipped": b[5] - a[5],
    }


async def main(phase: float) -> dict[str, Any]:
    spec = flowrt.Graph.from_file(REPO / "graphs" / "agent.yaml").spec
    nodes = {k: v for k, v in spec.nodes.items() if v.kind != "display"}
    graph = resolve(spec.model_copy(update={"nodes": nodes}))
    results: dict[str, dict[str, dict[str, float]]] = {}
    async with flowrt.Runtime(graph) as rt:
        await rt.run(1.0)  # warm-up
        marks = [_moments(rt)]
        for name in PHASES:
            if name == "wall disabled":
                rt.set_timing("wall", enabled=False)
            elif name == "wall enabled":
                rt.set_timing("wall", enabled=True)
            elif name == "track swapped":
                await rt.swap("track", "track_target")
            await rt.run(phase)
            marks.append(_moments(rt))
        for i, name in enumerate(PHASES):
            results[name] = {
                node: _phase(marks[i][node], marks[i + 1][node])
                for node in marks[i]
                if node not in ("wall", "track") or name == "nominal"
            }
        results["_loop"] = {"lag": rt.stats().loop.lag.model_dump()}
    return results


def report(results: dict[str, Any], phase: float) -> str:
    periods = {"robot": 20, "avoid": 20, "drive": 20, "track": 40, "wall": 100, "decide": 250}
    lines = [
        "| phase | node | activations (expected) | interval mean ms | std ms | misses | skipped |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in PHASES:
        for node, r in results[name].items():
            expected = round(phase * 1000 / periods[node])
            lines.append(
                f"| {name} | {node} | {r['activations']} ({expected}) | {r['mean_ms']:.2f} | "
                f"{r['std_ms']:.2f} | {r['misses']} | {r['skipped']} |"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phase", type=float, default=10.0, help="seconds per phase")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    res = flowrt.run(main(args.phase))
    print(report(res, args.phase))
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
