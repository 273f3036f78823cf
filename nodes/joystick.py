"""A joystick source: a real game controller (Linux evdev), the live view's on-screen stick, or a
scripted CSV file.

::

    joy:
      kind: joystick
      params: {source: "evdev:/dev/input/event5", rate_hz: 50}   # or evdev:NAME (substring)
      # params: {source: web}                 # the live view's on-screen stick and keyboard
      # params: {source: "script:drive.csv"}  # time, then axes and buttons

Output ``output``: a :class:`JoyState` (``axes``: name -> float in [-1, 1], ``buttons``: name ->
bool, ``timestamp``: runtime clock) on every activation, at ``rate_hz`` (default 50 Hz), as
long as the device is there. A joystick reports only changes; publishing the current state at
a steady rate is what lets a consumer (``teleop``) tell a still stick from a lost link: when
the device disappears, nothing is published (so the consumer times out to zero), the node is
in an error state with the reason, and it is reopened with backoff (attempts counted in the
node's log and events).

``script:FILE`` (relative to the graph file's folder, or absolute): a CSV with a header row;
column ``time`` (seconds from the start) first, then one column per axis (``x`` or
``axis:x``) and per button (``button:a``). At each activation the newest row whose time has
come is published; after the last row ``end`` says what happens: ``hold`` (keep publishing
it), ``loop`` (start again once the last row has been held as long as the gap before it)
or ``silent`` (publish nothing: a lost link, for tests).

``web``: the live view (``display`` node) has a joystick panel: tick "drive from this page",
then drag the on-screen stick (axes ``x``, ``y``), or use the keyboard (arrows or WASD for the
axes; Enter = ``start``, Escape = ``stop``, space = ``a``, b = ``b``, Shift = ``deadman``), or
the panel's buttons. The page sends its state at 20 Hz over its WebSocket (guarded like the
view: Host, Origin, and the view's token off loopback) and the display writes it to the RTDB
record ``joystick.web``, which this node reads. Before a page sends, and once it is closed,
hidden or silent for more than ``web_timeout_ms``, nothing is published (a consumer times out
to zero) and the node is in state ``waiting`` (for an operator), not in error: a run without
anyone at the page ends well.
"""

from __future__ import annotations

import bisect
import contextlib
import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from flowrt import Node, Output, TimerTrigger, resolve_path
from flowrt.files import check_regular_file, read_text
from flowrt.refusals import Refusals, finite_number

MAX_SCRIPT_BYTES = 16 << 20  # a scripted drive of hours at 1 kHz is a few MB

__all__ = ["JoyState", "Joystick", "load_script"]


@dataclass(frozen=True)
class JoyState:
    """One reading of a joystick."""

    axes: dict[str, float] = field(default_factory=dict)
    buttons: dict[str, bool] = field(default_factory=dict)
    timestamp: float = 0.0


class JoystickParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: str = Field(description="evdev:PATH|evdev:NAME, web, or script:FILE")
    rate_hz: float = Field(default=50.0, gt=0, le=1000, allow_inf_nan=False)
    end: Literal["hold", "loop", "silent"] = "hold"
    reopen_ms: float = Field(default=500.0, ge=10, le=60_000, allow_inf_nan=False)
    web_timeout_ms: float = Field(default=500.0, ge=10, le=60_000, allow_inf_nan=False)
    axis_names: dict[int, str] = Field(
        default_factory=dict, description="evdev: absolute-axis code -> name (default: ecodes)"
    )
    button_names: dict[int, str] = Field(
        default_factory=dict, description="evdev: key code -> name"
    )

    @field_validator("source")
    @classmethod
    def _known(cls, v: str, info: ValidationInfo) -> str:
        """``script:FILE`` resolves against the graph file's folder and must be a regular
        file of at most MAX_SCRIPT_BYTES (``script:/dev/zero`` is refused here, located)
        whose rows read (a missing ``time`` column failed the run, not the validation)."""
        kind, _, rest = v.partition(":")
        if kind == "web" and not rest:
            return v
        if kind == "evdev" and rest:
            return v
        if kind == "script" and rest:
            path = resolve_path(rest, info)
            try:
                check_regular_file(path, MAX_SCRIPT_BYTES)
            except FileNotFoundError:
                raise ValueError(f"joystick script not found: {path}") from None
            except OSError as e:
                raise ValueError(f"joystick script: {e.strerror or e}") from None
            load_script(path)  # its columns and numbers: a graph error, not a failed run
            return f"script:{path}"
        raise ValueError("source must be evdev:PATH, evdev:NAME, web or script:FILE")


