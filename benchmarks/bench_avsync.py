"""The acquisition document's A/V calibration, reproduced: flash + beep with a known offset.

For each injected lag (0, 40 and 120 ms, and a jittered 20..127 ms like the seed's measured
spread), a 30 fps synthetic:flash camera and a synthetic:beep microphone are recorded for
``--seconds`` and ``flowrt sync measure`` reports the lag; then two cameras 4 ms apart in
phase are measured against each other. Prints a markdown table for benchmarks/RESULTS.md.

    python -m benchmarks.bench_avsync --seconds 12
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

GRAPH = """\
name: avsync-bench
nodes:
  led: {{kind: capture, params: {{source: "synthetic:flash", fps: 30, size: [160, 120]}}}}
  led2:
    kind: capture
    params: {{source: "synthetic:flash", fps: 30, size: [160, 120]}}
    trigger: {{timer: 33.333ms, phase: 4ms}}
  mic:
    kind: audio
    params: {{source: "synthetic:beep", offset: {offset}ms, jitter: {jitter}ms, seed: 7}}
"""


def run(offset: float, jitter: float, seconds: float, work: Path) -> tuple[dict, dict]:
    g = work / f"g_{offset}_{jitter}.yaml"
    g.write_text(GRAPH.format(offset=offset, jitter=jitter))
    out = work / f"rec_{offset}_{jitter}"
    subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "record", str(g), "-o", str(out), "--duration",
         str(seconds), "--no-ui"], check=True, capture_output=True,
    )  # fmt: skip
    (session,) = out.glob("rec_*")

    def measure(*args: str) -> dict:
        r = subprocess.run(
            [sys.executable, "-m", "flowrt.cli", "sync", "measure", str(session), *args,
             "--json"], capture_output=True, text=True,
        )  # fmt: skip
        return json.loads(r.stdout)

    return (
        measure("--video", "led.frame", "--audio", "mic.audio"),
        measure("--video", "led.frame", "--video", "led2.frame"),
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=12.0)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}; {args.seconds:g} s per row, 30 fps\n")
    print("| injected audio lag | measured mean | min | max | std | events |")
    print("|---|---|---|---|---|---|")
    cams = None
    with tempfile.TemporaryDirectory() as tmp:
        for offset, jitter, label in (
            (0, 0, "0 ms"),
            (40, 0, "40 ms"),
            (120, 0, "120 ms"),
            (20, 107, "20 + U(0, 107) ms (the seed's 20-127 ms)"),
        ):
            av, cam = run(offset, jitter, args.seconds, Path(tmp))
            cams = cam
            print(
                f"| {label} | {av['lag_ms']:.2f} ms | {av['min_ms']:.2f} | {av['max_ms']:.2f} "
                f"| {av['std_ms']:.2f} | {av['events']} |"
            )
    assert cams is not None
    print(
        f"\ncamera against camera (phases 4 ms apart, one LED): {cams['lag_ms']:.3f} ms mean "
        f"(min {cams['min_ms']:.3f}, max {cams['max_ms']:.3f}, {cams['events']} events)"
    )


if __name__ == "__main__":
    main()
