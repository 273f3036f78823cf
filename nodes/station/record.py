"""The record panel: start and stop a named session from the live view, and watch it.

Two halves, one per process. In the view's server process, :class:`RecordApi` answers

- ``POST /api/record/start`` with ``{"name": "drive"}``: every recorder of the graph starts a
  new session ``drive_NNN``; answers ``{"session": "drive_NNN", "sessions": [...]}``;
- ``POST /api/record/stop``: the recorders stop; once their files are finished, answers the
  session's per-stream table (the recorder's ``streams.json``: ``expected``, ``received``,
  ``written``, ``lost`` per stream, and the totals);
- ``GET /api/record``: whether a session is being recorded, its elapsed time, its size on
  disk and each stream's rate over the last statistics interval.

State-changing requests must be ``application/json`` (a cross-site form cannot send that
without a preflight the view never grants) and pass the view's guard like every request:
an ``Origin`` other than the view's own is refused (403), the token is needed when the view
has one. In the runtime's process, :func:`obey` (called by the display node) writes the
recorders' RTDB command records (``flowrt.record.NODE``, the same ``flowrt ctl record``
writes) and waits for their answers (``flowrt.recording.NODE``): the view never touches a
recorder's files while it writes them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from flowrt.control.recorders import obey, recorders
from flowrt.rtdb import RECORD_COMMAND, RECORDING_FOLDER, RECORDING_SESSION

from .sessions import SESSION_FILE, session_length, valid_name

COMMAND = RECORD_COMMAND  # the recorder obeys it
STATUS = RECORDING_SESSION  # the session folder, "" stopped
FOLDER = RECORDING_FOLDER  # where its sessions go
OBEY_WAIT = 20.0  # seconds for the recorders to say they started (a writer process to spawn)
RATE_INTERVAL = 0.5  # seconds: the shortest interval a live rate is measured over
STOP_WITHIN = 9.0  # seconds a stop is answered within, from its arrival (files finished or not)
TURN_WAIT = 3.0  # seconds a start or stop waits for the one under way before it is refused
BODY_TIMEOUT = 5.0  # seconds for a request's body once its headers are in (then 408)

Call = Callable[..., Awaitable[dict[str, Any]]]


# --- the runtime's side -------------------------------------------------------------------


def state(rtdb: Any) -> dict[str, Any]:
    """Each recorder's session (``""``: stopped) and for how long, and the folders sessions
    go in: what the display node adds to its statistics for the page."""
    rows, folders = [], []
    for node in recorders(rtdb):
        rec = rtdb.read(STATUS + node)
        rows.append(
            {
                "node": node,
                "session": str(rec.value) if rec is not None and rec.value else "",
                "since": rec.age if rec is not None else None,
            }
        )
        folder = rtdb.value(FOLDER + node)
        if isinstance(folder, str) and folder not in folders:
            folders.append(folder)
    return {"recording": rows, "recordings": folders}


async def answer(
    rtdb: Any,
    header: dict[str, Any],
    send: Callable[[dict[str, Any]], None],
    turn: asyncio.Lock | None = None,
) -> None:
    """The display node's answer to the server's ``record`` request (its ``id`` echoed); one
    at a time under ``turn`` (two operators, a double click in two tabs)."""
    wait = header.get("wait")
    wait = float(wait) if isinstance(wait, int | float) and 0 < wait <= OBEY_WAIT else OBEY_WAIT
    action, name = str(header.get("action")), header.get("name")
    if action == "start" and not isinstance(name, str):  # the page always names its session
        result = {"status": 400, "error": "name: letters, digits, _ and - (at most 64)"}
        send({"op": "reply", "id": header.get("id"), "result": result})
        return
    try:
        async with turn if turn is not None else contextlib.nullcontext():
            result = await obey(rtdb, action, name, wait)
    except Exception as e:  # an RTDB that cannot be written: the page says why
        result = {"status": 500, "error": f"{type(e).__name__}: {e}"}
    send({"op": "reply", "id": header.get("id"), "result": result})


# --- the view's side ----------------------------------------------------------------------


class RecordApi:
    """The HTTP routes; ``call(op, **args)`` asks the display node and returns its answer."""

    def __init__(self, call: Call, refresh: Callable[[], Awaitable[None]] | None = None) -> None:
        self.call = call
        self.refresh = refresh  # new statistics into observe(), before a state is answered
        self.state: dict[str, Any] = {"recording": [], "recordings": []}
        # When this view last started or stopped a recording (``_now_recording``, monotonic):
        # statistics asked for before it are older than what it said, and do not undo it (a
        # page's poll in flight during a Start read "stopped" after it)
        self.changed_at = 0.0
        self._edges: tuple[float, dict[str, int]] | None = None  # the previous statistics
        self.rates: dict[str, float] = {}
        self.refused = 0  # requests refused for their body (not JSON, nested too deeply, ...)
        self.busy = 0  # starts and stops refused: another one was under way for TURN_WAIT
        self._lock = asyncio.Lock()

    def routes(self) -> list[web.RouteDef]:
        return [
            web.post("/api/record/start", self.start),
            web.post("/api/record/stop", self.stop),
            web.get("/api/record", self.status),
        ]

    def observe(self, stats: dict[str, Any], now: float, asked: float | None = None) -> None:
        """New statistics: the recorders' state, and each recorded stream's rate since the
        previous ones (from the counts of the edges into the recorders). ``asked``: when they
        were asked for (monotonic); before a start or stop since, their recorders' state is
        not taken (the rates are)."""
        display = stats.get("display") or {}
        if asked is None or asked >= self.changed_at:
            self.state = {
                "recording": display.get("recording", []),
                "recordings": display.get("recordings", []),
            }
        nodes = {r["node"] for r in self.state["recording"]}
        counts: dict[str, int] = {}
        for e in (stats.get("runtime") or {}).get("edges", []):
            _, _, dst = str(e.get("name", "")).partition("->")
            node, _, topic = dst.partition(".")
            if node in nodes:
                counts[topic] = int(e.get("delivered", 0))
        if self._edges is not None and now - self._edges[0] < RATE_INTERVAL:
            return  # too soon for a rate: keep the previous interval's
        if self._edges is not None:
            dt = now - self._edges[0]
            self.rates = {t: max(0, c - self._edges[1].get(t, c)) / dt for t, c in counts.items()}
        self._edges = (now, counts)

    def _now_recording(self, sessions: dict[str, str]) -> None:
        """What the recorders just said, without waiting for the next statistics."""
        rows = {r["node"]: r for r in self.state["recording"]}
        for node, folder in sessions.items():
            rows[node] = {"node": node, "session": folder, "since": 0.0}
        self.state = {**self.state, "recording": list(rows.values())}
        self.changed_at = time.monotonic()

    async def _body(self, request: web.Request) -> dict[str, Any]:
        try:
            return await _body(request)
        except web.HTTPException:
            self.refused += 1
            raise

    @contextlib.asynccontextmanager
    async def _turn(self) -> AsyncIterator[bool]:
        """One start or stop at a time; False when the one under way took too long."""
        try:
            async with asyncio.timeout(TURN_WAIT):
                await self._lock.acquire()
        except TimeoutError:
            self.busy += 1
            yield False
            return
        try:
            yield True
        finally:
            self._lock.release()

    async def start(self, request: web.Request) -> web.Response:
        body = await self._body(request)
        name = body.get("name")
        if not isinstance(name, str) or not valid_name(name):
            return _error(400, "name: a session name, letters, digits, _ and - (at most 64)")
        async with self._turn() as mine:
            if not mine:
                return _error(409, "another start or stop is under way: try again")
            return await self._start(name)

    async def _start(self, name: str) -> web.Response:
        answer = await self.call("record", action="start", name=name)
        if answer.get("status") != 200:
            return _error(int(answer.get("status", 500)), str(answer.get("error")))
        self._now_recording(answer["sessions"])
        folders = list(answer["sessions"].values())
        return _json(
            {
                "session": Path(folders[0]).name,
                "sessions": [Path(f).name for f in folders],
                "nodes": list(answer["sessions"]),
            }
        )

    async def stop(self, request: web.Request) -> web.Response:
        end = time.monotonic() + STOP_WITHIN
        await self._body(request)
        async with self._turn() as mine:
            if not mine:
                return _error(409, "another start or stop is under way: try again")
            return await self._stop(end)

    async def _stop(self, end: float) -> web.Response:
        """Stopped, and the sessions' tables once their files are finished, by ``end``; a
        file still being finished then is said (202): its table comes with the session."""
        wait = max(0.5, (end - time.monotonic()) * 0.6)
        answer = await self.call("record", action="stop", wait=wait)
        if answer.get("status") != 200:
            return _error(int(answer.get("status", 500)), str(answer.get("error")))
        self._now_recording(dict.fromkeys(answer["sessions"], ""))
        folders = [Path(f) for f in answer["sessions"].values()]
        reports = await _reports(folders, max(0.0, end - time.monotonic()))
        if reports is None:
            names = ", ".join(f.name for f in folders)
            return _json(
                {
                    "session": folders[0].name,
                    "sessions": [f.name for f in folders],
                    "finished": False,
                    "error": f"{names}: stopped; the files are still being finished (the "
                    "per-stream table will be in the session's streams.json)",
                },
                status=202,
            )
        streams = [s for r in reports for s in r.get("streams", [])]
        first = reports[0]
        return _json(
            {
                "session": Path(folders[0]).name,
                "sessions": [f.name for f in folders],
                "start_time": first.get("start_time"),
                "duration_s": session_length(first),
                "finished": True,
                "error": next((r["error"] for r in reports if r.get("error")), None),
                "lost": sum(int(s.get("lost", 0)) for s in streams),
                "streams": streams,
            }
        )

    async def status(self, request: web.Request) -> web.Response:
        if self.refresh is not None:
            await self.refresh()
        rows = [r for r in self.state["recording"] if r.get("session")]
        sessions = []
        for r in rows:
            folder = Path(r["session"])
            size = await asyncio.to_thread(_size, folder)
            sessions.append(
                {
                    "node": r["node"],
                    "session": folder.name,
                    "elapsed_s": r.get("since"),
                    "size_bytes": size,
                }
            )
        return _json(
            {
                "recording": bool(sessions),
                "session": sessions[0]["session"] if sessions else None,
                "elapsed_s": sessions[0]["elapsed_s"] if sessions else None,
                "size_bytes": sum(s["size_bytes"] for s in sessions),
                "sessions": sessions,
                "recorders": [r["node"] for r in self.state["recording"]],
                "streams": [
                    {"topic": t, "rate": round(v, 2)} for t, v in sorted(self.rates.items())
                ]
                if sessions
                else [],
            }
        )


async def _body(request: web.Request) -> dict[str, Any]:
    """The JSON object of a state-changing request; anything else is refused."""
    if request.content_type != "application/json":
        raise web.HTTPUnsupportedMediaType(text="send application/json\n")
    try:
        async with asyncio.timeout(BODY_TIMEOUT):  # a body sent a byte at a time: its slot
            text = await request.text()  # is not held for long (the headers have theirs)
    except TimeoutError:
        raise web.HTTPRequestTimeout(
            text=f"body not complete within {BODY_TIMEOUT:g} s\n"
        ) from None
    try:
        body = json.loads(text or "{}")
    except ValueError:
        raise web.HTTPBadRequest(text="the body is not JSON\n") from None
    except RecursionError:  # 100 000 nested [: refused, not a traceback
        raise web.HTTPBadRequest(text="the body is nested too deeply\n") from None
    if not isinstance(body, dict):
        raise web.HTTPBadRequest(text="the body is a JSON object\n")
    return body


async def _reports(folders: list[Path], wait: float) -> list[dict[str, Any]] | None:
    """Each session's ``streams.json`` once its recorder has finished the files."""
    end = time.monotonic() + wait
    while True:
        reports = []
        for folder in folders:
            try:
                reports.append(json.loads((folder / SESSION_FILE).read_text()))
            except (OSError, ValueError):
                break
        if len(reports) == len(folders):
            return reports
        if time.monotonic() > end:
            return None
        await asyncio.sleep(0.1)


def _size(folder: Path) -> int:
    try:
        return sum(f.stat().st_size for f in folder.iterdir() if f.suffix == ".mcap")
    except OSError:
        return 0


def _error(status: int, text: str) -> web.Response:
    return web.Response(
        status=status,
        text=json.dumps({"error": text}),
        content_type="application/json",
        headers={"Cache-Control": "no-store"},
    )


def _json(data: Any, status: int = 200) -> web.Response:
    return web.Response(
        status=status,
        text=json.dumps(data),
        content_type="application/json",
        headers={"Cache-Control": "no-store"},
    )
