"""The CAN paper's experiment (communication requirements of autonomous mobile robots), run.

The soccer robot's sensors (the paper's Tables 1 and 2): 2 infrared sensors at 20 ms, 3 motor
set-points at 33 Hz (30.303 ms, the paper's arithmetic), 3 encoders at 10 ms, at 125 kbit/s.
Scenario 1 piggybacks each sensor type into one message (2, 3 and 3 data bytes:
scenario1.dbc); scenario 2 sends one 1-byte message per sensor (scenario2.dbc).

    PYTHONPATH=benchmarks/can python benchmarks/can/paper.py [--duration 15] [--realtime]

For each scenario the script

1. runs ``flowrt can analyse scenarioN.dbc --bitrate 125000`` (the paper: 15 055 and
   32 435 bit/s) and keeps the worst-case response times;
2. runs the scenario as a flowrt graph on one python-can virtual bus (scenarioN.yaml): a
   ``can-signals`` simulator per message feeding the robot's ``can`` node (the encoders and
   infrared sensors) or the PC's (the motor set-points); a controller
   (:class:`Controller`) receives every sensor message from the PC's ``can`` node, and an
   actuator recorder the set-points from the robot's. Each ``can`` node sends on
   flowrt's timer at the DBC cycle times.
   A passive monitor bus (read only after the run) gives every frame, written to an .asc
   trace with python-can's ``Logger``;
3. measures the load with ``flowrt can stats trace.asc --bitrate 125000`` (frames x their
   worst-case length, the analysis' own measure) against the analysis;
4. measures, per message, the response time of every frame: from its nominal release
   instant (on the grid of its period: flowrt's schedule does not drift) to its decoding in
   the receiving ``can`` node. On the virtual bus a frame's transmission takes no time, so
   this is the software's share (release lateness + the receive path), held against the
   analysis' worst case, which counts the bus only. The largest release lateness of each
   message (send instant - nominal) is its queuing jitter J: the analysis run again with
   those J says what flowrt as the sender would give on a real 125 kbit/s bus;
5. the end-to-end jitter per message: max - min of those response times (the paper: 30 ms
   with plain CAN, 1 ms with FTT-CAN).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import can
from pydantic import BaseModel, ConfigDict

import flowrt
from flowrt import Input, Node

HERE = Path(__file__).resolve().parent


class Controller(Node):
    """The robot's controller: receives every sensor message and keeps when each arrived."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

    any_inputs = Input(object, required=False, doc="decoded sensor messages")

    def setup(self) -> None:
        self.records: list[tuple[str, float, float, bool]] = []

    def process(self, **msgs: Any) -> None:
        for m in msgs.values():
            if m is not None:
                self.records.append((m.name, m.timestamp, m.bus_timestamp, m.valid))


SENSORS = {  # name: (period ms, ECU)
    "Encoder": (10.0, "encoders"),
    "Infrared": (20.0, "infrared"),
    "Motor": (1000 / 33, "pc"),
}


def scenario_graph(n: int, channel: str) -> dict[str, Any]:
    """The graph of scenario ``n`` as a dict (also written out as scenarioN.yaml)."""
    dbc = str(HERE / f"scenario{n}.dbc")
    if n == 1:
        groups = {
            "encoders": {"Encoders": ("Encoder", 3, 10.0)},
            "infrared": {"Infrared": ("Infrared", 2, 20.0)},
            "pc": {"MotorSetpoints": ("Motor", 3, 1000 / 33)},
        }
    else:
        groups = {
            "encoders": {f"Encoder{i}": (f"Encoder{i}Value", 0, 10.0) for i in (1, 2, 3)},
            "infrared": {f"Infrared{i}": (f"Infrared{i}Value", 0, 20.0) for i in (1, 2)},
            "pc": {f"Motor{i}": (f"Motor{i}Value", 0, 1000 / 33) for i in (1, 2, 3)},
        }
    # Two bus participants, as on the robot: its sensor board (encoders and infrared) and
    # the PC (sends the motor set-points). Each is one ``can`` node; every node in this one
    # process wakes a reader thread per frame (the virtual bus is in-process), so fewer
    # participants disturb the measure less.
    sensor_msgs = [*groups["encoders"], *groups["infrared"]]
    motor_msgs = list(groups["pc"])
    nodes: dict[str, Any] = {}
    inputs: dict[str, dict[str, str]] = {"robot": {}, "pc": {}}
    for ecu, msgs in groups.items():
        side = "pc" if ecu == "pc" else "robot"
        for msg, (sig, count, period) in msgs.items():
            sigs = [f"{sig}{i}" for i in range(1, count + 1)] if count else [sig]
            sim = f"sim_{msg.lower()}"
            nodes[sim] = {
                "kind": "can-signals",
                "priority": 30,
                "params": {
                    "rate_ms": period,
                    "signals": {s: {"wave": "count", "modulo": 100} for s in sigs},
                },
            }
            inputs[side][msg] = f"{sim}.values"
    for side, tick, receive in (("robot", 10.0, motor_msgs), ("pc", 1000 / 33, sensor_msgs)):
        nodes[side] = {
            "kind": "can",
            "priority": 40,
            "params": {
                "interface": "virtual",
                "channel": channel,
                "dbc": dbc,
                "tick_ms": tick,
                "receive": receive,
            },
            "inputs": inputs[side],
        }
    nodes["controller"] = {  # the PC's controller: every sensor message
        "kind": "paper:Controller",
        "priority": 45,
        "inputs": {m: {"from": f"pc.{m}", "policy": "queue", "size": 64} for m in sensor_msgs},
    }
    nodes["actuators"] = {  # the motors' side of the set-points, for their response times
        "kind": "paper:Controller",
        "priority": 45,
        "inputs": {m: {"from": f"robot.{m}", "policy": "queue", "size": 64} for m in motor_msgs},
    }
    return {
        "name": f"can-paper-scenario{n}",
        "description": f"CAN paper scenario {n} on a virtual bus",
        "nodes": nodes,
    }


