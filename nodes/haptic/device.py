"""The device protocol of the haptic node: open, read state, apply force, close.

A force-feedback device is a loop partner, not a message source: the node reads its handle
once per tick and writes one force per tick, so the protocol is four synchronous calls that
must each return in well under a tick (a blocking read would stall the 1 kHz loop). A
device that cannot keep that promise (a USB HID one with its own 1 kHz servo, an OpenHaptics
scheduler) keeps its own thread and answers from it; the node never waits.

Devices are named by ``device:`` in the node's params:

- ``sim``: :class:`flowrt.nodes.haptic.sim.SimDevice`, a simulated 3-DoF handle;
- ``evdev:PATH`` (or ``evdev:NAME``): :class:`flowrt.nodes.haptic.evdev_device.EvdevDevice`;
- ``package.module:Class``: any class implementing :class:`HapticDevice`, built with
  ``device_options`` as keyword arguments (a SpaceMouse through ``pyspacemouse``, an
  OpenHaptics binding), with no change to the node.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

__all__ = ["DeviceError", "DeviceInfo", "DeviceState", "HapticDevice"]


class DeviceError(Exception):
    """The device cannot be read or driven now (unplugged, a motor fault); the node zeroes
    the force, reports the reason and reopens the device with backoff."""


@dataclass(frozen=True)
class DeviceInfo:
    """What the node asks the device once it is open.

    ``workspace`` is the range of each axis in millimetres (device space): the node scales
    it linearly to actuator space. ``max_force`` (newtons) is the device's own limit, or
    None when it renders no force (an input-only device): the node never asks for more than
    the smaller of it and its own ``max_force``.
    """

    axes: tuple[str, ...]
    workspace: tuple[tuple[float, float], ...]
    max_force: float | None
    buttons: tuple[str, ...] = ()


@dataclass(frozen=True)
class DeviceState:
    """One reading: handle position (mm) and velocity (mm/s) per axis, buttons held, and
    ``error`` when the device itself reports a fault (the node zeroes the force then)."""

    position: tuple[float, ...]
    velocity: tuple[float, ...]
    buttons: Mapping[str, bool] = field(default_factory=dict)
    error: str | None = None


@runtime_checkable
class HapticDevice(Protocol):
    """A force-feedback (or input-only) device; every call must return within a tick.

    ``now`` is the runtime clock (seconds): a simulated device integrates its physics up to
    it, so a test on a virtual clock is exact and repeatable. Failures raise
    :class:`DeviceError` (or ``OSError``).
    """

    def open(self) -> DeviceInfo: ...

    def read_state(self, now: float) -> DeviceState: ...

    def apply_force(self, force: Sequence[float], now: float) -> None: ...

    def close(self) -> None: ...
