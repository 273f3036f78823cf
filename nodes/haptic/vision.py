"""The ``vision_force`` kind: a tracked object becomes a virtual wall or spring.

::

    wall:
      kind: vision_force
      params:
        mode: wall                   # or spring
        stiffness: 300               # N/m (the README's stable value with the sim device)
        normal: [-1, 0]              # the wall's free side, on axes (device x, y)
        u_range: [-100, 100]         # mm the image's width spans on axes[0]
        v_range: [100, -100]         # mm its height spans on axes[1] (image rows grow down)
      inputs:
        detection: {from: ball.detection, policy: latest}

On each detection (the default trigger: the ``detection`` input, so at camera rate), the
object's image position (its ``centroid``, in an image of the detection's ``size`` or
``image_size``) is mapped linearly onto the device axes ``axes`` and published as a
:class:`~flowrt.nodes.haptic.fixtures.Fixture` on ``force``: the haptic node evaluates it
against its handle on every tick (see :mod:`flowrt.nodes.haptic.fixtures` for why not
newtons here). The fixture carries the detection's ``timestamp`` (the camera frame's time),
so the haptic node judges the whole vision-to-motor age, and a tracker that stalls makes the
force stale (zero at the device). An object not found gives a fixture that pushes nothing.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from flowrt import Input, InputTrigger, Node, Output
from flowrt.freshness import own_timestamp

from .fixtures import Fixture

__all__ = ["VisionForce"]


class VisionForceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["wall", "spring"] = "wall"
    stiffness: float = Field(
        default=300.0, ge=0, le=100_000, allow_inf_nan=False, description="N/m"
    )
    damping: float = Field(default=0.0, ge=0, le=10_000, allow_inf_nan=False, description="N·s/m")
    axes: tuple[str, str] = Field(default=("x", "y"), description="device axes of image u, v")
    u_range: tuple[float, float] = Field(default=(-100.0, 100.0), description="mm at u=0, u=w")
    v_range: tuple[float, float] = Field(default=(100.0, -100.0), description="mm at v=0, v=h")
    image_size: tuple[int, int] = Field(default=(320, 240), description="when not in detection")
    normal: tuple[float, float] = Field(default=(-1.0, 0.0), description="the wall's free side")

    @field_validator("u_range", "v_range")
    @classmethod
    def _span(cls, v: tuple[float, float]) -> Any:
        # equal ends put the wall at one place whatever the camera sees; NaN reached the loop
        if not all(math.isfinite(x) for x in v) or v[0] == v[1]:
            raise ValueError("a finite range [mm at one edge, mm at the other] of two values")
        return v

    @field_validator("image_size")
    @classmethod
    def _size(cls, v: tuple[int, int]) -> Any:
        if min(v) < 1:  # pixels are divided by it
            raise ValueError("[width, height] in pixels, each at least 1")
        return v

    @field_validator("normal")
    @classmethod
    def _unit(cls, v: tuple[float, float]) -> Any:
        if not all(math.isfinite(x) for x in v) or math.hypot(*v) == 0:
            raise ValueError("normal: a finite, non-zero vector")
        n = math.hypot(*v)
        return (v[0] / n, v[1] / n)


class VisionForce(Node):
    """Turns a tracked object into a wall or spring for the haptic loop (module doc)."""

    Params = VisionForceParams
    detection = Input(object, policy="latest", doc="a tracker's detection")
    force = Output(Fixture, doc="the wall or spring, stamped with the camera frame's time")

    @classmethod
    def default_trigger(cls, params: Any) -> InputTrigger:
        return InputTrigger(input="detection")

    def setup(self) -> None:
        self.found = 0
        self.missed = 0

    def process(self, detection: Any = None) -> Fixture | None:
        if detection is None:
            return None
        p = self.params
        stamp = own_timestamp(detection)
        if stamp is None:
            stamp = self.ctx.input_time("detection") or self.ctx.now()
        centroid: Any = getattr(detection, "centroid", None)
        found = bool(getattr(detection, "found", False)) and centroid is not None
        anchor: tuple[float, ...] = (0.0, 0.0)
        if found:
            self.found += 1
            size = getattr(detection, "size", None) or p.image_size
            anchor = tuple(
                lo + (hi - lo) * float(pix) / max(1, n)
                for pix, n, (lo, hi) in zip(centroid, size, (p.u_range, p.v_range), strict=True)
            )
        else:
            self.missed += 1
        return Fixture(p.mode, p.axes, anchor, p.normal, p.stiffness, p.damping, found, stamp)

    def report(self) -> dict[str, Any]:
        """What the statistics show (``reports``): detections with and without the object."""
        return {"found": self.found, "missed": self.missed}
