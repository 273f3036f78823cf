"""The live view: a web page of the cameras, detections and statistics, for a browser.

Connect any number of frame outputs and detection outputs to a ``display`` node under any
input names; it serves, at ``http://127.0.0.1:8750`` by default (the address is logged and
printed at start), a page showing per source the raw frame and the processed frame (the raw
one with the detections drawn) side by side, each source's frame rate, and the runtime's node
and edge statistics, all refreshed live::

    view:
      kind: display
      params: {port: 8750}
      inputs:
        front_cam: front_cam.frame                     # a frame source (any name)
        ball: {from: ball_fr.detection, policy: latest}
      # detections carry no frame; say which source each is drawn on when there are several:
      #   params: {draw_on: {ball: front_cam}}

Endpoints:

- ``/``: the page (HTML and JavaScript, no external resources).
- ``/ws``: a websocket pushing, per source, one binary message per frame pair (a 4-byte
  big-endian header length, a JSON header, the raw JPEG, the processed JPEG). The client acks
  each source's message once shown; the next one is sent only after the ack and only when a
  newer frame exists, so a client gets at most the source's rate and never a backlog.
- ``/stream/{source}.mjpg?kind=raw|processed``: the same frames as an MJPEG stream, for other
  tools; a slow reader gets the newest frame when it is ready for one.
- ``/frame/{source}.jpg?kind=raw|processed``: the newest frame as one JPEG.
- ``/stats.json``: ``{"runtime": RuntimeStats, "display": {...}}``: the runtime statistics
  (the schema of ``flowrt schema stats``) and what the display measures per source (fps,
  frames, encodes, detections), its clients and its total JPEG encodes.

Who may look: the view binds 127.0.0.1 and answers only requests addressed to a loopback name
(``Host``; add names with ``allowed_hosts``) and, when they carry an ``Origin`` (every
browser WebSocket), from its own origin: no other web page open in a browser on the robot's
computer can read the cameras (DNS rebinding: 421; cross-site WebSocket: 403). To serve it to
other machines on purpose, give ``host`` (e.g. 0.0.0.0) and a ``token`` (required off
loopback): clients send ``Authorization: Bearer TOKEN`` or open ``/?token=TOKEN`` once (a
cookie keeps it). ``max_clients`` connections at once; one that sends no complete request
within 10 s is closed, and at the cap the one idle longest makes room. MJPEG streams and the
pages' WebSockets take at most ``max_streams`` of them (half by default), MJPEG streams at most
``max_streams_per_peer`` per client address;
each has at most one frame queued in the server, and one that falls more than a second behind
is dropped (counted ``stalled``): the page, ``/stats.json`` and the API always find a slot.

Why neither the graph nor the cameras wait for a browser: the web server is a process of its
own (:mod:`flowrt.nodes.station.server`, at nice 19), so HTTP work and JPEG encoding take
neither the loop's time nor its GIL. ``process`` only keeps a link on the newest frame of each
source and the newest detections of each input. While a client waits for a frame newer than
the server has, the node lends the server the newest one (a descriptor of its shared-memory
slot, not the pixels), at most one per source at a time and at most ``max_fps``; the server
encodes it once and shares the JPEGs among all its clients. So the node's work per frame is
one small message whatever the number of clients, and none without clients; a client that is
slow, or does not read at all, holds at most one frame per source. The node owns the channel
on the event loop, so it must be placed ``inline`` (the default).

Detections are duck-typed: anything with ``found``, ``bbox`` (x, y, w, h) and ``centroid``
(e.g. ``flowrt.nodes.colour.Detection``), or a list of such; ``object`` labels it and
``confidence`` is shown when present. A detection is drawn on the source named by
``draw_on``, else by its ``source`` attribute (a source's input name or its frames' source
node), else on the only source; detections older than ``detection_ttl`` are not drawn.

Input policies: frames are best connected with ``policy: latest``, and so are detections
(a message input defaults to ``queue``, which also works: the display just stores the newest
as fast as they come).
"""

from __future__ import annotations

import asyncio
import math
import multiprocessing
import pickle
import secrets
import socket
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from flowrt import Frame, Input, InputTrigger, Node
from flowrt.control import serving
from flowrt.control.recorders import turn
from flowrt.refusals import Refusals
from flowrt.system import _spawned as spawned

from . import record as operator_record
from . import server as display_server
from .display_params import DisplayParams
from .render import Mark, render

