"""Two machines over a real link (issue 40): the e-stop across a cut, reconnection, losses,
and frame latency, with graphs/zenoh_robot.yaml and graphs/zenoh_base.yaml in two network
namespaces joined by a veth pair (tests/netns_bed.py; root).

    python benchmarks/bench_two_machines.py estop [--cuts 20] [--down 1.5]
    python benchmarks/bench_two_machines.py faults
    python benchmarks/bench_two_machines.py latency [--seconds 10]
    ... [--out FILE.json]

- ``estop``: the operator releases, the link is cut (robot's end down) for ``--down``
  seconds, restored, released again, ``--cuts`` times. Per cut: the e-stop's engagement (the
  first zero ``drive.command`` the robot recorded after the cut, minus the cut), whether the
  command stayed zero until the release after the link came back, and the reconnection (the
  base's import hears the robot again, minus the restore).
- ``faults``: the link down 2 s and 10 s, flapped (down/up every 0.5 s for 5 s), the base
  killed (SIGKILL) and restarted, the robot restarted (its Zenoh session is new). Per fault:
  reconnection, the e-stop held, and the detections lost across it: those the robot recorded
  that the base never received, against what was counted as lost: by the base (``sequence
  gap``, ``hand-over overrun`` on its ``zenoh:robot1/front/obstacle`` link) and, for the
  whole run, by the robot
  (drops at its export edge while the sender waited on the dead link). The sums should agree.
- ``latency``: benchmarks/bench_zenoh.py's exporter and importer roles (flowrt over Zenoh)
  and its plain Zenoh publisher/subscriber, each side in its namespace, over the veth link;
  640x480 and 1920x1080 frames at 20 Hz, one-way from the sender's stamp (one host, one clock).
  Zenoh finds the two processes on one host and passes frames through shared memory even
  across namespaces; ``--no-shm`` turns that off, so the bytes cross the link as between two
  machines.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from netns_bed import BASE_IP, ROBOT_EP, ROBOT_IP, Bed, unavailable  # noqa: E402

PAGE = "http://127.0.0.1:8751"
OBSTACLE_LINK = "zenoh:robot1/front/obstacle->remote_obstacle"
EXPORT_EDGE = "avoid_fr.detection->zenoh:robot1/front/obstacle"
FRAME_LINK = "zenoh:robot1/front/frame->remote_cam"
FRAME_EXPORT = "front_cam.frame->zenoh:robot1/front/frame"


def _read(folder: Path, topic: str) -> list[tuple[float, Any]]:
    """Every session's messages of ``topic``; a killed process's unfinished file up to its
    last complete chunk (a stream reader: no summary needed)."""
    from mcap.stream_reader import StreamReader

    out: list[tuple[float, Any]] = []
    for path in sorted(folder.glob("*/*.mcap")):
        channels: dict[int, str] = {}
        with path.open("rb") as f, contextlib.suppress(Exception):
            for record in StreamReader(f, skip_magic=False).records:
                if type(record).__name__ == "Channel":
                    channels[record.id] = record.topic
                elif (
                    type(record).__name__ == "Message" and channels.get(record.channel_id) == topic
                ):
                    out.append((record.log_time / 1e9, json.loads(record.data)))
    return sorted(out, key=lambda x: x[0])


def _zero(cmd: dict[str, Any]) -> bool:
    return cmd.get("v") == 0.0 and cmd.get("w") == 0.0


class Pair:
    """The robot and the base running in the bed, recording what the analysis needs."""

    def __init__(self, bed: Bed, tmp: Path) -> None:
        self.bed, self.tmp = bed, tmp
        self.robot: subprocess.Popen[bytes] | None = None
        self.base: subprocess.Popen[bytes] | None = None
        self.n_robot = self.n_base = 0

    def start_robot(self) -> None:
        self.n_robot += 1
        self.robot = self.bed.flowrt(
            self.bed.robot,
            [
                "record", str(REPO / "graphs/zenoh_robot.yaml"), "-o", str(self.tmp / "robot"),
                "--topics", "drive.command,avoid_fr.detection", "--no-ui",
                "--zenoh-listen", ROBOT_EP,
                "--stats-json", str(self.tmp / f"robot{self.n_robot}.json"),
            ],
            self.tmp / f"robot{self.n_robot}.log",
        )  # fmt: skip

    def start_base(self) -> None:
        self.n_base += 1
        self.base = self.bed.flowrt(
            self.bed.base,
            [
                "record", str(REPO / "graphs/zenoh_base.yaml"), "-o", str(self.tmp / "base"),
                "--topics", "remote_obstacle.output", "--no-ui", "--zenoh-connect", ROBOT_EP,
            ],
            self.tmp / f"base{self.n_base}.log",
        )  # fmt: skip

    def link_up(self, timeout: float = 60.0) -> float:
        """When the base's import hears the robot (time.time())."""
        out = self.bed.page("wait-link", PAGE, "remote_drive", str(timeout), timeout=timeout + 30)
        return float(out)

    def release(self) -> float:
        return float(self.bed.page("estop", "release", PAGE).split()[1])

    def stop(self) -> dict[str, int]:
        codes = {}
        if self.base is not None:
            codes["base"] = self.bed.stop(self.base)
        if self.robot is not None:
            codes["robot"] = self.bed.stop(self.robot)
        return codes


