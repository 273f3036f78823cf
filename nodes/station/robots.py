"""Several machines: the robots a base station's live view watches and records, over Zenoh.

A base station imports a robot's streams over Zenoh (``import:``); to run a campaign from
its page the operator also needs each robot's state and its recorder. Both go through the
robot's remote control channel, the one ``flowrt ctl --zenoh ENDPOINT --key KEY`` uses
(:mod:`flowrt.remote.control`: a graph with ``zenoh: {control: KEY}`` answers control
requests as Zenoh queries), so a robot opens no second network door::

    display:
      kind: display
      params:
        robots:
          robot1: {connect: ["tcp/192.168.1.10:7447"], control: robot1/flowrt/control}

Served by the view's server process (a Zenoh client session per robot, opened only when
``robots`` names one; queries run in threads):

- ``GET /api/robots``: per robot ``name``, ``reachable``, ``error``, ``graph``, ``uptime``,
  ``loop_lag_ms``, ``failed`` (nodes in error), ``streams`` (its sources: ``name``, ``fps``,
  ``state``), ``health`` (its ``health`` node's machine state, when it has one) and
  ``recording`` (each recorder's session, ``""`` when stopped); polled every ``POLL`` s.
- ``POST /api/robots/NAME/record/start`` ``{"name": "drive"}``: the robot's recorders start
  ``drive_NNN`` (``POST /record`` on the robot); answers ``{"session": ...}``.
- ``POST /api/robots/NAME/record/stop``: they stop; answers the robot's per-stream table once
  its recorder has finished the files (its ``reports`` in the robot's statistics).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from aiohttp import web

from flowrt.rtdb import RECORDING_SESSION

from .record import _body, _error, _json
from .sessions import valid_name

POLL = 2.0  # seconds between two looks at each robot
TIMEOUT = 3.0  # seconds a robot has to answer a query
RECORD_WAIT = 30.0  # seconds for a robot's recorders to start, or to finish their files
SOURCE_KINDS = ("capture", "replay", "audio", "can", "can-signals")


class _Robot:
    def __init__(self, name: str, spec: dict[str, Any]) -> None:
        self.name = name
        self.connect = [str(e) for e in spec.get("connect", [])]
        self.key = str(spec.get("control", ""))
        self.token: str | None = spec.get("token")
        self.client: Any = None
        self.state: dict[str, Any] = {"name": name, "reachable": False, "error": "not asked yet"}

    def _client(self) -> Any:
        if self.client is None:
            from flowrt.remote.control import ZenohControlClient

            self.client = ZenohControlClient(self.connect, self.key, self.token, timeout=TIMEOUT)
        return self.client

    def get(self, path: str) -> Any:
        return self._client().get(path)

    def post(self, path: str, body: Any) -> Any:
        return self._client().post(path, body)

    def reset(self) -> None:
        if self.client is not None:
            with contextlib.suppress(Exception):
                self.client.close()
            self.client = None

    def look(self) -> dict[str, Any]:
        """The robot's state now (on a thread: Zenoh queries block)."""
        from flowrt.control.server import ControlError

        try:
            stats = self.get("/stats")
            records = self.get("/rtdb")
        except ControlError as e:
            self.reset()
            return {"name": self.name, "reachable": False, "error": str(e), "at": time.time()}
        values = {r.get("name"): r.get("value") for r in records}
        recording = {
            k.removeprefix(RECORDING_SESSION): v
            for k, v in values.items()
            if isinstance(k, str) and k.startswith(RECORDING_SESSION)
        }
        health = values.get("health")
        machine = health.get("machine") if isinstance(health, dict) else None
        nodes = stats.get("nodes", [])
        return {
            "name": self.name,
            "reachable": True,
            "error": None,
            "at": time.time(),
            "graph": stats.get("graph"),
            "uptime": stats.get("uptime"),
            "loop_lag_ms": stats.get("loop", {}).get("lag", {}).get("p99"),
            "failed": [n["name"] for n in nodes if n.get("state") in ("error", "failed")],
            "streams": [
                {"name": n["name"], "fps": _fps(n), "state": n.get("state")}
                for n in nodes
                if n.get("kind") in SOURCE_KINDS
            ],
            "health": machine,
            "recording": recording,
            "reports": len((stats.get("reports") or {}).get(_recorder(recording), None) or []),
        }


