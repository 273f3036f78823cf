"""The ``haptic`` kind: a force-feedback handle in a fast loop, safe whatever its force input.

::

    haptic:
      kind: haptic
      params:
        device: sim                    # or evdev:/dev/input/event5, or package.module:Class
        rate_hz: 1000                  # the force loop (default trigger: a 1 ms timer)
        max_force: 2.0                 # N, the vector's magnitude (the device's own is lower?
                                       # then that one)
        max_rate: 100.0                # N/s
        timeout: 100ms                 # a force older than this is stale: zero
        actuator: {x: [0.0, 0.2], y: [0.0, 0.2], z: [0.0, 0.05]}   # device range -> this
        lock: [z]                      # axes whose target never moves (also the lock input)
        follow: trajectory             # or last_point
        max_speed: 0.05                # actuator units per second
      inputs:
        force: {from: wall.force, policy: latest}
        lock: {from: panel.lock, policy: latest}

Each activation reads the device once, publishes ``position`` (device space, mm),
``target`` (actuator space) and ``applied`` (the force given to the device, N), applies that
force, and publishes ``buttons`` when a button changed (the click events). The force input is
read from a ``latest`` edge: the loop never waits for vision, it takes the newest force there
is and judges its age on publication time like the arbiter (the older of the edge's stamp and
the force's own ``timestamp``; see README, "Safety rules of the driving nodes").

Safety (:mod:`flowrt.nodes.haptic.safety`): the force is zero when none was received, when it
is older than ``timeout``, when it is NaN/inf/of the wrong type (refused, counted, one
``HealthAlert`` per burst), when the device reports an error or fails (it is closed and
reopened with backoff; the node is in an error state meanwhile) and at stop (``teardown``
applies zero before closing). Otherwise it is clamped to ``max_force`` and its change per
tick limited to ``max_rate``.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import replace
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from flowrt import FatalError, Input, Node, Output, TimerTrigger, parse_duration_ms
from flowrt.refusals import Refusals

from .device import DeviceError, DeviceInfo, DeviceState, HapticDevice
from .devices import make_device
from .evdev_device import EvdevParams
from .fixtures import Fixture, fixture_force
from .follow import Follower, scale
from .messages import Buttons, Force, HandleState, Target
from .safety import ForceLimiter, parse_force
from .sim import AXES, SimParams

__all__ = ["Haptic", "HapticParams"]


def _seconds(v: Any) -> float:
    ms = parse_duration_ms(v)
    if ms <= 0 or ms > 60_000:
        raise ValueError("must be a duration between 0 and 60 s, e.g. 100ms")
    return ms / 1000


class HapticParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    device: str = Field(default="sim", description="sim, evdev:PATH|NAME, or module:Class")
    rate_hz: float = Field(default=1000.0, gt=0, le=10_000, allow_inf_nan=False)
    sim: SimParams = Field(default_factory=SimParams, description="the sim device's params")
    evdev: EvdevParams = Field(default_factory=EvdevParams, description="evdev device params")
    device_options: dict[str, Any] = Field(
        default_factory=dict, description="keyword arguments of a module:Class device"
    )
    max_force: float = Field(
        default=2.0, gt=0, le=100, allow_inf_nan=False, description="N (vector magnitude)"
    )
    max_rate: float = Field(default=100.0, gt=0, le=100_000, allow_inf_nan=False, description="N/s")
    timeout: float = Field(default=0.1, description="a force older than this is stale")
    reopen: float = Field(default=0.5, description="wait before reopening a failed device")
    actuator: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="axis -> actuator range (default: device range)"
    )
    lock: list[str] = Field(default_factory=list, description="axes whose target holds")
    follow: Literal["trajectory", "last_point"] = "last_point"
    max_speed: float | None = Field(
        default=None, gt=0, allow_inf_nan=False, description="actuator units/s (None: at once)"
    )
    path_points: int = Field(default=10_000, ge=1, le=1_000_000)
    enable_button: str | None = Field(
        default=None, description="force only while this device button is held (a deadman)"
    )

    @field_validator("timeout", "reopen", mode="before")
    @classmethod
    def _duration(cls, v: Any) -> Any:
        return _seconds(v)

    @field_validator("actuator")
    @classmethod
    def _ranges(cls, v: dict[str, tuple[float, float]]) -> Any:
        for axis, (lo, hi) in v.items():
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
                raise ValueError(f"actuator.{axis}: a finite range [lo, hi] with lo != hi")
        return v

    @field_validator("device")
    @classmethod
    def _device(cls, v: str) -> str:
        kind, _, rest = v.partition(":")
        if v != "sim" and not rest:
            raise ValueError(f"unknown device {v!r}: sim, evdev:PATH, evdev:NAME or module:Class")
        if v != "sim" and kind != "evdev":
            # a misspelt module was a failed run, not a graph error; its top-level package
            # is looked up without running any of its code (the module runs when the node
            # starts)
            top = kind.split(".")[0]
            if not top.isidentifier() or not _findable(top):
                raise ValueError(f"device {v!r}: no module named {top!r}")
        return v

    @field_validator("actuator", "lock")
    @classmethod
    def _sim_axes(cls, v: Any, info: ValidationInfo) -> Any:
        # the sim's axes are known now: a misspelt axis is a graph error, not a failed run
        unknown = sorted(set(v) - set(AXES)) if info.data.get("device") == "sim" else []
        if unknown:
            raise ValueError(f"{', '.join(unknown)}: not an axis of the sim device (x, y, z)")
        return v


class Haptic(Node):
    """A force-feedback device in a fast loop: position in, safe force out (module doc)."""

    Params = HapticParams
    # disabled or slowed over the control endpoint, the device kept its last force (1.5 N
    # for a whole second, the force input stale): its timing is the graph file's
    timing_fixed = True
    force = Input(
        object,
        required=False,
        policy="latest",
        doc="N per axis (a Force, a list, {axis: N}) or a Fixture; stale/invalid -> zero",
    )
    lock = Input(
        object,
        required=False,
        policy="latest",
        doc="axes to lock: a list of names, {axis: bool}, or a bool (all); latched",
    )
    position = Output(HandleState, doc="the handle in device space (mm, mm/s)")
    target = Output(Target, doc="actuator set-point after scaling, locks and follow mode")
    applied = Output(Force, doc="the force sent to the device (N) and why it is zero")
    buttons = Output(Buttons, doc="on a button change: every button's state and the clicks")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate_hz)

    def setup(self) -> None:
        p = self.params
        options: Any = {"sim": p.sim.model_dump(), "evdev": p.evdev.model_dump()}
        kind = "sim" if p.device == "sim" else p.device.partition(":")[0]
        self.info: DeviceInfo | None = None  # before the device: teardown runs if it fails
        try:
            self.device: HapticDevice = make_device(p.device, options.get(kind, p.device_options))
        except (ValueError, TypeError) as e:
            raise FatalError(str(e)) from None
        self.reopen_at = 0.0
        self.reopens = 0
        self.device_errors = 0
        self.stale = 0
        self.refused = Refusals("haptic-invalid", "force refused: NaN, inf or not a force")
        self.lock_refused = Refusals("haptic-invalid-lock", "lock refused: all axes locked")
        self.last_t: float | None = None
        self.flagged: str | None = None  # the reason of the error state the node is in
        self.held: dict[str, bool] = {}
        self.ages = _AgeHistogram()  # force age at the device, every tick since the start
        self._open(self.ctx.now())

    # --- the device -----------------------------------------------------------------------

    def _open(self, now: float) -> None:
        try:
            info = self.device.open()
        except (DeviceError, OSError) as e:
            self._failed(now, f"cannot open {self.params.device}: {e}")
            return
        self._opened(info)

    def _opened(self, info: DeviceInfo) -> None:
        p = self.params
        self.info = info
        self.axes = info.axes
        self.held = {b: False for b in info.buttons} | self.held  # a reopen keeps the held
        n = len(info.axes)
        unknown = sorted((set(p.actuator) | set(p.lock)) - set(info.axes))
        if unknown:
            raise FatalError(f"axes {unknown} are not the device's {list(info.axes)}")
        if p.enable_button is not None and p.enable_button not in info.buttons:
            # a deadman that cannot be held: the force would be zero for ever, unexplained
            raise FatalError(
                f"enable_button {p.enable_button!r} is not a button of the device "
                f"({', '.join(info.buttons) or 'it has none'})"
            )
        limit = p.max_force if info.max_force is None else min(p.max_force, info.max_force)
        self.has_force = info.max_force is not None
        old = getattr(self, "limiter", None)
        self.limiter = ForceLimiter(n, limit, p.max_rate, 2.0 / p.rate_hz)
        if old is not None:
            self.limiter.clamped, self.limiter.limited = old.clamped, old.limited
        self.ranges = [
            (info.workspace[i], tuple(p.actuator.get(a, info.workspace[i])))
            for i, a in enumerate(info.axes)
        ]
        path = getattr(self, "follower", None)
        self.follower = Follower(n, p.follow, p.max_speed, p.path_points)
        if path is not None:  # a reopened device: the actuators are where they were
            self.follower.target, self.follower.dropped = path.target, path.dropped
        self._flag(None)

    def _failed(self, now: float, reason: str) -> None:
        with contextlib.suppress(Exception):
            self.device.apply_force((0.0,) * len(getattr(self, "axes", ())), now)
        with contextlib.suppress(Exception):
            self.device.close()
        self.info = None
        self.reopen_at = now + self.params.reopen
        self._flag(reason)

    def teardown(self) -> None:
        """Zero force, then close: a handle left pushing would move the operator's hand."""
        if getattr(self, "info", None) is None:
            return  # never opened (or its device never made): nothing to zero or close
        with contextlib.suppress(Exception):
            self.device.apply_force((0.0,) * len(self.axes), self.ctx.now())
        with contextlib.suppress(Exception):
            self.device.close()

    def on_disable(self) -> dict[str, Any] | None:
        """Disabled (a mode, ``Runtime.set_timing``): zero force now; a handle left with its
        last force pushed the operator's hand for as long as the node stayed disabled. The
        limiter starts from zero when the node runs again (its rate limit ramps it back).
        ``applied`` says so (``disabled``): its last value, the force before, read as
        what the device still had."""
        if getattr(self, "info", None) is None:
            return None  # not open: nothing pushes
        now = self.ctx.now()
        self.limiter.cut()
        try:
            self.device.apply_force(self.limiter.applied, now)
        except (DeviceError, OSError) as e:
            self._failed(now, f"device {self.params.device}: {e}")
            return {"applied": Force(self.axes, self.limiter.applied, now, "device-error")}
        return {"applied": Force(self.axes, self.limiter.applied, now, "disabled")}

    # --- one tick -------------------------------------------------------------------------

    def process(self, force: Any = None, lock: Any = None) -> dict[str, Any] | None:
        now = self.ctx.now()
        # The first tick is one period after a zero force that held for ever.
        dt = 1.0 / self.params.rate_hz if self.last_t is None else max(0.0, now - self.last_t)
        self.last_t = now
        if self.info is None:
            if now < self.reopen_at:
                return None
            self.reopens += 1
            self._open(now)
            if self.info is None:
                return None
        try:
            state = self.device.read_state(now)
            garbled = not all(math.isfinite(x) for x in (*state.position, *state.velocity))
            if garbled:
                state = replace(state, error=f"non-finite position {state.position}")
            applied, reason = self._force(force, state, dt)
            self.device.apply_force(applied, now)
        except (DeviceError, OSError) as e:
            self._failed(now, f"device {self.params.device}: {e}")
            return {"applied": Force(self.axes, self.limiter.cut(), now, "device-error")}
        self._flag(None if state.error is None else f"device reports: {state.error}")
        if garbled:
            return {"applied": Force(self.axes, applied, now, reason)}  # no NaN target
        locked = self._locks(lock)
        point = [  # a handle past its reported range must not take the actuators past theirs
            min(max(scale(x, dev, act), min(act)), max(act))
            for x, (dev, act) in zip(state.position, self.ranges, strict=False)
        ]
        target = self.follower.update(point, locked, dt)
        out: dict[str, Any] = {
            "position": HandleState(self.axes, tuple(state.position), tuple(state.velocity), now),
            "target": Target(
                self.axes,
                tuple(target),
                now,
                tuple(a for a, lk in zip(self.axes, locked, strict=True) if lk),
            ),
            "applied": Force(self.axes, applied, now, reason),
        }
        if state.buttons != self.held:
            out["buttons"] = self._buttons(dict(state.buttons), now)
        return out

    def _flag(self, reason: str | None) -> None:
        """Enter or leave the node's error state when the device's condition changes (an
        episode counts once in ``device_errors``; the force is zero on each of its ticks)."""
        if reason == self.flagged:
            return
        if reason is None:
            with contextlib.suppress(RuntimeError):
                self.ctx.clear_error()
        else:
            self.device_errors += 1
            self.ctx.set_error(reason)
        self.flagged = reason

    def _force(self, force: Any, state: DeviceState, dt: float) -> tuple[tuple[float, ...], str]:
        if state.error is not None:
            return self.limiter.cut(), "device-error"
        if self.params.enable_button and not state.buttons.get(self.params.enable_button):
            return self.limiter.cut(), "disabled"
        if not self.has_force:
            return self.limiter.cut(), "no-force"
        if force is None:
            return self.limiter.cut(), "no-force"
        age = self.ctx.input_age("force", force)
        if age is None or age > self.params.timeout:
            self.stale += 1
            return self.limiter.cut(), "stale"
        if isinstance(force, Fixture):  # a wall from vision: rendered here, at the loop's rate
            wanted = fixture_force(force, self.axes, state.position, state.velocity)
        else:
            wanted = parse_force(force, self.axes)
        if wanted is None or not all(math.isfinite(f) for f in wanted):  # inf from a huge wall
            self.refused.refuse(self.ctx, self.ctx.input_time("force"))
            return self.limiter.cut(), "invalid"
        self.refused.accept()
        self.ages.add(age)
        clamped, limited = self.limiter.clamped, self.limiter.limited
        applied = self.limiter.step(wanted, dt)
        if self.limiter.clamped != clamped:
            return applied, "clamped"
        return applied, "rate-limited" if self.limiter.limited != limited else ""

    def _locks(self, value: Any) -> list[bool]:
        named = set(self.params.lock)
        if value is not None:
            extra = _lock_axes(value, self.axes)
            if extra is None:
                self.lock_refused.refuse(self.ctx, self.ctx.input_time("lock"))
                extra = set(self.axes)  # an unreadable lock: the safe side, hold everything
            else:
                self.lock_refused.accept()
            named |= extra
        return [a in named for a in self.axes]

    def _buttons(self, now_held: dict[str, bool], now: float) -> Buttons:
        before = self.held
        pressed = tuple(b for b, v in now_held.items() if v and not before.get(b, False))
        released = tuple(b for b, v in before.items() if v and not now_held.get(b, False))
        self.held = now_held
        return Buttons(dict(now_held), pressed, released, now)

    def report(self) -> dict[str, Any]:
        """What the statistics show of the haptic loop (``reports``: table, --stats-json)."""
        return {
            "device": self.params.device,
            "open": self.info is not None,
            "applied": list(self.limiter.applied) if hasattr(self, "limiter") else [],
            "invalid": self.refused.count,
            "invalid_locks": self.lock_refused.count,
            "stale": self.stale,
            "device_errors": self.device_errors,
            "reopens": self.reopens,
            "clamped": self.limiter.clamped if hasattr(self, "limiter") else 0,
            "rate_limited": self.limiter.limited if hasattr(self, "limiter") else 0,
            "path_dropped": self.follower.dropped if hasattr(self, "follower") else 0,
            "force_age_ms": self.ages.summary(),
        }


