"""The live view's web server: a process of its own, fed by the display node.

Why a process: every HTTP request costs Python time (parsing, a handler, a response), and
a JPEG encode holds the GIL for milliseconds. On the runtime's event loop that time delays
ticks; in a thread of the runtime's process it still takes the GIL from the loop; with 200
clients on the loop the cameras' interval std grew 10-30x (benchmarks/RESULTS.md). Here it
costs the runtime nothing per client: the display node lends a source's newest frame at
most once per frame (only while someone watches, at most at ``max_fps``) over a socket
pair; this process encodes it once and shares the JPEGs among every client, so the node's
work per tick does not grow with the number of clients. Slow or idle clients hold this
process's descriptors, never the runtime's.

The channel carries frames of ``>II`` (header length, body length), a JSON header and a
body. The node sends ``frame`` (a source's newest frame, pickled: a descriptor of its
shared-memory slot, which this process maps, and the detections to draw on it; one per
source at a time, encoded here in a thread), ``sources`` (the inputs that have sent frames),
``stats`` (an answer) and ``reply`` (the answer to a request with an ``id``); this process
sends ``ready``, ``want`` (a frame of a source newer than the one it has), ``done`` (the
node may release the frame it lent), ``stats`` (a request) and ``record`` (the record
panel's start or stop, with an ``id``). The frames as shown (encoded once, shared by every
client) are kept by :mod:`.shown`.

The operator's station lives here too (:mod:`.operator_station`): the record panel, the
review of recorded sessions, the health over time and the robots of a base station.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import hmac
import json
import secrets
import socket
import time
from typing import Any
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from flowrt.control.serving import (
    Conns,
    Refuse,
    Tracked,
    hostname,
    is_loopback,
    pack,
    serve_in_process,
    unpack,
)
from flowrt.refusals import finite_number

from ..display_streams import MAX_BEHIND, MAX_PER_PEER, StreamSlots
from .shown import ShownFrames
from .station import Calls, Station

STATS_MAX_AGE = 0.2  # seconds /stats.json is served from this process's cache
STATS_WAIT = 2.0  # seconds to wait for the node's statistics
SOURCE_WAIT = 3.0  # seconds a request for a source that has sent no frame yet waits for one
SNAPSHOT_WAIT = 0.5  # seconds a snapshot waits for a newer frame than the one cached
FIRST_WAIT = 5.0  # seconds a snapshot waits for a source's first encoded frame
HEADER_TIMEOUT = 10.0  # seconds a connection has to send a request's headers
CLOSE_TIMEOUT = 1.0  # seconds given to clients to close at the end
STREAM_CHECK = 0.25  # seconds between two checks of how far behind a stream client is
MAX_SESSIONS = 1024  # page sessions remembered (each page load makes one)
COOKIE = "flowrt_view"  # holds the token once the page was opened with ?token=
JPEG_PART = "Content-Type: image/jpeg\r\nContent-Length: "
CALL_WAIT = 30.0  # seconds the node has to answer a request (the recorders' start or stop)


def serve(sock: socket.socket, channel: socket.socket, settings: dict[str, Any]) -> None:
    """The process (see :func:`flowrt.control.serving.serve_in_process`)."""
    serve_in_process(ViewServer, sock, channel, settings)


class _Client:
    """A websocket client: what it was last sent per source and whether it acked it."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.sent: dict[str, int] = {}
        self.waiting_ack: set[str] = set()


