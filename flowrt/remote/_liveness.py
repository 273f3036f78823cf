"""Whether an imported stream is alive: stale after ``stale_after`` periods of silence.

An import that hears nothing for ``stale_after`` periods (its declared period, else the mean
interval between arrivals once three are known, else 0.2 s; never less than 0.1 s) is stale:
its node goes to the error state (``stale: error``, the default) or, with ``stale: state``,
stays running and raises one alert per outage. Each change is published on the import's
``state`` output (recorded like any output: a recording shows its gaps) and the outages and
time down are in the statistics' ``reports``.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from ..events import HealthAlert
from ..stats import Running
from ._host import BridgeHost

__all__ = ["ImportLiveness"]

log = logging.getLogger("flowrt.remote._bridge")


class ImportLiveness:
    """One import's liveness, on the loop. Invariant: ``stale_since`` is set exactly while
    ``stale``; ``down_s`` sums the finished outages only."""

    def __init__(
        self,
        host: BridgeHost,
        name: str,
        key: str,
        period_s: float | None,
        stale_after: float | None,
        stale_is: str,
    ) -> None:
        self.host = host
        self.name = name
        self.key = key
        self.period = period_s  # declared; None: measured from the arrivals
        self.stale_after = stale_after  # None: never stale
        self.stale_is = stale_is  # "error": the node's error state; "state": a counted state
        self.arrivals = Running()
        self.last_arrival: float | None = None  # loop clock
        self.started = host.now_mono()
        self.stale = False
        self.stale_since: float | None = None  # loop clock, while stale
        self.outages = 0  # times the import went stale (each one alert)
        self.down_s = 0.0  # time spent stale, over finished outages
        self.last_contact_wall: float | None = None  # our wall clock at the last arrival
        self.ctx: Any = None

    def arrived(self, now: float) -> None:
        """A value arrived at ``now`` (loop clock)."""
        if self.last_arrival is not None:
            self.arrivals.add(now - self.last_arrival)
        self.last_arrival = now

    def contact(self) -> None:
        """After a delivery's arrivals: the last contact, and the end of an outage."""
        self.last_contact_wall = time.time()
        if self.stale:
            self._resumed()

    def period_s(self) -> float | None:
        if self.period is not None:
            return self.period
        s = self.arrivals
        return s.mean if s.count >= 3 else None

    def validity_ms(self) -> float | None:
        """How long a value stays valid in the RTDB: ``stale_after`` periods."""
        p = self.period_s()
        if p is None or self.stale_after is None:
            return None
        return p * self.stale_after * 1000

    def check(self, ctx: Any) -> None:
        self.ctx = ctx
        if self.stale_after is None:  # stale_after: never
            return
        now = self.host.now_mono()
        p = self.period_s()
        limit = max(0.1, (p if p is not None else 0.2) * self.stale_after)
        since = now - (self.last_arrival if self.last_arrival is not None else self.started)
        if since <= limit or self.stale:
            return
        self.stale = True
        self.stale_since = now - since  # down since the last contact (or the start)
        self.outages += 1
        what = "no message yet" if self.last_arrival is None else "stale"
        # since when, not for how long: the reason stays true while the outage lasts (it
        # said "for 102 ms" at the run's end after 4 s of silence)
        began = time.strftime("%H:%M:%S", time.localtime(time.time() - since))
        reason = f"{what} on {self.key} since {began} (limit {limit * 1000:.0f} ms)"
        self._publish_state(since)
        if self.stale_is == "error":
            ctx.set_error(reason)
        else:  # a state: one alert per outage, the node stays running
            ctx.emit(HealthAlert(ctx.elapsed(), self.name, "import-stale", reason))
            log.warning("import %s: %s", self.name, reason)

    def _resumed(self) -> None:
        now = self.host.now_mono()
        down = 0.0 if self.stale_since is None else max(0.0, now - self.stale_since)
        self.down_s += down
        self.stale, self.stale_since = False, None
        self._publish_state(down)
        if self.ctx is None:
            return
        if self.stale_is == "error":
            self.ctx.clear_error()
        else:
            detail = f"{self.key} back after {down:.1f} s"
            self.ctx.emit(
                HealthAlert(self.ctx.elapsed(), self.name, "import-resumed", detail, "info")
            )
            log.info("import %s: %s", self.name, detail)

    def _publish_state(self, silent_s: float) -> None:
        """The link's state on the import's ``state`` output, at each change: recorded like
        any output, it marks a gap in the recording (stale from when, back after how long)."""
        self.host.publish(
            self.name,
            "state",
            {
                "key": self.key,
                "stale": self.stale,
                "silent_s": round(silent_s, 3),  # since the last contact / the outage's length
                "last_contact": self.last_contact_wall,
                "outages": self.outages,
            },
        )

    def report(self) -> dict[str, Any]:
        """The link's state for the statistics' ``reports``: stale or not, outages, the time
        down (the current outage included) and the last contact (Unix time, our clock)."""
        down = self.down_s
        if self.stale and self.stale_since is not None:
            down += max(0.0, self.host.now_mono() - self.stale_since)
        return {
            "key": self.key,
            "stale": self.stale,
            "stale_is": self.stale_is,
            "outages": self.outages,
            "down_s": round(down, 3),
            "last_contact": self.last_contact_wall,
        }
