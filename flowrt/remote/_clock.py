"""The clocks of the machines a graph imports from, measured so ages hold across machines.

Clocks of two machines differ, so each exporter answers a clock query
(``_flowrt/clock/<session id>``, :func:`answer_clock`); the importer estimates the offset
from the round trip (NTP's method, error <= rtt/2, the best of five probes) and reports a
message's age on the exporter's clock corrected by it, which holds without synchronised
clocks. Probes run on a thread of their own, once per exporter, never on the loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["CLOCK_PREFIX", "ClockOffsets", "answer_clock"]

log = logging.getLogger("flowrt.remote._bridge")

CLOCK_PREFIX = "_flowrt/clock"
_PROBES = 5


def answer_clock(query: Any) -> None:
    """The exporter's side: reply with this machine's wall clock."""
    query.reply(query.key_expr, repr(time.time()).encode())


class ClockOffsets:
    """Each exporter's clock minus ours, keyed by its Zenoh session id.

    ``session`` returns the open Zenoh session, or None once it is closed (then no probe
    starts). Invariants: at most one probe thread per zid runs (``_probing``); a measured zid
    (``_offsets``) is never probed again; one whose probes all failed is probed again by its
    next message.
    """

    def __init__(self, session: Callable[[], Any]) -> None:
        self._session = session
        self._offsets: dict[str, tuple[float, float]] = {}  # zid -> (offset s, rtt s)
        self._probing: set[str] = set()

    def offset(self, zid: str) -> float:
        """Exporter clock minus ours, seconds (0 until measured; same host: ~0)."""
        got = self._offsets.get(zid)
        return 0.0 if got is None else got[0]

    def measured(self, zid: str) -> bool:
        """Whether the exporter's clock is known (until then, :meth:`offset` is a guess)."""
        return zid in self._offsets

    def probe(self, zid: str) -> None:
        """From Zenoh's thread: measure an exporter's clock once, off the loop."""
        if zid in self._offsets or zid in self._probing or self._session() is None:
            return
        self._probing.add(zid)
        threading.Thread(target=self._probe, args=(zid,), daemon=True).start()

    def _probe(self, zid: str) -> None:
        best: tuple[float, float] | None = None
        for _ in range(_PROBES):
            t0 = time.time()
            try:
                replies = list(self._session().get(f"{CLOCK_PREFIX}/{zid}", timeout=1.0))
            except Exception:
                break
            t1 = time.time()
            for r in replies:
                ok = getattr(r, "ok", None)
                if ok is None:
                    continue
                remote = float(ok.payload.to_bytes())
                rtt = t1 - t0
                if best is None or rtt < best[1]:
                    best = (remote - (t0 + t1) / 2, rtt)
        if best is not None:
            self._offsets[zid] = best
            log.info(
                "zenoh: clock of %s: offset %.3f ms, rtt %.3f ms", zid, best[0] * 1e3, best[1] * 1e3
            )
        self._probing.discard(zid)

    def clocks(self) -> dict[str, tuple[float, float]]:
        """Every measured exporter: (offset, round trip) in seconds."""
        return dict(self._offsets)
