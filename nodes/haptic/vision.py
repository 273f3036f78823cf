"""The ``vision_force`` kind: a tracked object becomes a force, a virtual wall or spring.

::

    wall:
      kind: vision_force
      trigger: {input: handle}       # once per haptic tick, with the newest detection
      params:
        mode: wall                   # or spring
        stiffness: 300               # N/m (the README's stable value with the sim device)
        normal: [-1, 0, 0]           # the wall's free side: the handle is pushed along this
        u_range: [-100, 100]         # mm the image's width spans on axes[0]
        v_range: [100, -100]         # mm its height spans on axes[1] (image rows grow down)
        timeout: 150ms               # a detection older than this gives no force at all
      inputs:
        detection: {from: ball.detection, policy: latest}
        handle: {from: haptic.position, policy: latest}

The object's image position (the detection's ``centroid``, in an image of the detection's
``size`` or ``image_size``) is mapped linearly into the device's workspace on ``axes``; the
other axes take the handle's own coordinate. ``wall``: a plane through that point with
outward ``normal``; when the handle is behind it by d, the force is ``stiffness`` × d along
the normal, plus ``damping`` against the velocity into the wall. ``spring``: a pull of
``stiffness`` × distance towards the point on the image axes (minus ``damping`` × velocity).

Vision runs at camera rate (20-30 fps) and the force loop at 1 kHz: this node is meant to be
triggered by the handle position, so the force follows the hand at the loop's rate while the
wall moves at the camera's. The force carries the detection's ``timestamp`` (the camera
frame's time): the haptic node judges its age from it, so a tracker that stalls makes the
force stale (zero at the device) even while this node keeps publishing; a detection older
than ``timeout`` gives no force at all. An object not found gives a zero force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from flowrt import InputTrigger, Input, Node, Output, parse_duration_ms
from flowrt.freshness import own_timestamp

from .messages import Force, HandleState

__all__ = ["Anchor", "VisionForce"]


@dataclass(frozen=True)
class Anchor:
    """Where the wall or spring is in device space (mm), for the live view and recordings."""

    axes: tuple[str, ...]
    position: tuple[float, ...]
    normal: tuple[float, ...]
    mode: str
    found: bool
    timestamp: float


class VisionForceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["wall", "spring"] = "wall"
    stiffness: float = Field(default=300.0, ge=0, le=100_000, allow_inf_nan=False, description="N/m")
    damping: float = Field(default=0.0, ge=0, le=10_000, allow_inf_nan=False, description="N·s/m")
    axes: tuple[str, str] = Field(default=("x", "y"), description="device axes of image u, v")
    u_range: tuple[float, float] = Field(default=(-100.0, 100.0), description="mm at u=0, u=w")
    v_range: tuple[float, float] = Field(default=(100.0, -100.0), description="mm at v=0, v=h")
    image_size: tuple[int, int] = Field(default=(320, 240), description="when not in detection")
    normal: tuple[float, ...] = Field(default=(-1.0, 0.0, 0.0), description="wall's free side")
    timeout: float = Field(default=0.15, description="older detections give no force")

    @field_validator("timeout", mode="before")
    @classmethod
    def _duration(cls, v: Any) -> Any:
        ms = parse_duration_ms(v)
        if ms <= 0 or ms > 60_000:
            raise ValueError("must be a duration between 0 and 60 s, e.g. 150ms")
        return ms / 1000

    @field_validator("normal")
    @classmethod
    def _unit(cls, v: tuple[float, ...]) -> Any:
        n = math.sqrt(sum(x * x for x in v)) if all(math.isfinite(x) for x in v) else 0.0
        if n == 0:
            raise ValueError("normal: a finite, non-zero vector")
        return tuple(x / n for x in v)


class VisionForce(Node):
    """Turns a tracked object into a wall or spring force on the handle (module doc)."""

    Params = VisionForceParams
    detection = Input(object, required=False, policy="latest", doc="a tracker's detection")
    handle = Input(HandleState, required=False, policy="latest", doc="the haptic position")
    force = Output(Force, doc="N per handle axis, stamped with the camera frame's time")
    anchor = Output(Anchor, doc="the wall or spring point in device space (mm)")

    @classmethod
    def default_trigger(cls, params: Any) -> InputTrigger:
        return InputTrigger(input="handle")

    def setup(self) -> None:
        self.old = 0  # activations with a detection older than timeout (no force)
        self.contacts = 0  # activations with a non-zero force

    def process(self, detection: Any = None, handle: Any = None) -> dict[str, Any] | None:
        if not isinstance(handle, HandleState) or detection is None:
            return None
        age = self.ctx.input_age("detection", detection)
        if age is None or age > self.params.timeout:
            self.old += 1
            return None
        stamp = own_timestamp(detection)
        if stamp is None:
            stamp = self.ctx.input_time("detection") or self.ctx.now()
        axes = handle.axes
        n = len(axes)
        zero = Force(axes, (0.0,) * n, stamp)
        centroid = getattr(detection, "centroid", None)
        if not getattr(detection, "found", False) or centroid is None:
            return {"force": zero}
        p = self.params
        w, h = getattr(detection, "size", None) or p.image_size
        anchor = list(handle.position)
        for axis, pix, size, (lo, hi) in zip(
            p.axes, centroid, (w, h), (p.u_range, p.v_range), strict=True
        ):
            if axis in axes:
                anchor[axes.index(axis)] = lo + (hi - lo) * float(pix) / max(1, size)
        normal = tuple((p.normal[i] if i < len(p.normal) else 0.0) for i in range(n))
        values = self._wall(handle, anchor, normal) if p.mode == "wall" else self._spring(
            handle, anchor
        )
        if any(values):
            self.contacts += 1
        return {
            "force": Force(axes, values, stamp),
            "anchor": Anchor(axes, tuple(anchor), normal, p.mode, True, stamp),
        }

    def _wall(
        self, handle: HandleState, anchor: list[float], normal: tuple[float, ...]
    ) -> tuple[float, ...]:
        depth = sum((a - x) * k for a, x, k in zip(anchor, handle.position, normal)) / 1000
        if depth <= 0:  # on the free side
            return (0.0,) * len(anchor)
        v_in = -sum(v * k for v, k in zip(handle.velocity, normal)) / 1000  # into the wall
        push = self.params.stiffness * depth + self.params.damping * max(0.0, v_in)
        return tuple(push * k for k in normal)

    def _spring(self, handle: HandleState, anchor: list[float]) -> tuple[float, ...]:
        p = self.params
        return tuple(
            (p.stiffness * (a - x) - p.damping * v) / 1000 if axis in p.axes else 0.0
            for axis, a, x, v in zip(handle.axes, anchor, handle.position, handle.velocity)
        )

    def report(self) -> dict[str, Any]:
        """What the statistics show (``reports``): contacts, and detections too old to use."""
        return {"contacts": self.contacts, "old_detections": self.old}
