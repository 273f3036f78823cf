"""Remote edges over Zenoh on loopback: latency, sustained rate, memory, and the timing of a
critical node while frames are exported.

    python -m benchmarks.bench_zenoh [--duration 10] [--sustained 60] [--out FILE.json]
        [--rounds 3] [--payloads 8B,640x480,1920x1080]

``--rounds``: every latency variant that many times, interleaved; ``--sustained 0`` skips the
30 fps run.

Rows, each measured in the same run:

- latency from publication (the source's clock) to the activation of the remote sink, for a
  small message (8 B of payload in a JSON mapping), 640x480x3 and 1920x1080x3 frames at 20 Hz:
  flowrt local edge (one process), flowrt over Zenoh (two processes), and Zenoh's own Python
  publisher/subscriber sending the same bytes (two processes, no flowrt), its callback on
  Zenoh's thread (the criterion), and, informative, that callback handing each sample to a
  uvloop loop (what a user's own asyncio program pays), for the small message, the plain
  program sending flowrt's message itself (the same JSON mapping, ``json.dumps`` before the
  ``put``, ``json.loads`` in the callback: the criterion's 8 bytes carry no message), and, for
  frames, the publisher putting them from Zenoh's shared-memory API (as flowrt does when the
  session enables it);
- sustained 640x480x3 at 30 fps for ``--duration`` seconds: published, received, lost;
- memory (RSS, PSS) of the exporting and importing processes;
- a critical 20 Hz timer node's inter-activation std on the exporting side, with and without
  the 640x480 @ 30 fps export.

``--pm-qos`` (informative, root): the whole run with ``/dev/cpu_dma_latency`` held at 0, idle
CPUs polling instead of halting, as real-time set-ups do (cyclictest, tuned's
latency-performance profile): what the hop costs without the idle states' wake-ups.

Both processes run on this machine, so their clocks agree: latency is one-way, from the
sender's wall-clock stamp (in the JSON, in the frame's last 8 bytes, or in the attachment for
raw Zenoh) to the receiver's clock at the sink's activation; flowrt's clock-offset estimate
(error <= rtt/2) is not used here.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel

import flowrt
from flowrt import Frame, Input, Node, Output, TimerTrigger

SIZES = {"8B": None, "640x480": (480, 640, 3), "1920x1080": (1080, 1920, 3)}


def stamp(pixels: np.ndarray, t: float) -> None:
    """Write ``t`` into the last 8 bytes of a frame (as a float64)."""
    pixels.reshape(-1)[-8:] = np.frombuffer(np.float64(t).tobytes(), np.uint8)


def stamped(pixels: np.ndarray) -> float:
    return float(np.frombuffer(pixels.reshape(-1)[-8:].tobytes(), np.float64)[0])


class PayloadSource(Node):
    class Params(BaseModel):
        payload: str = "8B"
        rate: float = 20.0

    out = Output(object)
    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> Any:
        self.n += 1
        shape = SIZES[self.params.payload]
        if shape is None:
            return {"out": {"t": time.time(), "p": "12345678", "n": self.n}}
        f = self.ctx.new_frame(shape)
        f.data[0, 0, 0] = self.n % 256
        f.timestamp = self.ctx.now()
        stamp(f.data, time.time())
        return {"frame": f}


class LatencySink(Node):
    class Params(BaseModel):
        out: str = ""

    value = Input(object)

    def setup(self) -> None:
        self.lat: list[float] = []

    def process(self, value: Any) -> None:
        if isinstance(value, Frame):  # the source's wall clock, in the pixels: one host, one
            self.lat.append(time.time() - stamped(value.data))  # clock, no offset estimate
        elif isinstance(value, dict):
            self.lat.append(time.time() - value["t"])

    def teardown(self) -> None:
        if self.params.out:
            Path(self.params.out).write_text(json.dumps(self.lat))


class Critical(Node):
    tick = Output(int)

    def process(self) -> int:
        return 1


def _pss() -> dict[str, float]:
    import psutil

    m = psutil.Process().memory_full_info()
    return {"rss_mb": m.rss / 2**20, "pss_mb": getattr(m, "pss", m.rss) / 2**20}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def exporter_graph(
    payload: str,
    rate: float,
    port: int | None,
    critical: bool,
    host: str = "127.0.0.1",
    config: dict[str, Any] | None = None,
) -> Any:
    g = flowrt.GraphBuilder("exporter")
    g.add("src", PayloadSource, params={"payload": payload, "rate": rate})
    if critical:
        g.add("crit", Critical, trigger={"timer": "50ms"}, priority=90)
    if port is not None:
        g.zenoh(listen=[f"tcp/{host}:{port}"], config=config or {})
        g.export("bench/x", "src.out" if SIZES[payload] is None else "src.frame")
    return g.build()


def importer_graph(
    payload: str,
    port: int,
    out: str,
    rate: float,
    host: str = "127.0.0.1",
    config: dict[str, Any] | None = None,
) -> Any:
    g = flowrt.GraphBuilder("importer")
    g.zenoh(listen=[], connect=[f"tcp/{host}:{port}"], config=config or {})
    frames = SIZES[payload] is not None
    g.import_("rx", {"key": "bench/x", "frames": frames, "period": 1000 / rate})
    g.add("sink", LatencySink, params={"out": out}, inputs={"value": {"from": "rx.output"}})
    return g.build()


async def _run(spec: Any, seconds: float) -> dict[str, Any]:
    async with flowrt.Runtime(spec) as rt:
        await rt.run(seconds)
        stats = rt.stats()
        mem = _pss()
    return {"stats": json.loads(stats.model_dump_json()), "mem": mem}


def role_main(args: argparse.Namespace) -> None:
    if args.role == "exporter":
        spec = exporter_graph(
            args.payload, args.rate, args.port, args.critical, args.host, _no_shm(args)
        )
        Path(args.result).write_text(json.dumps(flowrt.run(_run(spec, args.seconds))))
    elif args.role == "importer":
        spec = importer_graph(
            args.payload, args.port, args.lat, args.rate, args.host, _no_shm(args)
        )
        Path(args.result).write_text(json.dumps(flowrt.run(_run(spec, args.seconds))))
    elif args.role == "raw_pub":
        raw_pub(args)
    elif args.role == "raw_sub":
        raw_sub(args)


def _no_shm(args: argparse.Namespace) -> dict[str, Any]:
    """``--no-shm``: bytes through the socket, as between two machines (one host's processes,
    even in two network namespaces, would otherwise share memory)."""
    return {"transport/shared_memory/enabled": False} if args.no_shm else {}


def _zenoh(listen: list[str], connect: list[str], no_shm: bool = False) -> Any:
    import zenoh

    c = zenoh.Config()
    if no_shm:
        c.insert_json5("transport/shared_memory/enabled", "false")
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(c)


def raw_pub(args: argparse.Namespace) -> None:
    s = _zenoh([f"tcp/{args.host}:{args.port}"], [], args.no_shm)
    pub = s.declare_publisher("bench/raw")
    shape = SIZES[args.payload]
    frame = None if shape is None else np.zeros(shape, np.uint8)
    pool = policy = None
    if args.shm and frame is not None:  # Zenoh's shared-memory API, as its examples use it
        import zenoh.shm as zshm

        pool = zshm.ShmProvider.default_backend(4 * frame.nbytes + (1 << 20))
        policy = zshm.GarbageCollect()
    end = time.monotonic() + args.seconds
    period = 1 / args.rate
    nxt = time.monotonic() + 1.0
    n = 0
    while time.monotonic() < end:
        time.sleep(max(0.0, nxt - time.monotonic()))
        sent = time.time()
        if args.json:  # flowrt's message itself, as a plain program sends a mapping
            n += 1
            pub.put(json.dumps({"t": sent, "p": "12345678", "n": n}).encode())
            nxt += period
            continue
        if frame is None:
            data = b"12345678"
        else:  # a program publishing its numpy frames pays this copy too (ZBytes takes bytes)
            n += 1
            frame[0, 0, 0] = n % 256
            data = frame.tobytes()
            if pool is not None:  # one copy more into the shared buffer (it takes bytes)
                buf = pool.alloc(len(data), policy)
                buf[0 : len(data)] = data
                data = buf
        pub.put(data, attachment=repr(sent).encode())
        nxt += period
    s.close()


def raw_sub(args: argparse.Namespace) -> None:
    """Zenoh's subscriber callback (on Zenoh's thread), or, with ``--asyncio``, that callback
    handing each sample to a uvloop loop (``call_soon_threadsafe``): what a user's own asyncio
    program pays to get a sample onto its loop."""
    lat: list[float] = []
    s = _zenoh([], [f"tcp/{args.host}:{args.port}"], args.no_shm)
    if not args.asyncio:

        def on(sample: Any) -> None:
            if args.json:  # the message, as a mapping (its stamp inside)
                lat.append(time.time() - json.loads(sample.payload.to_bytes())["t"])
                return
            np.frombuffer(sample.payload.to_bytes(), np.uint8)  # the bytes, as an array
            lat.append(time.time() - float(sample.attachment.to_bytes()))

        sub = s.declare_subscriber("bench/raw", on)
        time.sleep(args.seconds)
    else:
        from flowrt.system._eventloop import new_event_loop

        loop = new_event_loop()

        def arrived(payload: np.ndarray, sent: float) -> None:
            lat.append(time.time() - sent)

        def on_thread(sample: Any) -> None:
            payload = np.frombuffer(sample.payload.to_bytes(), np.uint8)
            loop.call_soon_threadsafe(arrived, payload, float(sample.attachment.to_bytes()))

        sub = s.declare_subscriber("bench/raw", on_thread)
        loop.run_until_complete(asyncio.sleep(args.seconds))
    sub.undeclare()
    s.close()
    Path(args.lat).write_text(json.dumps(lat))


def _spawn(role: str, module: str = "benchmarks.bench_zenoh", **kw: Any) -> subprocess.Popen[bytes]:
    """``python -m MODULE --role ROLE --key value ...`` (a True value: the bare flag)."""
    cmd = [sys.executable, "-m", module, "--role", role]
    for k, v in kw.items():
        if v is True:
            cmd.append(f"--{k}")
        elif v is not None and v is not False:
            cmd += [f"--{k}", str(v)]
    return subprocess.Popen(cmd)


def _summ(lat: list[float]) -> dict[str, float]:
    if not lat:
        return {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan")}
    a = np.array(lat[5:] or lat) * 1000
    return {
        "n": len(lat),
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
    }


def _local(payload: str, seconds: float, tmp: Path) -> dict[str, float]:
    """One process, an inline edge."""
    g = flowrt.GraphBuilder("local")
    g.add("src", PayloadSource, params={"payload": payload, "rate": 20.0})
    port = "out" if SIZES[payload] is None else "frame"
    g.add(
        "sink",
        LatencySink,
        params={"out": str(tmp / "local.json")},
        inputs={"value": {"from": f"src.{port}"}},
    )
    flowrt.run(_run(g.build(), seconds))
    return _summ(json.loads((tmp / "local.json").read_text()))


def _flowrt_zenoh(payload: str, seconds: float, tmp: Path) -> dict[str, float]:
    p = _port()
    exp = _spawn(
        "exporter", payload=payload, rate=20, port=p, seconds=seconds + 3, result=tmp / "exp.json"
    )
    time.sleep(1.0)
    imp = _spawn(
        "importer",
        payload=payload,
        rate=20,
        port=p,
        seconds=seconds,
        result=tmp / "imp.json",
        lat=tmp / "remote.json",
    )
    imp.wait()
    exp.wait()
    return _summ(json.loads((tmp / "remote.json").read_text()))


def _raw_zenoh(
    payload: str,
    seconds: float,
    tmp: Path,
    aio: bool = False,
    shm: bool = False,
    as_json: bool = False,
) -> dict[str, float]:
    """Zenoh's own publisher and subscriber (informative: ``aio``, the callback hands each
    sample to a uvloop loop; ``shm``, frames put from Zenoh's shared-memory API;
    ``as_json``, the small message as flowrt's JSON mapping)."""
    p = _port()
    pub = _spawn(
        "raw_pub", payload=payload, rate=20, port=p, seconds=seconds + 1, shm=shm, json=as_json
    )
    time.sleep(0.5)
    name = "raw_aio" if aio else "raw_shm" if shm else "raw_json" if as_json else "raw"
    out = tmp / f"{name}.json"
    sub = _spawn(
        "raw_sub",
        payload=payload,
        rate=20,
        port=p,
        seconds=seconds,
        lat=out,
        asyncio=aio,
        json=as_json,
    )
    sub.wait()
    pub.wait()
    return _summ(json.loads(out.read_text()))