__all__ = ["Display", "Mark", "render"]

PAGE = Path(__file__).with_name("display.html")
FPS_WINDOW = 2.0  # seconds of arrivals over which a source's rate is measured
STATS_MAX_AGE = 0.2  # seconds: the runtime's statistics are serialised at most 5 times a second
WEB_JOYSTICK = "joystick.web"  # RTDB record of the page's joystick (nodes/joystick.py reads it)
WEB_ESTOP = "estop.web"  # RTDB record of the page's last e-stop action (nodes/estop.py reads it)
SOURCE_WAIT = 3.0  # seconds a request for a source that has sent no frame yet waits for one
HEADER_TIMEOUT = 10.0  # seconds a connection has to send a complete request
START_TIMEOUT = 30.0  # seconds for the view's server process to start (spawn + imports)


def _drivers(ctx: Any) -> list[str]:
    """The nodes the page can drive through, by name: a joystick with ``source: web``, and
    an e-stop (its Release lets a robot move: no less a drive than a joystick's)."""
    from ..estop import Estop
    from ..joystick import Joystick

    try:
        graph = ctx.graph
    except RuntimeError:  # no runtime around the node (a bare test harness)
        return []
    return [
        name
        for name, n in graph.nodes.items()
        if (issubclass(n.cls, Joystick) and getattr(n.params, "source", None) == "web")
        or issubclass(n.cls, Estop)
    ]


def _inputs(ctx: Any) -> list[str] | None:
    """The display's input names (every frame source is one), or None when not known."""
    try:
        graph = ctx.graph
    except RuntimeError:  # no runtime around the node (a bare test harness)
        return None
    node = graph.nodes.get(ctx.name)
    return None if node is None else sorted(node.spec.inputs)


def _is_detection(value: Any) -> bool:
    return hasattr(value, "found") and (hasattr(value, "bbox") or hasattr(value, "centroid"))


def _detections(value: Any) -> list[Any] | None:
    """The detections in an input value (one or a list of them), or None if it holds none."""
    if _is_detection(value):
        return [value]
    if isinstance(value, Mapping):  # e.g. {object name: detection}
        value = list(value.values())
    if isinstance(value, list | tuple) and value and all(_is_detection(v) for v in value):
        return list(value)
    return None


