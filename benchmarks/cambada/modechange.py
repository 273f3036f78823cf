"""The paper's mode change (its Figures 9-10), in an embedded flowrt Runtime:

    python -m benchmarks.cambada.modechange --graph G --duration S --switch-at T --out DIR \
        [--realtime]

Runs the graph, switches to the graph's ``paper_mode_change`` mode after ``T`` seconds with
``rt.set_mode`` (Ball_Om off, Ball_Fr every 2 frames, Line every frame at priority 40), runs
on to ``S`` seconds, and writes ``stats.json`` and ``mode.json`` (the monotonic time of the
switch); the recording trackers write their own activations. A subprocess of its own, so that
SCHED_FIFO (``--realtime``) never leaks into the benchmark's driver.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path

import flowrt
from flowrt.cli import new_event_loop


async def _main(graph: Path, duration: float, switch_at: float, realtime: bool, out: Path) -> None:
    rt = flowrt.Runtime.from_file(graph, realtime=realtime)
    async with rt:
        t_start = time.monotonic()
        await rt.run(switch_at)
        rt.set_mode("paper_mode_change")
        t_switch = time.monotonic()
        await rt.run(max(0.0, duration - switch_at))
        stats = rt.stats()
    (out / "stats.json").write_text(stats.model_dump_json(indent=2))
    (out / "mode.json").write_text(
        json.dumps(
            {
                "start": t_start,
                "switch": t_switch,
                "mode": "paper_mode_change",
                "realtime": rt.realtime,
            }
        )
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graph", type=Path, required=True)
    ap.add_argument("--duration", type=float, required=True)
    ap.add_argument("--switch-at", type=float, required=True)
    ap.add_argument("--realtime", action="store_true")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        runner.run(_main(a.graph, a.duration, a.switch_at, a.realtime, a.out))


if __name__ == "__main__":
    main()