def response_times(
    records: list[tuple[str, float, float, bool]], periods: dict[str, float], offset: float
) -> dict[str, tuple[list[float], list[float]]]:
    """Per message, ms: (reception - nominal release, send - nominal release). The nominal
    release of the k-th frame is on the grid of the period anchored at the least late send
    (flowrt's schedule does not drift); the runtime clock is moved to wall time by
    ``offset`` (the virtual bus stamps sends with time.time())."""
    by: dict[str, list[tuple[float, float]]] = {}
    for name, rx, sent, _ in records:
        by.setdefault(name, []).append((sent, rx + offset))
    out: dict[str, tuple[list[float], list[float]]] = {}
    for name, rows in by.items():
        rows.sort()
        period = periods[name] / 1000
        t0 = rows[0][0]
        ks = [round((s - t0) / period) for s, _ in rows]
        base = min(s - k * period for (s, _), k in zip(rows, ks, strict=True))
        grid = [base + k * period for k in ks]
        out[name] = (
            [(rx - g) * 1000 for (_, rx), g in zip(rows, grid, strict=True)],
            [(s - g) * 1000 for (s, _), g in zip(rows, grid, strict=True)],
        )
    return out


async def run_scenario(
    n: int, duration: float, trace: Path, realtime: bool = False
) -> dict[str, Any]:
    import yaml

    from flowrt import Graph, Runtime

    channel = f"paper-{n}-{time.monotonic_ns()}"
    spec = scenario_graph(n, channel)
    path = trace.with_suffix(".yaml")
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    graph = Graph.from_file(str(path))
    # a passive monitor, read after the run: a reading thread would take the GIL per frame
    monitor = can.Bus(interface="virtual", channel=channel)
    offset = time.time() - time.monotonic()
    try:
        async with Runtime(graph, realtime=realtime) as rt:
            await asyncio.sleep(duration)
            records = [
                r
                for name in ("controller", "actuators")
                for r in rt.scheduler.runners[name].executor.node.records
            ]
            stats = rt.stats()
        with can.Logger(str(trace)) as logger:
            while (m := monitor.recv(0)) is not None:
                logger(m)
    finally:
        monitor.shutdown()
    return {"records": records, "offset": offset, "stats": stats}


