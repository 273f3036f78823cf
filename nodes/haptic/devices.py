"""Which device a ``device:`` spec names: the simulated handle, an evdev device, or a class of
the user's own (``package.module:Class``). Apart from :mod:`.device` (the protocol), which the
devices themselves import, so that no module of this package imports one that imports it.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from .device import HapticDevice

__all__ = ["make_device"]


def make_device(spec: str, options: Mapping[str, Any]) -> HapticDevice:
    """The device ``spec`` names (see the module docstring), not yet opened.

    ``options`` are the params of that device (``sim:``, ``evdev:`` or ``device_options``).
    A dotted path that does not import, or names no class, raises ``ValueError``.
    """
    kind, _, rest = spec.partition(":")
    if spec == "sim":
        from .sim import SimDevice, SimParams

        return SimDevice(SimParams.model_validate(dict(options)))
    if kind == "evdev" and rest:
        from .evdev_device import EvdevDevice, EvdevParams

        return EvdevDevice(rest, EvdevParams.model_validate(dict(options)))
    module, _, name = spec.partition(":")
    if not module or not name:
        raise ValueError(f"device {spec!r}: sim, evdev:PATH or package.module:Class")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"device {spec!r}: {e}") from None
    device = cls(**options)
    if not isinstance(device, HapticDevice):
        raise ValueError(f"device {spec!r}: no open/read_state/apply_force/close")
    return device
