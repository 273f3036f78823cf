"""The live view: a web page served from the runtime's own event loop.

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

Why the graph never waits for a browser: ``process`` only keeps a link on the newest frame of
each source and the newest detections of each input, and wakes the clients (none: nothing to
do). JPEG encoding happens only when a client asks for a frame newer than its last one, in a
thread (OpenCV releases the GIL), once per frame whatever the number of clients, at most at
``max_fps``; a client that is slow, or does not read at all, holds at most one frame in
flight per source. The server is on the event loop, so the display must be placed ``inline``
(the default).

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
import contextlib
import json
import math
import struct
import time
import zlib
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from aiohttp import WSMsgType, web
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from flowrt import Frame, Input, InputTrigger, Node

__all__ = ["Display", "Mark", "render"]

PAGE = Path(__file__).with_name("display.html")
FPS_WINDOW = 2.0  # seconds of arrivals over which a source's rate is measured
STATS_MAX_AGE = (
    0.2  # seconds: /stats.json is computed at most 5 times a second, whatever the clients
)
CLOSE_TIMEOUT = 1.0  # seconds given to clients to close at teardown
JPEG_PART = "Content-Type: image/jpeg\r\nContent-Length: "
SOURCE_WAIT = 3.0  # seconds a request for a source that has sent no frame yet waits for one

#: Colours (BGR) of the soccer objects; other labels get a colour from their name.
COLOURS: dict[str, tuple[int, int, int]] = {
    "ball": (0, 140, 255),
    "yellow_goal": (0, 230, 255),
    "yellow_post": (0, 230, 255),
    "blue_goal": (255, 140, 0),
    "blue_post": (255, 140, 0),
    "obstacle": (255, 0, 255),
    "lines": (255, 255, 255),
}


@dataclass(frozen=True)
class Mark:
    """A detection reduced to what is drawn: plain values, safe to hand to the encoder thread."""

    label: str
    found: bool
    bbox: tuple[int, int, int, int] | None
    centroid: tuple[float, float] | None
    confidence: float | None

    @classmethod
    def of(cls, det: Any, default_label: str) -> Mark:
        bbox = getattr(det, "bbox", None)
        centroid = getattr(det, "centroid", None)
        conf = getattr(det, "confidence", None)
        return cls(
            label=str(getattr(det, "object", "") or default_label),
            found=bool(getattr(det, "found", False)),
            bbox=None if bbox is None else (int(bbox[0]), int(bbox[1]), int(bbox[2]), int(bbox[3])),
            centroid=None if centroid is None else (float(centroid[0]), float(centroid[1])),
            confidence=None if conf is None else float(conf),
        )

    def json(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "found": self.found,
            "bbox": self.bbox,
            "centroid": self.centroid,
            "confidence": self.confidence,
        }


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


def colour_of(label: str) -> tuple[int, int, int]:
    """A stable, saturated BGR colour per label."""
    known = COLOURS.get(label)
    if known is not None:
        return known
    hue = zlib.crc32(label.encode()) % 180
    hsv = np.array([[[hue, 220, 255]]], dtype=np.uint8)
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def to_bgr8(data: np.ndarray, pixel_format: str) -> np.ndarray:
    """An 8-bit BGR or grey image that OpenCV can encode, from a frame's pixels."""
    img = data
    if img.dtype != np.uint8:
        lo, hi = float(img.min()), float(img.max())
        img = ((img.astype(np.float32) - lo) * (255.0 / (hi - lo) if hi > lo else 0.0)).astype(
            np.uint8
        )
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    fmt = pixel_format.upper()
    if img.ndim == 3 and img.shape[2] == 3 and fmt.startswith("RGB"):
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGR if fmt.startswith("RGB") else cv2.COLOR_BGRA2BGR)
    return img