def main() -> None:
    from flowrt.analysis.can import analyse_bus, timings_from_dbc
    from flowrt.cli.can import load_database, trace_stats

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=15.0, help="seconds per scenario")
    ap.add_argument("--realtime", action="store_true", help="as flowrt run --realtime")
    ap.add_argument("--out", default=str(HERE / "results"), help="traces and JSON here")
    ap.add_argument(
        "--write-graphs",
        action="store_true",
        help="only write scenario1.yaml and scenario2.yaml (channel 'paper')",
    )
    args = ap.parse_args()
    if args.write_graphs:
        import yaml

        for n in (1, 2):
            text = yaml.safe_dump(scenario_graph(n, "paper"), sort_keys=False)
            text = text.replace(str(HERE) + "/", "benchmarks/can/")
            head = (
                f"# CAN paper scenario {n} (generated by benchmarks/can/paper.py "
                "--write-graphs).\n# PYTHONPATH=benchmarks/can flowrt run "
                f"benchmarks/can/scenario{n}.yaml\n"
            )
            (HERE / f"scenario{n}.yaml").write_text(head + text)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"duration_s": args.duration, "scenarios": {}}
    for n in (1, 2):
        dbc = str(HERE / f"scenario{n}.dbc")
        db = load_database(dbc)
        analysis = analyse_bus(timings_from_dbc(db), 125_000)
        trace = out / f"scenario{n}.asc"
        run = flowrt.run(run_scenario(n, args.duration, trace, args.realtime))
        measured = trace_stats(str(trace), 125_000, db)
        periods = {m.name: m.timing.period_ms for m in analysis.messages}
        rts = response_times(run["records"], periods, run["offset"])
        # the measured release jitter (max send lateness) as the analysis' queuing jitter J:
        # what flowrt as the sender would give on a real 125 kbit/s bus
        jit = {m.name: max(rts[m.name][1]) for m in analysis.messages if m.name in rts}
        with_j = {
            m.name: m for m in analyse_bus(timings_from_dbc(db, jitters=jit), 125_000).messages
        }
        rows = []
        for m in analysis.messages:
            ids = [r for r in measured["ids"] if r["id"] == m.timing.id]
            r, late = rts.get(m.name, ([], []))
            mj = with_j[m.name]
            rows.append(
                {
                    "name": m.name,
                    "id": m.timing.id,
                    "period_ms": m.timing.period_ms,
                    "frame_bits": m.frame_bits,
                    "wcrt_ms": m.wcrt_ms,
                    "sent": ids[0]["count"] if ids else 0,
                    "measured_period_ms": ids[0]["period_ms"] if ids else None,
                    "period_std_ms": ids[0]["std_ms"] if ids else None,
                    "received": len(r),
                    "release_jitter_ms": max(late) if late else None,
                    "wcrt_with_jitter_ms": mj.wcrt_ms,
                    "schedulable_with_jitter": mj.schedulable,
                    "response_p50_ms": statistics.median(r) if r else None,
                    "response_p99_ms": sorted(r)[int(0.99 * (len(r) - 1))] if r else None,
                    "response_max_ms": max(r) if r else None,
                    "jitter_ms": (max(r) - min(r)) if r else None,
                    "within_wcrt": bool(r) and max(r) <= (m.wcrt_ms or 0),
                }
            )
        doc = {
            "analysis_bits_per_s": analysis.bits_per_s,
            "analysis_utilisation": analysis.utilisation,
            "measured_bits_per_s": measured["mean_load"] * 125_000,
            "measured_utilisation": measured["mean_load"],
            "frames": measured["frames"],
            "trace_duration_s": measured["duration_s"],
            "messages": rows,
        }
        summary["scenarios"][n] = doc
        print(
            f"\n### Scenario {n}: analysis {analysis.bits_per_s:,.0f} bit/s "
            f"({100 * analysis.utilisation:.2f} %), measured "
            f"{doc['measured_bits_per_s']:,.0f} bit/s ({100 * doc['measured_utilisation']:.2f} %)"
            f" over {measured['duration_s']:.1f} s, {measured['frames']} frames\n"
        )
        print(
            "| message | id | period ms | bits | WCRT ms | frames | period mean ms | "
            "period std ms | release jitter J ms | WCRT with J ms | response p50 ms | p99 ms | "
            "max ms | max <= WCRT | end-to-end jitter ms |"
        )
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|---:|")
        for r in rows:
            print(
                f"| {r['name']} | 0x{r['id']:03X} | {r['period_ms']:.3f} | {r['frame_bits']} | "
                f"{r['wcrt_ms']:.3f} | {r['sent']} | {r['measured_period_ms']:.3f} | "
                f"{r['period_std_ms']:.3f} | {r['release_jitter_ms']:.3f} | "
                f"{r['wcrt_with_jitter_ms']:.3f}{'' if r['schedulable_with_jitter'] else ' (!)'} | "
                f"{r['response_p50_ms']:.3f} | {r['response_p99_ms']:.3f} | "
                f"{r['response_max_ms']:.3f} | {'yes' if r['within_wcrt'] else 'NO'} | "
                f"{r['jitter_ms']:.3f} |"
            )
    (out / "paper.json").write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    sys.exit(main())
