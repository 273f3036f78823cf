"""Which side of a Zenoh hop costs what: flowrt's and a plain program's ends, crossed.

    python -m benchmarks.bench_zenoh_cross [--seconds 4] [--rounds 2]

8-byte messages at 20 Hz over ``tcp/127.0.0.1``, one host and one clock, each pair of ends
in two processes (median of the rounds' p50, rounds interleaved, the order reversed every
round):

- ``plain > plain``: a plain Zenoh publisher putting flowrt's header (the attachment) and a
  JSON payload, a plain subscriber reading them in its callback (Zenoh's thread);
- ``flowrt > plain``: flowrt's exporter (bench_zenoh's exporter graph) to that subscriber;
- ``plain > flowrt``: that publisher to flowrt's import (bench_zenoh's importer graph);
- ``flowrt > flowrt``: bench_zenoh's own row.

Two times per row: from the publication (the source's stamp in the payload) to the
subscriber's callback (plain) or the import callback's entry (flowrt), and to the sink's
activation (flowrt) or the end of the callback (plain). The plain publisher answers flowrt's
clock query (``_flowrt/clock/ZID``) as a flowrt exporter does. ``--stages`` also prints the
exporter's steps (source -> send, the message's encoding, the ``put``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import bench_zenoh as bench

VARIANTS = {
    "plain > plain": ("plain_pub", "plain_sub"),
    "flowrt > plain": ("flowrt_pub", "plain_sub"),
    "plain > flowrt": ("plain_pub", "flowrt_sub"),
    "flowrt > flowrt": ("flowrt_pub", "flowrt_sub"),
}


def plain_pub(a: argparse.Namespace) -> None:
    import zenoh

    from flowrt.remote._clock import CLOCK_PREFIX, answer_clock
    from flowrt.remote.wire import Header

    s = bench._zenoh([f"tcp/127.0.0.1:{a.port}"], [])
    zid = str(s.info.zid())
    q = s.declare_queryable(f"{CLOCK_PREFIX}/{zid}", answer_clock)
    pub = s.declare_publisher("bench/x")
    enc = zenoh.Encoding.APPLICATION_JSON.with_schema("builtins.dict")
    end = time.monotonic() + a.seconds
    nxt = time.monotonic() + 1.0
    seq = 0
    while time.monotonic() < end:
        time.sleep(max(0.0, nxt - time.monotonic()))
        t = time.time()
        payload = json.dumps({"t": t, "p": "12345678", "n": seq}, separators=(",", ":"))
        att = Header("plain0123456789a", zid, seq, t, t, "json").encode()
        pub.put(payload.encode(), attachment=att, encoding=enc)
        seq += 1
        nxt += 0.05
    q.undeclare()
    s.close()


def plain_sub(a: argparse.Namespace) -> None:
    entry: list[float] = []
    done: list[float] = []
    s = bench._zenoh([], [f"tcp/127.0.0.1:{a.port}"])

    def on(sample: Any) -> None:
        t = time.time()
        sample.attachment.to_bytes()
        sent = json.loads(sample.payload.to_bytes())["t"]
        entry.append(t - sent)
        done.append(time.time() - sent)

    sub = s.declare_subscriber("bench/x", on)
    time.sleep(a.seconds)
    sub.undeclare()
    s.close()
    Path(a.out).write_text(json.dumps({"entry": entry, "final": done}))


def flowrt_pub(a: argparse.Namespace) -> None:
    import flowrt
    import flowrt.remote._export as ex

    steps: list[tuple[float, float, float]] = []
    if a.stages:
        send = ex.ExportSender._send_message

        def timed(self: Any, exp: Any, value: Any) -> None:
            t0 = time.time()
            put = exp.publisher.put

            def timed_put(*args: Any, **kw: Any) -> None:
                t1 = time.time()
                put(*args, **kw)
                steps.append((t0 - value["t"], t1 - t0, time.time() - t1))

            exp.publisher = _Put(timed_put)
            try:
                send(self, exp, value)
            finally:
                exp.publisher = _Put(put)

        ex.ExportSender._send_message = timed  # type: ignore[method-assign]
    spec = bench.exporter_graph("8B", 20, a.port, False)
    flowrt.run(bench._run(spec, a.seconds))
    if steps:
        x = np.median(np.array(steps[5:]) * 1000, axis=0)
        print(
            f"  exporter: source -> send {x[0]:.3f} ms, encoding {x[1]:.3f} ms, "
            f"put {x[2]:.3f} ms (p50)"
        )


class _Put:
    def __init__(self, put: Any) -> None:
        self.put = put


def flowrt_sub(a: argparse.Namespace) -> None:
    import flowrt
    import flowrt.remote._importer as imp

    entry: list[float] = []
    decode = imp.ImportLink._decode

    def traced(self: Any, sample: Any) -> Any:
        t = time.time()  # the import callback's first step
        header, value = decode(self, sample)
        if isinstance(value, dict):
            entry.append(t - value["t"])
        return header, value

    imp.ImportLink._decode = traced  # type: ignore[method-assign]
    final = a.out + ".sink"
    spec = bench.importer_graph("8B", a.port, final, 20)
    flowrt.run(bench._run(spec, a.seconds))
    got = json.loads(Path(final).read_text()) if Path(final).exists() else []
    Path(a.out).write_text(json.dumps({"entry": entry, "final": got}))


def _spawn(role: str, **kw: Any) -> subprocess.Popen[bytes]:
    return bench._spawn(role, "benchmarks.bench_zenoh_cross", **kw)


def _p50(xs: list[float]) -> float:
    xs = xs[5:]
    return float(np.percentile(np.array(xs) * 1000, 50)) if xs else float("nan")


def run(pub: str, sub: str, seconds: float, tmp: Path, stages: bool) -> tuple[float, float]:
    port = bench._port()
    p = _spawn(pub, port=port, seconds=seconds + 2.5, stages=stages)
    time.sleep(1.0)
    out = tmp / f"{pub}-{sub}.json"
    out.unlink(missing_ok=True)
    _spawn(sub, port=port, seconds=seconds, out=out).wait()
    p.wait()
    if not out.exists():
        return float("nan"), float("nan")
    r = json.loads(out.read_text())
    return _p50(r["entry"]), _p50(r["final"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--stages", action="store_true", help="time the exporter's steps")
    ap.add_argument("--role")
    ap.add_argument("--port", type=int)
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    if a.role:
        {"plain_pub": plain_pub, "plain_sub": plain_sub}.get(
            a.role, flowrt_pub if a.role == "flowrt_pub" else flowrt_sub
        )(a)
        return
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_zenoh_cross_{os.getpid()}"
    tmp.mkdir(exist_ok=True)
    print(f"load average {os.getloadavg()} at the start")
    res: dict[str, list[tuple[float, float]]] = {k: [] for k in VARIANTS}
    names = list(VARIANTS)
    for r in range(a.rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            res[name].append(run(*VARIANTS[name], a.seconds, tmp, a.stages))
    print(f"load average {os.getloadavg()} at the end")
    print("| publisher > subscriber | -> callback p50 ms | -> end (sink) p50 ms |")
    print("|---|---|---|")
    for name, rs in res.items():
        e = float(np.nanmedian([x[0] for x in rs]))
        f = float(np.nanmedian([x[1] for x in rs]))
        print(f"| {name} | {e:.3f} | {f:.3f} |")


if __name__ == "__main__":
    main()
