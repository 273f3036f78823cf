"""The operator's station inside the live view's server process: its parts and their routes.

Each part is a module of its own: the record panel (:mod:`.operator_record`), the review of
recorded sessions (:mod:`.operator_sessions`), the machine and stream health over time
(:mod:`.health_history`, sampled here once a second from the statistics the display node
already answers) and the robots a base station watches (:mod:`.operator_robots`). The page's
scripts (``operator.js``, ``plots.js``) are served from this package: nothing from a CDN.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from ..health_history import HealthHistory
from .record import Call, RecordApi
from .robots import Robots
from .sessions import Sessions

STATIC = ("operator.js", "plots.js")  # the page's scripts, served from this package


class Calls:
    """Requests to the display node over the channel, each answered by a ``reply`` with its
    ``id`` (the recorders' start and stop take seconds: other traffic goes on meanwhile)."""

    def __init__(self, send: Callable[[dict[str, Any]], None], wait: float) -> None:
        self.send = send
        self.wait = wait
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._ids = itertools.count(1)

    async def call(self, op: str, **args: Any) -> dict[str, Any]:
        """Ask the node (``op`` with ``args``) and wait for its ``reply``."""
        n = next(self._ids)
        answer: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[n] = answer
        self.send({"op": op, "id": n, **args})
        wait = args.get("wait")  # the node answers within it: a little more for the way back
        wait = min(self.wait, float(wait) + 1.5) if isinstance(wait, int | float) else self.wait
        try:
            return await asyncio.wait_for(answer, wait)
        except TimeoutError:
            return {"status": 504, "error": f"the runtime did not answer {op} in {wait:g} s"}
        finally:
            self._waiting.pop(n, None)

    def reply(self, header: dict[str, Any]) -> None:
        waiting = self._waiting.pop(int(header.get("id") or 0), None)
        if waiting is not None and not waiting.done():
            waiting.set_result(dict(header.get("result") or {}))


class Station:
    """The parts, given how to ask the display node (``call``) and its newest statistics."""

    def __init__(
        self,
        settings: dict[str, Any],
        call: Call,
        fresh_stats: Callable[[float], Awaitable[bytes | None]],
    ) -> None:
        self.fresh_stats = fresh_stats
        self.recordings: list[str] = list(settings.get("recordings", ()))
        hz = float(settings.get("health_hz", 1.0))
        disk = self.recordings[0] if self.recordings else "/"
        self.history = HealthHistory(float(settings.get("health_keep_s", 900.0)), hz, disk)
        self.records = RecordApi(call, self._refresh)
        self.reviews = Sessions(self._folders, self._active)
        self.robots = Robots(dict(settings.get("robots", {})))

    def routes(self) -> list[web.RouteDef]:
        return [
            web.get("/api/health/history", self._health),
            *[web.get(f"/{name}", self._static) for name in STATIC],
            *self.records.routes(),
            *self.reviews.routes(),
            *self.robots.routes(),
        ]

    async def run(self) -> None:
        """The health sampler and the robots' poller, until cancelled."""
        await asyncio.gather(self._sample(), self.robots.poll())

    async def _refresh(self) -> None:
        """The recorders' state as of now (a page asking right after the start)."""
        await self._observed()

    async def _observed(self) -> dict[str, Any] | None:
        """Statistics no older than the view's last start or stop, given to the record API
        (which leaves out their recorders' state if another came meanwhile)."""
        asked = time.monotonic()
        try:
            body = await self.fresh_stats(self.records.changed_at)
            stats = json.loads(body) if body is not None else None
        except ValueError:
            return None
        if stats is not None:
            self.records.observe(stats, time.monotonic(), asked)
        return stats

    async def close(self) -> None:
        await asyncio.to_thread(self.robots.close)

    def _folders(self) -> list[str]:
        """Where sessions are: the display's folder, then every recorder's."""
        seen = list(self.recordings)
        for folder in self.records.state.get("recordings", []):
            if folder not in seen:
                seen.append(folder)
        return seen

    def _active(self) -> set[str]:
        """The sessions being written now (not to be scanned while they grow)."""
        rows = self.records.state.get("recording", [])
        return {Path(r["session"]).name for r in rows if r.get("session")}

    async def _sample(self) -> None:
        """Health: one sample per period, with the node's statistics of that moment."""
        period = 1.0 / self.history.hz
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while True:
            stats = await self._observed()
            self.history.sample(stats)  # psutil's reads: well under a millisecond
            next_at = max(next_at + period, loop.time())
            await asyncio.sleep(next_at - loop.time())

    async def _health(self, request: web.Request) -> web.Response:
        keep = (self.history.samples.maxlen or 1) / self.history.hz
        try:
            seconds = float(request.query.get("seconds", "600"))
        except ValueError:
            raise web.HTTPBadRequest(text="seconds: a number\n") from None
        if not 0 < seconds < float("inf"):
            raise web.HTTPBadRequest(text="seconds: a positive number\n")
        return web.Response(
            text=json.dumps(self.history.window(min(seconds, keep))),
            content_type="application/json",
            headers={"Cache-Control": "no-store"},
        )

    async def _static(self, request: web.Request) -> web.Response:
        name = request.path.lstrip("/")
        return web.Response(
            body=(Path(__file__).parent / name).read_bytes(),
            content_type="text/javascript",
            charset="utf-8",
            headers={"Cache-Control": "no-cache"},
        )