def load_script(path: str | Path) -> list[tuple[float, dict[str, float], dict[str, bool]]]:
    """Rows of a scripted joystick CSV, sorted by time (see the module docstring)."""
    rows: list[tuple[float, dict[str, float], dict[str, bool]]] = []
    text = read_text(path, MAX_SCRIPT_BYTES)  # a regular file of bounded size, or OSError
    with io.StringIO(text, newline="") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader)]
        if not header or header[0] != "time":
            raise ValueError(f"{path}: the first column must be 'time'")
        for lineno, row in enumerate(reader, start=2):
            if not row or not "".join(row).strip():
                continue
            try:
                values = [float(x) for x in row]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: not a number in {row}") from None
            if len(values) != len(header) or not all(math.isfinite(v) for v in values):
                raise ValueError(f"{path}:{lineno}: expected {len(header)} finite numbers")
            axes: dict[str, float] = {}
            buttons: dict[str, bool] = {}
            for name, v in zip(header[1:], values[1:], strict=True):
                if name.startswith("button:"):
                    buttons[name[7:]] = v != 0
                else:
                    axes[name.removeprefix("axis:")] = max(-1.0, min(1.0, v))
            rows.append((values[0], axes, buttons))
    rows.sort(key=lambda r: r[0])
    return rows


