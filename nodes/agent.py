"""The agent-based control scenario: a simulated robot and three behaviours (graphs/agent.yaml).

After the flexible real-time control system's experiment: behaviours at different rates each
propose a command, a decision table picks the situation every 250 ms (target seen ->
tracking; danger -> avoidance; else wall-following) and, through the graph's modes, sets the
weights with which the ``arbiter`` blends the proposals.

- ``robot_sim`` (:class:`RobotSim`): a kinematic differential-drive robot (unicycle model) in a
  walled arena with round obstacles and a target moving on a closed path; a fan of range
  rays and a target detector (field of view, range, occlusion by obstacles). Each step it
  writes what it senses to the RTDB (``robot.pose``, ``robot.ranges``, ``robot.sense``: the
  blackboard the behaviours and the decision table read, which also keeps the control loop
  out of the graph's edges) and draws the arena as a frame for the live view.
- ``track_target``, ``avoid_obstacles``, ``follow_wall``: behaviours reading the RTDB on their
  own timers and publishing ``command`` ``{v, w, timestamp}``; a behaviour with nothing to say
  (no target seen) publishes nothing, so the arbiter leaves it out of the blend.

No external simulator: the geometry is a few lines of ray casting against segments and
circles, fast enough to run inline at 50 Hz.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import cv2
from pydantic import BaseModel, ConfigDict, Field

from flowrt import Frame, Input, Node, Output, TimerTrigger

__all__ = ["AvoidObstacles", "FollowWall", "RobotSim", "TrackTarget", "cast"]

ARENA = (6.0, 4.0)  # metres
OBSTACLES = ((2.0, 1.4, 0.35), (4.1, 2.7, 0.30), (3.3, 0.8, 0.25), (1.2, 3.0, 0.25))
ROBOT_RADIUS = 0.18


def cast(x: float, y: float, angle: float, max_range: float, circles: Any = OBSTACLES) -> float:
    """Distance from (x, y) along ``angle`` to the first wall or circle, capped at max_range."""
    dx, dy = math.cos(angle), math.sin(angle)
    best = max_range
    w, h = ARENA
    for t in (
        (-x / dx) if dx < 0 else ((w - x) / dx) if dx > 0 else math.inf,
        (-y / dy) if dy < 0 else ((h - y) / dy) if dy > 0 else math.inf,
    ):
        if 0 <= t < best:
            best = t
    for cx, cy, r in circles:
        fx, fy = x - cx, y - cy
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - r * r
        disc = b * b - c
        if disc < 0:
            continue
        t = -b - math.sqrt(disc)
        if 0 <= t < best:
            best = t
    return best


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class RobotSimParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rate_hz: float = Field(default=50.0, gt=0, le=1000, allow_inf_nan=False)
    rays: int = Field(default=9, ge=3, le=181)
    fov_deg: float = Field(default=180.0, gt=0, le=360)
    max_range: float = Field(default=4.0, gt=0, le=100, allow_inf_nan=False)
    target_speed: float = Field(default=0.25, ge=0, le=5, allow_inf_nan=False)
    start: tuple[float, float, float] = (0.6, 0.6, 0.3)
    render_every: int = Field(default=5, ge=1, le=1000, description="steps per arena frame")
    size: tuple[int, int] = (360, 240)


class RobotSim(Node):
    """Kinematic robot, arena, sensors; see the module docstring."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset(
        {"rate_hz", "rays", "fov_deg", "max_range", "target_speed", "render_every"}
    )

    Params = RobotSimParams
    command = Input(object, required=False, policy="latest", doc="{v, w}: m/s and rad/s")
    pose = Output(dict, doc="{x, y, heading, v, w, collisions}")
    sense = Output(dict, doc="{min_range, target_seen, target_bearing, target_distance}")
    arena = Output(Frame, doc="the arena drawn for the live view")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate_hz)

    @classmethod
    def output_rates(cls, params: Any) -> Mapping[str, float | None]:
        """``arena`` is drawn every ``render_every`` steps, not every step: without saying so
        a recording's stream table expected it at the step rate and called four frames in
        five "missing". The rate assumes the default trigger (``rate_hz``); a graph that
        gives the robot a timer of its own should set ``rate_hz`` to match."""
        return {**super().output_rates(params), "arena": params.rate_hz / params.render_every}

    def setup(self) -> None:
        p = self.params
        self.x, self.y, self.heading = p.start
        self.v = self.w = 0.0
        self.collisions = 0
        self.steps = 0
        self.t_last: float | None = None
        self.sim_t = 0.0
        n = p.rays
        span = math.radians(p.fov_deg)
        self.ray_angles = [-span / 2 + span * i / (n - 1) for i in range(n)]
        self.ranges = [p.max_range] * n
        self.target = (3.0, 2.0)

    def _target_at(self, t: float) -> tuple[float, float]:
        s = self.params.target_speed * t / 1.6  # a closed Lissajous path, ~1.6 m radius
        return 3.0 + 2.2 * math.sin(s), 2.0 + 1.3 * math.sin(2 * s + 0.5)

    def process(self, command: Any = None) -> dict[str, Any]:
        now = self.ctx.now()
        dt = 0.0 if self.t_last is None else min(0.1, max(0.0, now - self.t_last))
        self.t_last = now
        self.sim_t += dt
        v = w = 0.0
        if isinstance(command, dict):
            v = float(command.get("v", 0.0) or 0.0)
            w = float(command.get("w", 0.0) or 0.0)
        v = max(-0.6, min(0.6, v if math.isfinite(v) else 0.0))
        w = max(-2.5, min(2.5, w if math.isfinite(w) else 0.0))
        self.v, self.w = v, w
        heading = _wrap(self.heading + w * dt)
        nx = self.x + v * dt * math.cos(heading)
        ny = self.y + v * dt * math.sin(heading)
        if self._free(nx, ny):
            self.x, self.y = nx, ny
        elif v != 0:
            self.collisions += 1
        self.heading = heading
        self.target = self._target_at(self.sim_t)
        return self._sense()

    def _free(self, x: float, y: float) -> bool:
        w, h = ARENA
        r = ROBOT_RADIUS
        if not (r <= x <= w - r and r <= y <= h - r):
            return False
        return all(math.hypot(x - cx, y - cy) > cr + r for cx, cy, cr in OBSTACLES)

    def _sense(self) -> dict[str, Any]:
        p = self.params
        for i, a in enumerate(self.ray_angles):
            self.ranges[i] = cast(self.x, self.y, self.heading + a, p.max_range)
        tx, ty = self.target
        dist = math.hypot(tx - self.x, ty - self.y)
        bearing = _wrap(math.atan2(ty - self.y, tx - self.x) - self.heading)
        seen = (
            abs(bearing) <= math.radians(p.fov_deg) / 2
            and dist <= p.max_range
            and cast(self.x, self.y, self.heading + bearing, dist + 1.0) >= dist - 0.05
        )
        pose = {
            "x": self.x,
            "y": self.y,
            "heading": self.heading,
            "v": self.v,
            "w": self.w,
            "collisions": self.collisions,
        }
        sense = {
            "min_range": min(self.ranges),
            "target_seen": bool(seen),
            "target_bearing": bearing if seen else None,
            "target_distance": dist if seen else None,
        }
        db = self.ctx.rtdb
        db.write("robot.pose", pose, validity_ms=200)
        db.write(
            "robot.ranges",
            {"angles": self.ray_angles, "ranges": list(self.ranges)},
            validity_ms=200,
        )
        db.write("robot.sense", sense, validity_ms=200)
        out: dict[str, Any] = {"pose": pose, "sense": sense}
        self.steps += 1
        if self.steps % p.render_every == 0:
            out["arena"] = self._render(sense)
        return out

    def _render(self, sense: dict[str, Any]) -> Frame:
        wpx, hpx = self.params.size
        frame = self.ctx.new_frame((hpx, wpx, 3))
        img = frame.data
        img[:] = (40, 40, 40)
        sx, sy = wpx / ARENA[0], hpx / ARENA[1]

        def px(x: float, y: float) -> tuple[int, int]:
            return int(x * sx), int(hpx - 1 - y * sy)

        cv2.rectangle(img, (0, 0), (wpx - 1, hpx - 1), (200, 200, 200), 2)
        for cx, cy, r in OBSTACLES:
            cv2.circle(img, px(cx, cy), int(r * sx), (90, 90, 160), -1)
        for a, rng in zip(self.ray_angles, self.ranges, strict=True):
            end = px(
                self.x + rng * math.cos(self.heading + a), self.y + rng * math.sin(self.heading + a)
            )
            cv2.line(img, px(self.x, self.y), end, (60, 110, 60), 1)
        cv2.circle(img, px(*self.target), int(0.12 * sx), (0, 200, 255), -1)
        cv2.circle(img, px(self.x, self.y), int(ROBOT_RADIUS * sx), (230, 160, 60), -1)
        hx = self.x + ROBOT_RADIUS * math.cos(self.heading)
        hy = self.y + ROBOT_RADIUS * math.sin(self.heading)
        cv2.line(img, px(self.x, self.y), px(hx, hy), (255, 255, 255), 2)
        mode = self.ctx.rtdb.value("flowrt.mode") or "-"
        label = f"mode {mode}  collisions {self.collisions}"
        cv2.putText(img, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
        return frame


class BehaviourParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    speed: float = Field(default=0.35, ge=0, le=2, allow_inf_nan=False)
    gain: float = Field(default=1.5, ge=0, le=100, allow_inf_nan=False)
    distance: float = Field(default=0.5, gt=0, le=10, allow_inf_nan=False, description="metres")


class _Behaviour(Node):
    """Reads the RTDB blackboard; proposes ``{v, w, timestamp}`` or nothing."""

    swappable = frozenset({"speed", "gain", "distance"})  # over the control endpoint: flowrt kinds

    Params = BehaviourParams
    command = Output(dict)

    def _records(self) -> tuple[Any, Any]:
        db = self.ctx.rtdb
        return db.value("robot.sense", fresh=True), db.value("robot.ranges", fresh=True)

    def _cmd(self, v: float, w: float) -> dict[str, float]:
        return {"v": v, "w": w, "timestamp": self.ctx.now()}


class TrackTarget(_Behaviour):
    """Turns towards the target and drives to it; silent when the target is not seen."""

    def process(self) -> dict[str, float] | None:
        sense, _ = self._records()
        if not sense or not sense.get("target_seen"):
            return None
        bearing = float(sense["target_bearing"])
        dist = float(sense["target_distance"])
        v = self.params.speed * max(0.0, 1 - abs(bearing) / (math.pi / 2))
        if dist < self.params.distance:
            v = 0.0
        return self._cmd(v, self.params.gain * bearing)


class AvoidObstacles(_Behaviour):
    """Slows and turns away from the nearer side when something is close."""

    def process(self) -> dict[str, float] | None:
        _, rays = self._records()
        if not rays:
            return None
        angles, ranges = rays["angles"], rays["ranges"]
        d = self.params.distance
        nearest = min(ranges)
        if nearest > 2 * d:
            return self._cmd(self.params.speed, 0.0)
        push = sum(
            -math.copysign(1.0, a) * (2 * d - r)
            for a, r in zip(angles, ranges, strict=True)
            if r < 2 * d and abs(a) > 1e-6
        )
        front = min(r for a, r in zip(angles, ranges, strict=True) if abs(a) < math.radians(35))
        v = self.params.speed * max(0.0, min(1.0, (front - d) / d))
        if push == 0.0:
            push = 1.0
        return self._cmd(v, self.params.gain * push)


class FollowWall(_Behaviour):
    """Keeps the wall on the right at ``distance``; turns left at a wall ahead."""

    def process(self) -> dict[str, float] | None:
        _, rays = self._records()
        if not rays:
            return None
        angles, ranges = rays["angles"], rays["ranges"]
        right = min(r for a, r in zip(angles, ranges, strict=True) if a < -math.radians(45))
        front = min(r for a, r in zip(angles, ranges, strict=True) if abs(a) < math.radians(25))
        d = self.params.distance
        if front < 1.5 * d:
            return self._cmd(0.1, 1.2)
        w = self.params.gain * (d - right) if right < 3 * d else -0.4
        return self._cmd(self.params.speed, max(-1.5, min(1.5, w)))
