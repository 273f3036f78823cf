"""The control endpoint: a local HTTP API of a running runtime, and ``flowrt ctl``, its client.

    flowrt run graph.yaml --control 8766          # serve on 127.0.0.1:8766
    flowrt ctl stats                              # the status table of the running graph
    flowrt ctl timing ball_fr --period 2          # applied between ticks
    flowrt ctl mode defend

From Python, the endpoint is a user of a started runtime (the runtime does not know it)::

    async with flowrt.Runtime.from_file("graph.yaml") as rt:
        async with flowrt.ControlServer(rt, "127.0.0.1:8766"):
            await rt.run()

Endpoints (JSON in and out): ``GET /stats`` (``RuntimeStats``), ``GET /events?n=50``,
``GET /modes``, ``POST /mode {"mode": NAME}``, ``POST /timing {"node": NAME, "period": 2,
"phase": 0, "timer": ms, "deadline": ms, "priority": 40, "enabled": true}``, ``GET /qos``,
``GET /rtdb`` and ``GET /rtdb/NAME?n=8``.

Off the scheduler's path: HTTP is served by a process of its own (``flowrt-control``, nice
19), not by the runtime's event loop nor a thread of its process, so that no number of
clients takes the loop's time or its GIL, and slow clients hold that process's descriptors,
never the runtime's (which its workers need to restart). The server forwards what it cannot
answer itself over a socket pair to the runtime, which answers one request at a time, in the
quiet gap between timer releases (:meth:`flowrt.Runtime.quiet_delay`); reads are cached for
``READ_MAX_AGE`` and shared by every client asking meanwhile, so 200 clients polling
``/stats`` cost the loop what one client polling 5 times a second costs; and a connection
that asks again sooner than that is answered when the cache may hold news (its client waits
rather than spins). The routes are one table (:mod:`flowrt.control.routes`); a body
is refused here unless its request model accepts it, and a timing change is checked once
more, whole, against its node (``Runtime.apply_timing``) before any of it is applied, then
applied between ticks, at once. Limits: ``MAX_CONNECTIONS`` at once (more are
closed as they arrive), a request's headers within ``REQUEST_TIMEOUT`` of the connection or
of its previous request, a whole request within ``REQUEST_TIMEOUT``, bodies up to
``MAX_BODY``.

Who may do what: the server binds 127.0.0.1 by default. Without a token any local process
may read and change (modes, timing); ``--control-token-required`` (``ControlConfig(...,
token_required=True)``) requires ``Authorization: Bearer TOKEN`` on loopback too. Bound to
any other address it refuses to start without a token. On loopback without a token,
requests whose ``Host`` is not a loopback name are refused (a web page cannot reach the API
through DNS rebinding), and changes must be sent as ``application/json`` (which a browser
will not send cross-site without asking).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import multiprocessing
import socket
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from ..system import _spawned as spawned
from .client import DEFAULT_PORT as DEFAULT_PORT  # the client's, re-exported
from .client import DEFAULT_URL as DEFAULT_URL
from .client import ControlClient as ControlClient
from .client import ControlError as ControlError
from .routes import ENDPOINTS as ENDPOINTS  # what GET / lists
from .routes import ROUTES, Route, answer, one_line
from .routes import dumps as _dumps
from .serving import (
    Conns,
    Refuse,
    Tracked,
    hostname,
    is_loopback,
    lower_priority,
    pack,
    serve_in_process,
    stop_server,
    unpack,
)

if TYPE_CHECKING:
    from aiohttp import web

    from ..runtime._runtime import Runtime

log = logging.getLogger("flowrt.control.server")


MAX_CONNECTIONS = 256  # open connections at once; more are closed as they arrive
REQUEST_TIMEOUT = 10.0  # seconds for a request's headers (from the previous one)
FIRST_REQUEST_TIMEOUT = 2.0  # seconds a new connection has for its first request
BODY_TIMEOUT = 5.0  # seconds for a request's body, once its headers are in (then 408)
QUEUE_WAIT = 5.0  # seconds a change waits behind others before it is refused, not sent
RESERVED = 8  # connections over the cap, kept for requests that carry the token
MAX_BODY = 1 << 20  # bytes of a request body
READ_MAX_AGE = 0.2  # seconds a read (stats, events, ...) is served from the server's cache
MAX_EVENTS = 1000  # ?n= of /events, /rtdb/NAME
START_TIMEOUT = 30.0  # seconds for the server process to start (spawn + imports)


@dataclass(frozen=True)
class ControlConfig:
    """Where the control endpoint listens and the token it requires (None: loopback only)."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT  # 0: any free port (see ``ControlServer.url``)
    token: str | None = None
    token_required: bool = False  # require the token on loopback too (a shared computer)
    # kinds POST /swap may name besides those the graph uses (--control-allow-kinds and the
    # graph's control_allow_kinds): a caller never makes the runtime import anything else
    allow_kinds: tuple[str, ...] = ()

    @classmethod
    def parse(
        cls, text: str, token: str | None = None, token_required: bool = False
    ) -> ControlConfig:
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
        return cls(host, number, token, token_required)

    @property
    def needs_token(self) -> bool:
        return self.token_required or not is_loopback(self.host)

    @classmethod
    def checked(cls, config: ControlConfig | str) -> ControlConfig:
        """Parse and check: beyond loopback, a token is required (ValueError otherwise)."""
        config = cls.parse(config) if isinstance(config, str) else config
        if config.needs_token and not config.token:
            where = "with token_required" if is_loopback(config.host) else f"on {config.host}"
            raise ValueError(
                f"refusing to serve the control endpoint {where} without a token: "
                "give --token (or FLOWRT_TOKEN), or bind 127.0.0.1"
            )
        return config


