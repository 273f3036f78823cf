"""Both Foxglove WebSocket subprotocols on one port: ``foxglove.sdk.v1`` and
``foxglove.websocket.v1``.

The ``foxglove`` SDK's server (which ``--foxglove`` runs) answers only clients that ask for
``foxglove.sdk.v1``, and refuses the others with HTTP 400 at the handshake; Lichtblick,
Foxglove Studio 1.x and every tool built on ``@foxglove/ws-protocol`` ask for
``foxglove.websocket.v1``. Both name the same ws-protocol messages (serverInfo, advertise,
subscribe, binary message data...), so this bridge listens on the user's port, accepts
either name, and relays frames both ways to the SDK server on a private loopback port, which
it asks for ``foxglove.sdk.v1``. It runs on its own thread and event loop: a viewer never
takes the graph's loop.

It also closes a race of the SDK's server: a channel added while a viewer is connected is
advertised to the viewer (queued to its socket) before the server notes it among that
viewer's channels, so a viewer that subscribes as soon as it reads the advertisement (a
panel already showing that topic) may be answered ``Unknown channel ID`` and never gets a
message. The server has noted it for every viewer once ``foxglove.Channel()`` has
returned; :meth:`SubprotocolBridge.holding` around that call keeps the bridge from relaying
anything from the server to the viewers meanwhile, so no viewer sees the advertisement early.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

__all__ = ["SUBPROTOCOLS", "SubprotocolBridge"]

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
SDK_SUBPROTOCOL = "foxglove.sdk.v1"

log = logging.getLogger("flowrt.foxglove")


class SubprotocolBridge:
    """Listen on ``host:port`` for either subprotocol; relay to ``ws://127.0.0.1:upstream``."""

    def __init__(self, host: str, port: int, upstream: int) -> None:
        self.host = host
        self.upstream = upstream
        # bound here, in the caller's thread: a taken port is an OSError before anything runs
        self._sock = socket.create_server((host, port), reuse_port=False)
        self.port = int(self._sock.getsockname()[1])
        self.clients = 0  # connected viewers, both subprotocols
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._run, name="foxglove-bridge", daemon=True)
        self._ready = threading.Event()
        self._holds = 0  # callers adding a channel now: nothing goes from the server to viewers
        self._holds_lock = threading.Lock()
        self._released: asyncio.Event | None = None  # on the bridge's loop

    def start(self) -> None:
        self._thread.start()
        self._ready.wait(10)

    @contextlib.contextmanager
    def holding(self) -> Iterator[None]:
        """Relay nothing from the server to the viewers until the block is done.

        Wrap ``foxglove.Channel()`` (any thread): its advertisement reaches a viewer only once
        the server accepts a subscription to it (see the module docstring).
        """
        with self._holds_lock:
            self._holds += 1
        try:
            yield
        finally:
            with self._holds_lock:
                self._holds -= 1
                last = self._holds == 0
            loop, released = self._loop, self._released
            if last and loop is not None and released is not None:
                with contextlib.suppress(RuntimeError):  # the bridge's loop is closed
                    loop.call_soon_threadsafe(released.set)

    async def _unheld(self) -> None:
        """Return when no channel is being added (on the bridge's loop)."""
        released = self._released
        while self._holds and released is not None:
            released.clear()  # a set() for this hold is queued on this loop after this line
            await released.wait()

    def close(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        self._thread.join(5)
        with contextlib.suppress(OSError):
            self._sock.close()

    # --- the bridge's thread ----------------------------------------------------------------

    def _run(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        from aiohttp import web

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._released = asyncio.Event()
        app = web.Application()
        app.add_routes([web.get("/", self._client), web.get("/{tail:.*}", self._client)])
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.SockSite(runner, self._sock)
        await site.start()
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(runner.cleanup(), 2.0)

    async def _client(self, request: Any) -> Any:
        import aiohttp
        from aiohttp import web

        ws = web.WebSocketResponse(protocols=SUBPROTOCOLS, max_msg_size=0, compress=False)
        await ws.prepare(request)
        if ws.ws_protocol is None:  # asked for neither: the handshake named what we speak
            await ws.close(code=1002, message=b"subprotocol: foxglove.websocket.v1 or .sdk.v1")
            return ws
        self.clients += 1
        try:
            async with (
                aiohttp.ClientSession() as session,
                session.ws_connect(
                    f"ws://127.0.0.1:{self.upstream}/",
                    protocols=[SDK_SUBPROTOCOL],
                    max_msg_size=0,
                    compress=0,
                ) as up,
            ):
                await asyncio.gather(_pump(ws, up), _pump(up, ws, self._unheld))
        except (aiohttp.ClientError, ConnectionError) as e:
            log.debug("foxglove bridge: %s", e)
        finally:
            self.clients -= 1
            await ws.close()
        return ws


async def _pump(src: Any, dst: Any, gate: Callable[[], Awaitable[None]] | None = None) -> None:
    """Relay text and binary frames from ``src`` to ``dst`` until either side closes; each
    one, in order, once ``gate`` returns."""
    from aiohttp import WSMsgType

    try:
        async for msg in src:
            if gate is not None:
                await gate()
            if msg.type is WSMsgType.TEXT:
                await dst.send_str(msg.data)
            elif msg.type is WSMsgType.BINARY:
                await dst.send_bytes(msg.data)
            else:
                break
    except (ConnectionError, RuntimeError):
        pass
    finally:
        with contextlib.suppress(Exception):
            await dst.close()