class Joystick(Node):
    """Publishes the joystick's state at a steady rate while the device is there."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset({"reopen_ms"})  # never a timeout: what keeps a lost link safe

    Params = JoystickParams
    output = Output(JoyState)

    @classmethod
    def default_trigger(cls, params: Any) -> Any:
        return TimerTrigger(timer=1000.0 / params.rate_hz)

    def setup(self) -> None:
        kind, _, rest = self.params.source.partition(":")
        self.kind = kind
        self.target = rest
        self.device: Any = None
        self.reopen_at = 0.0
        self.attempts = 0
        self.axes: dict[str, float] = {}
        self.buttons: dict[str, bool] = {}
        self.ranges: dict[int, tuple[float, float]] = {}
        self.script: list[tuple[float, dict[str, float], dict[str, bool]]] = []
        self.times: list[float] = []  # each row's time: found by bisection, not a scan
        self.row = -1
        self.t0: float | None = None
        self.refused = Refusals(
            "joystick-invalid", "joystick message refused: an axis is NaN, inf or not a number"
        )
        if kind == "script":
            self.script = load_script(rest)  # a bad file fails set-up: one clear reason
            if not self.script:
                raise ValueError(f"{rest}: no rows")
            self.times = [row[0] for row in self.script]

    def teardown(self) -> None:
        self._close()

    def process(self) -> JoyState | None:
        now = self.ctx.now()
        if self.kind == "script":
            return self._script(now)
        if self.kind == "web":
            return self._web(now)
        return self._evdev(now)

    # --- script -------------------------------------------------------------------------

    def _script(self, now: float) -> JoyState | None:
        """The newest row whose time has come. Looping, the last row is held as long as the
        gap before it, then row 0 again: it was held for 1 ms, so a last row that lets go of
        the deadman was never published and the row before it (driving) went on for good."""
        if self.t0 is None:
            self.t0 = now
        t = now - self.t0
        times = self.times
        last = times[-1]
        if t > last + 1e-9 and self.params.end == "silent" and self.row == len(self.script) - 1:
            return None
        if self.params.end == "loop" and last > 0:
            gap = last - times[-2] if len(times) > 1 else last
            t %= last + max(gap, 1e-3)
        self.row = bisect.bisect_right(times, t + 1e-9) - 1
        if self.row < 0:
            return None
        _, axes, buttons = self.script[self.row]
        return JoyState(dict(axes), dict(buttons), now)

    # --- web ----------------------------------------------------------------------------

    def _web(self, now: float) -> JoyState | None:
        rec = self.ctx.rtdb.read("joystick.web")
        if rec is None or rec.age > self.params.web_timeout_ms / 1000:
            # No operator at the page: nothing published (teleop gives zero), a state the
            # table shows, not an error (issue 43 item 6: a headless station is normal).
            self.ctx.set_waiting(
                "waiting for an operator: open the live view and tick 'drive from this page'"
                if rec is None
                else "waiting for an operator: the page stopped sending (closed, hidden or cut)"
            )
            return None
        self.ctx.set_waiting(None)
        value = rec.value if isinstance(rec.value, dict) else {}
        raw_axes = value.get("axes") or {}
        if not isinstance(raw_axes, dict) or not all(finite_number(v) for v in raw_axes.values()):
            self.refused.refuse(self.ctx, rec.timestamp)
            return None  # nothing published: teleop sees a stale input and gives zero
        self.refused.accept()
        axes = {str(k): _clamp(v) for k, v in raw_axes.items()}
        buttons = {str(k): bool(v) for k, v in (value.get("buttons") or {}).items()}
        return JoyState(axes, buttons, now)

    def report(self) -> dict[str, Any]:
        """What the statistics show of the joystick (``reports``: table, --stats-json)."""
        return {"source": self.kind, "invalid": self.refused.count}

    # --- evdev --------------------------------------------------------------------------

    def _evdev(self, now: float) -> JoyState | None:
        if self.device is None:
            if now < self.reopen_at:
                return None
            self._open(now)
            if self.device is None:
                return None
        try:
            while True:
                event = self.device.read_one()
                if event is None:
                    break
                self._apply(event)
        except OSError as e:  # unplugged: ENODEV
            self._close()
            self.reopen_at = now + self.params.reopen_ms / 1000
            self._lost(f"device lost: {e.strerror or e}")
            return None
        return JoyState(dict(self.axes), dict(self.buttons), now)

    def _open(self, now: float) -> None:
        self.attempts += 1
        try:
            import evdev
        except ImportError:
            self._lost("the evdev package is not installed (pip install evdev)")
            self.reopen_at = math.inf
            return
        path = self.target
        try:
            if not path.startswith("/"):
                matches = [p for p in evdev.list_devices() if path in evdev.InputDevice(p).name]
                if not matches:
                    raise FileNotFoundError(f"no input device named like {path!r}")
                path = matches[0]
            dev = evdev.InputDevice(path)
        except OSError as e:
            self.reopen_at = now + self.params.reopen_ms / 1000
            self._lost(f"cannot open {path}: {e.strerror or e} (attempt {self.attempts})")
            return
        self.device = dev
        self.ranges = {}
        for code, info in dev.capabilities(absinfo=True).get(evdev.ecodes.EV_ABS, []):
            self.ranges[code] = (float(info.min), float(info.max))
        self._found()

    def _apply(self, event: Any) -> None:
        import evdev

        ec = evdev.ecodes
        if event.type == ec.EV_ABS:
            lo, hi = self.ranges.get(event.code, (-1.0, 1.0))
            v = 0.0 if hi == lo else 2.0 * (event.value - lo) / (hi - lo) - 1.0
            name = self.params.axis_names.get(event.code) or _code_name(ec.ABS, event.code)
            self.axes[name] = _clamp(v)
        elif event.type == ec.EV_KEY:
            name = self.params.button_names.get(event.code) or _code_name(ec.BTN, event.code)
            self.buttons[name] = event.value != 0

    def _close(self) -> None:
        if self.device is not None:
            with contextlib.suppress(OSError):
                self.device.close()
            self.device = None

    def _lost(self, reason: str) -> None:
        self.ctx.set_error(reason)

    def _found(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.ctx.clear_error()


def _code_name(table: Any, code: int) -> str:
    name = table.get(code, str(code))
    if isinstance(name, list):
        name = name[0]
    return str(name).lower().removeprefix("abs_").removeprefix("btn_")


def _clamp(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return 0.0
    return max(-1.0, min(1.0, x)) if math.isfinite(x) else 0.0