def draw(img: np.ndarray, marks: Iterable[Mark]) -> np.ndarray:
    """A BGR copy of ``img`` with every found mark drawn (box, centroid, label)."""
    canvas = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    h, w = canvas.shape[:2]
    scale = max(w, h) / 320
    thick = max(1, round(scale))
    font = 0.4 * max(scale, 0.75)
    for m in marks:
        if not m.found:
            continue
        colour = colour_of(m.label)
        text = m.label if m.confidence is None else f"{m.label} {m.confidence:.2f}"
        x, y = 2, 2
        if m.bbox is not None:
            x, y, bw, bh = m.bbox
            cv2.rectangle(canvas, (x, y), (x + bw - 1, y + bh - 1), colour, thick)
        if m.centroid is not None:
            cx, cy = round(m.centroid[0]), round(m.centroid[1])
            cv2.drawMarker(canvas, (cx, cy), colour, cv2.MARKER_CROSS, max(6, 4 * thick), thick)
            if m.bbox is None:
                x, y = cx + 4, cy - 4
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font, 1)
        ty = y - 3 if y - th - base - 3 >= 0 else y + th + 3
        cv2.rectangle(canvas, (x, ty - th - 1), (x + tw + 1, ty + base - 1), (0, 0, 0), cv2.FILLED)
        cv2.putText(
            canvas, text, (x + 1, ty - 1), cv2.FONT_HERSHEY_SIMPLEX, font, colour, 1, cv2.LINE_AA
        )
    return canvas


def render(
    data: np.ndarray, pixel_format: str, marks: list[Mark], quality: int
) -> tuple[bytes, bytes]:
    """JPEGs of the raw frame and of the processed one (the same bytes when nothing is drawn)."""
    img = to_bgr8(data, pixel_format)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality]
    ok, raw = cv2.imencode(".jpg", img, params)
    if not ok:
        raise ValueError(f"cannot encode a {data.shape} {data.dtype} {pixel_format} frame as JPEG")
    raw_bytes = raw.tobytes()
    if not any(m.found for m in marks):
        return raw_bytes, raw_bytes
    ok, proc = cv2.imencode(".jpg", draw(img, marks), params)
    if not ok:
        raise ValueError("cannot encode the processed frame")
    return raw_bytes, proc.tobytes()


@dataclass(frozen=True)
class Encoded:
    """One source's frame as sent: both JPEGs and what the page shows beside them."""

    n: int  # the display's count of frames received from the source
    seq: int
    timestamp: float
    shape: tuple[int, ...]
    pixel_format: str
    marks: tuple[Mark, ...]
    raw: bytes
    processed: bytes


class _Source:
    """The newest frame of one input, its arrival times and its encoding cache."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.frame: Frame | None = None
        self.n = 0
        self.arrivals: deque[float] = deque(maxlen=256)
        self.encoded: Encoded | None = None
        self.encoding: asyncio.Task[Encoded] | None = None
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


class _Client:
    """A websocket client: what it was last sent per source and whether it acked it."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.wake = asyncio.Event()
        self.sent: dict[str, int] = {}
        self.waiting_ack: set[str] = set()
        self.messages = 0


def _local_host(host: str) -> str:
    """An IP address, or a name that resolves to an address of this machine.

    Checked when the graph is validated: a name that does not resolve (``example.invalid``)
    or resolves elsewhere made the view fail to listen at every restart. Resolution is given
    ``RESOLVE_TIMEOUT`` seconds, so a dead DNS server cannot hang ``flowrt validate``.
    """
    import concurrent.futures
    import ipaddress
    import socket

    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    if host in ("", "localhost"):
        return host
    pool = concurrent.futures.ThreadPoolExecutor(1)
    try:
        infos = pool.submit(socket.getaddrinfo, host, None, 0, socket.SOCK_STREAM).result(
            RESOLVE_TIMEOUT
        )
    except concurrent.futures.TimeoutError:
        raise ValueError(
            f"host {host!r} does not resolve (no answer within {RESOLVE_TIMEOUT:g} s): "
            "give an IP address (127.0.0.1, ::1, 0.0.0.0)"
        ) from None
    except (OSError, UnicodeError) as e:
        raise ValueError(
            f"host {host!r} does not resolve ({e}): give an IP address (127.0.0.1, ::1, "
            "0.0.0.0) or a name of this machine"
        ) from None
    finally:
        pool.shutdown(wait=False)
    addresses = sorted({str(info[4][0]) for info in infos})
    for family, _, _, _, sockaddr in infos:
        with contextlib.suppress(OSError), socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((sockaddr[0], 0))
            return host
    raise ValueError(
        f"host {host!r} resolves to {', '.join(addresses)}, not an address of this machine"
    )


