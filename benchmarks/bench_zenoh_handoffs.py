"""Where the time of a remote edge goes: timestamps at each hand-off of an import.

    python -m benchmarks.bench_zenoh_handoffs [--payload 8B|640x480|1920x1080] [--seconds 6]
        [--rate 20]
    python -m benchmarks.bench_zenoh_handoffs --put-cost 1000

Runs bench_zenoh's exporter role in a second process and its importer here, with the
import's Zenoh callback, its loop delivery and the sink wrapped to take wall-clock stamps
(one host: one clock). Per message, p50/p90 of each step:

- capture -> sent: the source's publication to the sender thread's stamp (loop -> thread);
- sent -> callback: encoding, Zenoh's put, the transport and Zenoh's receive;
- callback: decoding and (frames) the copy into the local pool, on Zenoh's thread, plus the
  ``call_soon_threadsafe`` that wakes the loop (the wrapper adds ~0.03 ms of its own);
- callback end -> deliver: the loop waking;
- deliver: publication on the import node's output;
- deliver end -> sink: the sink's activation by the scheduler.

``--rate``: messages per second (default 20, the latency benchmark's). At 20 Hz every step
runs cold (the caches are another program's after 50 ms asleep); at a few hundred it runs
warm: the ratio is what the same code costs cold.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import flowrt.remote._importer as remote
from benchmarks import bench_zenoh as bench

STEPS = (
    ("cap", "sent"),
    ("sent", "on"),
    ("on", "on_end"),
    ("on_end", "deliver"),
    ("deliver", "deliver_end"),
    ("deliver_end", "sink"),
    ("cap", "sink"),
)


def put_cost(n: int) -> None:
    """What one Zenoh ``put`` of 8 B costs its caller (would it block the loop?): ``n`` puts
    at 100 Hz from this process to a subscriber in another."""
    port = bench._port()
    session = bench._zenoh([f"tcp/127.0.0.1:{port}"], [])
    pub = session.declare_publisher("bench/raw")
    sub = bench._spawn("raw_sub", port=port, seconds=n / 100 + 3, lat=os.devnull)
    time.sleep(1.5)
    cost = []
    for _ in range(n):
        t0 = time.perf_counter()
        pub.put(b"12345678", attachment=repr(time.time()).encode())
        cost.append(time.perf_counter() - t0)
        time.sleep(0.01)
    sub.wait()
    session.close()
    a = np.array(cost) * 1000
    print(
        f"put of 8 B on the caller, {n} puts at 100 Hz: p50 {np.percentile(a, 50):.3f} ms, "
        f"p99 {np.percentile(a, 99):.3f} ms, max {a.max():.3f} ms; load {os.getloadavg()}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--payload", default="8B", choices=list(bench.SIZES))
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--rate", type=float, default=20.0, help="messages per second")
    ap.add_argument("--put-cost", type=int, metavar="N", help="time N puts instead")
    args = ap.parse_args()
    if args.put_cost:
        put_cost(args.put_cost)
        return
    rec: dict[int, dict[str, float]] = {}
    on_sample, deliver = remote.ImportLink.on_sample, remote.ImportLink.deliver
    process = bench.LatencySink.process
    sink_times: list[float] = []

    def traced_on_sample(self: Any, sample: Any) -> None:
        t = time.time()
        h = remote.Header.decode(sample.attachment.to_bytes())
        r = rec.setdefault(h.seq, {})
        r.update(on=t, sent=h.sent, cap=h.captured)
        if h.kind == "json":  # the source's own stamp
            r["cap"] = json.loads(sample.payload.to_bytes())["t"]
        on_sample(self, sample)
        r["on_end"] = time.time()

    def traced_deliver(self: Any) -> None:
        t = time.time()
        with self.lock:
            seqs = [h.seq for h, _ in self.pending]
        deliver(self)
        t2 = time.time()
        for s in seqs:
            rec.setdefault(s, {}).update(deliver=t, deliver_end=t2)

    def traced_process(self: Any, value: Any) -> None:
        sink_times.append(time.time())
        process(self, value)

    remote.ImportLink.on_sample = traced_on_sample  # type: ignore[method-assign]
    remote.ImportLink.deliver = traced_deliver  # type: ignore[method-assign]
    bench.LatencySink.process = traced_process  # type: ignore[method-assign]

    port = bench._port()
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_handoffs_{os.getpid()}"
    tmp.mkdir(exist_ok=True)
    exporter = bench._spawn(
        "exporter",
        payload=args.payload,
        rate=args.rate,
        port=port,
        seconds=args.seconds + 3,
        result=tmp / "exp.json",
    )
    time.sleep(1.5)
    spec = bench.importer_graph(args.payload, port, "", args.rate)
    import flowrt

    flowrt.run(bench._run(spec, args.seconds))
    exporter.wait()
    delivered = sorted(s for s, r in rec.items() if "deliver" in r)
    for s, t in zip(delivered[-len(sink_times) :], sink_times[-len(delivered) :], strict=False):
        rec[s]["sink"] = t
    rows = [r for r in rec.values() if all(k in r for a_b in STEPS for k in a_b)][5:]
    print(f"{args.payload} at {args.rate:g} Hz: {len(rows)} messages, load {os.getloadavg()}")
    for a, b in STEPS:
        x = np.array([r[b] - r[a] for r in rows]) * 1000
        p50, p90 = np.percentile(x, 50), np.percentile(x, 90)
        print(f"  {a:>11} -> {b:<11} p50 {p50:6.3f} ms  p90 {p90:6.3f} ms")
    if exporter.returncode:
        sys.exit(exporter.returncode)
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
