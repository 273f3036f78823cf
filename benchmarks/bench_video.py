"""An offline run over a real video: frames/s of flowrt against a plain OpenCV loop.

graphs/video.yaml as it is (capture -> candle tracker -> display), with the capture switched to
``pacing: fast`` and ``on_eof: exit`` (process the file once, as fast as the graph consumes it)
and the display on a free port. The reference (``plain``) is the loop a user would write
without flowrt: ``cv2.VideoCapture.read()`` and the same tracker object (the ``candle``
:class:`ObjectTracker` the node builds) called on every frame, in this process. The three
(``plain``, the tracker ``inline`` and in a ``process``) alternate in the same run, ``--reps``
times each (the order reverses every round; one uncounted warm-up run of each before), so that
the ratios are measured under the same load. Time is from opening the file (flowrt: the
runtime's start, workers up) to the end of stream; every frame of the file must be tracked.

Run from the repository root:
python benchmarks/bench_video.py [--reps 3] [--video PATH] [--repeat N] [--realtime] [--unpipelined]

``--repeat N``: the clip N times over in one file (written once into a temporary folder, same
codec), for the steady-state rate: the sample's 270 frames take 0.15 s, where the few
milliseconds of opening the file and of the first frame weigh several per cent and the
plain loop's own runs spread 1540-2020 frames/s.

Without ``--video``: ../shared/data/sample_720x528.avi when present, else a 720x528 clip of
graphs/make_sample_video.py's scene rendered into a temporary folder.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import yaml

import flowrt
from flowrt.graph.spec import GraphSpec
from flowrt.system._priorities import lowest_nice

REPO = Path(__file__).resolve().parents[1]
CANDIDATES = (
    REPO.parent / "shared/data/sample_720x528.avi",
    Path("/work/shared/data/sample_720x528.avi"),
)


UNPIPELINED = "process-1"  # --unpipelined: the tracker in a worker with pipeline: 1
DISPLAY = False  # --display: keep graphs/video.yaml's display node (its server process)
PLAIN = "plain"  # the reference: an OpenCV loop calling the same tracker, no flowrt


def render_clip(folder: Path, size: tuple[int, int] = (720, 528)) -> Path:
    """graphs/make_sample_video.py's scene at ``size`` (the benchmark needs no shared data)."""
    sys.path.insert(0, str(REPO / "graphs"))
    from make_sample_video import FPS, SECONDS, frame  # type: ignore[import-not-found]

    path = folder / f"sample_{size[0]}x{size[1]}.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, size)
    for k in range(FPS * SECONDS):
        out.write(cv2.resize(frame(k), size, interpolation=cv2.INTER_LINEAR))
    out.release()
    return path


def plain_run(video: Path, realtime: bool = False) -> dict[str, Any]:
    """What the graph does, written as one loop: decode a frame, track it, next.

    At the nice level flowrt's loop takes (the lowest permitted), or with ``realtime`` at its
    SCHED_FIFO priority, so that the ratio measures flowrt's work and not its priority on a
    loaded machine."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, lowest_nice())
        if realtime:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(90))  # flowrt's loop's
    try:
        return _plain_loop(video)
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, param)
            os.setpriority(os.PRIO_PROCESS, 0, before)


def _plain_loop(video: Path) -> dict[str, Any]:
    from flowrt.nodes.colour import ObjectTracker
    from flowrt.nodes.tracker import TrackerParams

    data = yaml.safe_load((REPO / "graphs/video.yaml").read_text())
    p = TrackerParams.model_validate(data["nodes"]["lamp"]["params"])
    tracker = ObjectTracker(p.object_spec(), p.table(), name=p.object)
    t0 = time.perf_counter()
    cap = cv2.VideoCapture(str(video))
    n = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        tracker.track(img)
        n += 1
    cap.release()
    elapsed = time.perf_counter() - t0
    return {
        "placement": PLAIN,
        "published": n,
        "tracked": n,
        "skipped": 0,
        "seconds": elapsed,
        "exec_p50": float("nan"),
        "cam_p50": float("nan"),
    }


def repeated(video: Path, times: int, folder: Path) -> Path:
    """``video`` ``times`` over, in one file of the same codec (``--repeat``), read again for
    each time rather than held in memory (the sample's frames are 300 MB decoded)."""
    cap = cv2.VideoCapture(str(video))
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)) or cv2.VideoWriter.fourcc(*"MJPG")
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    cap.release()
    path = folder / f"{video.stem}_x{times}{video.suffix}"
    out = cv2.VideoWriter(str(path), fourcc, fps, size)
    for _ in range(times):
        cap = cv2.VideoCapture(str(video))
        while True:
            ok, img = cap.read()
            if not ok:
                break
            out.write(img)
        cap.release()
    out.release()
    return path


def frames_in(path: Path) -> int:
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.grab():
        n += 1
    cap.release()
    return n


