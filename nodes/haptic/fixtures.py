"""Virtual fixtures: a force given as a function of the handle's position, rendered in the loop.

Vision runs at 20-30 fps, the force loop at 1 kHz. A vision node that computed newtons would
compute them from a handle position one camera frame old, and the loop would hold each for
33 ms: a wall sampled that way pushes late and gains energy (it chatters, then throws the
hand). So the vision node publishes the wall itself (where it is, which way it faces, how
stiff it is) and the haptic node evaluates it against the handle on every tick: the wall
moves at camera rate, the force follows the hand at the loop's rate (the "intermediate
representation" of haptic rendering). The fixture's age (camera frame to motor) is judged
like any force's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from flowrt.refusals import finite_number

__all__ = ["Fixture", "fixture_force"]


@dataclass(frozen=True)
class Fixture:
    """A wall or a spring in device space, on ``axes`` (the others feel nothing).

    ``wall``: a plane through ``anchor`` (mm) with outward ``normal``: behind it by d metres
    the handle is pushed out with ``stiffness`` x d (N/m), plus ``damping`` (N·s/m) against
    its speed into the wall. ``spring``: a pull of ``stiffness`` x distance towards
    ``anchor``, minus ``damping`` x velocity. ``found`` False: nothing there, zero force.
    ``timestamp``: when the measurement was taken (a camera frame's time)."""

    mode: str
    axes: tuple[str, ...]
    anchor: tuple[float, ...]
    normal: tuple[float, ...]
    stiffness: float
    damping: float
    found: bool
    timestamp: float


def _valid(f: Fixture, device_axes: tuple[str, ...]) -> bool:
    n = len(f.axes)
    return (
        f.mode in ("wall", "spring")
        and all(isinstance(a, str) and a in device_axes for a in f.axes)
        and len(f.anchor) == n
        and len(f.normal) == n
        and all(finite_number(x) for x in (*f.anchor, *f.normal))
        and all(finite_number(x) and x >= 0 for x in (f.stiffness, f.damping))
    )


def fixture_force(
    f: Any, axes: tuple[str, ...], position: tuple[float, ...], velocity: tuple[float, ...]
) -> tuple[float, ...] | None:
    """The force (N per device axis) fixture ``f`` puts on a handle at ``position`` (mm)
    moving at ``velocity`` (mm/s); None when ``f`` is not a valid fixture (refused)."""
    if not isinstance(f, Fixture) or not _valid(f, axes):
        return None
    out = [0.0] * len(axes)
    if not f.found:
        return tuple(out)
    idx = [axes.index(a) for a in f.axes]
    if f.mode == "wall":
        norm = math.sqrt(sum(k * k for k in f.normal))
        if norm == 0:
            return None
        n = [k / norm for k in f.normal]
        depth = sum((a - position[i]) * k for a, i, k in zip(f.anchor, idx, n, strict=True))
        depth /= 1000  # mm -> m
        if depth <= 0:
            return tuple(out)
        v_in = -sum(velocity[i] * k for i, k in zip(idx, n, strict=True)) / 1000
        push = f.stiffness * depth + f.damping * max(0.0, v_in)
        for i, k in zip(idx, n, strict=True):
            out[i] = push * k
        return tuple(out)
    for a, i in zip(f.anchor, idx, strict=True):
        out[i] = (f.stiffness * (a - position[i]) - f.damping * velocity[i]) / 1000
    return tuple(out)