def _fps(node: dict[str, Any]) -> float | None:
    iv = node.get("interval") or {}
    mean = iv.get("mean")
    return round(1000.0 / mean, 2) if iv.get("count") and mean else None


def _recorder(recording: dict[str, Any]) -> str:
    return next(iter(sorted(recording)), "")


class Robots:
    """The routes and the poller over the display's ``robots``."""

    def __init__(self, robots: dict[str, dict[str, Any]]) -> None:
        self.robots = {name: _Robot(name, spec) for name, spec in robots.items()}

    def routes(self) -> list[web.RouteDef]:
        return [
            web.get("/api/robots", self.list),
            web.post("/api/robots/{name}/record/{action}", self.record),
        ]

    async def poll(self) -> None:
        """Look at each robot every POLL seconds, all of them at once."""
        while self.robots:
            for robot, state in zip(
                self.robots.values(),
                await asyncio.gather(*(asyncio.to_thread(r.look) for r in self.robots.values())),
                strict=True,
            ):
                robot.state = state
            await asyncio.sleep(POLL)

    def close(self) -> None:
        for r in self.robots.values():
            r.reset()

    async def list(self, request: web.Request) -> web.Response:
        return _json({"robots": [r.state for r in self.robots.values()]})

    async def record(self, request: web.Request) -> web.Response:
        robot = self.robots.get(request.match_info["name"])
        action = request.match_info["action"]
        if robot is None or action not in ("start", "stop"):
            raise web.HTTPNotFound(text="no such robot or action\n")
        body = await _body(request)
        name = body.get("name")
        if action == "start" and (not isinstance(name, str) or not valid_name(name)):
            return _error(400, "name: a session name, letters, digits, _ and - (at most 64)")
        from flowrt.control.server import ControlError

        try:
            return await asyncio.to_thread(_record, robot, action, name)
        except ControlError as e:
            robot.reset()
            return _error(502, f"{robot.name}: {e}")


def _record(robot: _Robot, action: str, name: Any) -> web.Response:
    """Start or stop the robot's recorders and wait for their answer (on a thread)."""
    before = robot.look()
    if not before["reachable"]:
        return _error(502, f"{robot.name}: {before['error']}")
    recording = before["recording"]
    if action == "start" and any(recording.values()):
        return _error(409, f"{robot.name} is already recording")
    if action == "stop" and not any(recording.values()):
        return _error(409, f"{robot.name} is not recording")
    body: dict[str, Any] = {"action": action}
    if action == "start":
        body["name"] = name
    nodes = robot.post("/record", body)["nodes"]
    end = time.monotonic() + RECORD_WAIT
    while time.monotonic() < end:
        now = robot.look()
        sessions = now.get("recording", {})
        if action == "start" and all(sessions.get(n) for n in nodes):
            robot.state = now
            first = str(sessions[nodes[0]])
            return _json({"robot": robot.name, "session": first.rsplit("/", 1)[-1]})
        if action == "stop" and now.get("reports", 0) > before.get("reports", 0):
            robot.state = now
            reports = robot.get("/stats").get("reports", {}).get(nodes[0]) or [{}]
            table = reports[-1]
            streams = table.get("streams", [])
            return _json(
                {
                    "robot": robot.name,
                    "session": table.get("session"),
                    "duration_s": table.get("duration"),
                    "lost": sum(int(s.get("lost", 0)) for s in streams),
                    "streams": streams,
                }
            )
        time.sleep(0.2)
    return _error(504, f"{robot.name}: the recorders did not {action} in {RECORD_WAIT:g} s")
