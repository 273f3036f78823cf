"""Deterministic synthetic robot-soccer scene with exact ground truth.

The vision nodes need footage whose truth is known to the pixel, that is the same on every run
and that can be rendered at any frame index (a capture node may start anywhere, a test may jump
to frame 10 000). The scene is laid out on a reference canvas of 320x240 pixels and scaled to
the requested size, so the same seed shows the same game at every resolution.

Rendering is cheap because everything static (carpet, lines, goals, posts, clutter blobs) is
drawn once into a background slightly wider than the view; a frame is a crop of it (the camera
pans slowly), a handful of small disc patches (ball, obstacle robots) and two saturating adds
of a pre-computed noise bank.

Dynamics are simulated in chunks of frames. Each chunk draws its random numbers from a
generator seeded with (seed, chunk), and only the state at the start of each chunk is kept, so
random access costs at most one chunk of simulation once the chunks before it are known.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Generator
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["MIN_VISIBLE_PIXELS", "ObjectTruth", "SceneTruth", "SoccerScene"]

#: An object counts as visible when at least this many of its pixels are in view and unoccluded.
MIN_VISIBLE_PIXELS = 30

# Reference canvas: all geometry below is in these units and scaled to the output size.
REF_W, REF_H = 320.0, 240.0
PAN = 16.0  # how far the camera pans sideways (the background is REF_W + PAN wide)
GOAL_DEPTH, GOAL_HALF_H = 20.0, 35.0
GOAL_LINE = 22.0  # distance of each goal line from its end of the background
POST_R = 5.0
BALL_R = 6.0
OBSTACLE_R = 16.0
N_OBSTACLES = 3
CHUNK = 256  # frames simulated per chunk
AHEAD_STEPS = 2  # frames of the next chunk simulated per frame rendered

# BGR colours, chosen to sit well inside the default colour classes of colour.py.
CARPET = (50, 150, 40)
LINE = (235, 235, 235)
BALL = (0, 110, 255)
BLUE = (200, 90, 20)
YELLOW = (0, 220, 240)
OBSTACLE = (22, 22, 24)
# Distractors are deliberately no class colour: magenta, purple and mid grey.
DISTRACTORS = ((200, 60, 200), (140, 40, 110), (120, 120, 120))


@dataclass(frozen=True)
class ObjectTruth:
    """Where an object is in one frame, counting only its visible (in view, unoccluded) pixels.

    `centroid` and `bbox` are given whenever at least one pixel is visible, so a tracker that
    sees a sliver can still be scored; `visible` is the stricter "worth detecting" flag.
    """

    visible: bool
    centroid: tuple[float, float] | None
    bbox: tuple[int, int, int, int] | None  # x, y, w, h
    pixels: int = 0


NOT_VISIBLE = ObjectTruth(False, None, None, 0)


@dataclass(frozen=True)
class SceneTruth:
    """Ground truth of one frame: per object name, its visible extent.

    Names: "ball", "blue_goal", "yellow_goal", "blue_post", "yellow_post", "lines",
    "obstacle_0".. and "obstacle" (the obstacle robot with the most visible pixels).
    """

    index: int
    time: float  # scene time: seconds into the synthetic scene (index / fps), not a clock
    objects: dict[str, ObjectTruth]
    #: the frame's time (runtime clock; in a recording, Unix time as every timestamp there)
    timestamp: float = 0.0

    def __getitem__(self, name: str) -> ObjectTruth:
        return self.objects[name]


def _truth_from_mask(mask: np.ndarray, x0: int, y0: int) -> ObjectTruth:
    """Truth of a boolean patch whose top-left pixel is (x0, y0) in the image."""
    ys, xs = np.nonzero(mask)
    n = int(xs.size)
    if n == 0:
        return NOT_VISIBLE
    bbox = (
        int(xs.min()) + x0,
        int(ys.min()) + y0,
        int(xs.max() - xs.min()) + 1,
        int(ys.max() - ys.min()) + 1,
    )
    centroid = (float(xs.mean()) + x0, float(ys.mean()) + y0)
    return ObjectTruth(n >= MIN_VISIBLE_PIXELS, centroid, bbox, n)


@dataclass
class _Layer:
    """A disc drawn on top of the background: its clipped mask in image coordinates."""

    name: str
    colour: tuple[int, int, int]
    x0: int
    y0: int
    mask: np.ndarray  # bool, what this layer paints

    def overlap(self, other: _Layer) -> tuple[slice, slice, slice, slice] | None:
        """Slices (self rows, self cols, other rows, other cols) of the overlap, if any."""
        h, w = self.mask.shape
        oh, ow = other.mask.shape
        xa, xb = max(self.x0, other.x0), min(self.x0 + w, other.x0 + ow)
        ya, yb = max(self.y0, other.y0), min(self.y0 + h, other.y0 + oh)
        if xa >= xb or ya >= yb:
            return None
        return (
            slice(ya - self.y0, yb - self.y0),
            slice(xa - self.x0, xb - self.x0),
            slice(ya - other.y0, yb - other.y0),
            slice(xa - other.x0, xb - other.x0),
        )


def _disc(cx: float, cy: float, r: float, width: int, height: int) -> tuple[int, int, np.ndarray]:
    """Mask of the pixels whose centres lie within r of (cx, cy), clipped to the image.

    Computed rather than drawn with cv2.circle so that the centroid of the full disc is the
    sub-pixel centre: the truth then moves smoothly, like the real ball does.
    """
    x0, x1 = max(0, math.floor(cx - r)), min(width, math.ceil(cx + r) + 1)
    y0, y1 = max(0, math.floor(cy - r)), min(height, math.ceil(cy + r) + 1)
    if x0 >= x1 or y0 >= y1:
        return x0, y0, np.zeros((0, 0), dtype=bool)
    xs = np.arange(x0, x1, dtype=np.float32) - cx
    ys = np.arange(y0, y1, dtype=np.float32)[:, None] - cy
    return x0, y0, (xs * xs + ys * ys) <= r * r


class SoccerScene:
    """A robot-soccer field seen by a slowly panning camera, rendered frame by frame.

    `clutter` (0..1) scales the sensor noise, the lighting variation (global gain flicker and
    a fixed gradient) and the number of distractor blobs, none of which has a tracked colour.
    """

    def __init__(
        self,
        width: int = 320,
        height: int = 240,
        seed: int = 0,
        clutter: float = 0.0,
        fps: float = 20.0,
    ) -> None:
        if width < 32 or height < 24:
            raise ValueError(f"scene too small: {width}x{height}")
        if not 0.0 <= clutter <= 1.0:
            raise ValueError(f"clutter must be in 0..1, got {clutter}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.width, self.height = int(width), int(height)
        self.seed, self.clutter, self.fps = int(seed), float(clutter), float(fps)
        self._sx, self._sy = self.width / REF_W, self.height / REF_H
        self._s = min(self._sx, self._sy)  # scale of sizes (radii, line widths)
        rng = np.random.default_rng([self.seed, 0xB6])
        self._pan_phase = float(rng.uniform(0, 2 * math.pi))
        self._gain_phases = rng.uniform(0, 2 * math.pi, size=2)
        self._build_background(rng)
        # Separate streams, so that the game (dynamics) is the same at every resolution.
        self._build_noise(np.random.default_rng([self.seed, 0x01]))
        initial = self._initial_state(np.random.default_rng([self.seed, 0x02]))
        self._checkpoints: list[tuple[float, ...]] = [initial]
        self._chunks: OrderedDict[int, np.ndarray] = OrderedDict()
        # the next chunk, simulated a few frames at a time while this one is shown
        self._ahead: tuple[int, Generator[None, None, np.ndarray]] | None = None
        self._positions(0)  # the first chunk at set-up, not at the first frame

    # ------------------------------------------------------------------ static content

    def _px(self, x: float, y: float) -> tuple[int, int]:
        return round(x * self._sx), round(y * self._sy)

    def _build_background(self, rng: np.random.Generator) -> None:
        """Draw carpet, lines, goals, posts and distractors once; remember the object masks."""
        bw, h = round((REF_W + PAN) * self._sx), self.height
        self._bg_w = bw
        # Carpet: base green, a low-frequency texture and a lighting gradient.
        tex = rng.normal(0.0, 1.0, size=(8, 10)).astype(np.float32)
        tex = cv2.resize(tex, (bw, h), interpolation=cv2.INTER_CUBIC)
        grad = 1.0 - 0.18 * self.clutter * np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
        bg = np.empty((h, bw, 3), dtype=np.float32)
        for c in range(3):
            bg[..., c] = (CARPET[c] + 6.0 * tex) * grad
        bg = np.clip(bg, 0, 255).astype(np.uint8)

        # Field lines on the reference layout: goal lines, halfway line, centre circle,
        # goal areas and a penalty mark on each side.
        lines = np.zeros((h, bw), dtype=np.uint8)
        t = max(1, round(2 * self._s))
        mid = (REF_W + PAN) / 2
        right = REF_W + PAN - GOAL_LINE
        cy = REF_H / 2
        segments = [
            ((GOAL_LINE, -10.0), (GOAL_LINE, REF_H + 10)),
            ((right, -10.0), (right, REF_H + 10)),
            ((mid, -10.0), (mid, REF_H + 10)),
        ]
        for x_goal, sign in ((GOAL_LINE, 1.0), (right, -1.0)):
            xa = x_goal + sign * 40.0
            segments += [
                ((x_goal, cy - 60), (xa, cy - 60)),
                ((x_goal, cy + 60), (xa, cy + 60)),
                ((xa, cy - 60), (xa, cy + 60)),
            ]
            cv2.circle(lines, self._px(x_goal + sign * 70.0, cy), t, 255, -1)
        for a, b in segments:
            cv2.line(lines, self._px(*a), self._px(*b), 255, t)
        cv2.circle(lines, self._px(mid, cy), round(40 * self._s), 255, t)

        # Goals (behind the goal lines, reaching the background's ends) and corner posts.
        statics: dict[str, np.ndarray] = {"lines": lines}
        for name, x_a, x_b in (
            ("blue_goal", 0.0, GOAL_DEPTH),
            ("yellow_goal", REF_W + PAN - GOAL_DEPTH, REF_W + PAN),
        ):
            m = np.zeros_like(lines)
            p0, p1 = self._px(x_a, cy - GOAL_HALF_H), self._px(x_b, cy + GOAL_HALF_H)
            cv2.rectangle(m, p0, (p1[0] - 1, p1[1] - 1), 255, -1)
            statics[name] = m
        for name, x in (("blue_post", 8.0), ("yellow_post", REF_W + PAN - 8.0)):
            m = np.zeros_like(lines)
            x0, y0, disc = _disc(x * self._sx, 12.0 * self._sy, POST_R * self._s, bw, h)
            m[y0 : y0 + disc.shape[0], x0 : x0 + disc.shape[1]][disc] = 255
            statics[name] = m

        # Distractor blobs on the carpet, kept clear of goals and posts.
        distract = np.zeros_like(lines)
        bg_dis = bg.copy()
        for i in range(round(6 * self.clutter)):
            colour = DISTRACTORS[i % len(DISTRACTORS)]
            x = rng.uniform(50, REF_W + PAN - 50)
            y = rng.uniform(20, REF_H - 20)
            axes = (round(rng.uniform(4, 10) * self._s), round(rng.uniform(4, 10) * self._s))
            m = np.zeros_like(lines)
            cv2.ellipse(m, self._px(x, y), axes, float(rng.uniform(0, 180)), 0, 360, 255, -1)
            bg_dis[m > 0] = colour
            distract |= m

        colours = {"lines": LINE, "blue_goal": BLUE, "yellow_goal": YELLOW}
        colours |= {"blue_post": BLUE, "yellow_post": YELLOW}
        for name, m in statics.items():
            bg[m > 0] = colours[name]
        bg[distract > 0] = bg_dis[distract > 0]
        statics["lines"] = cv2.bitwise_and(lines, cv2.bitwise_not(distract))
        self._bg = bg
        self._static = statics
        # Tight boxes of the small static objects, so per-frame truth only looks at patches.
        self._static_boxes = {
            name: cv2.boundingRect(m) for name, m in statics.items() if name != "lines"
        }

    def _build_noise(self, rng: np.random.Generator) -> None:
        """A bank of sensor noise, larger than a frame; each frame uses a shifted crop of it."""
        sigma = 1.0 + 6.0 * self.clutter
        shape = (self.height + 32, self.width + 32, 3)
        noise = rng.normal(0.0, sigma, size=shape)
        self._noise_pos = np.clip(noise, 0, 255).astype(np.uint8)
        self._noise_neg = np.clip(-noise, 0, 255).astype(np.uint8)

    # ------------------------------------------------------------------ dynamics

    @staticmethod
    def _initial_state(rng: np.random.Generator) -> tuple[float, ...]:
        """Ball (x, y, vx, vy) then per obstacle (x, y, target x, target y, speed)."""
        state = [REF_W / 2 + 30, REF_H / 2 - 20, 0.0, 0.0]
        for _ in range(N_OBSTACLES):
            state += [
                float(rng.uniform(70, REF_W + PAN - 70)),
                float(rng.uniform(40, REF_H - 20)),
                float(rng.uniform(70, REF_W + PAN - 70)),
                float(rng.uniform(40, REF_H - 20)),
                float(rng.uniform(10, 25)),
            ]
        return tuple(state)

    def _simulate_chunk(self, chunk: int) -> np.ndarray:
        """Positions (ball x, y, then obstacle x, y...) of every frame of one chunk."""
        steps = self._chunk_steps(chunk)
        while True:
            try:
                next(steps)
            except StopIteration as done:
                out: np.ndarray = done.value
                return out

    def _chunk_steps(self, chunk: int) -> Generator[None, None, np.ndarray]:
        """:meth:`_simulate_chunk` one frame per step (see :meth:`_step_ahead`).

        Also records the state at the start of the next chunk. The ball rolls with friction,
        bounces off the field boundary (which extends beyond the camera's view above and
        below, so the ball leaves the view), is kicked at random and sometimes by an obstacle
        robot it touches; otherwise it rolls behind the robots and is occluded.
        """
        rng = np.random.default_rng([self.seed, chunk, 0x5C])
        dt = 1.0 / self.fps
        kick_u = rng.random(CHUNK)
        kick_angle = rng.uniform(0, 2 * math.pi, CHUNK)
        kick_speed = rng.uniform(70, 240, CHUNK)
        touch_u = rng.random(CHUNK)
        retarget = rng.random((CHUNK, N_OBSTACLES))
        targets = rng.uniform(0, 1, (CHUNK, N_OBSTACLES, 3))

        s = list(self._checkpoints[chunk])
        out = np.empty((CHUNK, 2 + 2 * N_OBSTACLES), dtype=np.float64)
        x_lo, x_hi = GOAL_LINE + BALL_R, REF_W + PAN - GOAL_LINE - BALL_R
        y_lo, y_hi = -45.0, REF_H + 45.0
        for i in range(CHUNK):
            # Obstacles walk slowly towards a target that changes now and then.
            for k in range(N_OBSTACLES):
                j = 4 + 5 * k
                ox, oy, tx, ty, sp = s[j : j + 5]
                dx, dy = tx - ox, ty - oy
                d = math.hypot(dx, dy)
                if d < 2.0 or retarget[i, k] < 0.2 * dt:
                    u = targets[i, k]
                    tx = 70 + u[0] * (REF_W + PAN - 140)
                    ty = 30 + u[1] * (REF_H - 20)
                    sp = 10 + 20 * u[2]
                else:
                    step = min(d, sp * dt)
                    ox, oy = ox + dx / d * step, oy + dy / d * step
                s[j : j + 5] = [ox, oy, tx, ty, sp]
            # Ball: rolling friction, random kicks, kicks by a touching robot, bounces.
            bx, by, vx, vy = s[0:4]
            speed = math.hypot(vx, vy)
            rate = 0.35 if speed > 8 else 1.2
            if kick_u[i] < rate * dt:
                vx = kick_speed[i] * math.cos(kick_angle[i])
                vy = kick_speed[i] * math.sin(kick_angle[i])
            else:
                for k in range(N_OBSTACLES):
                    ox, oy = s[4 + 5 * k], s[5 + 5 * k]
                    d = math.hypot(bx - ox, by - oy)
                    if d < OBSTACLE_R + BALL_R + 1 and touch_u[i] < 0.25:
                        sp_k = kick_speed[i] * 0.8
                        vx, vy = (bx - ox) / max(d, 1e-6) * sp_k, (by - oy) / max(d, 1e-6) * sp_k
                        break
            speed = math.hypot(vx, vy)
            if speed > 0:
                new = max(0.0, speed * (1 - 0.5 * dt) - 15.0 * dt)
                vx, vy = vx * new / speed, vy * new / speed
            bx, by = bx + vx * dt, by + vy * dt
            if bx < x_lo or bx > x_hi:
                bx = min(max(bx, x_lo), x_hi)
                vx = -0.6 * vx
            if by < y_lo or by > y_hi:
                by = min(max(by, y_lo), y_hi)
                vy = -0.6 * vy
            s[0:4] = [bx, by, vx, vy]
            out[i, 0:2] = bx, by
            for k in range(N_OBSTACLES):
                out[i, 2 + 2 * k : 4 + 2 * k] = s[4 + 5 * k], s[5 + 5 * k]
            yield
        if len(self._checkpoints) == chunk + 1:
            self._checkpoints.append(tuple(s))
        return out

    def _positions(self, index: int) -> np.ndarray:
        chunk, offset = divmod(index, CHUNK)
        if self._ahead is not None and self._ahead[0] == chunk:
            self._step_ahead(CHUNK)  # wanted before it was done: finish it now
        if chunk not in self._chunks:
            for c in range(len(self._checkpoints) - 1, chunk):
                self._simulate_chunk(c)  # only to extend the checkpoints
            self._chunks[chunk] = self._simulate_chunk(chunk)
            while len(self._chunks) > 4:
                self._chunks.popitem(last=False)
        self._chunks.move_to_end(chunk)
        self._step_ahead(AHEAD_STEPS, chunk + 1)
        return self._chunks[chunk][offset]

    def _step_ahead(self, steps: int, chunk: int | None = None) -> None:
        """Simulate ``steps`` frames of the chunk after the one in use, a few per frame
        rendered: a whole chunk at once is ~4 ms of Python, which a camera on the event loop
        of a 1 kHz control loop cannot take in one go (the result is the same either way)."""
        if self._ahead is None:
            if chunk is None or chunk in self._chunks or len(self._checkpoints) <= chunk:
                return
            self._ahead = (chunk, self._chunk_steps(chunk))
        at, gen = self._ahead
        try:
            for _ in range(steps):
                next(gen)
        except StopIteration as done:
            self._ahead = None
            self._chunks[at] = done.value
            while len(self._chunks) > 4:
                self._chunks.popitem(last=False)

    # ------------------------------------------------------------------ rendering

    def pan_offset(self, index: int) -> int:
        """Horizontal offset of the view in the background, in pixels (a slow sinusoid)."""
        t = index / self.fps
        u = 0.5 + 0.5 * math.sin(2 * math.pi * t / 17.0 + self._pan_phase)
        return min(self._bg_w - self.width, round(u * PAN * self._sx))

    def gain(self, index: int) -> float:
        """Global lighting gain of frame `index` (flicker and slow drift, scaled by clutter)."""
        t = index / self.fps
        p0, p1 = self._gain_phases
        wave = 0.7 * math.sin(2 * math.pi * t / 9.0 + p0) + 0.3 * math.sin(
            2 * math.pi * t / 1.3 + p1
        )
        return 1.0 + 0.2 * self.clutter * wave

    def render(self, index: int) -> tuple[np.ndarray, SceneTruth]:
        """Frame `index` (BGR uint8, height x width x 3) and its ground truth."""
        if index < 0:
            raise ValueError(f"frame index must be >= 0, got {index}")
        pos = self._positions(index)
        w, h = self.width, self.height
        ox = self.pan_offset(index)
        frame = self._bg[:, ox : ox + w].copy()

        # Dynamic layers in drawing order: the ball first, so robots occlude it.
        layers: list[_Layer] = []
        specs = [("ball", BALL, pos[0], pos[1], BALL_R)]
        specs += [
            (f"obstacle_{k}", OBSTACLE, pos[2 + 2 * k], pos[3 + 2 * k], OBSTACLE_R)
            for k in range(N_OBSTACLES)
        ]
        for name, colour, x, y, r in specs:
            x0, y0, mask = _disc(x * self._sx - ox, y * self._sy, r * self._s, w, h)
            layers.append(_Layer(name, colour, x0, y0, mask))
            if mask.size:
                frame[y0 : y0 + mask.shape[0], x0 : x0 + mask.shape[1]][mask] = colour

        objects: dict[str, ObjectTruth] = {}
        for i, layer in enumerate(layers):
            if not layer.mask.size:
                objects[layer.name] = NOT_VISIBLE
                continue
            visible = layer.mask.copy()
            for later in layers[i + 1 :]:
                sl = layer.overlap(later) if later.mask.size else None
                if sl is not None:
                    visible[sl[0], sl[1]] &= ~later.mask[sl[2], sl[3]]
            objects[layer.name] = _truth_from_mask(visible, layer.x0, layer.y0)
        obstacles = [objects[f"obstacle_{k}"] for k in range(N_OBSTACLES)]
        objects["obstacle"] = max(obstacles, key=lambda o: o.pixels)

        for name, (bx, by, bw, bh) in self._static_boxes.items():
            x0, x1 = max(bx, ox), min(bx + bw, ox + w)
            if x0 >= x1:
                objects[name] = NOT_VISIBLE
                continue
            patch = self._static[name][by : by + bh, x0:x1] > 0
            objects[name] = _truth_from_mask(patch, x0 - ox, by)

        lines = self._static["lines"][:, ox : ox + w].copy()
        for layer in layers:
            if layer.mask.size:
                ys, xs = layer.y0, layer.x0
                sub = lines[ys : ys + layer.mask.shape[0], xs : xs + layer.mask.shape[1]]
                sub[layer.mask] = 0
        objects["lines"] = _truth_from_mask(lines > 0, 0, 0)

        # Sensor: shifted crop of the noise bank, then the lighting gain.
        nrng = np.random.default_rng([self.seed, index, 0x10])
        dy, dx = (int(v) for v in nrng.integers(0, 32, size=2))
        cv2.add(frame, self._noise_pos[dy : dy + h, dx : dx + w], dst=frame)
        cv2.subtract(frame, self._noise_neg[31 - dy : 31 - dy + h, dx : dx + w], dst=frame)
        g = self.gain(index)
        if g != 1.0:
            frame = cv2.convertScaleAbs(frame, alpha=g)
        return frame, SceneTruth(index, index / self.fps, objects)

    def frame(self, index: int) -> np.ndarray:
        """Only the image of frame `index`."""
        return self.render(index)[0]