def spec_for(video: Path, placement: str) -> GraphSpec:
    data: dict[str, Any] = yaml.safe_load((REPO / "graphs/video.yaml").read_text())
    cam = data["nodes"]["cam"]["params"]
    cam.update(source=f"file:{video}", pacing="fast", on_eof="exit")
    data["nodes"]["lamp"]["placement"] = "process" if placement.startswith("process") else placement
    if placement == "inline":  # no worker to pin
        data["nodes"]["lamp"].pop("cpus", None)
    if placement == UNPIPELINED:  # one call at a time: the worker as before it was pipelined
        data["nodes"]["lamp"]["pipeline"] = 1
    if DISPLAY:
        data["nodes"]["view"]["params"]["port"] = 0  # a free port: nothing else is disturbed
    else:  # what the plain loop does: decode and track, nothing shown
        del data["nodes"]["view"]
    return GraphSpec.model_validate(data)


def one(video: Path, placement: str, realtime: bool) -> dict[str, Any]:
    if placement == PLAIN:
        return plain_run(video, realtime)
    return flowrt.run(one_run(video, placement, realtime))


async def one_run(video: Path, placement: str, realtime: bool = False) -> dict[str, Any]:
    rt = flowrt.Runtime(spec_for(video, placement), realtime=realtime)
    async with rt:
        t0 = time.perf_counter()
        await rt.run(300.0)  # ends at the end of the file (on_eof: exit)
        elapsed = time.perf_counter() - t0
    stats = rt.stats()
    lamp = stats.node("lamp")
    edge = stats.edge("lamp.frame")
    return {
        "placement": placement,
        "published": edge.published,
        "tracked": lamp.completions,
        "skipped": lamp.skipped,
        "seconds": elapsed,
        "exec_p50": lamp.execution.p50,  # ms; in a worker: the call's round trip included
        "cam_p50": stats.node("cam").execution.p50,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--video", type=Path, default=None)
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="play the clip this many times over in one file (the steady-state rate)",
    )
    ap.add_argument(
        "--realtime",
        action="store_true",
        help="as flowrt run --realtime: SCHED_FIFO loop and workers (wake-ups not delayed by "
        "other processes' load)",
    )
    ap.add_argument(
        "--unpipelined",
        action="store_true",
        help="also run the worker with pipeline: 1 (one call at a time, the source one frame "
        "ahead: the behaviour before paced readers were pipelined), alternating with the others",
    )
    ap.add_argument(
        "--display",
        action="store_true",
        help="keep graphs/video.yaml's display node (a server process, an activation per "
        "frame) in the graph; by default the graph does what the plain loop does",
    )
    args = ap.parse_args()
    global DISPLAY
    DISPLAY = args.display
    with tempfile.TemporaryDirectory(prefix="flowrt-bench-video-") as tmp:
        video = args.video or next((p for p in CANDIDATES if p.exists()), None)
        if video is None:
            video = render_clip(Path(tmp))
        if args.repeat > 1:
            video = repeated(video, args.repeat, Path(tmp))
        bench(video, args)


def bench(video: Path, args: argparse.Namespace) -> None:
    total = frames_in(video)
    runs: dict[str, list[dict[str, Any]]] = {PLAIN: [], "inline": [], "process": []}
    if args.unpipelined:
        runs[UNPIPELINED] = []
    for placement in runs:  # warm-up, not counted: the forkserver, OpenCV's first decode
        one(video, placement, args.realtime)
    for rep in range(args.reps):
        for placement in sorted(runs, reverse=rep % 2 == 1):  # alternate which goes first
            r = one(video, placement, args.realtime)
            runs[placement].append(r)
            print(
                f"{placement:9s} tracked {r['tracked']}/{total} (published {r['published']}, "
                f"skipped {r['skipped']}) in {r['seconds']:.2f} s = "
                f"{r['tracked'] / r['seconds']:.1f} frames/s; tracker call p50 "
                f"{r['exec_p50']:.2f} ms, capture activation p50 {r['cam_p50']:.2f} ms",
                flush=True,
            )
    print()
    mode = "--realtime (SCHED_FIFO)" if args.realtime else "fair scheduler (nice levels)"
    print(f"video: {video.name}, {total} frames; {args.reps} runs per placement; {mode}")
    print("load average: " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print(
        "| placement | frames tracked / in file | frames/s (median) | min-max "
        "| tracker call p50 ms | capture activation p50 ms |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    fps: dict[str, float] = {}
    for placement, rs in runs.items():
        rates = [r["tracked"] / r["seconds"] for r in rs]
        fps[placement] = statistics.median(rates)
        tracked = min(r["tracked"] for r in rs)
        call = statistics.median(r["exec_p50"] for r in rs)
        cam = statistics.median(r["cam_p50"] for r in rs)
        print(
            f"| {placement} | {tracked}/{total} | {fps[placement]:.1f} | "
            f"{min(rates):.1f}-{max(rates):.1f} | {call:.2f} | {cam:.2f} |"
        )
    print(f"\ninline / plain throughput: {fps['inline'] / fps[PLAIN]:.2f}x")
    print(f"process / plain throughput: {fps['process'] / fps[PLAIN]:.2f}x")
    print(f"process / inline throughput: {fps['process'] / fps['inline']:.2f}")
    if args.unpipelined:
        print(f"process pipeline: 1 / inline: {fps[UNPIPELINED] / fps['inline']:.2f}")


if __name__ == "__main__":
    main()
