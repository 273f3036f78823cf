"""How fast the ``can`` node's trace writer keeps a bus, per format.

    .venv/bin/python benchmarks/can/bench_trace.py [--frames 50000]

Feeds the node's :class:`~flowrt.nodes.can.bus.TraceLog` (python-can's writers in a thread
of their own) with frames as fast as a producer can put them, half classic 8-byte, half
CAN FD 64-byte, and reports frames per second written, frames dropped (the writer's queue
holds 100 000) and the file size; then reads the file back with python-can and checks the
count. A saturated 1 Mbit/s classic bus carries at most ~7 400 frames/s (135-bit frames);
the writer must stay above that with margin for a loaded machine.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import can
from flowrt.nodes.can.bus import TraceLog


def run(suffix: str, frames: int, folder: Path) -> dict[str, float]:
    path = folder / f"bench{suffix}"
    log = TraceLog(str(path))
    t0 = time.perf_counter()
    for k in range(frames):
        fd = k % 2 == 1
        log.put(
            can.Message(
                timestamp=1000 + k * 1e-4,
                arbitration_id=0x100 + k % 64,
                data=bytes(64) if fd else k.to_bytes(8, "little"),
                is_fd=fd,
                bitrate_switch=fd,
                is_extended_id=False,
                channel="can0",
            )
        )
    log.close()
    elapsed = time.perf_counter() - t0
    with can.LogReader(str(path)) as reader:
        back = sum(1 for _ in reader)
    return {
        "frames_per_s": frames / elapsed,
        "dropped": log.dropped,
        "read_back": back,
        "mb": os.path.getsize(path) / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=50_000, help="frames per format")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    print("| format | frames/s written | dropped | read back | MB |")
    print("|---|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".log", ".asc", ".blf"):
            r = run(suffix, args.frames, Path(tmp))
            print(
                f"| {suffix} | {r['frames_per_s']:,.0f} | {r['dropped']:.0f} | "
                f"{r['read_back']:.0f} | {r['mb']:.1f} |"
            )


if __name__ == "__main__":
    main()
