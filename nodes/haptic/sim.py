"""A simulated 3-DoF haptic handle with a virtual operator's hand, for tests and demos.

The handle is a point mass (``mass``, kg) with viscous ``damping`` (N·s/m) inside a box
``workspace`` (mm per axis; a hard stop at the limits, as a real arm's mechanical end stops).
Two forces move it: the force the node applies (held constant between two ``apply_force``
calls, as a motor amplifier holds its set-point) and the operator's hand, a spring-damper
towards where the operator wants the handle (``hand``):

- ``spring``: a fixed ``target`` (mm), e.g. an operator pushing towards a point;
- ``script``: ``points`` ``[[t, x, y, z], ...]`` (seconds, mm) interpolated linearly, looped
  when ``loop``: the operator's hand moving through a scripted path;
- ``none``: nobody holds the handle (the wall-stability benchmark).

Buttons are scripted too (``buttons: [[t, name, pressed], ...]``), and so are device faults
(``faults: [[t0, t1], ...]``: the device reports an error in that window), so the node's
reactions are tested without hardware. Physics is integrated up to the ``now`` each read
gives (semi-implicit Euler, steps of at most ``step`` seconds), so a run on a virtual clock is
exact and repeatable.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from .device import DeviceError, DeviceInfo, DeviceState

__all__ = ["HandParams", "SimDevice", "SimParams"]

AXES = ("x", "y", "z")
Vec3 = tuple[float, float, float]


class HandParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["spring", "script", "none"] = "spring"
    target: Vec3 = Field(default=(60.0, 0.0, 0.0), description="spring: where the hand pulls (mm)")
    points: list[tuple[float, float, float, float]] = Field(
        default_factory=list, description="script: [t, x, y, z] rows (s, mm)"
    )
    loop: bool = True
    stiffness: float = Field(default=40.0, ge=0, le=10_000, description="N/m")
    damping: float = Field(default=3.0, ge=0, le=1_000, description="N·s/m")

    @field_validator("points")
    @classmethod
    def _sorted(cls, v: list[tuple[float, float, float, float]]) -> Any:
        if any(not all(math.isfinite(x) for x in row) for row in v):
            raise ValueError("points must be finite")
        return sorted(v)


class SimParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mass: float = Field(default=0.2, ge=0.001, le=100, description="moving mass (kg)")
    damping: float = Field(default=1.0, ge=0, le=1_000, description="viscous damping (N·s/m)")
    workspace: tuple[tuple[float, float], ...] = Field(
        default=((-100.0, 100.0),) * 3, description="per axis [lo, hi] (mm)"
    )
    max_force: float = Field(default=5.0, gt=0, le=1_000, description="the motors' limit (N)")
    start: Vec3 = (0.0, 0.0, 0.0)
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="initial velocity (mm/s)")
    hand: HandParams = Field(default_factory=HandParams)
    buttons: list[tuple[float, str, bool]] = Field(
        default_factory=list, description="[t, name, pressed] rows (s)"
    )
    faults: list[tuple[float, float]] = Field(
        default_factory=list, description="[t0, t1] windows where the device reports an error"
    )
    step: float = Field(default=0.00025, ge=1e-5, le=0.01, description="integration step (s)")

    @field_validator("workspace")
    @classmethod
    def _three(cls, v: tuple[tuple[float, float], ...]) -> Any:
        if len(v) != 3 or any(not lo < hi for lo, hi in v):
            raise ValueError("workspace: three [lo, hi] ranges in mm, lo < hi")
        return v


class SimDevice:
    """The simulated handle (see the module docstring); implements ``HapticDevice``."""

    def __init__(self, params: SimParams | None = None) -> None:
        self.p = params or SimParams()
        self.pos = [x / 1000 for x in self.p.start]  # metres
        self.vel = [v / 1000 for v in self.p.velocity]  # m/s
        self.force = [0.0, 0.0, 0.0]  # newtons, held until the next apply_force
        self.t: float | None = None  # simulated up to this runtime-clock time
        self.t0 = 0.0
        self.opened = False
        self.buttons = {name: False for _, name, _ in self.p.buttons}
        self.button_row = 0
        self.forces_applied = 0

    # --- HapticDevice ---------------------------------------------------------------------

    def open(self) -> DeviceInfo:
        self.opened = True
        return DeviceInfo(
            AXES, tuple(self.p.workspace), self.p.max_force, tuple(sorted(self.buttons))
        )

    def read_state(self, now: float) -> DeviceState:
        if not self.opened:
            raise DeviceError("not open")
        self.advance(now)
        t = now - self.t0
        while self.button_row < len(self.p.buttons) and self.p.buttons[self.button_row][0] <= t:
            _, name, pressed = self.p.buttons[self.button_row]
            self.buttons[name] = pressed
            self.button_row += 1
        error = next((f"motor fault (simulated, {a:g}-{b:g} s)" for a, b in self.p.faults
                      if a <= t < b), None)  # fmt: skip
        return DeviceState(
            (self.pos[0] * 1000, self.pos[1] * 1000, self.pos[2] * 1000),
            (self.vel[0] * 1000, self.vel[1] * 1000, self.vel[2] * 1000),
            dict(self.buttons),
            error,
        )

    def apply_force(self, force: Sequence[float], now: float) -> None:
        if not self.opened:
            raise DeviceError("not open")
        self.advance(now)  # the old force acted until now
        limit = self.p.max_force
        self.force = [max(-limit, min(limit, float(f))) for f in force[:3]]
        self.forces_applied += 1

    def close(self) -> None:
        self.force = [0.0, 0.0, 0.0]
        self.opened = False

    # --- physics --------------------------------------------------------------------------

    def hand_target(self, t: float) -> Vec3 | None:
        """Where the operator's hand pulls the handle at script time ``t`` (mm), or None."""
        h = self.p.hand
        if h.mode == "none":
            return None
        if h.mode == "spring" or not h.points:
            return h.target
        pts = h.points
        end = pts[-1][0]
        if h.loop and end > 0:
            t %= end
        if t <= pts[0][0]:
            return pts[0][1:]
        for a, b in itertools.pairwise(pts):
            if t <= b[0]:
                s = 0.0 if b[0] == a[0] else (t - a[0]) / (b[0] - a[0])
                return (
                    a[1] + s * (b[1] - a[1]),
                    a[2] + s * (b[2] - a[2]),
                    a[3] + s * (b[3] - a[3]),
                )
        return pts[-1][1:]

    def advance(self, now: float) -> None:
        """Integrate the handle from the last call up to ``now`` (a jump of more than 1 s,
        a stalled loop, is integrated as 1 s: the simulation does not spin for minutes)."""
        if self.t is None:
            self.t = self.t0 = now
            return
        span = min(now - self.t, 1.0)
        self.t = now
        if span <= 0:
            return
        n = max(1, math.ceil(span / self.p.step))
        dt = span / n
        start = now - span - self.t0
        for i in range(n):
            self._step(dt, start + (i + 1) * dt)

    def _step(self, dt: float, t: float) -> None:
        p = self.p
        target = self.hand_target(t)
        for i in range(3):
            f = self.force[i] - p.damping * self.vel[i]
            if target is not None:
                f += p.hand.stiffness * (target[i] / 1000 - self.pos[i])
                f -= p.hand.damping * self.vel[i]
            self.vel[i] += f / p.mass * dt
            x = self.pos[i] + self.vel[i] * dt
            lo, hi = p.workspace[i][0] / 1000, p.workspace[i][1] / 1000
            if x < lo or x > hi:  # the end stop: an inelastic hit
                x = min(hi, max(lo, x))
                self.vel[i] = 0.0
            self.pos[i] = x

    def kinetic_energy(self) -> float:
        """½ m v² (joules): the wall benchmark adds the wall's spring energy to it."""
        return 0.5 * self.p.mass * sum(v * v for v in self.vel)
