"""The operator's e-stop: a latching button on the live view, published as a heartbeat.

::

    estop:
      kind: estop
      params: {rate_hz: 20}            # the heartbeat: the state published 20 times a second
    # export: {base/estop: estop.output}   and on the robot, the arbiter's lock:
    #   locks: {estop: {heartbeat: 300ms, after_silence: hold}}

The live view (``display`` node) shows an e-stop panel when a graph has this node: **STOP**
latches the stop, **Release** lifts it. The page sends the action over its WebSocket (the
same guard as the joystick: Host, Origin, the page's session, the view's token off loopback)
and the display writes it to the RTDB record ``estop.web``; this node applies each new
action once (each carries an id the page made) and latches the result.

Output ``output`` on every activation, as long as the process lives (that is the heartbeat a
robot's arbiter watches): ``{"active": bool, "release": id | None, "since": unix time}``.
``active`` is the stop; ``release`` is the id of the operator's last release (None before
the first), new at every release, so a robot that lost the heartbeat and holds its lock
(``after_silence: hold``) can tell a deliberate release from the station merely coming back.
The node starts engaged (``initial: engaged``): a robot does not move until someone releases.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from flowrt import Node, Output, TimerTrigger

__all__ = ["WEB_ESTOP", "Estop"]

WEB_ESTOP = "estop.web"  # RTDB record of the page's last e-stop action (the display writes it)


class EstopParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rate_hz: float = Field(
        default=20.0, gt=0, le=1000, allow_inf_nan=False, description="heartbeat rate"
    )
    initial: Literal["engaged", "released"] = Field(
        default="engaged", description="the state at start, before any action on the page"
    )


class Estop(Node):
    """A latching stop from the live view, published at ``rate_hz`` (see the module doc)."""

    Params = EstopParams
    output: Output[dict[str, Any]] = Output(
        dict, doc="{active, release, since}: the latched stop, as a heartbeat"
    )

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=1000.0 / params.rate_hz)

    def setup(self) -> None:
        self.active = self.params.initial == "engaged"
        self.release: str | None = None
        self.since = time.time()
        self.applied: str | None = None  # id of the last page action applied
        self.presses = 0
        self.releases = 0

    def process(self) -> dict[str, Any]:
        self._apply(self.ctx.rtdb.value(WEB_ESTOP))
        return {"active": self.active, "release": self.release, "since": self.since}

    def _apply(self, action: Any) -> None:
        """A new action of the page, once: stop or release (anything else is ignored)."""
        if not isinstance(action, Mapping) or action.get("id") == self.applied:
            return
        what, aid = action.get("action"), action.get("id")
        if not isinstance(aid, str) or what not in ("stop", "release"):
            return
        self.applied = aid
        stop = what == "stop"
        if stop:
            self.presses += 1
        else:
            self.releases += 1
            self.release = aid
        if stop != self.active:
            self.active, self.since = stop, time.time()
            self.ctx.log.warning("e-stop %s from the live view", "ENGAGED" if stop else "released")

    def report(self) -> dict[str, Any]:
        """For the page's panel and the statistics: the state, since when, and the counts."""
        return {
            "estop": "engaged" if self.active else "released",
            "since": self.since,
            "presses": self.presses,
            "releases": self.releases,
        }