def _held(drive: list[tuple[float, Any]], cut: float, until: float) -> dict[str, Any]:
    """The e-stop over one cut: engagement (ms) and whether it held until ``until``."""
    first_zero = next((t for t, c in drive if t >= cut and _zero(c)), None)
    moving = [t for t, c in drive if cut + 0.5 <= t < until and not _zero(c)]
    return {
        "engaged_ms": None if first_zero is None else round((first_zero - cut) * 1000, 1),
        "held": not moving,
    }


def _export_drops(tmp: Path, name: str = EXPORT_EDGE) -> dict[str, int]:
    """An export edge of the robots, over their runs: published into it, sent (delivered),
    dropped and unread (a ``latest`` edge keeps the newest frame while the sender waits)."""
    out = {"published": 0, "delivered": 0, "dropped": 0, "unread": 0}
    for path in tmp.glob("robot*.json"):
        for edge in json.loads(path.read_text()).get("edges", []):
            if edge.get("name") == name:
                for k in out:
                    out[k] += int(edge.get(k, 0) or 0)
    return out


def _frame_link(pair: Pair) -> dict[str, int]:
    """The base's frame link counters now: published (by sequence number), delivered, and
    drops by reason."""
    edge = json.loads(pair.bed.page("edge", PAGE, FRAME_LINK))
    out = {"published": int(edge.get("published", 0)), "delivered": int(edge.get("delivered", 0))}
    out.update({str(k): int(v) for k, v in (edge.get("drop_reasons") or {}).items()})
    return out


def _gaps(pair: Pair) -> dict[str, int]:
    """What the running base has counted as lost on the link, by reason (a sequence gap:
    lost on the way; a hand-over overrun: a backlog arriving faster than the loop took it)."""
    edge = json.loads(pair.bed.page("edge", PAGE, OBSTACLE_LINK))
    return {str(k): int(v) for k, v in (edge.get("drop_reasons") or {}).items()}


def _missing(tmp: Path, windows: list[tuple[float, float]]) -> dict[str, int]:
    """Detections the robot recorded in each window that no base received (by seq)."""
    robot = _read(tmp / "robot", "avoid_fr.detection")
    got = {d["seq"] for _, d in _read(tmp / "base", "remote_obstacle.output")}
    first = min(got) if got else 0
    missing = {}
    for i, (a, b) in enumerate(windows):
        seqs = {d["seq"] for t, d in robot if a <= t <= b and d["seq"] >= first}
        missing[str(i)] = len(seqs - got)
    return missing


def estop(args: argparse.Namespace, bed: Bed, tmp: Path) -> dict[str, Any]:
    pair = Pair(bed, tmp)
    pair.start_robot()
    pair.start_base()
    rows = []
    try:
        pair.link_up(120)
        pair.release()
        for _ in range(args.cuts):
            time.sleep(1.5)
            cut = bed.cut()
            time.sleep(args.down)
            restored = bed.restore()
            back = pair.link_up(30)
            time.sleep(0.3)
            released = pair.release()
            rows.append({"cut": cut, "restored": restored, "back": back, "released": released})
        time.sleep(1.0)
    finally:
        codes = pair.stop()
    drive = _read(tmp / "robot", "drive.command")
    for r in rows:
        r.update(_held(drive, r["cut"], r["released"]))
        r["reconnect_s"] = round(r["back"] - r["restored"], 2)
    engaged = [r["engaged_ms"] for r in rows if r["engaged_ms"] is not None]
    return {
        "cuts": len(rows),
        "down_s": args.down,
        "engaged_ms_p50": statistics.median(engaged) if engaged else None,
        "engaged_ms_max": max(engaged) if engaged else None,
        "held_every_time": all(r["held"] for r in rows),
        "reconnect_s_p50": statistics.median(r["reconnect_s"] for r in rows) if rows else None,
        "reconnect_s_max": max((r["reconnect_s"] for r in rows), default=None),
        "exit_codes": codes,
        "rows": rows,
    }