VARIANTS = {
    "local": _local,
    "flowrt_zenoh": _flowrt_zenoh,
    "raw_zenoh": _raw_zenoh,
    "raw_zenoh_asyncio": lambda payload, seconds, tmp: _raw_zenoh(payload, seconds, tmp, True),
    "raw_zenoh_shm": lambda payload, seconds, tmp: _raw_zenoh(payload, seconds, tmp, shm=True),
    "raw_zenoh_json": lambda payload, seconds, tmp: _raw_zenoh(payload, seconds, tmp, as_json=True),
}
FRAMES_ONLY = {"raw_zenoh_shm"}  # an 8-byte message is put the same way with or without
MESSAGES_ONLY = {"raw_zenoh_json"}  # a frame is no JSON mapping


def latency_row(payload: str, seconds: float, tmp: Path, rounds: int = 1) -> dict[str, Any]:
    """Every variant ``rounds`` times, interleaved (the order reverses every round): each
    figure is the median over the rounds of that round's p50 and p99, and ``ratios`` the
    per-round flowrt / raw p50 (the two measured minutes apart at most)."""
    skip = FRAMES_ONLY if SIZES[payload] is None else MESSAGES_ONLY
    names = [k for k in VARIANTS if k not in skip]
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in names}
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            runs[name].append(VARIANTS[name](payload, seconds, tmp))
    row: dict[str, Any] = {"payload": payload, "rounds": rounds}
    for name, rs in runs.items():
        row[name] = {
            "n": sum(x["n"] for x in rs),
            "p50_ms": float(np.median([x["p50_ms"] for x in rs])),
            "p99_ms": float(np.median([x["p99_ms"] for x in rs])),
            "p50_rounds": [x["p50_ms"] for x in rs],
        }
    for key, ref in (("ratios", "raw_zenoh"), ("ratios_json", "raw_zenoh_json")):
        if ref in runs:  # per round: flowrt / the plain program, measured minutes apart at most
            row[key] = [
                f["p50_ms"] / r["p50_ms"]
                for f, r in zip(runs["flowrt_zenoh"], runs[ref], strict=True)
            ]
    return row


