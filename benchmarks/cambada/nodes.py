"""The benchmark's nodes: recording trackers (real, or paper-calibrated CPU burners) and cameras.

Trackers (``RecordingTracker``: the built-in one; ``CalibratedTracker``: a burner) both record,
for every activation, ``(frame seq, frame timestamp, start, end)`` on the system-wide monotonic
clock, *inside the process that runs them* (a flowrt worker, or the monolithic loop), and write
them to ``{record_dir}/{node}.json`` at teardown. The monolithic loop calls the very same
classes, so both architectures are measured by the same code.

Paper-calibrated execution times (CPU time burnt, never slept, so a preempted tracker takes
longer in wall time exactly as real work would). The draw depends only on (seed, node name,
frame seq), so the monolithic loop and flowrt burn the same time for the same frame:

========================  ===================================================================
object                    execution time (ms)
========================  ===================================================================
obstacle (Avoid_*)        uniform 1-5 (paper: obstacle tracking under 5 ms)
ball (Ball_*)             1-5 w.p. 0.761, 25-35 w.p. 0.139 (paper); the remaining 10 %
                          (not given by the paper): 5-25 w.p. 0.090, 35-38.75 w.p. 0.010
                          (paper: at most 38.75)
blue_goal, yellow_goal    uniform 4-10 (our choice: not in the paper's summary)
line                      uniform 8-16 (our choice)
blue_post, yellow_post    uniform 2-6 (our choice)
========================  ===================================================================

Cameras: ``WarmCapture`` and ``AheadCapture``, the built-in capture node with the synthetic
scene's cost moved out of the tick (same frames; see their docstrings).
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
from flowrt.nodes.capture.node import Capture
from flowrt.nodes.colour import Detection
from flowrt.nodes.scene import CHUNK, SoccerScene
from flowrt.nodes.tracker import FrameDetection, Tracker, TrackerParams
from pydantic import BaseModel, ConfigDict

from flowrt import Frame, Input, Node, Output

__all__ = [
    "PROFILES",
    "AheadCapture",
    "CalibratedTracker",
    "RecordingTracker",
    "WarmCapture",
    "burn",
    "execution_ms",
    "warm_scene",
]

WARM_CHUNKS = 4  # the scene caches 4 chunks of 256 frames: 51 s at 20 fps

# object -> [(probability, low ms, high ms)], drawn uniformly within the chosen band
PROFILES: dict[str, list[tuple[float, float, float]]] = {
    "obstacle": [(1.0, 1.0, 5.0)],
    "ball": [(0.761, 1.0, 5.0), (0.090, 5.0, 25.0), (0.139, 25.0, 35.0), (0.010, 35.0, 38.75)],
    "blue_goal": [(1.0, 4.0, 10.0)],
    "yellow_goal": [(1.0, 4.0, 10.0)],
    "line": [(1.0, 8.0, 16.0)],
    "blue_post": [(1.0, 2.0, 6.0)],
    "yellow_post": [(1.0, 2.0, 6.0)],
}


def execution_ms(node: str, obj: str, seq: int, seed: int = 0) -> float:
    """The execution time of ``node`` (tracking ``obj``) on frame ``seq``: deterministic."""
    rng = random.Random(f"{seed}:{node}:{seq}")  # str seeds hash with sha512: same everywhere
    u = rng.random()
    for p, lo, hi in PROFILES[obj]:
        if u < p:
            return lo + (hi - lo) * rng.random()
        u -= p
    _, lo, hi = PROFILES[obj][-1]
    return lo + (hi - lo) * rng.random()


def burn(ms: float) -> None:
    """Spin until this thread has used ``ms`` of CPU time."""
    end = time.thread_time() + ms / 1000
    while time.thread_time() < end:
        pass


def warm_scene(scene: SoccerScene) -> None:
    """Simulate the scene's motion for the first ``WARM_CHUNKS`` chunks now, not mid-run.

    SoccerScene simulates its dynamics lazily, 256 frames at a time, on the frame that first
    needs them: that render takes ~2 ms longer (frames 0, 256, 512... at 20 fps: every 12.8 s),
    which would show as tick jitter of every task of that camera, in both architectures.
    """
    for c in range(WARM_CHUNKS):
        scene.render(c * CHUNK)


class WarmCapture(Capture):
    """The built-in ``capture`` node, with its synthetic scene warmed at setup (same frames)."""

    def setup(self) -> None:
        super().setup()
        scene = getattr(self, "_scene", None)  # the synthetic source (None for real ones)
        if scene is not None:
            warm_scene(scene)


AHEAD_DELAY = 0.010  # s after a publication: past the tick's dispatch, before any other tick


class AheadCapture(WarmCapture):
    """WarmCapture that renders the next synthetic frame ahead, in the idle time after a tick.

    The next image is rendered straight into a frame slot; at the timer instant the node only
    stamps that frame and publishes it, so the tick (the trackers' release) follows the timer
    by a constant few tens of microseconds instead of a render (0.5-1.5 ms, varying with
    content and cache state) plus a copy — what a camera that has DMA'd its frame into memory
    gives. The frames are the same; only when they are computed changes. Plain BGR synthetic
    sources only (anything else behaves as the built-in node).
    """

    def setup(self) -> None:
        super().setup()
        p = self.params
        self._direct = (
            getattr(self, "_scene", None) is not None
            and (p.input_format or "BGR") == "BGR"
            and p.pixel_format == "BGR"
        )
        self._next = 0
        self._ahead: tuple[int, Frame, Any] | None = None
        self._pending: asyncio.TimerHandle | None = None

    async def process(self) -> Any:
        if not self._direct:
            return await super().process()
        seq = self._next
        ready, self._ahead = self._ahead, None
        if ready is not None and ready[0] == seq:
            _, frame, truth = ready
        else:
            frame, truth = self._fill(seq)
        frame.seq = seq
        frame.timestamp = self.ctx.now()
        frame.source = self.ctx.name
        self._next = seq + 1
        self._pending = asyncio.get_running_loop().call_later(AHEAD_DELAY, self._render, seq + 1)
        return {"frame": frame, "truth": truth}

    def _fill(self, seq: int) -> tuple[Frame, Any]:
        img, truth = self._scene.render(seq)
        frame = self.ctx.new_frame(img.shape, np.uint8, "BGR")
        frame.data[...] = img
        return frame, truth

    def _render(self, seq: int) -> None:
        # The frame joins this node's created frames: its link is released after the
        # activation that publishes it, as for a frame made during process().
        self._ahead = (seq, *self._fill(seq))

    async def teardown(self) -> None:
        if self._pending is not None:
            self._pending.cancel()
        await super().teardown()


class _Recorder:
    """Activation records kept in memory, written once at teardown (nothing on the hot path)."""

    def __init__(self, name: str, record_dir: str | None) -> None:
        self.name = name
        self.path = Path(record_dir) / f"{name}.json" if record_dir else None
        self.rows: list[tuple[int, float, float, float]] = []

    def add(self, frame: Frame, start: float, end: float) -> None:
        self.rows.append((frame.seq, frame.timestamp, start, end))

    def dump(self) -> None:
        if self.path is None:
            return
        data = {"node": self.name, "pid": os.getpid(), "records": self.rows}
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data))
        tmp.replace(self.path)


class RecordingParams(TrackerParams):
    record_dir: str | None = None


class RecordingTracker(Tracker):
    """The built-in ``tracker`` node, recording its activations."""

    Params = RecordingParams

    def setup(self) -> None:
        super().setup()
        self._rec = _Recorder(self.ctx.name, self.params.record_dir)

    def process(self, frame: Frame) -> FrameDetection:
        start = time.monotonic()
        det = super().process(frame)
        self._rec.add(frame, start, time.monotonic())
        return det

    def teardown(self) -> None:
        self._rec.dump()


class CalibratedParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object: str = "ball"
    seed: int = 0
    record_dir: str | None = None


class CalibratedTracker(Node):
    """Burns the paper-calibrated CPU time for each frame instead of tracking; records."""

    Params = CalibratedParams

    frame = Input(Frame)
    detection = Output(FrameDetection)

    def setup(self) -> None:
        if self.params.object not in PROFILES:
            raise ValueError(f"no execution-time profile for {self.params.object!r}")
        self._rec = _Recorder(self.ctx.name, self.params.record_dir)
        burn(0.5)  # warm the code path

    def process(self, frame: Frame) -> Any:
        start = time.monotonic()
        p = self.params
        _ = int(frame.data[0, 0, 0])  # touch the (shared-memory) pixels
        burn(execution_ms(self.ctx.name, p.object, frame.seq, p.seed))
        det = FrameDetection.of(Detection(False, None, None, 0, 0.0, 0, p.object), frame)
        self._rec.add(frame, start, time.monotonic())
        return det

    def teardown(self) -> None:
        self._rec.dump()
