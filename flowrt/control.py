"""The control endpoint: a local HTTP API of a running runtime, and ``flowrt ctl``, its client.

    flowrt run graph.yaml --control 8765          # serve on 127.0.0.1:8765
    flowrt ctl stats                              # the status table of the running graph
    flowrt ctl timing ball_fr --period 2          # applied between ticks
    flowrt ctl mode defend

Endpoints (JSON in and out): ``GET /stats`` (``RuntimeStats``), ``GET /events?n=50``,
``GET /modes``, ``POST /mode {"mode": NAME}``, ``POST /timing {"node": NAME, "period": 2,
"phase": 0, "timer": ms, "deadline": ms, "priority": 40, "enabled": true}``, ``GET /qos``,
``GET /rtdb`` and ``GET /rtdb/NAME?n=8``.

Security: the server runs on the runtime's event loop (a request is handled between ticks,
so a change is atomic like any other) and binds 127.0.0.1 by default. Bound to any other
address it refuses to start without a bearer token, and every request must carry
``Authorization: Bearer TOKEN``; a token given on loopback is required too. On loopback
without a token, requests whose ``Host`` is not a loopback name are refused (a web page
cannot reach the API through DNS rebinding), and changes must be sent as
``application/json`` (which a browser will not send cross-site without asking).
"""

from __future__ import annotations

import dataclasses
import hmac
import ipaddress
import json
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, ValidationError

from .events import Event, NodeFailed

if TYPE_CHECKING:
    from aiohttp import web

    from .runtime import Runtime

DEFAULT_PORT = 8765
DEFAULT_URL = f"http://127.0.0.1:{DEFAULT_PORT}"


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses; any other name counts as exposed."""
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class ControlConfig:
    """Where the control endpoint listens and the token it requires (None: loopback only)."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT  # 0: any free port (see ``ControlServer.url``)
    token: str | None = None

    @classmethod
    def parse(cls, text: str, token: str | None = None) -> ControlConfig:
        """``PORT``, ``HOST:PORT`` or ``[IPV6]:PORT``."""
        host, sep, port = text.rpartition(":")
        if not sep:
            host, port = "127.0.0.1", text
        host = host.strip("[]") or "127.0.0.1"
        try:
            number = int(port)
        except ValueError:
            raise ValueError(f"--control expects [HOST:]PORT, got {text!r}") from None
        if not 0 <= number <= 65535:
            raise ValueError(f"port out of range: {number}")
        return cls(host, number, token)

    @property
    def needs_token(self) -> bool:
        return not is_loopback(self.host)

    @classmethod
    def checked(cls, config: ControlConfig | str) -> ControlConfig:
        """Parse and check: beyond loopback, a token is required (ValueError otherwise)."""
        config = cls.parse(config) if isinstance(config, str) else config
        if config.needs_token and not config.token:
            raise ValueError(
                f"refusing to serve the control endpoint on {config.host} without a token: "
                "give --token (or FLOWRT_TOKEN), or bind 127.0.0.1"
            )
        return config


class TimingRequest(BaseModel):
    """Body of ``POST /timing``: the node and the fields to change (ms for timer/deadline)."""

    model_config = ConfigDict(extra="forbid")
    node: str
    period: int | None = None
    phase: int | None = None
    timer: float | None = None
    deadline: float | None = None
    priority: int | None = None
    enabled: bool | None = None
    force: bool = False  # past admission control


class ModeRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: str
    force: bool = False  # past admission control


