"""The serial gateway: frames/s through slcan at 115200 baud against the line's ceiling, and the
latency it adds, measured through a flowrt ``can`` node.

The gateway is tests/slcan_device.py on a pty, pacing its bytes at the baud rate (10 bits per
byte) and bridging to a python-can virtual bus, where this script plays the robot. In the
same run, the same node on the virtual bus directly is the baseline of the latency.

    python benchmarks/can/bench_slcan.py [--frames 3000] [--probes 200]

- throughput: the robot queues ``--frames`` 8-byte frames at once; the gateway forwards them
  as fast as the line allows; frames/s = frames received by the node / time from the first
  to the last, against 115200 / 10 / 22 = 523.6 frames/s (22 characters per frame line);
- latency: ``--probes`` frames, one every 20 ms, each stamped when the robot sends it; the
  latency is the node's receive time (runtime clock, when the frame reaches the event loop)
  minus the send time; added latency = through the gateway minus directly.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
from slcan_device import SlcanDevice, line_bytes, max_frames_per_s  # noqa: E402

from flowrt import GraphBuilder, Runtime  # noqa: E402

DBC = str(ROOT / "nodes" / "robot.dbc")
BAUD = 115200


def graph(params: dict[str, Any]) -> Any:
    g = GraphBuilder()
    g.add("gw", "can", params={"dbc": DBC, "unknown_output": True, **params})
    return g.build()


async def measure(params: dict[str, Any], peer: can.BusABC, frames: int, probes: int) -> dict:
    async with Runtime(graph(params)) as rt:
        sub = rt.subscribe("gw.unknown", size=frames + probes + 16)
        node = rt.scheduler.runners["gw"].executor.node
        end = time.monotonic() + 10
        while (node is None or node.bus is None) and time.monotonic() < end:
            await asyncio.sleep(0.01)
            node = rt.scheduler.runners["gw"].executor.node
        await asyncio.sleep(0.3)
        # latency probes: id 0x700, data = probe number
        sent: dict[int, float] = {}
        for k in range(probes):
            sent[k] = time.monotonic()
            peer.send(
                can.Message(
                    arbitration_id=0x700, data=k.to_bytes(2, "big") + bytes(6), is_extended_id=False
                )
            )
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.3)
        lat = []
        while True:
            try:
                f = sub.get_nowait()
            except LookupError:
                break
            if f.id == 0x700:
                lat.append((f.timestamp - sent[int.from_bytes(f.data[:2], "big")]) * 1000)
        # throughput: a burst of 8-byte frames
        for k in range(frames):
            peer.send(
                can.Message(arbitration_id=0x701, data=k.to_bytes(8, "big"), is_extended_id=False)
            )
        got: list[float] = []
        last_new = time.monotonic()
        while len(got) < frames and time.monotonic() - last_new < 2.0:
            try:
                f = sub.get_nowait()
            except LookupError:
                await asyncio.sleep(0.005)
                continue
            got.append(f.timestamp)
            last_new = time.monotonic()
        fps = (len(got) - 1) / (got[-1] - got[0]) if len(got) > 1 else 0.0
        return {
            "latency_ms": {
                "n": len(lat),
                "mean": statistics.fmean(lat),
                "p50": statistics.median(lat),
                "p99": sorted(lat)[int(0.99 * (len(lat) - 1))],
                "max": max(lat),
            },
            "burst": frames,
            "received": len(got),
            "frames_per_s": fps,
        }


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--probes", type=int, default=200)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        chan = f"bench-slcan-{time.monotonic_ns()}"
        dev = SlcanDevice(Path(tmp) / "ttyCAN0", chan, baud=BAUD)
        peer = can.Bus(interface="virtual", channel=chan)
        try:
            slcan = await measure(
                {
                    "interface": "slcan",
                    "channel": str(dev.path),
                    "bitrate": 250000,
                    "options": {"tty_baudrate": BAUD, "sleep_after_open": 0},
                },
                peer,
                args.frames,
                args.probes,
            )
        finally:
            peer.shutdown()
            dev.close()
    chan = f"bench-direct-{time.monotonic_ns()}"
    peer = can.Bus(interface="virtual", channel=chan)
    try:
        direct = await measure(
            {"interface": "virtual", "channel": chan}, peer, args.frames, args.probes
        )
    finally:
        peer.shutdown()
    ceiling = max_frames_per_s(BAUD, 8)
    wire_ms = line_bytes(8) * 10 / BAUD * 1000
    doc = {
        "baud": BAUD,
        "ceiling_frames_per_s": ceiling,
        "line_ms": wire_ms,
        "slcan": slcan,
        "direct": direct,
    }
    print(json.dumps(doc, indent=2))
    s, d = slcan["latency_ms"], direct["latency_ms"]
    print(
        f"\n| path | frames/s (burst of {args.frames}) | of ceiling | latency p50 ms | "
        "p99 ms | max ms |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    print(
        f"| slcan 115200 baud via pty | {slcan['frames_per_s']:.1f} | "
        f"{100 * slcan['frames_per_s'] / ceiling:.1f} % | {s['p50']:.3f} | {s['p99']:.3f} | "
        f"{s['max']:.3f} |"
    )
    print(
        f"| virtual bus directly | {direct['frames_per_s']:.0f} | - | {d['p50']:.3f} | "
        f"{d['p99']:.3f} | {d['max']:.3f} |"
    )
    print(
        f"\nceiling {ceiling:.1f} frames/s (22-character lines); one line on the wire "
        f"{wire_ms:.3f} ms; added latency p50 {s['p50'] - d['p50']:.3f} ms"
    )
    if args.json:
        with open(args.json, "w") as f:  # noqa: ASYNC230 (after the measurement)
            json.dump(doc, f, indent=2)


if __name__ == "__main__":
    asyncio.run(main())
