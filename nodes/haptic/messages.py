"""What the haptic nodes publish: typed, JSON-recordable messages (one field per concept).

Each carries ``axes`` (its axis names) so that a reader, a recording or the live view needs
no side channel to know what ``values[i]`` means, and ``timestamp`` (runtime clock, seconds):
for a force, the time the measurement it comes from was taken (a camera frame's), so its age
at the device is the whole vision-to-motor latency.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Buttons", "Force", "HandleState", "Target"]


@dataclass(frozen=True)
class HandleState:
    """The handle in device space: ``position`` (mm) and ``velocity`` (mm/s) per axis."""

    axes: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    timestamp: float

    def get(self, axis: str) -> float:
        return self.position[self.axes.index(axis)]


@dataclass(frozen=True)
class Target:
    """The actuators' set-point (actuator units) after scaling, locks and the follow mode;
    ``locked`` names the axes held still at this tick."""

    axes: tuple[str, ...]
    values: tuple[float, ...]
    timestamp: float
    locked: tuple[str, ...] = ()


@dataclass(frozen=True)
class Force:
    """A force per axis (newtons). From a sensor or a vision node on the ``force`` input;
    on the ``applied`` output, what the device was given, with ``reason`` saying why it is
    zero or held back ("" = as asked; ``stale``, ``invalid``, ``device-error``, ``no-force``,
    ``disabled``, ``clamped``, ``rate-limited``)."""

    axes: tuple[str, ...]
    values: tuple[float, ...]
    timestamp: float
    reason: str = ""


@dataclass(frozen=True)
class Buttons:
    """Published when a button changes: every button's state, and what changed this tick
    (``pressed``/``released`` names: the click events)."""

    held: dict[str, bool] = field(default_factory=dict)
    pressed: tuple[str, ...] = ()
    released: tuple[str, ...] = ()
    timestamp: float = 0.0