def sustained(seconds: float, tmp: Path) -> dict[str, Any]:
    p = _port()
    exp = _spawn(
        "exporter",
        payload="640x480",
        rate=30,
        port=p,
        seconds=seconds + 4,
        result=tmp / "exp.json",
        critical=True,
    )
    time.sleep(1.5)
    imp = _spawn(
        "importer",
        payload="640x480",
        rate=30,
        port=p,
        seconds=seconds,
        result=tmp / "imp.json",
        lat=tmp / "s.json",
    )
    imp.wait()
    exp.wait()
    e = json.loads((tmp / "exp.json").read_text())
    i = json.loads((tmp / "imp.json").read_text())
    link = next(x for x in i["stats"]["edges"] if x["policy"] == "remote")
    export = next(x for x in e["stats"]["edges"] if "zenoh:" in x["name"])
    crit = next(n for n in e["stats"]["nodes"] if n["name"] == "crit")
    # baseline: the same exporter graph without the export
    base = flowrt.run(_run(exporter_graph("640x480", 30, None, True), seconds))
    crit0 = next(n for n in base["stats"]["nodes"] if n["name"] == "crit")
    return {
        "seconds": seconds,
        "export_edge": {k: export[k] for k in ("published", "delivered", "dropped")},
        "remote_link": {k: link[k] for k in ("published", "delivered", "dropped", "drop_reasons")},
        "latency": _summ(json.loads((tmp / "s.json").read_text())),
        "mem_exporter": e["mem"],
        "mem_importer": i["mem"],
        "crit_std_ms_with_export": crit["interval"]["std"],
        "crit_std_ms_without": crit0["interval"]["std"],
    }