def faults(args: argparse.Namespace, bed: Bed, tmp: Path) -> dict[str, Any]:
    pair = Pair(bed, tmp)
    pair.start_robot()
    pair.start_base()
    rows: list[dict[str, Any]] = []
    try:
        pair.link_up(120)
        pair.release()
        for name, down in (("down 2 s", 2.0), ("down 10 s", 10.0), ("flap 0.5 s x 5 s", None)):
            time.sleep(2.0)
            if down is None:
                cut = time.time()
                bed.flap(0.5, 5.0)
                restored = time.time()
            else:
                cut = bed.cut()
                time.sleep(down)
                restored = bed.restore()
            back = pair.link_up(60)
            time.sleep(0.3)
            released = pair.release()
            time.sleep(1.0)  # what arrives late is not lost: counted a second later
            rows.append({"fault": name, "cut": cut, "restored": restored, "back": back,
                         "released": released, "counted": _gaps(pair),
                         "frames": _frame_link(pair)})  # fmt: skip
        time.sleep(2.0)
        assert pair.base is not None
        cut = time.time()
        pair.base.send_signal(signal.SIGKILL)  # the base station dies
        pair.base.wait(10)
        time.sleep(2.0)
        restored = time.time()
        pair.start_base()
        back = pair.link_up(120)
        released = pair.release()
        rows.append({"fault": "base killed, restarted", "cut": cut, "restored": restored,
                     "back": back, "released": released})  # fmt: skip
        time.sleep(2.0)
        assert pair.robot is not None
        cut = time.time()
        code = bed.stop(pair.robot)  # the robot restarts: a new Zenoh session
        restored = time.time()
        pair.start_robot()
        back = pair.link_up(120)
        released = pair.release()
        rows.append({"fault": f"robot restarted (exit {code})", "cut": cut,
                     "restored": restored, "back": back, "released": released})  # fmt: skip
        time.sleep(2.0)
    finally:
        codes = pair.stop()
    drive = _read(tmp / "robot", "drive.command")
    link_faults = rows[:3]
    missing = _missing(tmp, [(r["cut"] - 0.5, r["back"] + 0.5) for r in link_faults])
    counted: dict[str, int] = {}
    frames: dict[str, int] = {}
    for i, r in enumerate(rows):
        r["reconnect_s"] = round(r["back"] - r["restored"], 2)
        r.update(_held(drive, r["cut"], r["released"]))  # a restart: zero until released too
        if i < 3:
            r["detections_lost"] = missing[str(i)]  # recorded by the robot, never received
            now = r.pop("counted")  # by the base, since the previous fault
            r["counted_lost"] = {
                k: v - counted.get(k, 0) for k, v in now.items() if v > counted.get(k, 0)
            }
            counted = now
            f = r.pop("frames")  # the base's frame link over this fault
            r["frames"] = {k: v - frames.get(k, 0) for k, v in f.items()}
            frames = f
    return {
        "rows": rows,
        "detections_lost_link_faults": sum(missing.values()),
        "detections_counted_lost_by_base": counted,  # by reason
        "detections_robot_export": _export_drops(tmp),  # the whole run
        "frames_robot_export": _export_drops(tmp, FRAME_EXPORT),  # the whole run
        "exit_codes": codes,
    }


def latency(args: argparse.Namespace, bed: Bed, tmp: Path) -> dict[str, Any]:
    """bench_zenoh's roles across the namespaces: flowrt's hop against plain Zenoh."""
    cmd = [sys.executable, "-m", "benchmarks.bench_zenoh", "--host", ROBOT_IP, "--rate", "20"]
    if args.no_shm:  # the bytes through the link, as between two machines
        cmd.append("--no-shm")
    rows = {}
    for payload in ("640x480", "1920x1080"):
        row: dict[str, Any] = {}
        for kind, (tx, rx) in {"flowrt_zenoh": ("exporter", "importer"),
                               "raw_zenoh": ("raw_pub", "raw_sub")}.items():  # fmt: skip
            lat = tmp / f"{payload}-{kind}.json"
            common = [*cmd, "--payload", payload, "--port", "7460"]
            tx_args = ["--role", tx, "--seconds", str(args.seconds + 4)]
            pub = bed.start(
                bed.robot, [*common, *tx_args, "--result", str(tmp / "tx.json")], cwd=REPO
            )
            time.sleep(2.0)
            rx_args = ["--role", rx, "--seconds", str(args.seconds), "--lat", str(lat)]
            sub = bed.start(
                bed.base, [*common, *rx_args, "--result", str(tmp / "rx.json")], cwd=REPO
            )
            sub.wait(args.seconds + 120)
            pub.wait(args.seconds + 120)
            values = sorted(json.loads(lat.read_text())[5:]) if lat.exists() else []
            row[kind] = {
                "n": len(values),
                "p50_ms": round(values[len(values) // 2] * 1000, 2) if values else None,
                "p99_ms": round(values[int(len(values) * 0.99)] * 1000, 2) if values else None,
            }
        rows[payload] = row
    link = f"veth {ROBOT_IP} <-> {BASE_IP}" + (", no shared memory" if args.no_shm else "")
    return {"link": link, "rate_hz": 20, "rows": rows}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=["estop", "faults", "latency"])
    ap.add_argument("--cuts", type=int, default=20)
    ap.add_argument("--down", type=float, default=1.5, help="estop: seconds each cut lasts")
    ap.add_argument("--seconds", type=float, default=10.0, help="latency: seconds per row")
    ap.add_argument(
        "--no-shm", action="store_true", help="latency: no Zenoh shared memory across the link"
    )
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    why = unavailable()
    if why is not None:
        print(f"bench_two_machines: {why}", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="flowrt-2m-") as d, Bed() as bed:
        tmp = Path(d)
        load0 = Path("/proc/loadavg").read_text().split()[:3]
        result = {"estop": estop, "faults": faults, "latency": latency}[args.what](args, bed, tmp)
        result["loadavg"] = {"start": load0, "end": Path("/proc/loadavg").read_text().split()[:3]}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        with contextlib.suppress(OSError):
            args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