class ViewServer:
    """The HTTP side of the live view; see the module docstring."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.token: str | None = settings.get("token")
        self.allowed_hosts: list[str] = list(settings.get("allowed_hosts", ()))
        self.max_clients: int = int(settings.get("max_clients", 32))
        self.url: str = settings.get("url", "")
        self.page: bytes = settings.get("page", b"")
        self.source_wait = float(settings.get("source_wait", SOURCE_WAIT))
        inputs = settings.get("inputs")
        self.inputs = None if inputs is None else frozenset(inputs)  # None: not known
        self.header_timeout = float(settings.get("header_timeout", HEADER_TIMEOUT))
        self.names: set[str] = set()  # inputs that have sent frames, as the node says
        self.clients: set[_Client] = set()
        max_streams = int(settings.get("max_streams", max(1, self.max_clients // 2)))
        per_peer = int(settings.get("max_streams_per_peer", MAX_PER_PEER))
        self.streams = StreamSlots(max_streams, per_peer)
        self.conns = Conns()
        self.refused = 0
        self.evicted = 0  # idle connections closed at the cap to make room for a new one
        self.refused_control = 0  # control messages from a WebSocket without a page session
        self.refused_messages = 0  # WebSocket messages refused: not JSON, too deep, bad values
        self.sessions: dict[str, None] = {}  # secrets of the pages served (oldest first)
        self.any_change = asyncio.Event()
        self.shown = ShownFrames(self._send, self.any_change)
        self._writer: asyncio.StreamWriter | None = None
        self._stats: tuple[float, bytes] | None = None
        # Statistics asked for, in order (each reply answers the oldest): when each was asked,
        # and who waits for statistics asked at or after a time (fresh_stats' ``since``)
        self._stats_asks: collections.deque[float] = collections.deque()
        self._stats_waiters: list[tuple[float, asyncio.Future[bytes]]] = []
        self.calls = Calls(self._send, CALL_WAIT)
        self.station = Station(settings, self.calls.call, self.fresh_stats)

    # --- the channel ------------------------------------------------------------------------

    async def run(self, sock: socket.socket, channel: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        reader, self._writer = await asyncio.open_unix_connection(sock=channel)
        app = web.Application(middlewares=[self._guard])
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/ws", self._websocket),
                web.get("/stats.json", self._stats_json),
                web.get("/frame/{source}.jpg", self._snapshot),
                web.get("/stream/{source}.mjpg", self._mjpeg),
                *self.station.routes(),
            ]
        )
        runner = web.AppRunner(
            app,
            access_log=None,
            handle_signals=False,
            shutdown_timeout=CLOSE_TIMEOUT,
            keepalive_timeout=self.header_timeout,
        )
        await runner.setup()
        server = runner.server
        assert server is not None

        def factory() -> asyncio.Protocol:
            """At the cap, the connection idle longest (no request running) makes room:
            streams are capped below the cap, so the page and the API always find one."""
            if self.conns.count() >= self.max_clients:
                idle = [c for c in self.conns.values() if not c.busy and not c.headers_in]
                if not idle:
                    self.refused += 1
                    return Refuse()
                oldest = min(idle, key=lambda c: c.deadline)
                self.conns.pop(oldest.transport, None)
                oldest.transport.close()
                self.evicted += 1
            return Tracked(server(), self.conns, self.header_timeout)

        listener = await loop.create_server(factory, sock=sock)
        sweeper = loop.create_task(self._sweep())
        station = loop.create_task(self.station.run())
        self._send({"op": "ready"})
        try:
            await self._read(reader)
        finally:
            sweeper.cancel()
            station.cancel()
            await self.station.close()
            listener.close()
            closing = [c.ws.close(code=1001, message=b"runtime stopping") for c in self.clients]
            if closing:
                await asyncio.wait([asyncio.ensure_future(c) for c in closing], timeout=1.0)
            for conn in list(self.conns.values()):
                conn.transport.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(runner.cleanup(), 2.0)

    async def _read(self, reader: asyncio.StreamReader) -> None:
        """Take what the node sends until it closes the channel (the display's teardown)."""
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                header, body = await unpack(reader)
                op = header.get("op")
                if op == "frame":
                    self.shown.frame(header, body)
                elif op == "sources":
                    self.names = set(header["names"])
                    self.any_change.set()
                elif op == "stats":
                    display = {
                        **header["display"],
                        "clients": len(self.clients),
                        "streams": len(self.streams.clients),
                        "refused": self.refused,
                        "refused_streams": self.streams.refused,
                        "stalled": self.streams.stalled,
                        "evicted": self.evicted,
                        "refused_control": self.refused_control,
                        "refused_messages": self.refused_messages,
                        "refused_requests": self.station.records.refused,
                    }
                    data = b'{"runtime":' + body + b',"display":' + json.dumps(display).encode()
                    data += b"}"
                    # stamped when asked for: what they say is at least that new (a reply to a
                    # request sent before a recording's start is not news of after it)
                    asked = self._stats_asks.popleft() if self._stats_asks else time.monotonic()
                    self._stats = (asked, data)
                    waiting = []
                    for since, fut in self._stats_waiters:
                        if asked < since:
                            waiting.append((since, fut))
                        elif not fut.done():
                            fut.set_result(data)
                    self._stats_waiters = waiting
                elif op == "reply":
                    self.calls.reply(header)

    def _send(self, header: dict[str, Any]) -> None:
        if self._writer is not None and not self._writer.is_closing():
            self._writer.write(pack(header))

    async def _sweep(self) -> None:
        """Close connections that sent no complete request in time (slow or idle clients)."""
        while True:
            await asyncio.sleep(min(1.0, self.header_timeout / 4))
            now = time.monotonic()
            for conn in list(self.conns.values()):
                if conn.late(now):
                    conn.transport.close()

    # --- who may connect ----------------------------------------------------------------------

    @property
    def _guard(self) -> Any:
        """Host and Origin checks (or the token), so that no web page can read the cameras.

        Without a token the view answers only requests addressed to a loopback name (or one
        of ``allowed_hosts``): a page that rebinds its own DNS name to 127.0.0.1 sends its
        own name in ``Host`` and is refused (421). A request that carries an ``Origin``
        (every WebSocket upgrade from a browser, every cross-origin fetch) must come from the
        view's own origin, else 403: another page cannot open ``/ws`` on the user's behalf.
        """

        @web.middleware
        async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
            conn = self.conns.get(request.transport) if request.transport is not None else None
            if conn is not None:
                conn.busy += 1
            try:
                refused = refusal(request, self.token, self.allowed_hosts)
                if refused is not None:
                    return refused
                response: web.StreamResponse = await handler(request)
                if self.token and request.query.get("token") == self.token:
                    response.set_cookie(COOKIE, self.token, httponly=True, samesite="Strict")
                return response
            finally:
                if conn is not None:
                    conn.busy -= 1
                    conn.answered(self.header_timeout)

        return guard

    # --- HTTP -------------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.Response:
        """The page, with a session secret of its own: only a WebSocket opened with it may send
        control messages (the joystick), so a local program that merely connects cannot
        drive the robot; with a token, the token is needed to get the page at all."""
        session = secrets.token_urlsafe(18)
        self.sessions[session] = None
        while len(self.sessions) > MAX_SESSIONS:  # the oldest pages forgotten first
            del self.sessions[next(iter(self.sessions))]
        body = self.page.replace(b"__FLOWRT_SESSION__", session.encode())
        # the newest statistics inline, so the first tables render from this response; "</"
        # escaped so no value can close the script element
        stats = self._stats[1] if self._stats is not None else b"null"
        body = body.replace(b"__FLOWRT_STATS__", stats.replace(b"</", b"<\\/"))
        return web.Response(
            body=body,
            content_type="text/html",
            charset="utf-8",
            headers={"Cache-Control": "no-store"},
        )

    async def fresh_stats(self, since: float = 0.0) -> bytes | None:
        """The node's statistics, at most STATS_MAX_AGE old and asked for at or after
        ``since`` (monotonic: a recording's start or stop this view made, which statistics
        from before it contradict); None: it gave none in time."""
        cached = self._stats
        now = time.monotonic()
        if cached is not None and cached[0] >= since and now - cached[0] < STATS_MAX_AGE:
            return cached[1]
        while self._stats_asks and now - self._stats_asks[0] > 10 * STATS_WAIT:
            self._stats_asks.popleft()  # never answered (the runtime busy, or gone)
        if not self._stats_asks or self._stats_asks[-1] < since:  # none in flight will do
            self._stats_asks.append(now)
            self._send({"op": "stats"})
        fut: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self._stats_waiters.append((since, fut))
        try:
            return await asyncio.wait_for(fut, STATS_WAIT)
        except TimeoutError:
            return cached[1] if cached is not None else None
        finally:
            self._stats_waiters = [w for w in self._stats_waiters if w[1] is not fut]

    async def _stats_json(self, request: web.Request) -> web.Response:
        body = await self.fresh_stats()
        if body is None:
            raise web.HTTPServiceUnavailable(text="no statistics from the runtime")
        return web.Response(
            body=body, content_type="application/json", headers={"Cache-Control": "no-store"}
        )

    async def _requested(self, request: web.Request) -> tuple[str, str]:
        """The source and kind a frame request names; a source not seen yet is waited for."""
        name = request.match_info["source"]
        kind = request.query.get("kind", "processed")
        if kind not in ("raw", "processed"):
            raise web.HTTPBadRequest(text="kind must be raw or processed")
        if self.inputs is not None and name not in self.inputs and name not in self.names:
            raise web.HTTPNotFound(
                text=f"no input {name!r} on this display; its inputs: {sorted(self.inputs)}"
            )
        end = time.monotonic() + self.source_wait
        while name not in self.names:
            left = end - time.monotonic()
            if left <= 0:
                raise web.HTTPNotFound(
                    text=f"no frames from {name!r}; sources: {sorted(self.names)}"
                )
            self.any_change.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.any_change.wait(), left)
        return name, kind

    async def _snapshot(self, request: web.Request) -> web.Response:
        name, kind = await self._requested(request)
        held = self.shown.source(name).n
        src = await self.shown.newer(name, held, SNAPSHOT_WAIT if held else FIRST_WAIT)
        if src is None:
            src = self.shown.source(name)
            if not src.n:
                raise web.HTTPServiceUnavailable(text=f"no frame of {name!r} could be encoded")
        if src.failed:
            raise web.HTTPInternalServerError(text=f"cannot show {name!r}: {src.failed}")
        return web.Response(
            body=src.raw if kind == "raw" else src.processed,
            content_type="image/jpeg",
            headers={"Cache-Control": "no-store", "X-Frame-Seq": str(src.header.get("seq"))},
        )

    async def _mjpeg(self, request: web.Request) -> web.StreamResponse:
        """The newest frames as MJPEG, one queued at most; see :mod:`.display_streams`."""
        peer = request.remote or "?"
        refused = self.streams.refusal(peer, len(self.clients))
        if refused is not None:
            raise web.HTTPServiceUnavailable(text=refused + "\n")
        name, kind = await self._requested(request)
        resp = web.StreamResponse(
            headers={
                "Content-Type": "multipart/x-mixed-replace; boundary=flowrtframe",
                "Cache-Control": "no-store",
            }
        )
        client = self.streams.open(peer, request.transport)
        sent = 0
        try:
            await resp.prepare(request)
            while self.streams.check(client):
                src = await self.shown.newer(name, sent, STREAM_CHECK)
                if src is None or not client.ready():
                    if src is not None:  # the previous frame is still in our buffer
                        client.skipped += 1
                        sent = src.n
                    continue
                sent = src.n
                if src.failed:
                    continue
                jpeg = src.raw if kind == "raw" else src.processed
                part = f"--flowrtframe\r\n{JPEG_PART}{len(jpeg)}\r\n\r\n".encode() + jpeg
                client.wrote(len(part) + 2, time.monotonic())
                # The buffer was empty: this returns at once, or waits for the kernel to take
                # this one frame; a client that takes nothing is dropped by check() meanwhile.
                await asyncio.wait_for(resp.write(part + b"\r\n"), MAX_BEHIND)
        except TimeoutError:
            self.streams.stalled += 1
            if request.transport is not None:
                request.transport.abort()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.streams.close(client)
        return resp

    async def _websocket(self, request: web.Request) -> web.WebSocketResponse:
        if len(self.clients) + len(self.streams.clients) >= self.streams.max_streams:
            # a WebSocket holds its slot like a stream: together they leave the rest free
            self.streams.refused += 1
            raise web.HTTPServiceUnavailable(
                text=f"{self.streams.max_streams} live connections already (max_streams)\n"
            )
        ws = web.WebSocketResponse(
            heartbeat=10.0, compress=False, timeout=CLOSE_TIMEOUT, max_msg_size=1 << 16
        )
        may_control = request.query.get("session", "") in self.sessions
        await ws.prepare(request)
        client = _Client(ws)
        self.clients.add(client)
        feeder = asyncio.get_running_loop().create_task(self._feed(client))
        try:
            async for msg in ws:
                if msg.type is not WSMsgType.TEXT:
                    continue
                try:
                    data = json.loads(msg.data)
                    ack = data.get("ack")
                except (ValueError, AttributeError, RecursionError):
                    self.refused_messages += 1  # not a JSON object, or nested too deeply
                    continue
                joy = _joystick(data.get("joy"))
                if joy is None and data.get("joy") is not None:
                    self.refused_messages += 1  # an axis not a finite number, a bad shape
                    self._send({"op": "joy-refused"})  # the node's joystick-invalid alert
                if joy is not None and not may_control:
                    self.refused_control += 1  # a connection, not a page of this view
                elif joy is not None:
                    self._send({"op": "joy", "value": joy})  # the node writes the RTDB
                estop = _estop(data.get("estop"))
                if estop is not None and not may_control:
                    self.refused_control += 1
                elif estop is not None:
                    self._send({"op": "estop", "value": estop})
                if isinstance(ack, str):
                    client.waiting_ack.discard(ack)
                    self.any_change.set()
        finally:
            feeder.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await feeder
            self.clients.discard(client)
        return ws

    async def _feed(self, client: _Client) -> None:
        """Send each source's newest frame to one client, one unacknowledged message at most."""
        while not client.ws.closed:
            self.any_change.clear()
            sent_any = False
            for name in sorted(self.names):
                if name in client.waiting_ack:
                    continue
                src = self.shown.source(name)
                after = client.sent.get(name, 0)
                if src.n <= after:
                    self.shown.want(name, after)
                    continue
                client.sent[name] = src.n
                if src.failed:
                    self.shown.want(name, src.n)
                    continue
                client.waiting_ack.add(name)
                await client.ws.send_bytes(src.message)
                sent_any = True
            if not sent_any:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self.any_change.wait(), 1.0)


