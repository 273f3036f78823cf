"""Force feedback: the ``haptic`` kind, its devices, and forces computed from vision.

- :mod:`.device`: the device protocol (open, read state, apply force, close) and its factory;
- :mod:`.sim`, :mod:`.evdev_device`: the simulated handle and Linux force-feedback devices;
- :mod:`.fixtures`: walls and springs from vision, rendered in the loop;
- :mod:`.safety`: what force may reach the device (clamp, rate limit, cut to zero);
- :mod:`.follow`: device space to actuator space, axis locks, follow modes;
- :mod:`.node`: the ``haptic`` kind; :mod:`.vision`: the ``vision_force`` kind;
- :mod:`.view`: the ``haptic_view`` kind, the live view's picture of handle, target and force.
"""

from .device import DeviceError, DeviceInfo, DeviceState, HapticDevice
from .devices import make_device
from .fixtures import Fixture
from .messages import Buttons, Force, HandleState, Target
from .node import Haptic
from .sim import SimDevice
from .view import HapticView
from .vision import VisionForce

__all__ = [
    "Buttons",
    "DeviceError",
    "DeviceInfo",
    "DeviceState",
    "Fixture",
    "Force",
    "HandleState",
    "Haptic",
    "HapticDevice",
    "HapticView",
    "SimDevice",
    "Target",
    "VisionForce",
    "make_device",
]
