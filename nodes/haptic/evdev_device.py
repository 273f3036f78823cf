"""``evdev:PATH``: a Linux input device with force feedback (a joystick, a wheel).

Untested on hardware: tests/test_haptic_devices.py drives it against a fake device object
with python-evdev's own codes and force-feedback structures; a real device may need other
axis codes (``axes``), another level scale (``max_force``) or a different direction
convention, and its motors are far weaker and slower than a haptic arm's.

Absolute axes (``axes``: name -> ``ABS_*`` code) give the position: the range the device
reports for each (``absinfo``) is mapped onto ``[-travel/2, travel/2]`` mm, so the node's
device space is millimetres whatever the device; velocity is the difference of two reads.
Keys (``EV_KEY``) are the buttons. The force is rendered by one effect, uploaded once and
updated in place when it changes:

- ``effect: constant`` (``FF_CONSTANT``): the force vector's x/y as a direction and a level,
  full level (0x7fff) = ``max_force`` newtons;
- ``effect: spring`` (``FF_SPRING``): the device's own spring, centred where the asked
  force would vanish (position + force / ``stiffness``), so the device renders the
  stiffness at its own rate between two updates.

``evdev:NAME`` (no leading ``/``) opens the first device whose name contains NAME.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .device import DeviceError, DeviceInfo, DeviceState

__all__ = ["EvdevDevice", "EvdevParams"]

LEVEL = 0x7FFF


class EvdevParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    axes: dict[str, str | int] = Field(
        default_factory=lambda: dict[str, str | int](x="ABS_X", y="ABS_Y"),
        description="axis name -> ABS_* code (name or number)",
    )
    travel: float = Field(default=100.0, gt=0, le=10_000, description="mm the full range is")
    effect: Literal["constant", "spring"] = "constant"
    max_force: float = Field(default=2.0, gt=0, le=1_000, description="N at full level")
    stiffness: float = Field(default=200.0, gt=0, le=100_000, description="spring N/m")


def _code(ecodes: Any, v: str | int) -> int:
    if isinstance(v, int):
        return v
    code = getattr(ecodes, v, None)
    if not isinstance(code, int):
        raise DeviceError(f"unknown axis code {v!r}")
    return code


class EvdevDevice:
    """A force-feedback input device through python-evdev; implements ``HapticDevice``.

    ``opener`` builds the ``evdev.InputDevice`` (tests pass a fake)."""

    def __init__(
        self,
        path: str,
        params: EvdevParams | None = None,
        opener: Callable[[str], Any] | None = None,
    ) -> None:
        self.path = path
        self.p = params or EvdevParams()
        self.opener = opener
        self.dev: Any = None
        self.effect_id: int | None = None
        self.sent: tuple[int, ...] | None = None  # what the effect holds now (no re-upload)
        self.uploads = 0

    def open(self) -> DeviceInfo:
        try:
            import evdev
        except ImportError:
            raise DeviceError("the evdev package is not installed (pip install evdev)") from None
        ec = evdev.ecodes
        self.ec, self.ff = ec, evdev.ff
        opener = self.opener or evdev.InputDevice
        path = self.path
        try:
            if not path.startswith("/"):
                found = [p for p in evdev.list_devices() if path in opener(p).name]
                if not found:
                    raise DeviceError(f"no input device named like {path!r}")
                path = found[0]
            self.dev = opener(path)
            caps = self.dev.capabilities(absinfo=True)
        except OSError as e:
            raise DeviceError(f"cannot open {path}: {e.strerror or e}") from None
        absinfo = dict(caps.get(ec.EV_ABS, []))
        self.codes: list[int] = []
        self.lo: list[float] = []
        self.hi: list[float] = []
        for name, spec in self.p.axes.items():
            code = _code(ec, spec)
            if code not in absinfo:
                raise DeviceError(f"{path} has no axis {spec} (for {name})")
            info = absinfo[code]
            self.codes.append(code)
            self.lo.append(float(info.min))
            self.hi.append(float(info.max))
        self.raw = [(lo + hi) / 2 for lo, hi in zip(self.lo, self.hi, strict=True)]
        self.keys = {code: _key_name(ec, code) for code in caps.get(ec.EV_KEY, [])}
        self.buttons = {name: False for name in self.keys.values()}
        wanted = ec.FF_CONSTANT if self.p.effect == "constant" else ec.FF_SPRING
        has_ff = wanted in caps.get(ec.EV_FF, [])
        self.last: tuple[float, list[float]] | None = None
        self.velocity = [0.0] * len(self.codes)
        half = self.p.travel / 2
        return DeviceInfo(
            tuple(self.p.axes),
            tuple((-half, half) for _ in self.codes),
            self.p.max_force if has_ff else None,
            tuple(sorted(self.buttons)),
        )

    def _mm(self, i: int) -> float:
        lo, hi = self.lo[i], self.hi[i]
        return 0.0 if hi == lo else ((self.raw[i] - lo) / (hi - lo) - 0.5) * self.p.travel

    def read_state(self, now: float) -> DeviceState:
        if self.dev is None:
            raise DeviceError("not open")
        ec = self.ec
        try:
            while (event := self.dev.read_one()) is not None:
                if event.type == ec.EV_ABS and event.code in self.codes:
                    self.raw[self.codes.index(event.code)] = float(event.value)
                elif event.type == ec.EV_KEY and event.code in self.keys:
                    self.buttons[self.keys[event.code]] = event.value != 0
        except OSError as e:  # unplugged: ENODEV
            raise DeviceError(f"read: {e.strerror or e}") from None
        pos = [self._mm(i) for i in range(len(self.codes))]
        if self.last is not None and now > self.last[0]:
            dt = now - self.last[0]
            self.velocity = [(a - b) / dt for a, b in zip(pos, self.last[1], strict=True)]
        self.last = (now, pos)
        return DeviceState(tuple(pos), tuple(self.velocity), dict(self.buttons))

    def apply_force(self, force: Sequence[float], now: float) -> None:
        if self.dev is None:
            raise DeviceError("not open")
        fx = float(force[0]) if len(force) > 0 else 0.0
        fy = float(force[1]) if len(force) > 1 else 0.0
        effect = self._constant(fx, fy) if self.p.effect == "constant" else self._spring(fx, fy)
        key = _key_of(effect, self.ec.FF_CONSTANT)
        if key == self.sent:
            return
        try:
            if self.effect_id is not None:
                effect.id = self.effect_id  # update in place: no gap in the force
            self.effect_id = self.dev.upload_effect(effect)
            if self.sent is None:
                self.dev.write(self.ec.EV_FF, self.effect_id, 1)  # play (length 0: for ever)
        except OSError as e:
            raise DeviceError(f"force: {e.strerror or e}") from None
        self.sent = key
        self.uploads += 1

    def close(self) -> None:
        if self.dev is None:
            return
        with contextlib.suppress(OSError):
            if self.effect_id is not None:
                self.dev.write(self.ec.EV_FF, self.effect_id, 0)
                self.dev.erase_effect(self.effect_id)
        with contextlib.suppress(OSError):
            self.dev.close()
        self.dev, self.effect_id, self.sent = None, None, None

    # --- effects --------------------------------------------------------------------------

    def _constant(self, fx: float, fy: float) -> Any:
        """Linux directions: 0 = down (+y), 0x4000 = left (-x), 0x8000 = up, 0xC000 = right."""
        ff = self.ff
        mag = min(1.0, math.hypot(fx, fy) / self.p.max_force)
        angle = math.atan2(-fx, fy) % (2 * math.pi)
        direction = round(angle / (2 * math.pi) * 0x10000) & 0xFFFF
        level = round(mag * LEVEL)
        if level == 0:
            direction = 0
        return ff.Effect(
            self.ec.FF_CONSTANT,
            -1,
            direction,
            ff.Trigger(0, 0),
            ff.Replay(0, 0),
            ff.EffectType(ff_constant_effect=ff.Constant(level, ff.Envelope(0, 0, 0, 0))),
        )

    def _spring(self, fx: float, fy: float) -> Any:
        ff = self.ff
        conds = (ff.Condition * 2)()
        sat = 0xFFFF  # the device's own limit: max_force is applied by the node
        for i, f in enumerate((fx, fy)):
            if i >= len(self.codes):
                break
            offset_mm = f / self.p.stiffness * 1000  # where this force would vanish
            centre_mm = self._mm(i) + offset_mm
            centre = max(-LEVEL, min(LEVEL, round(centre_mm / (self.p.travel / 2) * LEVEL)))
            coeff = LEVEL if f != 0 else 0
            conds[i] = ff.Condition(sat, sat, coeff, coeff, 0, centre)
        return ff.Effect(
            self.ec.FF_SPRING,
            -1,
            0,
            ff.Trigger(0, 0),
            ff.Replay(0, 0),
            ff.EffectType(ff_condition_effect=conds),
        )


def _key_of(effect: Any, constant: int) -> tuple[int, ...]:
    """The effect's content as a tuple: unchanged content is not uploaded again."""
    u = effect.u
    if effect.type == constant:
        return (effect.type, effect.direction, u.ff_constant_effect.level)
    c = u.ff_condition_effect
    return (effect.type, *(x for i in range(2) for x in (c[i].right_coeff, c[i].center)))


def _key_name(ec: Any, code: int) -> str:
    name = ec.BTN.get(code) or ec.KEY.get(code) or str(code)
    if isinstance(name, list | tuple):  # aliases: the last is the specific one (BTN_TRIGGER)
        name = name[-1]
    return str(name).lower().removeprefix("btn_").removeprefix("key_")