def listen(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port``; OSError names the address when it cannot."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError as e:
        raise OSError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    family, *_, address = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError as e:
        sock.close()
        raise OSError(e.errno, f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    sock.setblocking(False)
    return sock


# --- the runtime's side -------------------------------------------------------------------


class ControlServer:
    """The HTTP API of a started runtime ``rt``; see the module docstring.

    ``bind()`` takes the port (and fails, with the address in the message, when it is taken)
    without starting anything, so a program can check it before it starts the runtime;
    ``start()`` binds if needed, starts the server process and waits until it serves. Use as
    ``async with``. ``spawn()`` and ``wait_ready()`` are ``start()``'s two halves, for a
    caller that runs meanwhile: the server process starts at the lowest priority, and on a
    machine the graph keeps busy its imports take seconds (clients wait in the bound port's
    backlog), which ``flowrt run --duration`` must not count nor a signal wait for.
    """

    def __init__(
        self,
        rt: Runtime,
        config: ControlConfig | str,
        *,
        max_connections: int = MAX_CONNECTIONS,
        request_timeout: float = REQUEST_TIMEOUT,
    ) -> None:
        self.rt = rt
        self.config = ControlConfig.checked(config)
        self.limits = {"max_connections": max_connections, "request_timeout": request_timeout}
        self.port = self.config.port
        self._sock: socket.socket | None = None
        self._proc: Any = None
        self._task: asyncio.Task[None] | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._ready: asyncio.Future[None] | None = None  # set by the process's "ready"
        self.answered = 0  # requests the runtime answered (the rest came from the cache)

    @property
    def url(self) -> str:
        host = self.config.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}"

    def bind(self) -> None:
        """Take the address now (OSError: e.g. ``cannot listen on 127.0.0.1:8766: ...``)."""
        if self._sock is None:
            self._sock = listen(self.config.host, self.config.port)
            self.port = int(self._sock.getsockname()[1])

    async def __aenter__(self) -> ControlServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        await self.spawn()
        await self.wait_ready()

    async def spawn(self) -> None:
        """Start the server process; it serves once :meth:`wait_ready` returns."""
        if self._proc is not None:
            return
        if not self.rt.started:
            raise RuntimeError("start the runtime before its control endpoint")
        self.bind()
        assert self._sock is not None
        ours, theirs = socket.socketpair()
        ctx = multiprocessing.get_context("spawn")
        settings = {"host": self.config.host, "token": self.config.token, **self.limits}
        proc = ctx.Process(
            target=_serve, args=(self._sock, theirs, settings), name="flowrt-control", daemon=True
        )
        spawned.start(proc)
        if proc.pid is not None:  # before its imports, which would compete with the loop
            lower_priority(proc.pid)
        theirs.close()
        self._sock.close()  # the server process holds its own copy
        self._sock = None
        self._proc = proc
        reader, self._writer = await asyncio.open_unix_connection(sock=ours)
        ready = self._ready = asyncio.get_running_loop().create_future()
        self._task = asyncio.get_running_loop().create_task(self._answer_all(reader, ready))

    async def wait_ready(self) -> None:
        """Until the server process serves; RuntimeError (the server stopped) if it does
        not within :data:`START_TIMEOUT`."""
        if self._ready is None:
            raise RuntimeError("the control endpoint was not started")
        try:
            await asyncio.wait_for(asyncio.shield(self._ready), START_TIMEOUT)
        except (TimeoutError, ConnectionError, asyncio.IncompleteReadError) as e:
            await self.stop()
            raise RuntimeError(f"the control endpoint's process did not start: {e!r}") from None

    @property
    def serving(self) -> bool:
        """The server process said it serves."""
        ready = self._ready
        if ready is None or not ready.done() or ready.cancelled():
            return False
        return ready.exception() is None

    async def stop(self) -> None:
        """Close the server (its process ends when the channel closes)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        writer, task, proc = self._writer, self._task, self._proc
        grace = 2.0 if self.serving else 0.0  # still importing: nothing to close in order
        self._writer = self._task = self._proc = None
        await stop_server(writer, task, proc, grace=grace)

    async def _answer_all(self, reader: asyncio.StreamReader, ready: asyncio.Future[None]) -> None:
        """Answer the server's requests one at a time, each between ticks."""
        try:
            while True:
                header, body = await unpack(reader)
                if header.get("op") == "ready":
                    if not ready.done():
                        ready.set_result(None)
                    continue
                if self.rt.started:
                    # Serialising the statistics holds the loop ~1 ms: between ticks.
                    await asyncio.sleep(self.rt.quiet_delay(0.0))
                status, data = await answer(self, str(header.get("op")), body)
                self.answered += 1
                writer = self._writer
                if writer is None:
                    return
                writer.write(pack({"id": header.get("id"), "status": status}, data))
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError) as e:
            if not ready.done():
                ready.set_exception(e)
            elif self.rt.started and self._writer is not None:
                log.warning("control endpoint: its server process ended; %s is gone", self.url)

    def allowed_kinds(self) -> set[str]:
        """What ``POST /swap`` may name: the graph's kinds, the graph's and the config's list."""
        spec = self.rt.graph.spec
        return {
            *(n.kind for n in spec.nodes.values()),
            *spec.control_allow_kinds,
            *self.config.allow_kinds,
        }


