"""The ``can`` node with a whole vehicle's bus: every message of a production DBC at its cycle.

    python benchmarks/can/bench_vehicle.py [--dbc ford_lincoln_base_pt.dbc] [--duration 10]

A peer on python-can's ``virtual`` bus (a thread sleeping to absolute deadlines) sends every
message of the DBC (opendbc's, by name, or a path) at its cycle time, and the event messages
once a second, FD where the DBC says so; the ``can`` node receives them at default params
(its timer at the gcd of the cycles). After ``--duration`` seconds of real time it prints,
as JSON: frames sent and received, decoded messages, decode errors, unknown ids, the node's
restarts and errors, its execution time per tick (p50/p99/max, ms) and the loop's lateness.
Issue 38: at default params a 331-message CAN FD DBC restarted the node every second and
lost frames (its status was over the RTDB's value limit).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import random
import threading
import time
from pathlib import Path
from typing import Any

import can
from flowrt.nodes.can.dbc import load_dbc, message_is_fd

from flowrt import GraphBuilder, Runtime
from flowrt.analysis.can_frames import fd_payload_length


def _dbc(name: str) -> str:
    if Path(name).is_file():
        return name
    import opendbc

    return str(Path(opendbc.DBC_PATH) / name)


def _peer(channel: str, db: Any, stop: threading.Event, sent: list[int]) -> None:
    """Every message at its cycle (event ones every second), to absolute deadlines."""
    rnd = random.Random(1)
    bus = can.Bus(interface="virtual", channel=channel)
    plan = []
    for m in db.messages:
        fd = message_is_fd(m)
        n = fd_payload_length(m.length) if fd else m.length
        data = bytes(rnd.getrandbits(8) for _ in range(m.length)) + bytes(n - m.length)
        msg = can.Message(
            arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame, is_fd=fd, data=data
        )
        period = (m.cycle_time or 1000) / 1000
        plan.append([rnd.random() * period, period, msg])
    start = time.monotonic()
    try:
        while not stop.is_set():
            due = min(plan, key=lambda p: p[0])
            wait = start + due[0] - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            bus.send(due[2])
            sent[0] += 1
            due[0] += due[1]
    finally:
        bus.shutdown()


async def run(dbc: str, duration: float) -> dict[str, Any]:
    db = load_dbc(dbc)
    channel = f"vehicle-bench-{time.monotonic_ns()}"
    g = GraphBuilder()
    g.add("car", "can", params={"interface": "virtual", "channel": channel, "dbc": dbc})
    stop, sent = threading.Event(), [0]
    async with Runtime(g.build()) as rt:
        runner = rt.scheduler.runners["car"]
        for _ in range(1000):  # the node set up and its bus open (polled: no event for it)
            node = getattr(runner.executor, "node", None)
            if node is not None and node.bus is not None:
                break
            await asyncio.sleep(0.01)
        assert node is not None, "the can node did not open its bus in 10 s"
        peer = threading.Thread(target=_peer, args=(channel, db, stop, sent), daemon=True)
        peer.start()
        await asyncio.sleep(duration)
        stop.set()
        peer.join()
        await asyncio.sleep(0.2)  # the last frames across the reader thread
        stats = rt.stats()
        row = stats.node("car")
        return {
            "dbc": Path(dbc).name,
            "messages": len(db.messages),
            "tick_ms": node.tick * 1000,
            "duration_s": duration,
            "sent": sent[0],
            "received": node.received,
            "decoded": sum(st.received for st in node.msgs.values()) - node.decode_errors,
            "decode_errors": node.decode_errors,
            "unknown": node.unknown_count,
            "restarts": row.restarts,
            "errors": row.errors,
            "deadline_misses": row.deadline_misses,
            "exec_ms": {
                "p50": row.execution.p50,
                "p99": row.execution.p99,
                "max": row.execution.max,
            },
            "loop_lag_ms": {"p99": stats.loop.lag.p99, "max": stats.loop.lag.max},
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dbc", default="ford_lincoln_base_pt.dbc")
    ap.add_argument("--duration", type=float, default=10.0)
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the DBC's strict-loading warnings
    print(json.dumps(asyncio.run(run(_dbc(args.dbc), args.duration)), indent=1))


if __name__ == "__main__":
    main()
