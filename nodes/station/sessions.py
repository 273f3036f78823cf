"""Review: the recorded sessions, their per-stream tables, and a camera's frame at any instant.

Served by the live view's server process (:mod:`flowrt.nodes.station.server`):

- ``GET /api/sessions``: every session under the recordings folders (the display's
  ``recordings`` and every recorder's folder), newest first: ``name``, ``start``,
  ``duration_s``, ``size_bytes``, ``recording`` (being written now), ``lost`` and ``streams``
  (``topic``, ``frames``, ``rate``, ``lost``). A finished session is described by its own
  ``streams.json`` (the recorder's table); one without it (killed) is scanned.
- ``GET /api/sessions/NAME``: one session for the player: its cameras (image topics), the
  stream table (``expected``/``received``/``written``/``lost`` when the recorder wrote them)
  and each stream's gaps (intervals longer than twice its usual period).
- ``GET /api/sessions/NAME/frame?topic=T&t=SECONDS``: the camera's frame at ``t`` seconds
  from the session's start (the newest at or before it), with the detections recorded for
  it drawn, as a JPEG.

A session name comes from a URL: it must be a bare session name (letters, digits, ``_``,
``-``; no ``/``, no ``..``) naming a folder directly under a recordings folder, else 404 (400
for a malformed one). Reading and encoding run in a thread; nothing heavy (mcap, the
protobuf decoders) is imported before the first review request.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import math
import statistics
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aiohttp import web

SESSION_FILE = "streams.json"  # flowrt.recording.session.SESSION_FILE (not imported: mcap)
NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")
INDEXES_KEPT = 4  # sessions whose message index is kept (the one being played, a few more)
DETECTION_WINDOW = 0.5  # seconds: a detection older than this is not drawn on a frame
JPEG_QUALITY = 85


def valid_name(name: str) -> bool:
    """A bare session name: never a path (no ``/``, ``\\``, ``.``), bounded."""
    return 0 < len(name) <= 64 and set(name) <= NAME_CHARS


class Sessions:
    """The review API over the folders ``folders()`` names (they may change as recorders
    appear); ``active()`` names the sessions being recorded now."""

    def __init__(self, folders: Callable[[], list[str]], active: Callable[[], set[str]]) -> None:
        self.folders = folders
        self.active = active
        self._summaries: dict[Path, tuple[Any, dict[str, Any]]] = {}
        self._indexes: OrderedDict[Path, tuple[Any, Any]] = OrderedDict()
        self._lock = asyncio.Lock()  # one index build at a time (they read whole sessions)

    def routes(self) -> list[web.RouteDef]:
        return [
            web.get("/api/sessions", self.list),
            web.get("/api/sessions/{name}", self.detail),
            web.get("/api/sessions/{name}/frame", self.frame),
        ]

    # --- finding sessions ------------------------------------------------------------------

    def _dirs(self) -> dict[str, Path]:
        """Session name -> folder, over every recordings folder (the first folder wins)."""
        out: dict[str, Path] = {}
        for folder in self.folders():
            root = Path(folder)
            with contextlib.suppress(OSError):
                for p in sorted(root.iterdir()):
                    if valid_name(p.name) and p.name not in out and _is_session(p):
                        out[p.name] = p
        return out

    def _find(self, request: web.Request) -> Path:
        name = request.match_info["name"]
        if not valid_name(name):
            raise web.HTTPBadRequest(text="a session name is letters, digits, _ and -\n")
        path = self._dirs().get(name)
        if path is None:
            raise web.HTTPNotFound(text=f"no session {name!r}\n")
        return path

    # --- the list ---------------------------------------------------------------------------

    async def list(self, request: web.Request) -> web.Response:
        dirs = self._dirs()
        active = self.active()
        rows = await asyncio.to_thread(
            lambda: [self._summary(p, p.name in active) for p in dirs.values()]
        )
        rows.sort(key=lambda r: (r["start"] or "", r["name"]), reverse=True)
        return _json({"folders": self.folders(), "sessions": rows})

    def _summary(self, path: Path, recording: bool) -> dict[str, Any]:
        files = _files(path)
        size = sum(f.stat().st_size for f in files if f.exists())
        signature = (
            tuple((f.name, f.stat().st_size) for f in files),
            (path / SESSION_FILE).exists(),
        )
        cached = self._summaries.get(path)
        if cached is not None and cached[0] == signature and not recording:
            return cached[1]
        row: dict[str, Any] = {
            "name": path.name,
            "start": None,
            "duration_s": None,
            "size_bytes": size,
            "recording": recording,
            "closed": (path / SESSION_FILE).exists(),
            "lost": None,
            "streams": [],
        }
        report = _report(path)
        if report is not None:
            streams = report.get("streams", [])
            row.update(
                start=report.get("start_time"),
                duration_s=session_length(report),
                lost=sum(int(s.get("lost", 0)) for s in streams),
                error=report.get("error"),
                streams=[
                    {
                        "topic": s.get("topic"),
                        "frames": s.get("written"),
                        "rate": _r(s.get("rate_mean")),
                        "lost": s.get("lost"),
                    }
                    for s in streams
                ],
            )
        elif not recording and files:  # killed before its table: what the files hold
            from flowrt.recording.reader import scan_session

            info = scan_session(path)
            row.update(
                start=_iso(info.start),
                duration_s=info.duration,
                streams=[
                    {"topic": s.topic, "frames": s.count, "rate": _r(s.rate_mean), "lost": None}
                    for s in info.streams
                ],
                damage=info.damage,
            )
        if not recording:
            self._summaries[path] = (signature, row)
        return row

    # --- one session ------------------------------------------------------------------------

    async def _index(self, path: Path) -> Any:
        signature = tuple((f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in _files(path))
        async with self._lock:
            cached = self._indexes.get(path)
            if cached is not None and cached[0] == signature:
                self._indexes.move_to_end(path)
                return cached[1]
            from flowrt.recording.seek import SessionIndex

            index = await asyncio.to_thread(SessionIndex, path)
            self._indexes[path] = (signature, index)
            while len(self._indexes) > INDEXES_KEPT:
                self._indexes.popitem(last=False)
            return index

    async def detail(self, request: web.Request) -> web.Response:
        path = self._find(request)
        index = await self._index(path)
        report = await asyncio.to_thread(_report, path) or {}
        rows = {s.get("topic"): s for s in report.get("streams", [])}
        streams = []
        for topic, t in index.topics.items():
            row = rows.get(topic, {})
            streams.append(
                {
                    "topic": topic,
                    "schema": t.schema_name,
                    "frames": len(t.times),
                    "rate": _r(_rate(t.times)),
                    "expected": row.get("expected"),
                    "received": row.get("received"),
                    "written": row.get("written"),
                    "lost": row.get("lost"),
                    "gaps": _gaps(t.times, index.start_ns),
                }
            )
        cameras = [s["topic"] for s in streams if s["schema"] in IMAGE_SCHEMAS]
        return _json(
            {
                "name": path.name,
                "start": report.get("start_time") or _iso(index.start_ns / 1e9),
                "duration_s": index.duration,
                "cameras": cameras,
                "streams": streams,
                "damage": index.damage,
            }
        )

    async def frame(self, request: web.Request) -> web.Response:
        path = self._find(request)
        topic = request.query.get("topic", "")
        try:
            t = float(request.query.get("t", "0"))
        except ValueError:
            raise web.HTTPBadRequest(text="t is seconds from the session's start\n") from None
        if not math.isfinite(t) or abs(t) > MAX_T_S:  # 1e308 ns overflowed in the lookup
            raise web.HTTPBadRequest(
                text=f"t is seconds from the session's start, at most {MAX_T_S:g}\n"
            )
        index = await self._index(path)
        stream = index.topics.get(topic)
        if stream is None or stream.schema_name not in IMAGE_SCHEMAS or not stream.times:
            cameras = [k for k, v in index.topics.items() if v.schema_name in IMAGE_SCHEMAS]
            raise web.HTTPNotFound(text=f"no camera {topic!r} in {path.name}; cameras: {cameras}\n")
        try:
            jpeg, at, seq = await asyncio.to_thread(frame_jpeg, index, topic, t)
        except Exception as e:  # a frame that does not decode: say which, keep serving
            raise web.HTTPUnprocessableEntity(text=f"{topic} at {t:g} s: {e}\n") from None
        return web.Response(
            body=jpeg,
            content_type="image/jpeg",
            headers={
                "Cache-Control": "no-store",
                "X-Frame-Time": f"{at:.6f}",
                "X-Frame-Seq": str(seq),
            },
        )


IMAGE_SCHEMAS = ("foxglove.RawImage", "foxglove.CompressedImage")
#: The largest ``t`` of the frame API: about 31 years, far inside nanoseconds in an int64.
MAX_T_S = 1e9


def frame_jpeg(index: Any, topic: str, t: float) -> tuple[bytes, float, int]:
    """(JPEG, its time from the start in s, its sequence) of ``topic`` at ``t`` seconds, with
    the detections recorded for that frame drawn (on a thread: decoding and encoding)."""
    import cv2

    from flowrt.recording.encoding import Decoder

    from .render import draw, to_bgr8

    stream = index.topics[topic]
    i = stream.at(index.start_ns + round(t * 1e9))
    msg = index.message(topic, i)
    decoder = index.decoders.setdefault(stream.where[i][0], None) or Decoder()
    index.decoders[stream.where[i][0]] = decoder
    pixels, pixel_format = decoder.image(msg.schema, msg.data)
    img = draw(to_bgr8(pixels, pixel_format), _marks(index, topic, msg.log_time))
    ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("cannot encode the frame as JPEG")
    return jpeg.tobytes(), (msg.log_time - index.start_ns) / 1e9, msg.sequence


def _marks(index: Any, camera: str, at_ns: int) -> list[Any]:
    """The detections of ``camera``'s frame at ``at_ns``: for each detection stream the
    recorder annotated on this camera (``CAM/annotations/DET``), its newest message at or
    before the frame (within ``DETECTION_WINDOW``)."""
    from .render import Mark

    prefix = f"{camera}/annotations/"
    marks = []
    for name in index.topics:
        if not name.startswith(prefix):
            continue
        det_topic = name[len(prefix) :]
        det = index.topics.get(det_topic)
        if det is None or not det.times or det.encoding != "json":
            continue
        i = det.at(at_ns + 1_000_000)  # stamped with its frame's time; 1 ms of rounding
        if det.times[i] > at_ns + 1_000_000 or at_ns - det.times[i] > DETECTION_WINDOW * 1e9:
            continue
        try:
            value = json.loads(index.message(det_topic, i).data)
        except ValueError:
            continue
        for d in value if isinstance(value, list) else [value]:
            if isinstance(d, dict):
                with contextlib.suppress(TypeError, ValueError, IndexError):
                    marks.append(_mark(Mark, d, det_topic))
    return marks


def _mark(mark: Any, d: dict[str, Any], topic: str) -> Any:
    bbox, centroid, conf = d.get("bbox"), d.get("centroid"), d.get("confidence")
    return mark(
        label=str(d.get("object") or topic.split(".")[0]),
        found=bool(d.get("found")),
        bbox=None if bbox is None else tuple(int(v) for v in bbox[:4]),
        centroid=None if centroid is None else (float(centroid[0]), float(centroid[1])),
        confidence=None if conf is None else float(conf),
    )


def session_length(report: dict[str, Any]) -> float | None:
    """A finished session's ``duration_s``: first message to last (the report's ``span``),
    as the player measures it from the files; the recorder's start-to-stop time for a report
    written before it had one."""
    span = report.get("span")
    return float(span) if span is not None else report.get("duration")


def _is_session(path: Path) -> bool:
    return path.is_dir() and (any(path.glob("*.mcap")) or (path / SESSION_FILE).exists())


def _files(path: Path) -> list[Path]:
    return sorted(f for f in path.glob("*.mcap") if ".damaged" not in f.name)


def _report(path: Path) -> dict[str, Any] | None:
    """The recorder's own table (``streams.json``), or None when it did not finish one."""
    try:
        data = json.loads((path / SESSION_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _rate(times: list[int]) -> float | None:
    if len(times) < 2 or times[-1] <= times[0]:
        return None
    return (len(times) - 1) / ((times[-1] - times[0]) / 1e9)


def _gaps(times: list[int], start_ns: int) -> list[dict[str, float]]:
    """Intervals longer than twice the stream's median interval (as ``flowrt info``)."""
    if len(times) < 3:
        return []
    iv = [b - a for a, b in itertools.pairwise(times)]
    period = statistics.median(iv)
    if period <= 0:
        return []
    return [
        {"at": round((times[i] - start_ns) / 1e9, 3), "length": round(d / 1e9, 3)}
        for i, d in enumerate(iv)
        if d > 2 * period
    ][:100]


def _iso(t: float | None) -> str | None:
    import datetime as dt

    return None if t is None else dt.datetime.fromtimestamp(t, dt.UTC).isoformat()


def _r(x: Any) -> float | None:
    return None if x is None else round(float(x), 2)


def _json(data: Any) -> web.Response:
    return web.Response(
        text=json.dumps(data),
        content_type="application/json",
        headers={"Cache-Control": "no-store"},
    )