RESOLVE_TIMEOUT = 2.0


class Display(Node):
    """Live web view of frames, detections and statistics; see the module docstring."""

    inline_only = True

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

        host: Annotated[str, AfterValidator(_local_host)] = Field(
            "127.0.0.1",
            description="address to listen on: an IP address (0.0.0.0: every interface) or a "
            "name of this machine",
        )
        port: int = Field(8750, ge=0, le=65535, description="TCP port; 0 picks a free one")
        max_fps: float | None = Field(
            None,
            gt=0,
            le=1000,
            description="cap on the frames encoded per second and source; none: the source's rate",
        )
        jpeg_quality: int = Field(80, ge=1, le=100)
        draw_on: dict[str, str] = Field(
            default_factory=dict, description="detection input -> the frame input it is drawn on"
        )
        detection_ttl: float = Field(
            1.0, gt=0, le=3600, description="seconds after which a detection is no longer drawn"
        )
        refresh_ms: int = Field(
            333, ge=50, le=3_600_000, description="how often the page polls the statistics"
        )

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
        self.clients: set[_Client] = set()
        self.streams: set[asyncio.Task[Any]] = set()
        self.wakers: set[asyncio.Event] = set()
        self.encodes = 0
        self.ignored: set[str] = set()
        self._stats_cache: tuple[float, bytes] | None = None
        self._page = PAGE.read_bytes().replace(
            b"__REFRESH_MS__", str(self.params.refresh_ms).encode()
        )
        app = web.Application()
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/ws", self._websocket),
                web.get("/stats.json", self._stats),
                web.get("/frame/{source}.jpg", self._snapshot),
                web.get("/stream/{source}.mjpg", self._mjpeg),
            ]
        )
        self._runner = web.AppRunner(
            app, access_log=None, handle_signals=False, shutdown_timeout=CLOSE_TIMEOUT
        )
        await self._runner.setup()
        host, port = self.params.host, self.params.port
        try:
            await web.TCPSite(self._runner, host, port).start()
        except OSError as e:
            await self._runner.cleanup()
            raise RuntimeError(f"display: cannot listen on {host}:{port}: {e.strerror or e}") from e
        self.port = int(self._runner.addresses[0][1])
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else shown}:{self.port}"
        self.ctx.log.info("%s: live view at %s", self.ctx.name, self.url)
        print(f"display: {self.url}", flush=True)

    async def teardown(self) -> None:
        runner = getattr(self, "_runner", None)
        if runner is None:
            return
        closing = [c.ws.close(code=1001, message=b"runtime stopping") for c in list(self.clients)]
        if closing:
            tasks = [asyncio.ensure_future(c) for c in closing]
            _, late = await asyncio.wait(tasks, timeout=CLOSE_TIMEOUT)
            for task in late:
                task.cancel()
        for task in list(self.streams):
            task.cancel()
        await runner.cleanup()
        # An encode in flight reads frame pixels in a thread: let it finish before the links go.
        pending = [s.encoding for s in self.sources.values() if s.encoding is not None]
        if pending:
            await asyncio.wait(pending)
        for src in self.sources.values():
            if src.frame is not None:
                src.frame.release()
                src.frame = None

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
        for ev in self.wakers:
            ev.set()

    def _frame(self, port: str, frame: Frame, now: float) -> None:
        src = self.sources.get(port)
        if src is None:
            src = self.sources[port] = _Source(port)
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

    async def _latest(self, src: _Source) -> Encoded:
        """The newest frame of ``src`` encoded: cached, or shared with an encode in flight."""
        enc = src.encoded
        if enc is not None and enc.n == src.n:
            return enc
        if src.encoding is None:
            src.encoding = asyncio.get_running_loop().create_task(self._encode(src))
        # Shielded: a client going away must not cancel an encode that reads frame pixels.
        return await asyncio.shield(src.encoding)

    async def _encode(self, src: _Source) -> Encoded:
        frame = src.frame
        assert frame is not None
        n, marks = src.n, self._marks(src)
        src.last_encode = time.monotonic()
        frame.acquire()  # kept until the thread is done, whatever arrives meanwhile
        try:
            raw, processed = await asyncio.to_thread(
                render, frame.data, frame.pixel_format, marks, self.params.jpeg_quality
            )
            enc = Encoded(
                n,
                frame.seq,
                frame.timestamp,
                frame.shape,
                frame.pixel_format,
                tuple(marks),
                raw,
                processed,
            )
        except Exception as e:
            if not src.failing:
                src.failing = True
                self.ctx.log.warning("%s: cannot show %s frames: %s", self.ctx.name, src.name, e)
            raise
        finally:
            frame.release()
            src.encoding = None
        src.failing = False
        src.encoded = enc
        src.encodes += 1
        self.encodes += 1
        return enc

    def _message(self, src: _Source, enc: Encoded) -> bytes:
        same = enc.processed is enc.raw
        header = json.dumps(
            {
                "source": src.name,
                "node": src.frame.source if src.frame is not None else "",
                "n": enc.n,
                "seq": enc.seq,
                "timestamp": enc.timestamp,
                "shape": enc.shape,
                "pixel_format": enc.pixel_format,
                "fps": round(src.fps(self.ctx.now()), 2),
                "marks": [m.json() for m in enc.marks],
                "raw": len(enc.raw),
                "processed": 0 if same else len(enc.processed),
            }
        ).encode()
        return b"".join(
            (struct.pack(">I", len(header)), header, enc.raw, b"" if same else enc.processed)
        )

    # --- HTTP ---------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(body=self._page, content_type="text/html", charset="utf-8")

    async def _stats(self, request: web.Request) -> web.Response:
        return web.Response(
            body=self.stats_json(),
            content_type="application/json",
            headers={"Cache-Control": "no-store"},
        )

    def stats_json(self) -> bytes:
        """``{"runtime": RuntimeStats | null, "display": {...}}``, cached for STATS_MAX_AGE."""
        mono = time.monotonic()
        if self._stats_cache is not None and mono - self._stats_cache[0] < STATS_MAX_AGE:
            return self._stats_cache[1]
        try:
            runtime: bytes = self.ctx.stats().model_dump_json().encode()
        except RuntimeError:  # no runtime around the node (a bare test harness)
            runtime = b"null"
        body = (
            b'{"runtime":'
            + runtime
            + b',"display":'
            + json.dumps(self.display_stats()).encode()
            + b"}"
        )
        self._stats_cache = (mono, body)
        return body

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
        return {
            "url": self.url,
            "clients": len(self.clients),
            "streams": len(self.streams),
            "encodes": self.encodes,
            "sources": sources,
            "detections": detections,
        }

    async def _snapshot(self, request: web.Request) -> web.Response:
        src, kind = await self._requested(request)
        try:
            enc = await self._latest(src)
        except Exception as e:
            raise web.HTTPInternalServerError(text=f"cannot show {src.name!r}: {e}") from e
        return web.Response(
            body=enc.raw if kind == "raw" else enc.processed,
            content_type="image/jpeg",
            headers={"Cache-Control": "no-store", "X-Frame-Seq": str(enc.seq)},
        )

    async def _requested(self, request: web.Request) -> tuple[_Source, str]:
        """The source and kind a frame request names; a source not seen yet is waited for."""
        name = request.match_info["source"]
        kind = request.query.get("kind", "processed")
        if kind not in ("raw", "processed"):
            raise web.HTTPBadRequest(text="kind must be raw or processed")
        src = self.sources.get(name)
        if src is None:
            wake = asyncio.Event()
            self.wakers.add(wake)
            try:
                async with asyncio.timeout(SOURCE_WAIT):
                    while (src := self.sources.get(name)) is None:
                        wake.clear()
                        await wake.wait()
            except TimeoutError:
                raise web.HTTPNotFound(
                    text=f"no frames from {name!r}; sources: {sorted(self.sources)}"
                ) from None
            finally:
                self.wakers.discard(wake)
        return src, kind

    async def _mjpeg(self, request: web.Request) -> web.StreamResponse:
        src, kind = await self._requested(request)
        resp = web.StreamResponse(
            headers={
                "Content-Type": "multipart/x-mixed-replace; boundary=flowrtframe",
                "Cache-Control": "no-store",
            }
        )
        await resp.prepare(request)
        wake = asyncio.Event()
        task = asyncio.current_task()
        assert task is not None
        self.wakers.add(wake)
        self.streams.add(task)
        sent = 0
        try:
            while True:
                if src.n <= sent or src.frame is None:
                    wake.clear()
                    await wake.wait()
                    continue
                delay = self._throttle(src)
                if delay > 0:
                    await asyncio.sleep(delay)
                try:
                    enc = await self._latest(src)
                except Exception:  # logged by _encode; wait for the next frame
                    sent = src.n
                    continue
                jpeg = enc.raw if kind == "raw" else enc.processed
                head = f"--flowrtframe\r\n{JPEG_PART}{len(jpeg)}\r\n\r\n"
                # write() waits for the socket to drain once its buffer is full: a slow reader
                # holds this loop, and when it continues it gets the newest frame.
                await resp.write(head.encode() + jpeg + b"\r\n")
                sent = enc.n
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.wakers.discard(wake)
            self.streams.discard(task)
        return resp

    async def _websocket(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(
            heartbeat=10.0, compress=False, timeout=CLOSE_TIMEOUT, max_msg_size=1 << 16
        )
        await ws.prepare(request)
        client = _Client(ws)
        self.clients.add(client)
        self.wakers.add(client.wake)
        client.wake.set()
        feeder = asyncio.get_running_loop().create_task(self._feed(client))
        try:
            async for msg in ws:
                if msg.type is not WSMsgType.TEXT:
                    continue
                try:
                    ack = json.loads(msg.data).get("ack")
                except (ValueError, AttributeError):
                    continue
                if isinstance(ack, str):
                    client.waiting_ack.discard(ack)
                    client.wake.set()
        finally:
            feeder.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await feeder
            self.wakers.discard(client.wake)
            self.clients.discard(client)
        return ws

    async def _feed(self, client: _Client) -> None:
        """Send each source's newest frame to one client, one unacknowledged message at most."""
        while not client.ws.closed:
            ready, wait = [], None
            for src in list(self.sources.values()):
                if (
                    src.name in client.waiting_ack
                    or src.frame is None
                    or src.n <= client.sent.get(src.name, 0)
                ):
                    continue
                delay = self._throttle(src)
                if delay > 0:
                    wait = delay if wait is None else min(wait, delay)
                else:
                    ready.append(src)
            if not ready:
                client.wake.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(client.wake.wait(), wait)
                continue
            encoded = await asyncio.gather(
                *(self._latest(s) for s in ready), return_exceptions=True
            )
            for src, enc in zip(ready, encoded, strict=True):
                if isinstance(enc, BaseException):  # logged by _encode; wait for the next frame
                    client.sent[src.name] = src.n
                    continue
                client.waiting_ack.add(src.name)
                client.sent[src.name] = enc.n
                await client.ws.send_bytes(self._message(src, enc))
                client.messages += 1