class _AgeHistogram:
    """Ages in 0.25 ms bins up to 1 s: O(1) per tick, and a report (the status table asks
    several times a second) that scans 4000 bins instead of sorting every tick's age, which
    would be a millisecond taken from the loop."""

    BIN = 0.00025
    BINS = 4000

    def __init__(self) -> None:
        self.counts = [0] * (self.BINS + 1)  # the last bin: 1 s and older
        self.n = 0
        self.max = 0.0

    def add(self, age: float) -> None:
        self.counts[min(self.BINS, max(0, int(age / self.BIN)))] += 1
        self.n += 1
        self.max = max(self.max, age)

    def summary(self) -> dict[str, float | None]:
        """p50, p99 (bin upper edges, ms) and max (exact, ms); None before the first force."""
        if self.n == 0:
            return {"p50": None, "p99": None, "max": None}
        out: dict[str, float | None] = {}
        seen = 0
        wanted = [("p50", 0.5 * self.n), ("p99", 0.99 * self.n)]
        for i, c in enumerate(self.counts):
            seen += c
            while wanted and seen >= wanted[0][1]:
                out[wanted.pop(0)[0]] = round(min((i + 1) * self.BIN, self.max) * 1e3, 3)
            if not wanted:
                break
        out["max"] = round(self.max * 1e3, 3)
        return out


def _lock_axes(value: Any, axes: tuple[str, ...]) -> set[str] | None:
    """The axes a ``lock`` input value locks, or None when it is not a lock value."""
    if isinstance(value, bool):
        return set(axes) if value else set()
    if isinstance(value, str):
        return {value} if value in axes else None
    if isinstance(value, dict):
        if not all(k in axes and isinstance(v, bool) for k, v in value.items()):
            return None
        return {k for k, v in value.items() if v}
    if isinstance(value, list | tuple | set | frozenset):
        if not all(isinstance(a, str) and a in axes for a in value):
            return None
        return set(value)
    return None


def _findable(top: str) -> bool:
    """A top-level module imported already (``__main__``: a program's own device class) or
    one Python can find, without running any of its code."""
    import importlib.util
    import sys

    if top in sys.modules:
        return True
    try:
        return importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        return False
