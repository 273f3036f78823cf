"""From the hand to the slow actuators: linear scaling, axis locks and the two follow modes.

The fibre-characterisation system's haptic chapter: the handle moves in millimetres within
the device's workspace and in a fraction of a second; the actuators (motorised stages) have
their own range and a top speed far below a hand's. So the handle position is scaled
linearly from device space to actuator space, any subset of axes can be locked (the target
holds its value on those axes), and the actuators follow quick hand moves in one of two ways:

- ``trajectory``: the actuators travel the hand's path, point by point, at ``max_speed``
  (the path is kept, at most ``path_points`` points; the oldest dropped are counted);
- ``last_point``: they head straight for the newest point at ``max_speed`` (the path the
  hand took in between is skipped).

Without ``max_speed`` both modes give the scaled point at once.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Literal

__all__ = ["Follower", "scale"]


def scale(x: float, device: tuple[float, float], actuator: tuple[float, float]) -> float:
    """``x`` (device units) mapped linearly from the ``device`` range onto ``actuator``'s."""
    d0, d1 = device
    a0, a1 = actuator
    return a0 + (x - d0) * (a1 - a0) / (d1 - d0)


class Follower:
    """The actuators' set-point, moved towards the hand tick by tick."""

    def __init__(
        self,
        n: int,
        mode: Literal["trajectory", "last_point"],
        max_speed: float | None,
        path_points: int,
    ) -> None:
        self.n = n
        self.mode = mode
        self.max_speed = max_speed
        self.path: deque[tuple[float, ...]] = deque()
        self.path_points = path_points
        self.dropped = 0  # path points dropped because the path was full
        self.target: list[float] | None = None

    def update(self, point: Sequence[float], locked: Sequence[bool], dt: float) -> list[float]:
        """The new set-point for the hand at ``point`` (actuator units); ``locked[i]``: axis
        ``i`` keeps its value. ``dt``: seconds since the last update."""
        if self.target is None:
            self.target = list(point)
            return list(self.target)
        target = self.target
        free = [not lk for lk in locked]
        wanted = tuple(p if f else t for p, f, t in zip(point, free, target, strict=True))
        if self.mode == "last_point" or self.max_speed is None:
            self.path.clear()
            self.path.append(wanted)
        elif not self.path or self.path[-1] != wanted:
            if len(self.path) >= self.path_points:
                self.path.popleft()
                self.dropped += 1
            self.path.append(wanted)
        budget = math.inf if self.max_speed is None else self.max_speed * max(dt, 0.0)
        while self.path and budget > 0:
            goal = self.path[0]
            delta = [(g - t) if f else 0.0 for g, t, f in zip(goal, target, free, strict=True)]
            dist = math.sqrt(sum(d * d for d in delta))
            if dist <= budget:
                for i in range(self.n):
                    if free[i]:
                        target[i] = goal[i]
                budget -= dist
                if len(self.path) > 1 or self.mode == "trajectory":
                    self.path.popleft()
                else:
                    break
            else:
                s = budget / dist
                for i in range(self.n):
                    target[i] += delta[i] * s
                budget = 0.0
        return list(target)