def refusal(request: web.Request, token: str | None, allowed: list[str]) -> web.Response | None:
    """Why ``request`` is refused (the token, the Host, the Origin), or None; see ``_guard``."""
    if token:
        scheme, _, given = request.headers.get("Authorization", "").partition(" ")
        candidates = [
            given.strip() if scheme.lower() == "bearer" else "",
            request.cookies.get(COOKIE, ""),
            request.query.get("token", ""),
        ]
        if not any(hmac.compare_digest(c.encode(), token.encode()) for c in candidates):
            return web.Response(
                status=401,
                text="this live view needs its token: open it as /?token=TOKEN\n",
                headers={"WWW-Authenticate": 'Bearer realm="flowrt view"'},
            )
    else:
        name = hostname(request.host)
        if not is_loopback(name) and name not in allowed:
            return web.Response(
                status=421,
                text=f"Host {request.host!r} is not this view's address "
                "(add it to the display's allowed_hosts, or give it a token)\n",
            )
    origin = request.headers.get("Origin")
    if origin is not None and urlsplit(origin).netloc.lower() != request.host.lower():
        return web.Response(status=403, text=f"Origin {origin!r} is not this view's own\n")
    return None


def _joystick(value: Any) -> dict[str, Any] | None:
    """The page's joystick state, bounded and typed (a page is not trusted with more).

    None, the message refused whole, when an axis is not a finite number: a 401-digit
    integer (beyond a float), NaN or a string is not a stick position, and guessing one
    (0, or clamped to 1) would drive the robot on a value nobody sent."""
    if not isinstance(value, dict):
        return None
    axes, buttons = value.get("axes"), value.get("buttons")
    if not isinstance(axes, dict) or not isinstance(buttons, dict):
        return None
    out_axes: dict[str, float] = {}
    for k, v in list(axes.items())[:16]:
        if not isinstance(k, str) or len(k) > 32:
            continue
        if not finite_number(v):
            return None
        out_axes[k] = max(-1.0, min(1.0, float(v)))
    out_buttons = {
        k: bool(v) for k, v in list(buttons.items())[:32] if isinstance(k, str) and len(k) <= 32
    }
    return {"axes": out_axes, "buttons": out_buttons}


def _estop(value: Any) -> dict[str, str] | None:
    """The page's e-stop action, ``{"action": "stop"|"release", "id": str}``, or None."""
    if not isinstance(value, dict):
        return None
    action, aid = value.get("action"), value.get("id")
    if action not in ("stop", "release") or not isinstance(aid, str) or not 0 < len(aid) <= 64:
        return None
    return {"action": action, "id": aid}
