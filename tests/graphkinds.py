"""Typed node kinds for the graph-file tests, referenced as ``graphkinds:Class``.

The built-in kinds carry ``int`` and ``object``; these add a frame source and a frame reader,
so that port-type and frame-trigger checks have something to check.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from flowrt import Frame, Input, Node, Output, TimerTrigger


class FrameSource(Node):
    """A tiny synthetic camera: a grey frame every ``period_ms`` (its default trigger)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        period_ms: float = 10.0
        size: tuple[int, int] = (8, 6)

    frame = Output(Frame)

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=params.period_ms)

    def setup(self) -> None:
        self.seq = 0

    def process(self) -> Frame:
        w, h = self.params.size
        self.seq += 1
        return Frame(
            np.full((h, w, 3), self.seq % 256, np.uint8), source=self.ctx.name, seq=self.seq
        )


class FrameReader(Node):
    """Reads a frame and outputs its mean brightness."""

    frame = Input(Frame)
    mean = Output(float)

    def process(self, frame: Frame) -> float:
        return float(frame.data.mean())


class Scale(Node):
    """A user's node as the README writes one: ``Params`` without a ``model_config``."""

    class Params(BaseModel):
        factor: float = 2.0

    value = Input(int)
    scaled = Output(float)

    def process(self, value: int) -> float:
        return value * self.params.factor
