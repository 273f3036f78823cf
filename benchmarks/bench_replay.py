"""Deterministic replay: its speed against the recorded time, and what it adds to a recording.

    python benchmarks/bench_replay.py --seconds 6 --rounds 3

What runs (each a ``flowrt`` command, as a user types it):

1. ``flowrt record graphs/cambada.yaml --duration S --no-ui --no-display`` (plain) and the same
   with ``--deterministic``; sizes of both sessions, and in the deterministic one the bytes of
   the ``/flowrt/det/*`` channels (the log) against the rest (``flowrt info --json``): the
   overhead is measured within one file, the two sessions' sizes differ by their frame counts.
2. ``flowrt replay SESSION --graph graphs/cambada.yaml --deterministic --check --json``, with
   the trackers in worker processes as placed and with ``--inline``, ``rounds`` times each:
   ``wall_s`` (the replay: reading the log, starting the nodes, re-executing, comparing) against
   ``recorded_s``, the process's own wall time (Python start and imports on top), identical?

The machine is shared (2 cores): the load average is printed with each figure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
GRAPH = REPO / "graphs/cambada.yaml"


def flowrt(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "COLUMNS": "200"},
    )


def record(out: Path, seconds: float, deterministic: bool) -> Path:
    extra = ["--deterministic"] if deterministic else []
    r = flowrt("record", str(GRAPH), "-o", str(out), "--duration", str(seconds), "--no-ui",
               "--no-display", *extra)  # fmt: skip
    if r.returncode != 0:
        raise SystemExit(f"record failed: {r.stderr.strip()}")
    return out / "rec_001"


def sizes(session: Path) -> tuple[int, int]:
    """(file bytes, bytes of the /flowrt/det/* channels' messages)."""
    info = json.loads(flowrt("info", str(session), "--json").stdout)
    log = sum(s["bytes"] for s in info["streams"] if s["topic"].startswith("/flowrt/det/"))
    return int(info["size"]), int(log)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as tmp:
        root = Path(tmp)
        plain = record(root / "plain", args.seconds, False)
        det = record(root / "det", args.seconds, True)
        plain_size, _ = sizes(plain)
        det_size, log_bytes = sizes(det)
        print(f"load average {os.getloadavg()[0]:.2f}; {args.seconds:g} s of cambada")
        print(
            f"plain session {plain_size / 2**20:.1f} MiB, deterministic {det_size / 2**20:.1f} "
            f"MiB, of which the log {log_bytes / 2**10:.0f} KiB "
            f"({100 * log_bytes / (det_size - log_bytes):.2f} % of the rest)"
        )
        print("| placement | round | wall_s | recorded_s | x recorded | process s | identical "
              "| activations | compared | load |")  # fmt: skip
        print("|---|---:|---:|---:|---:|---:|:---:|---:|---:|---:|")
        for label, extra in (("as placed (workers)", []), ("--inline", ["--inline"])):
            for k in range(args.rounds):
                t0 = time.perf_counter()
                r = flowrt("replay", str(det), "--graph", str(GRAPH), "--deterministic",
                           "--check", "--json", *extra)  # fmt: skip
                proc = time.perf_counter() - t0
                if r.returncode not in (0, 1):
                    raise SystemExit(f"replay failed: {r.stderr.strip()}")
                res = json.loads(r.stdout)
                print(
                    f"| {label} | {k + 1} | {res['wall_s']:.2f} | {res['recorded_s']:.2f} | "
                    f"{res['wall_s'] / res['recorded_s']:.2f} | {proc:.2f} | "
                    f"{'yes' if res['identical'] else 'NO'} | {res['activations']} | "
                    f"{res['compared']} | {os.getloadavg()[0]:.2f} |"
                )


if __name__ == "__main__":
    main()