class _Source:
    """The newest frame of one input and its arrival times."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.frame: Frame | None = None
        self.n = 0
        self.arrivals: deque[float] = deque(maxlen=256)
        self.delayed = False  # the next frame for the server waits for max_fps
        self.lent: Frame | None = None  # the frame the server is encoding (a link held)
        self.last_encode = -math.inf  # time.monotonic() of the last encode start
        self.encodes = 0
        self.failing = False  # the last encode failed (logged once until one succeeds)

    def fps(self, now: float) -> float:
        """Frames per second over the last FPS_WINDOW seconds; 0 once the source stalls."""
        times = [t for t in self.arrivals if now - t <= FPS_WINDOW]
        if len(times) < 2:
            return 0.0
        span = times[-1] - times[0]
        gap = now - times[-1]
        if span <= 0 or gap > max(1.0, 3 * span / (len(times) - 1)):
            return 0.0
        return (len(times) - 1) / span


def _listen(host: str, port: int) -> socket.socket:
    """A listening socket (taken here, so that a taken port fails the set-up at once)."""
    family, *_, address = socket.getaddrinfo(
        host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
    )[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


class Display(Node):
    """Live web view of frames, detections and statistics; see the module docstring."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset(
        {
            "max_fps",
            "jpeg_quality",
            "draw_on",
            "detection_ttl",
            "refresh_ms",
            "health_hz",
            "health_keep_s",
        }
    )

    inline_only = True
    listens = True  # params host/port: `flowrt run --display-host/--display-port` set them

    Params = DisplayParams

    any_inputs = Input(
        object, required=False, doc="frames (a source each) and detections, under any name"
    )

    @classmethod
    def default_trigger(cls, params: Any) -> InputTrigger:
        # Every arrival is stored at once; also lets a display without inputs serve statistics.
        return InputTrigger()

    # --- lifecycle ----------------------------------------------------------------------

    async def setup(self) -> None:
        self.sources: dict[str, _Source] = {}
        self.detections: dict[str, tuple[float, list[Any]]] = {}  # input -> (arrival, detections)
        self.encodes = 0
        self.ignored: set[str] = set()
        self.wanted: dict[str, int] = {}  # source -> the server holds its frame n; wants newer
        # the page's joystick messages the server refused (NaN, not a number): an alert per
        # burst, as the README says (only /stats.json's refused_messages counted them)
        self.joy_refused = Refusals(
            "joystick-invalid", "web joystick message refused: an axis is NaN, inf or not a number"
        )
        self._kick_due = False
        self._stats_cache: tuple[float, bytes] | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._proc: Any = None
        self._task: asyncio.Task[None] | None = None
        self._calls: set[asyncio.Task[None]] = set()  # the server's requests being answered
        host, port = self.params.host, self.params.port
        self.url = ""
        self.open_url = ""  # the URL to open: with ?token= when the view has one
        self.drivers = _drivers(self.ctx)
        token = self.params.token
        required = self.params.token_required
        if required is None:
            required = bool(self.drivers)
        if required and not token:  # generated, as Jupyter does: printed as a URL to open
            token = secrets.token_urlsafe(16)
        try:
            sock = _listen(host, port)
        except OSError as e:
            # An error state, not a failure: restarting cannot free the port (flowrt run checks
            # it before anything starts; an embedding program sees the state and the reason).
            reason = f"cannot listen on {host}:{port}: {e.strerror or e}"  # (its name: once)
            try:
                self.ctx.set_error(reason)
            except RuntimeError:  # no runtime around the node (a bare test harness)
                raise RuntimeError(reason) from e
            self.ctx.log.error("%s: %s; the live view is off", self.ctx.name, reason)
            return
        self.port = int(sock.getsockname()[1])
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '::', '') else shown}:{self.port}"
        page = PAGE.read_bytes().replace(b"__REFRESH_MS__", str(self.params.refresh_ms).encode())
        self.open_url = f"{self.url}/?token={token}" if token else self.url
        settings = {
            "token": token,
            "allowed_hosts": list(self.params.allowed_hosts),
            "max_clients": self.params.max_clients,
            "max_streams": self.params.max_streams or max(1, self.params.max_clients // 2),
            "max_streams_per_peer": self.params.max_streams_per_peer,
            "url": self.url,
            "page": page,
            "source_wait": SOURCE_WAIT,
            "inputs": _inputs(self.ctx),  # a name none of them is: 404 at once, not waited for
            "header_timeout": HEADER_TIMEOUT,
            "recordings": [self.params.recordings] if self.params.recordings else [],
            "health_hz": self.params.health_hz,
            "health_keep_s": self.params.health_keep_s,
            "robots": {k: v.model_dump() for k, v in self.params.robots.items()},
        }
        ours, theirs = socket.socketpair()
        ctx = multiprocessing.get_context("spawn")
        self._proc = ctx.Process(
            target=display_server.serve,
            args=(sock, theirs, settings),
            name=f"flowrt-view-{self.ctx.name}",
            daemon=True,
        )
        try:
            spawned.start(self._proc)  # Ctrl-C is the runtime's, from the child's first instant
            if self._proc.pid is not None:
                serving.lower_priority(self._proc.pid)
        finally:
            theirs.close()
            sock.close()  # the server's process holds its own copy
        reader, self._writer = await asyncio.open_unix_connection(sock=ours)
        ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._task = asyncio.get_running_loop().create_task(self._talk(reader, ready))
        try:
            await asyncio.wait_for(asyncio.shield(ready), START_TIMEOUT)
        except (TimeoutError, ConnectionError, asyncio.IncompleteReadError) as e:
            await self.teardown()
            raise RuntimeError(f"display: the view's server did not start: {e!r}") from None
        if token and not self.params.token:
            why = f"{', '.join(self.drivers)} can drive from the page" if self.drivers else ""
            print(
                f"display: {self.url} needs its token{': ' + why if why else ''}; open "
                f"{self.open_url}",
                flush=True,
            )
        else:
            print(f"display: {self.url}", flush=True)  # once: scripts and tests read this line

    async def teardown(self) -> None:
        writer, task, proc = self._writer, self._task, self._proc
        self._writer = self._task = self._proc = None
        # within the scheduler's 2 s for a teardown, however loaded the machine: the server
        # holds nothing to save, so one that has not exited after 1 s is killed
        await serving.stop_server(writer, task, proc, grace=1.0)
        for src in self.sources.values():
            if src.lent is not None:
                src.lent.release()
                src.lent = None
            if src.frame is not None:
                src.frame.release()
                src.frame = None

    async def _talk(self, reader: asyncio.StreamReader, ready: asyncio.Future[None]) -> None:
        """Answer the server: a frame it wants, statistics. Bounded whatever its clients do."""
        try:
            while True:
                header, _ = await serving.unpack(reader)
                op = header.get("op")
                if op == "ready":
                    ready.set_result(None)
                elif op == "want":
                    name, after = str(header["source"]), int(header["after"])
                    self.wanted[name] = after
                    src = self.sources.get(name)
                    if src is not None and src.n > after:
                        self._kick(src)
                elif op == "done":
                    self._returned(str(header["source"]))
                elif op == "stats":
                    self._send_stats()
                elif op == "joy":  # the page's on-screen joystick: for `joystick` source: web
                    self.joy_refused.accept()
                    self.ctx.rtdb.write(WEB_JOYSTICK, header["value"], validity_ms=500)
                elif op == "joy-refused":  # counted by the server; alerted once per burst
                    self.joy_refused.refuse(self.ctx, None)
                elif op == "estop":  # the page's e-stop panel: for an `estop` node
                    self.ctx.rtdb.write(WEB_ESTOP, header["value"])
                elif op == "record":  # the record panel: answered when the recorders have
                    rtdb = self.ctx.rtdb  # one turn with the control endpoint's POST /record
                    answer = operator_record.answer(rtdb, header, self._send, turn(rtdb))
                    task = asyncio.get_running_loop().create_task(answer)
                    self._calls.add(task)
                    task.add_done_callback(self._calls.discard)
        except (asyncio.IncompleteReadError, ConnectionError) as e:
            if not ready.done():
                ready.set_exception(e)
            elif self._writer is not None:  # not our teardown: the server's process died
                reason = f"display: the view's server process ended; {self.url} is gone"
                self.ctx.set_error(reason)
                self.ctx.log.error("%s: %s", self.ctx.name, reason)

    def _send(self, header: dict[str, Any], body: bytes = b"") -> None:
        if self._writer is not None and not self._writer.is_closing():
            self._writer.write(serving.pack(header, body))

    def _send_stats(self) -> None:
        try:
            runtime: bytes = self._runtime_stats()
        except RuntimeError:  # no runtime around the node (a bare test harness)
            runtime = b"null"
        self._send({"op": "stats", "display": self.display_stats()}, runtime)

    def _runtime_stats(self) -> bytes:
        """The runtime's statistics, serialised at most every STATS_MAX_AGE."""
        mono = time.monotonic()
        if self._stats_cache is not None and mono - self._stats_cache[0] < STATS_MAX_AGE:
            return self._stats_cache[1]
        body: bytes = self.ctx.stats().model_dump_json().encode()
        self._stats_cache = (mono, body)
        return body

    # --- the hot path -------------------------------------------------------------------

    def process(self, **inputs: Any) -> None:
        now = self.ctx.now()
        for port, value in inputs.items():
            if value is None:
                continue
            if isinstance(value, Frame):
                self._frame(port, value, now)
                continue
            dets = _detections(value)
            if dets is not None:
                self.detections[port] = (now, dets)
            elif port not in self.ignored:
                self.ignored.add(port)
                self.ctx.log.warning(
                    "%s: input %r carries %s, neither frames nor detections: ignored",
                    self.ctx.name,
                    port,
                    type(value).__name__,
                )
        if self.wanted and not self._kick_due:
            # Lent after this call, in a callback of its own: process() only stores.
            self._kick_due = True
            asyncio.get_running_loop().call_soon(self._kick_wanted)

    def _kick_wanted(self) -> None:
        self._kick_due = False
        for name, after in list(self.wanted.items()):
            src = self.sources.get(name)
            if src is not None and src.n > after:
                self._kick(src)

    def _frame(self, port: str, frame: Frame, now: float) -> None:
        src = self.sources.get(port)
        if src is None:
            src = self.sources[port] = _Source(port)
            self._send({"op": "sources", "names": list(self.sources)})
        if frame is src.frame:  # a periodic trigger re-reads the same newest frame
            return
        frame.acquire()  # the runtime releases the activation's link when process returns
        if src.frame is not None:
            src.frame.release()
        src.frame = frame
        src.n += 1
        src.arrivals.append(now)

    # --- encoding (only on request) -----------------------------------------------------

    def _target(self, port: str, det: Any) -> str | None:
        """The source a detection is drawn on."""
        explicit: str | None = self.params.draw_on.get(port)
        if explicit is not None:
            return explicit
        name = getattr(det, "source", None)
        if name:
            for src in self.sources.values():
                if name == src.name or (src.frame is not None and name == src.frame.source):
                    return src.name
            return None
        if len(self.sources) == 1:
            return next(iter(self.sources))
        return None

    def _marks(self, src: _Source) -> list[Mark]:
        now = self.ctx.now()
        marks: list[Mark] = []
        for port, (t, dets) in self.detections.items():
            if now - t > self.params.detection_ttl:
                continue
            marks.extend(Mark.of(d, port) for d in dets if self._target(port, d) == src.name)
        return marks

    def _throttle(self, src: _Source) -> float:
        """Seconds to wait before this source may be encoded again (0: now)."""
        if self.params.max_fps is None:
            return 0.0
        cap = float(self.params.max_fps)
        return max(0.0, src.last_encode + 1.0 / cap - time.monotonic())

    def _kick(self, src: _Source) -> None:
        """Hand the newest frame of ``src`` to the server, which encodes and shares it.

        A frame in the shared frame pool travels as a descriptor (``pickle``: the slot's
        name, not its pixels); the server maps the slot and encodes there, so the JPEG work
        (milliseconds holding a GIL) is not this process's. A link keeps the slot until the
        server says it is done; one frame per source is in its hands at a time.
        """
        frame = src.frame
        if frame is None or src.delayed or src.lent is not None:
            return
        delay = self._throttle(src)
        if delay > 0:
            src.delayed = True
            asyncio.get_running_loop().call_later(delay, self._rekick, src)
            return
        src.last_encode = time.monotonic()
        self.wanted.pop(src.name, None)
        header = {
            "op": "frame",
            "source": src.name,
            "node": frame.source,
            "n": src.n,
            "seq": frame.seq,
            "timestamp": frame.timestamp,
            "shape": list(frame.shape),
            "pixel_format": frame.pixel_format,
            "fps": round(src.fps(self.ctx.now()), 2),
            "marks": [m.json() for m in self._marks(src)],
            "quality": self.params.jpeg_quality,
        }
        frame.acquire()  # until the server is done with it
        src.lent = frame
        self._send(header, pickle.dumps(frame, protocol=pickle.HIGHEST_PROTOCOL))
        src.encodes += 1
        self.encodes += 1

    def _returned(self, name: str) -> None:
        """The server is done with the frame of ``name`` it was lent."""
        src = self.sources.get(name)
        if src is None or src.lent is None:
            return
        src.lent.release()
        src.lent = None
        after = self.wanted.get(name)
        if after is not None and src.n > after:
            self._kick(src)

    def _rekick(self, src: _Source) -> None:
        src.delayed = False
        after = self.wanted.get(src.name)
        if after is not None and src.n > after:
            self._kick(src)

    # --- statistics ----------------------------------------------------------------

    def report(self) -> Any:
        """``reports.NODE.url`` in the statistics: where a view on port 0 is."""
        return {"url": self.url} if getattr(self, "url", "") else None

    def display_stats(self) -> dict[str, Any]:
        """What the display measures: per source fps and frames, its clients and encodes."""
        now = self.ctx.now()
        sources = []
        for src in self.sources.values():
            f = src.frame
            sources.append(
                {
                    "name": src.name,
                    "node": f.source if f is not None else "",
                    "fps": src.fps(now),
                    "frames": src.n,
                    "seq": f.seq if f is not None else None,
                    "shape": list(f.shape) if f is not None else None,
                    "pixel_format": f.pixel_format if f is not None else None,
                    "age": now - src.arrivals[-1] if src.arrivals else None,
                    "encodes": src.encodes,
                    "marks": [m.json() for m in self._marks(src)],
                }
            )
        detections = [
            {
                "input": port,
                "age": now - t,
                "target": [self._target(port, d) for d in dets],
                "marks": [Mark.of(d, port).json() for d in dets],
            }
            for port, (t, dets) in self.detections.items()
        ]
        try:
            recording = operator_record.state(self.ctx.rtdb)
        except RuntimeError:  # no runtime around the node (a bare test harness)
            recording = {"recording": [], "recordings": []}
        return {
            "url": self.url,
            "encodes": self.encodes,
            "sources": sources,
            "detections": detections,
            **recording,
        }
