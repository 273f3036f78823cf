"""The monolithic baseline: one process per camera running every due tracker in sequence.

This is the CAMBADA paper's original architecture (its Frontvision and Omnivision processes):

    python -m benchmarks.cambada.monolithic --graph G --camera omni_cam --start T0 \
        --duration S --out DIR

The camera delivers frame ``k`` at ``T0 + phase + k * period`` (the same synthetic frames,
seeds and phases as the flowrt graph). The loop takes the newest frame the camera has
delivered; if none is newer than the last one processed it waits for the next (sleeping to an
absolute time). Frames delivered while the loop was busy and overtaken by a newer one are
skipped (counted). For each frame it renders the image (the grab; with the graph's ``ahead``
capture, rendered in advance right after the previous frame, as flowrt's capture node then
does), then runs the trackers of
that camera whose period/phase in frames match, in flowrt's dispatch order (priority, then
file order) — each node object is the same class flowrt runs, created with the same params,
and records its own activations. It runs at normal priority, like the paper's processes.

``--every-frame`` runs every tracker on every frame, whatever its period: the paper's original
Frontvision/Omnivision, before its tasks got periods and phases (Table 2).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from flowrt.nodes.scene import SoccerScene

from flowrt import Frame, NodeContext
from flowrt.graph._registry import resolve_kind
from flowrt.node import make_node

from .graph import load
from .nodes import warm_scene


def run(
    graph: Path, camera: str, start: float, duration: float, out: Path, every_frame: bool = False
) -> None:
    cams, all_tasks = load(graph)
    cam = cams[camera]
    tasks = [t for t in all_tasks if t.camera == camera]
    p = cam.params
    w, h = p.get("size", (320, 240))
    fps = float(p.get("fps", 20))
    period = 1.0 / fps
    scene = SoccerScene(w, h, seed=p.get("seed", 0), clutter=p.get("clutter", 0.0), fps=fps)
    nodes = []
    for t in tasks:
        cls = resolve_kind(t.kind)
        node = make_node(cls, cls.Params.model_validate(t.params), NodeContext(t.name))
        node.setup()
        nodes.append((t, node))
    if cam.capture != "builtin":
        warm_scene(scene)  # as the benchmark's capture nodes do at setup
    ahead: tuple[int, np.ndarray] | None = None  # capture "ahead": the next frame, rendered

    t0 = start + cam.phase_ms / 1000
    end = start + duration
    last = -1
    skipped = 0
    processed = 0
    while True:
        now = time.monotonic()
        newest = int((now - t0) // period) if now >= t0 else -1
        if newest > last:
            k = newest  # a frame arrived while busy: take the newest, skip older ones
            skipped += k - last - 1
        else:
            k = last + 1
            release = t0 + k * period
            if release >= end:
                break
            time.sleep(max(0.0, release - time.monotonic()))
        release = t0 + k * period
        if release >= end:
            break
        img = ahead[1] if ahead is not None and ahead[0] == k else scene.render(k)[0]
        frame = Frame(img, source=camera, seq=k, timestamp=release, pixel_format="BGR")
        for t, node in nodes:
            if every_frame or k % t.period == t.phase:
                node.process(frame=frame)
        processed += 1
        last = k
        if cam.capture == "ahead":  # render the next frame before waiting for it
            ahead = (k + 1, scene.render(k + 1)[0])
    for _, node in nodes:
        node.teardown()
    (out / f"{camera}.loop.json").write_text(
        json.dumps({"camera": camera, "processed": processed, "skipped": skipped, "last": last})
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graph", type=Path, required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--start", type=float, required=True, help="time.monotonic() of frame 0")
    ap.add_argument("--duration", type=float, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--every-frame", action="store_true", help="every tracker on every frame")
    a = ap.parse_args(argv)
    run(a.graph, a.camera, a.start, a.duration, a.out, a.every_frame)


if __name__ == "__main__":
    main()
