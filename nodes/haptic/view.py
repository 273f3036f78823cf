"""The ``haptic_view`` kind: the handle, the target and the force drawn for the live view.

A 1 kHz loop cannot draw: this node samples the newest values at its own rate (default
30 fps) and draws a top view (device x to the right, y up) of the workspace: the handle
(green disc), the actuators' target (a cross, mapped back from actuator space onto the
workspace), the applied force (a red arrow from the handle, ``px_per_newton``), and the
vision node's wall (a line) or spring point. Connect its ``view`` output to a ``display``.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from flowrt import Frame, Input, Node, Output, TimerTrigger

from .follow import scale

__all__ = ["HapticView"]


class HapticViewParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    fps: float = Field(default=30.0, gt=0, le=120)
    size: int = Field(default=320, ge=64, le=2048, description="pixels (square)")
    workspace: tuple[tuple[float, float], tuple[float, float]] = Field(
        default=((-100.0, 100.0), (-100.0, 100.0)), description="x, y ranges drawn (mm)"
    )
    actuator: tuple[tuple[float, float], tuple[float, float]] | None = Field(
        default=None, description="the haptic node's actuator x, y ranges (default workspace)"
    )
    px_per_newton: float = Field(default=30.0, gt=0, le=10_000)

    @field_validator("workspace", "actuator")
    @classmethod
    def _spans(cls, v: Any) -> Any:
        # each range is divided by its width: equal ends were a ZeroDivisionError per frame
        for lo, hi in v or ():
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
                raise ValueError("x, y ranges [lo, hi], finite, with lo != hi")
        return v


class HapticView(Node):
    """Draws handle, target, force and the vision wall for the live view (module doc)."""

    Params = HapticViewParams
    position = Input(object, required=False, policy="latest", doc="haptic.position")
    target = Input(object, required=False, policy="latest", doc="haptic.target")
    applied = Input(object, required=False, policy="latest", doc="haptic.applied")
    fixture = Input(object, required=False, policy="latest", doc="vision_force.force")
    view = Output(Frame, doc="the picture")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.fps)

    def _px(self, x: float, y: float) -> tuple[int, int]:
        (x0, x1), (y0, y1) = self.params.workspace
        s = self.params.size - 1
        return round((x - x0) / (x1 - x0) * s), round((y1 - y) / (y1 - y0) * s)

    def setup(self) -> None:
        """Draw once: OpenCV's first text and arrow take ~20 ms (its fonts and tables), which
        on the loop would be 20 missed haptic ticks at the first frame."""
        img = np.zeros((self.params.size, self.params.size, 3), np.uint8)
        self._draw(img, None, None, None, None)
        cv2.putText(img, "0.00 N", (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1)
        cv2.arrowedLine(img, (10, 10), (30, 30), (0, 0, 255), 2, tipLength=0.3)

    def process(
        self, position: Any = None, target: Any = None, applied: Any = None, fixture: Any = None
    ) -> Frame:
        p = self.params
        frame = self.ctx.new_frame((p.size, p.size, 3))
        self._draw(frame.data, position, target, applied, fixture)
        return frame

    def _draw(
        self, img: np.ndarray, position: Any, target: Any, applied: Any, fixture: Any
    ) -> None:
        p = self.params
        img[:] = (40, 40, 40)
        if fixture is not None and getattr(fixture, "found", False):
            ax, ay = fixture.anchor[0], fixture.anchor[1]
            if fixture.mode == "wall":
                nx, ny = fixture.normal[0], fixture.normal[1]
                far = 1e4
                a = self._px(ax - ny * far, ay + nx * far)
                b = self._px(ax + ny * far, ay - nx * far)
                cv2.line(img, a, b, (0, 200, 255), 2)
            else:
                cv2.circle(img, self._px(ax, ay), 6, (0, 200, 255), 2)
        if target is not None:
            tx, ty = target.values[0], target.values[1]
            if p.actuator is not None:
                tx = scale(tx, p.actuator[0], p.workspace[0])
                ty = scale(ty, p.actuator[1], p.workspace[1])
            cx, cy = self._px(tx, ty)
            cv2.drawMarker(img, (cx, cy), (255, 200, 0), cv2.MARKER_CROSS, 14, 2)
        if position is not None:
            hx, hy = position.position[0], position.position[1]
            centre = self._px(hx, hy)
            cv2.circle(img, centre, 7, (0, 220, 0), -1)
            if applied is not None:
                fx, fy = applied.values[0], applied.values[1]
                tip = (
                    int(centre[0] + fx * p.px_per_newton),
                    int(centre[1] - fy * p.px_per_newton),
                )
                if tip != centre:
                    cv2.arrowedLine(img, centre, tip, (0, 0, 255), 2, tipLength=0.3)
        if applied is not None:
            mag = float(np.hypot(*applied.values[:2]))
            text = f"{mag:.2f} N {applied.reason}"
            cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1)
