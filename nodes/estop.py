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
    timing_fixed = True  # disabled, no Stop reaches the arbiter (its lock's heartbeat aside)
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
        self.read_once = False  # the first read takes the newest action only
        self.presses = 0
        self.releases = 0
        self.refused = 0  # releases sent in the same period as a Stop (never applied)

    def process(self) -> dict[str, Any]:
        for action, stopped in self._new_actions():
            self._apply(action, stopped)
        return {"active": self.active, "release": self.release, "since": self.since}

    def _new_actions(self) -> list[tuple[Mapping[str, Any], bool]]:
        """The page's actions since the last one applied, oldest first, each with whether a
        Stop came before it in this batch. Only the newest was read: a Stop followed within
        one period by another page's Release was never applied, nor counted."""
        history = [r.value for r in self.ctx.rtdb.history(WEB_ESTOP)]
        actions = [a for a in history if isinstance(a, Mapping) and isinstance(a.get("id"), str)]
        ids = [a["id"] for a in actions]
        if not self.read_once:  # a fresh instance: the page's state now, not its past
            self.read_once = True
            actions = actions[-1:]
        elif self.applied in ids:
            actions = actions[ids.index(self.applied) + 1 :]
        out, stopped = [], False
        for a in actions:
            out.append((a, stopped))
            stopped = stopped or a.get("action") == "stop"
        return out

    def _apply(self, action: Mapping[str, Any], stopped: bool) -> None:
        """A new action of the page, once: stop or release (anything else is ignored). A
        Release sent in the same period as a Stop before it is refused (counted): its sender
        had not seen that Stop, and the Stop is published at least once."""
        what, aid = action.get("action"), action.get("id")
        if not isinstance(aid, str) or what not in ("stop", "release"):
            return
        self.applied = aid
        if what == "release" and stopped:
            self.refused += 1
            self.ctx.log.warning("e-stop release refused: a Stop came in the same instant")
            return
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
            "releases_refused": self.refused,
        }
