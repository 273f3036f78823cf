"""Per-frame cost of the CAMBADA-style tracker vs classifying the whole frame.

Three cases per resolution, on the synthetic soccer scene (clutter 0.3):
  tracked   - the ball is where the last frame put it (the normal case): small windows only;
  lost      - the ball is out of view, so every frame ends in a full search;
  full-frame baseline - classify every pixel with the lookup table and label the ball colour's
              connected components, which is what a tracker without search windows pays.
Frames are rendered before timing. Run: python benchmarks/bench_tracker.py [--frames N]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from flowrt.nodes.colour import default_table, tracker_for
from flowrt.nodes.scene import SoccerScene


def _stats(times: list[float]) -> tuple[float, float]:
    ms = np.array(times) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def bench(
    width: int, height: int, frames: int, seed: int
) -> list[tuple[str, int, float, float, float]]:
    scene = SoccerScene(width, height, seed=seed, clutter=0.3)
    rendered = [scene.render(i) for i in range(frames)]
    rows = []

    # Tracked: sequential tracking; time only frames where the ball was found in the
    # previous frame and is visible now (the object is where it was).
    tracker = tracker_for("ball")
    times, costs, prev_found = [], [], False
    for frame, truth in rendered:
        t0 = time.perf_counter()
        d = tracker.track(frame)
        dt = time.perf_counter() - t0
        if prev_found and truth["ball"].visible:
            times.append(dt)
            costs.append(d.cost)
        prev_found = d.found
    rows.append(
        ("tracked (object where it was)", len(times), *_stats(times), float(np.median(costs)))
    )

    # Lost: frames with the ball out of view; the tracker keeps searching everywhere.
    lost_frames = [f for f, t in rendered if t["ball"].pixels == 0]
    tracker = tracker_for("ball")
    times, costs = [], []
    for frame in lost_frames:
        t0 = time.perf_counter()
        d = tracker.track(frame)
        times.append(time.perf_counter() - t0)
        costs.append(d.cost)
    rows.append(("lost (full search)", len(times), *_stats(times), float(np.median(costs))))

    # Baseline: classify the full frame, then components of the ball colour.
    table = default_table("hsv")
    orange = table.label("orange")
    times = []
    for frame, _ in rendered:
        t0 = time.perf_counter()
        mask = (table.classify(frame) == orange).view(np.uint8)
        cv2.connectedComponentsWithStats(mask, connectivity=8)
        times.append(time.perf_counter() - t0)
    rows.append(
        ("full-frame classification baseline", len(times), *_stats(times), float(width * height))
    )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    cv2.setNumThreads(1)  # one core per tracker, as in a worker process
    print("| size | case | frames | median ms | p99 ms | median cost (px) |")
    print("|---|---|---:|---:|---:|---:|")
    for w, h in ((320, 240), (640, 480)):
        for case, n, med, p99, cost in bench(w, h, args.frames, args.seed):
            print(f"| {w}x{h} | {case} | {n} | {med:.3f} | {p99:.3f} | {cost:.0f} |")


if __name__ == "__main__":
    main()