def report(res: dict[str, Any]) -> str:
    lines = [
        f"load average {res['loadavg_start']} at the start, {res['loadavg_end']} at the end",
        "",
        "| payload | local p50/p99 ms | flowrt over Zenoh p50/p99 ms | raw Zenoh p50/p99 ms "
        "| raw Zenoh -> asyncio p50/p99 ms | raw Zenoh, shared memory p50/p99 ms "
        "| raw Zenoh, the JSON message p50/p99 ms "
        "| flowrt / raw (p50, median of rounds) | flowrt / raw JSON message |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    columns = ("local", "flowrt_zenoh", "raw_zenoh", "raw_zenoh_asyncio", "raw_zenoh_shm")
    for r in res["latency"]:
        cells = [
            f"{r[k]['p50_ms']:.2f} / {r[k]['p99_ms']:.2f}" if k in r else "-"
            for k in (*columns, "raw_zenoh_json")
        ]
        ratios = [_ratio_cell(r.get(k)) for k in ("ratios", "ratios_json")]
        lines.append(f"| {r['payload']} | " + " | ".join(cells + ratios) + " |")
    s = res["sustained"]
    if s is None:  # --sustained 0
        return "\n".join(lines)
    lines.append("")
    lines.append(
        f"sustained 640x480x3 @ 30 fps, {s['seconds']:g} s: exported {s['export_edge']}, "
        f"remote link {s['remote_link']}, latency p50 {s['latency']['p50_ms']:.2f} ms "
        f"p99 {s['latency']['p99_ms']:.2f} ms; memory exporter {s['mem_exporter']}, "
        f"importer {s['mem_importer']}; critical 20 Hz node interval std "
        f"{s['crit_std_ms_with_export']:.3f} ms with the export vs "
        f"{s['crit_std_ms_without']:.3f} ms without"
    )
    return "\n".join(lines)


def _ratio_cell(ratios: list[float] | None) -> str:
    if not ratios:
        return "-"
    per = " ".join(f"{x:.2f}" for x in ratios)
    return f"{float(np.median(ratios)):.2f} (rounds: {per})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--role")
    ap.add_argument("--payload", default="8B")
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--port", type=int)
    ap.add_argument("--host", default="127.0.0.1", help="the exporter's address (a role)")
    ap.add_argument("--no-shm", action="store_true", help="no Zenoh shared memory (a role)")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--result")
    ap.add_argument("--lat", default="")
    ap.add_argument("--critical", action="store_true")
    ap.add_argument("--asyncio", action="store_true")
    ap.add_argument("--shm", action="store_true", help="frames from Zenoh's shared memory (raw)")
    ap.add_argument("--json", action="store_true", help="the JSON message, not 8 bytes (raw)")
    ap.add_argument(
        "--pm-qos", action="store_true", help="hold /dev/cpu_dma_latency at 0 (root; informative)"
    )
    ap.add_argument("--sustained", type=float, help="seconds of the 30 fps run (default 3x)")
    ap.add_argument(
        "--rounds", type=int, default=1, help="interleaved rounds of every latency variant"
    )
    ap.add_argument(
        "--payloads", default=",".join(SIZES), help=f"latency rows (of {', '.join(SIZES)})"
    )
    args = ap.parse_args()
    if args.role:
        role_main(args)
        return
    if args.pm_qos:  # held until this process exits: every variant of the run alike
        from flowrt.system._cpu_latency import CpuLatencyRequest

        qos = CpuLatencyRequest(0.0)
        if not qos.hold():
            raise SystemExit(f"--pm-qos: {qos.granted}")
        print(f"/dev/cpu_dma_latency {qos.granted}: idle CPUs poll, never halt")
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_zenoh_{os.getpid()}"
    tmp.mkdir(exist_ok=True)
    start_load = os.getloadavg()
    res = {
        "latency": [
            latency_row(p, args.duration, tmp, args.rounds) for p in args.payloads.split(",")
        ],
        "sustained": (
            sustained(args.sustained or args.duration * 3, tmp) if args.sustained != 0 else None
        ),
        "loadavg_start": start_load,
        "loadavg_end": os.getloadavg(),
    }
    print(report(res))
    if args.out:
        args.out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