def jsonable(value: Any) -> Any:
    """A JSON-friendly copy of event fields and RTDB values (repr for what is not data)."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    item = getattr(value, "item", None)  # numpy scalars
    if callable(item) and getattr(value, "shape", None) == ():
        return jsonable(item())
    return repr(value)


def event_json(event: Event) -> dict[str, Any]:
    out = {"kind": event.kind, **jsonable(event)}
    if isinstance(event, NodeFailed):
        out.pop("traceback", None)
    return out


class ControlServer:
    """The HTTP API of ``rt``, served on the runtime's event loop (aiohttp)."""

    def __init__(self, rt: Runtime, config: ControlConfig | str) -> None:
        self.rt = rt
        self.config = ControlConfig.checked(config)
        self._runner: web.AppRunner | None = None
        self.port = self.config.port

    @property
    def url(self) -> str:
        host = self.config.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}"

    async def start(self) -> None:
        from aiohttp import web

        app = web.Application(middlewares=[self._guard])
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/stats", self._stats),
                web.get("/events", self._events),
                web.get("/modes", self._modes),
                web.post("/mode", self._mode),
                web.post("/timing", self._timing),
                web.get("/qos", self._qos),
                web.get("/rtdb", self._rtdb),
                web.get("/rtdb/{name}", self._rtdb_record),
            ]
        )
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        await site.start()
        addresses = self._runner.addresses
        if addresses:
            self.port = int(addresses[0][1])

    async def stop(self) -> None:
        if self._runner is not None:
            runner, self._runner = self._runner, None
            await runner.cleanup()

    # --- guard ----------------------------------------------------------------------------

    @property
    def _guard(self) -> Any:
        from aiohttp import web

        token = self.config.token
        loopback_only = not token

        @web.middleware
        async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
            if token:
                scheme, _, given = request.headers.get("Authorization", "").partition(" ")
                if scheme.lower() != "bearer" or not hmac.compare_digest(
                    given.strip().encode(), token.encode()
                ):
                    return _error(
                        401,
                        "missing or wrong bearer token",
                        {"WWW-Authenticate": 'Bearer realm="flowrt"'},
                    )
            elif loopback_only and not is_loopback(_hostname(request.host)):
                return _error(403, f"Host {request.host!r} is not a loopback name")
            if request.method == "POST" and request.content_type != "application/json":
                return _error(415, "send a JSON body with Content-Type: application/json")
            return await handler(request)  # type: ignore[no-any-return]

        return guard

    # --- handlers -------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.Response:
        return _json(
            {
                "graph": self.rt.graph.spec.name,
                "endpoints": [
                    "GET /stats",
                    "GET /events?n=50",
                    "GET /modes",
                    "POST /mode",
                    "POST /timing",
                    "GET /qos",
                    "GET /rtdb",
                    "GET /rtdb/{name}?n=8",
                ],
            }
        )

    async def _stats(self, request: web.Request) -> web.Response:
        from aiohttp import web

        return web.Response(text=self.rt.stats().model_dump_json(), content_type="application/json")

    async def _events(self, request: web.Request) -> web.Response:
        n = _int_query(request, "n", 50)
        events = list(self.rt.events)[-n:] if n > 0 else []
        return _json([event_json(e) for e in events])

    async def _modes(self, request: web.Request) -> web.Response:
        return _json({"modes": list(self.rt.graph.spec.modes), "current": self.rt.mode})

    async def _mode(self, request: web.Request) -> web.Response:
        body = await _body(request, ModeRequest)
        try:
            self.rt.set_mode(body.mode, origin="control", force=body.force)
        except KeyError as e:
            return _error(404, str(e.args[0]))
        except ValueError as e:
            return _error(400, str(e))
        return _json({"mode": self.rt.mode})

    async def _timing(self, request: web.Request) -> web.Response:
        body = await _body(request, TimingRequest)
        fields = body.model_dump(exclude={"node"})
        try:
            change = self.rt.set_timing(body.node, origin="control", **fields)
        except KeyError as e:
            return _error(404, str(e.args[0]))
        except ValueError as e:
            return _error(400, str(e))
        return _json({"node": body.node, "change": change})

    async def _qos(self, request: web.Request) -> web.Response:
        status = self.rt.qos_status()
        return _json({**jsonable(status), "summary": status.describe()})

    async def _rtdb(self, request: web.Request) -> web.Response:
        return _json([_record_json(r) for r in self.rt.rtdb.records()])

    async def _rtdb_record(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        records = self.rt.rtdb.history(name, _int_query(request, "n", 1))
        if not records:
            return _error(404, f"no record {name!r}")
        return _json([_record_json(r) for r in records])


def _record_json(rec: Any) -> dict[str, Any]:
    out = jsonable(rec)
    assert isinstance(out, dict)
    return out


def _hostname(host: str) -> str:
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _int_query(request: web.Request, key: str, default: int) -> int:
    from aiohttp import web

    try:
        return int(request.query.get(key, default))
    except ValueError:
        raise web.HTTPBadRequest(text=json.dumps({"error": f"{key} must be an integer"})) from None


async def _body(request: web.Request, model: type[Any]) -> Any:
    from aiohttp import web

    try:
        return model.model_validate(await request.json())
    except (ValueError, ValidationError) as e:
        text = json.dumps({"error": f"bad request body: {e}"})
        raise web.HTTPBadRequest(text=text, content_type="application/json") from None


def _json(data: Any) -> web.Response:
    from aiohttp import web

    return web.json_response(data)


def _error(status: int, message: str, headers: dict[str, str] | None = None) -> web.Response:
    from aiohttp import web

    return web.json_response({"error": message}, status=status, headers=headers)


# --- the client: flowrt ctl ---------------------------------------------------------------


class ControlError(Exception):
    """The runtime could not be reached or refused the request; the message says which."""


class ControlClient:
    """A small synchronous client of the control endpoint (stdlib only)."""

    def __init__(
        self, url: str = DEFAULT_URL, token: str | None = None, timeout: float = 5.0
    ) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    def request(self, method: str, path: str, body: Any = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method)
        if data is not None:
            req.add_header("Content-Type", "application/json")
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return json.loads(resp.read() or b"null")
        except urllib.error.HTTPError as e:
            try:
                message = json.loads(e.read()).get("error", e.reason)
            except (ValueError, AttributeError):
                message = e.reason
            if e.code == 401:
                message = f"{message} (give --token or set FLOWRT_TOKEN)"
            raise ControlError(f"{e.code}: {message}") from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise ControlError(
                f"cannot reach the runtime at {self.url} ({reason}); "
                "is `flowrt run --control` running?"
            ) from None

    def get(self, path: str) -> Any:
        return self.request("GET", path)

    def post(self, path: str, body: Any) -> Any:
        return self.request("POST", path, body)
