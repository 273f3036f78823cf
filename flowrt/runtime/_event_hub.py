"""Where a run's events go: the last thousand kept, then every monitor and listener told.

A monitor or listener that raises is logged and skipped: watching a run never breaks it.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from ..events import Event

log = logging.getLogger("flowrt")


class Monitor(Protocol):
    """Something that watches a runtime: told when it starts, of each event, when it stops."""

    def started(self, rt: Any) -> None: ...

    def event(self, event: Event) -> None: ...

    def stopped(self, rt: Any) -> None: ...


class EventHub:
    """Invariant: ``count`` is every event ever published; ``events`` the last 1000 of them."""

    def __init__(self, monitors: list[Monitor]) -> None:
        self.monitors = monitors
        self.events: deque[Event] = deque(maxlen=1000)
        self.count = 0
        self._listeners: list[Callable[[Event], None]] = []

    def publish(self, event: Event) -> None:
        self.events.append(event)
        self.count += 1
        for m in self.monitors:
            try:
                m.event(event)
            except Exception:
                log.exception("monitor failed on %s", event.kind)
        for cb in self._listeners:
            try:
                cb(event)
            except Exception:
                log.exception("event listener failed on %s", event.kind)

    def listen(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call ``callback`` for every event; returns a function that unsubscribes."""
        self._listeners.append(callback)
        return lambda: self._listeners.remove(callback)