# --- the server's process -----------------------------------------------------------------


def _serve(sock: socket.socket, channel: socket.socket, settings: dict[str, Any]) -> None:
    """The server process (see :func:`serving.serve_in_process`)."""
    serve_in_process(_Gateway, sock, channel, settings)


class _Gateway:
    """The HTTP side: guards, limits and a cache in front of the runtime's answers."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.host: str = settings["host"]
        self.token: str | None = settings["token"]
        self.max_connections: int = settings["max_connections"]
        self.timeout: float = settings["request_timeout"]
        self.conns = Conns()
        self.refused = 0
        self.timed_out = 0
        self.evicted = 0  # connections closed at the cap before their first request
        self._next_id = 0
        self._pending: dict[int, asyncio.Future[tuple[int, bytes]]] = {}
        self._cache: dict[str, tuple[float, int, bytes]] = {}
        self._inflight: dict[str, asyncio.Future[tuple[int, bytes]]] = {}
        self._changes = asyncio.Lock()
        self._writer: asyncio.StreamWriter | None = None
        self._closed = asyncio.Event()

    async def run(self, sock: socket.socket, channel: socket.socket) -> None:
        from aiohttp import web

        loop = asyncio.get_running_loop()
        reader, self._writer = await asyncio.open_unix_connection(sock=channel)
        app = web.Application(middlewares=[self._guard], client_max_size=MAX_BODY)
        app.add_routes([web.route(r.method, r.path, self._handler(r)) for r in ROUTES])
        runner = web.AppRunner(
            app, access_log=None, handle_signals=False, keepalive_timeout=self.timeout
        )
        await runner.setup()
        server = runner.server
        assert server is not None
        gateway = self
        first = min(FIRST_REQUEST_TIMEOUT, self.timeout)

        def factory() -> asyncio.Protocol:
            """A slot for every new connection while there are some; at the cap, the oldest
            connection that has not sent a request yet makes room (slow clients cannot hold
            the slots: they have FIRST_REQUEST_TIMEOUT, and are first to go); else one of
            RESERVED more, which only a request carrying the token keeps."""
            if gateway.conns.count() >= gateway.max_connections:
                idle = [
                    c
                    for c in gateway.conns.values()
                    if not c.requests and not c.busy and not c.headers_in
                ]
                if idle:
                    oldest = min(idle, key=lambda c: c.deadline)
                    gateway.conns.pop(oldest.transport, None)
                    oldest.transport.close()
                    gateway.evicted += 1
                elif gateway.token and gateway.conns.count() < gateway.max_connections + RESERVED:
                    return Tracked(server(), gateway.conns, first, reserve=True)
                else:
                    gateway.refused += 1
                    return Refuse()
            return Tracked(server(), gateway.conns, first)

        listener = await loop.create_server(factory, sock=sock)
        sweeper = loop.create_task(self._sweep())
        self._writer.write(pack({"op": "ready"}))
        try:
            await self._read_answers(reader)
        finally:
            sweeper.cancel()
            listener.close()
            for conn in list(self.conns.values()):
                conn.transport.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(runner.cleanup(), 2.0)

    async def _read_answers(self, reader: asyncio.StreamReader) -> None:
        """Hand each answer to the request waiting for it; return when the runtime is gone."""
        try:
            while True:
                header, body = await unpack(reader)
                fut = self._pending.pop(header["id"], None)
                if fut is not None and not fut.done():
                    fut.set_result((int(header["status"]), body))
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        for fut in self._pending.values():
            if not fut.done():
                fut.set_result((503, _dumps({"error": "the runtime has stopped"})))

    async def _sweep(self) -> None:
        """Close connections that sent no complete request in time (slow or idle clients)."""
        while True:
            await asyncio.sleep(min(0.5, self.timeout / 4))
            now = time.monotonic()
            for conn in list(self.conns.values()):
                if conn.late(now):
                    self.timed_out += 1
                    conn.transport.close()

    # --- talking to the runtime -----------------------------------------------------------

    async def _ask(self, op: str, args: Any) -> tuple[int, bytes]:
        if self._writer is None or self._writer.is_closing():
            return 503, _dumps({"error": "the runtime has stopped"})
        self._next_id += 1
        fut: asyncio.Future[tuple[int, bytes]] = asyncio.get_running_loop().create_future()
        self._pending[self._next_id] = fut
        self._writer.write(pack({"id": self._next_id, "op": op}, _dumps(args)))
        return await fut

    async def read(self, op: str, args: dict[str, Any]) -> tuple[int, bytes]:
        """A read, from the cache when fresh, shared with the same read in flight."""
        key = op + json.dumps(args, sort_keys=True)
        cached = self._cache.get(key)
        if cached is not None and time.monotonic() - cached[0] < READ_MAX_AGE:
            return cached[1], cached[2]
        fut = self._inflight.get(key)
        if fut is None:
            fut = asyncio.ensure_future(self._ask(op, args))
            self._inflight[key] = fut
            fut.add_done_callback(lambda f: self._store(key, f))
        return await asyncio.shield(fut)

    def _store(self, key: str, fut: asyncio.Future[tuple[int, bytes]]) -> None:
        self._inflight.pop(key, None)
        if not fut.cancelled() and fut.exception() is None:
            if len(self._cache) > 256:  # keys vary by query: keep the cache bounded
                self._cache.clear()
            self._cache[key] = (time.monotonic(), *fut.result())

    async def change(self, op: str, args: Any) -> tuple[int, bytes]:
        """A change: one at a time, and the reads cached before it are forgotten.

        Every answer says whether it was applied: one that waited :data:`QUEUE_WAIT` behind
        others is never sent (503, not applied); one sent is applied by the runtime at its
        next quiet gap, and is answered with what it did, or, past ``timeout``, 504 (sent,
        the outcome unknown): never a 408 for a change applied after all."""
        try:
            async with asyncio.timeout(min(QUEUE_WAIT, self.timeout)):
                await self._changes.acquire()
        except TimeoutError:
            return 503, _dumps(
                {"error": "busy: other changes are ahead of this one; not applied, try again"}
            )
        try:
            async with asyncio.timeout(self.timeout):
                return await self._ask(op, args)
        except TimeoutError:
            return 504, _dumps(
                {
                    "error": f"sent, but the runtime did not answer within {self.timeout:g} s: "
                    "it may still be applied (see `flowrt ctl events`)"
                }
            )
        finally:
            self._cache.clear()
            self._changes.release()

    # --- HTTP -------------------------------------------------------------------------------

    @property
    def _guard(self) -> Any:
        from aiohttp import web

        token = self.token

        @web.middleware
        async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
            conn = self.conns.get(request.transport) if request.transport is not None else None
            if conn is not None:
                conn.busy += 1
            try:
                if conn is not None:
                    conn.requests += 1
                if token:
                    scheme, _, given = request.headers.get("Authorization", "").partition(" ")
                    if scheme.lower() != "bearer" or not hmac.compare_digest(
                        given.strip().encode(), token.encode()
                    ):
                        if conn is not None and conn.reserve:  # the token holder's slot
                            conn.transport.close()
                        return _error(
                            401,
                            "missing or wrong bearer token",
                            headers={"WWW-Authenticate": 'Bearer realm="flowrt"'},
                        )
                elif not is_loopback(hostname(request.host)):
                    return _error(403, f"Host {request.host!r} is not a loopback name")
                if request.transport is None or request.transport.is_closing():
                    # closed before its turn came (evicted, the client gone): no answer can
                    # reach it, so nothing is done either (a change applied unanswered)
                    return _error(503, "the connection closed before the request was read")
                if request.method == "POST" and request.content_type != "application/json":
                    return _error(415, "send a JSON body with Content-Type: application/json")
                if conn is not None and request.method == "GET":
                    # One connection polling faster than the data changes gets the next
                    # answer when there may be news: its client waits instead of spinning.
                    now = time.monotonic()
                    if conn.next_read > now:
                        await asyncio.sleep(conn.next_read - now)
                    conn.next_read = max(now, conn.next_read) + READ_MAX_AGE
                return await handler(request)  # type: ignore[no-any-return]
            finally:
                if conn is not None:
                    conn.busy -= 1
                    conn.answered(self.timeout)

        return guard

    def _handler(self, route: Route) -> Callable[[web.Request], Awaitable[web.Response]]:
        """A POST's body is refused here unless its request model accepts it (the runtime
        then trusts it); a GET reads its path and integer query parameters."""
        model = route.body
        if model is not None:

            async def post(request: web.Request) -> web.Response:
                wait = min(BODY_TIMEOUT, self.timeout)
                try:
                    async with asyncio.timeout(wait):  # a body sent a byte at a time
                        raw = await request.read()
                except TimeoutError:
                    return _error(408, f"request body not complete within {wait:g} s")
                try:
                    data = json.loads(raw, parse_constant=_no_constant)
                    body = model.model_validate(data)
                except RecursionError:
                    return _error(400, "bad request body: nested too deeply", MALFORMED)
                except (ValueError, ValidationError) as e:  # JSONDecodeError is a ValueError
                    return _error(400, f"bad request body: {one_line(e)}", MALFORMED)
                status, answer = await self.change(route.op, body.model_dump(mode="json"))
                return _reply(status, answer, {"Retry-After": "1"} if status == 503 else None)

            return post

        async def get(request: web.Request) -> web.Response:
            args: dict[str, Any] = dict(request.match_info)
            for key, default in route.query:
                args[key] = _int_query(request, key, default)
            try:
                async with asyncio.timeout(self.timeout):
                    return _reply(*await self.read(route.op, args))
            except TimeoutError:
                return _error(408, f"request not complete within {self.timeout:g} s")

        return get


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number here")


def _int_query(request: web.Request, key: str, default: int) -> int:
    from aiohttp import web

    try:
        value = int(request.query.get(key, default))
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_EVENTS:
        text = json.dumps({"error": f"{key} must be an integer in 0..{MAX_EVENTS}"})
        raise web.HTTPBadRequest(text=text, content_type="application/json")
    return value


def _reply(status: int, body: bytes, headers: dict[str, str] | None = None) -> web.Response:
    from aiohttp import web

    return web.Response(status=status, body=body, content_type="application/json", headers=headers)


MALFORMED = "malformed"  # a refusal's ``code``: the body, not the change it asks for


def _error(
    status: int, message: str, code: str | None = None, headers: dict[str, str] | None = None
) -> web.Response:
    """``{"error": message}``, and ``"code"`` where a script must tell refusals of one status
    apart (a 400 for a malformed body, ``malformed``, from admission control's 400)."""
    from aiohttp import web

    body = {"error": message} if code is None else {"error": message, "code": code}
    return web.json_response(body, status=status, headers=headers)


# --- the client: flowrt ctl ---------------------------------------------------------------
