"""Capture: the frame source of a graph — camera, video file, image sequence or synthetic scene.

Every frame a capture node publishes is a tick of its frame clock (CAMBADA's ``PMan_tick``):
the trackers of a graph run on those ticks with their period and phase in frames.

Sources (``source`` param)
--------------------------
``synthetic:soccer`` (default)
    The embedded deterministic robot-soccer scene (:class:`~flowrt.nodes.scene.SoccerScene`),
    rendered at ``size`` with ``seed`` and ``clutter``. Frame ``seq`` is the scene's frame index
    and the ground truth of every frame is published on the ``truth`` output.
``camera:0`` / ``camera:/dev/video0``
    An OpenCV capture device. ``size`` and ``fps`` are requested from the device (and ``size``
    enforced by resizing). The device paces itself: the node free-runs and waits for frames.
``file:PATH`` or a bare path (or an ``rtsp://``/``http://`` URL)
    Anything OpenCV/FFmpeg decodes. A relative path in a graph file resolves against the
    graph file's directory (:func:`flowrt.resolve_path`); a file that does not exist is a
    validation error located at ``source``. ``on_eof``: ``stop`` (an ``end-of-stream`` info event,
    then no more frames), ``loop`` (start over, seamlessly) or ``exit`` (as ``stop``, then the
    runtime is asked to stop: a recording played through a graph).
``images:GLOB`` or a bare path with ``*``/``?``/``[``
    The matching image files in sorted order; ``on_eof`` as for files. An unreadable file is
    reported (``source-error`` event) and skipped.

Pacing: ``realtime`` publishes at ``fps`` on a precise timer of the runtime (cameras: at the
device's rate); ``fast`` publishes as fast as the source delivers and the graph consumes: each
frame waits until every period-1 frame-triggered reader (inline or in a worker) has taken the
previous one (``ctx.wait_readers()``), so an offline run processes every frame. The thread
that decodes a file or reads images then runs below the graph's workers when every such
reader is in one and the loop runs ``--realtime`` (SCHED_FIFO 1), with FFmpeg's own decoding
threads: it only needs to stay a few frames ahead of them, and at the loop's priority it
preempted them in their calls.

Pixel formats: ``pixel_format`` is what the node publishes (BGR, RGB or GRAY). ``input_format``
is what the source delivers: for a camera, a raw device format (YUYV, UYVY, I420, NV12, or
BGR/RGB/GRAY); for the synthetic scene the rendered image is first encoded to it, which
simulates a raw camera. Decoded files and images are BGR (``RGB`` declares channel-swapped
content, ``GRAY`` reads images as grey). Conversion and resizing happen once, at capture,
straight into the published frame (a shared-memory slot when the runtime provides a pool).
A video file whose frames need neither (BGR or RGB as published, at its own size) is decoded
straight into its slot by the reader thread (a few slots are lent to it ahead, at most
``LEND``): the loop publishes the frame without copying a pixel.

Stalls and errors never block the runtime nor raise a traceback. Devices and decoders are
read by a daemon thread each (which alone opens, reads and releases its device, so a hung
driver call can never race a release); an activation waits for the next frame at most
``grab_timeout`` (default two frame periods). Then the node emits a :class:`flowrt.HealthAlert`
(``alert="grab-timeout"``, the reason in ``detail``):

- a camera is abandoned and reopened after an exponential backoff (``backoff`` doubling up to
  ``max_backoff``);
- a file or image sequence is only reported as slow, and reopened if it delivers nothing for
  ``open_timeout``, resuming at the frame it stalled on (never replaying from the start).

A failed open or read (missing file, corrupt or unreadable video, no such camera, a glob that
matches nothing) emits ``source-error`` and is retried with the same backoff, so it shows up
as an event every backoff interval until the source becomes readable; ``max_retries`` bounds
that (then ``source-gave-up``, severity error, and the node is failed for good: a
:class:`flowrt.FatalError`, so ``flowrt run`` stops unless ``--keep-going``). When frames flow
again after a problem, a ``source-recovered`` info event follows. The first frame after an
open gets ``open_timeout`` rather than ``grab_timeout``. Every alert is also logged, once per
distinct problem.

Meanwhile the node is in an error state (``ctx.set_error``: red in the table, the reason in
the statistics, a ``node-error`` alert), left when frames flow again. A source that never
delivered a frame is left in the error state at teardown ("never delivered a frame", with the
count of failed attempts and the last error), so the run's verdict (``Runtime.failures()``,
the exit code of ``flowrt run``) says it failed. What OpenCV, V4L2 and FFmpeg print on stderr
while a device opens goes to the node's log (each kind of line once at INFO, then DEBUG).

Where the parts live: the params and their validation in :mod:`.capture_params`, pixel
format conversion in :mod:`.capture_formats`, the camera, video and image devices in
:mod:`.capture_sources`, the thread that reads a device in :mod:`.capture_reader` (and the
native stderr it collects in :mod:`.capture_stderr`), the stall and failure policy in
:mod:`.capture_recovery`. This module is the node: pacing, the synthetic scene, the frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from flowrt import Frame, LoopTrigger, Node, Output, TimerTrigger

from ..scene import SceneTruth
from .formats import (
    INPUT_FORMATS,
    OUTPUT_FORMATS,
    convert_into,
    encode_raw,
    output_shape,
    raw_size,
)
from .params import (
    WARN_FRAME_BYTES,
    CaptureParams,
    frame_bytes,
    parse_source,
    pool_memory_text,
)
from .reader import ALERT, EOF, ERROR, LOG, Reader
from .recovery import SourceRecovery
from .sources import Device, ImageDevice, SourceError, VideoDevice

__all__ = [
    "INPUT_FORMATS",
    "LEND",
    "OUTPUT_FORMATS",
    "Capture",
    "CaptureParams",
    "SourceError",
    "convert_into",
    "encode_raw",
    "parse_source",
]


LEND = 5
"""Slots lent to a file's reader thread to decode into: its read-ahead (4 frames, see
:class:`~.reader.Reader`) plus the one it decodes while the loop takes a frame, so a blank is
always there (else it decodes into an
array of its own, copied once into a slot by the loop)."""


class Capture(Node):
    """A frame source: camera, video file, image sequence or the synthetic soccer scene.

    Outputs ``frame`` (each publication is a tick of this node's frame clock) and ``truth``
    (the synthetic scene's :class:`~flowrt.nodes.scene.SceneTruth` of that frame; nothing for
    real sources). Runs inline: it needs the runtime's frame pool and event stream.
    """

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset(
        {
            "fps",
            "clutter",
            "flash_on",
            "flash_period",
            "grab_timeout",
            "backoff",
            "max_backoff",
            "max_retries",
        }
    )

    Params = CaptureParams
    inline_only = True

    frame = Output(Frame, doc="the captured frame, in pixel_format, at size")
    truth = Output(SceneTruth, doc="ground truth of the synthetic scene, per frame")

    @classmethod
    def advise(cls, params: Any) -> list[tuple[str, str]]:
        p: CaptureParams = params
        if p.size is not None and frame_bytes(p.size, p.pixel_format) > WARN_FRAME_BYTES:
            return [("size", pool_memory_text(p.size, p.pixel_format))]
        return []

    @classmethod
    def default_trigger(cls, params: Any) -> Any:
        kind, _ = params.kind()
        if kind == "camera" or params.pacing == "fast":
            return LoopTrigger()
        return TimerTrigger(timer=1000.0 / params.fps)

    # -- lifecycle

    def setup(self) -> None:
        p: CaptureParams = self.params
        self._kind, self._target = p.kind()
        self._loop_mode = self._kind == "camera" or p.pacing == "fast"
        self._seq = 0
        self._scene: Any = None
        self._reader: Reader | None = None
        self._abandoned: list[Reader] = []
        self._recovery = SourceRecovery(self.ctx, p)
        self._position = 0  # where a reopened file or image sequence resumes
        self._held: Frame | None = None  # a frame decoded in its slot, published: its link
        if self._kind == "synthetic" and p.kind()[1] == "flash":
            from ..calibration import FlashScene

            w, h = p.size or (320, 240)
            self._scene = FlashScene(w, h, p.flash_on / 1000, p.flash_period / 1000)
        elif self._kind == "synthetic":
            from ..scene import SoccerScene

            w, h = p.size or (320, 240)
            self._scene = SoccerScene(w, h, seed=p.seed, clutter=p.clutter, fps=p.fps)

    async def teardown(self) -> None:
        if self._scene is None and self._seq == 0:  # the run's verdict: this source failed
            with contextlib.suppress(RuntimeError):
                self.ctx.set_error(self._recovery.never_delivered())
        self._unhold()
        readers = [*self._abandoned, *([self._reader] if self._reader else [])]
        self._reader = None
        self._abandoned = []
        for r in readers:
            r.stop()
        # Let the threads release their devices; a thread stuck in a driver call is left
        # behind (a daemon), never waited for.
        for _ in range(100):
            if not any(r.thread.is_alive() for r in readers):
                break
            await asyncio.sleep(0.01)
        for r in readers:
            _release(r.unused())  # a thread still stuck keeps its blanks: it may write them
        stuck = [r.thread.name for r in readers if r.thread.is_alive()]
        if stuck:
            self.ctx.log.warning(
                "%s: %d reader thread(s) still blocked in the device at teardown (left behind)",
                self.ctx.name,
                len(stuck),
            )

    async def process(self) -> dict[str, Any] | None:
        self._unhold()
        out = self._synthetic() if self._scene is not None else await self._grab()
        if out is not None and self.params.pacing == "fast" and self._kind != "camera":
            # Offline: every period-1 frame reader (inline or in a worker) takes every frame.
            await self.ctx.wait_readers()
        return out

    # -- synthetic

    def _synthetic(self) -> dict[str, Any]:
        p: CaptureParams = self.params
        if not hasattr(self._scene, "render"):  # the flash: lit by the time of the exposure
            t = self.ctx.now()
            img, _ = self._scene.render_at(t, 1 / p.fps)
            frame = self._publishable(img, "BGR", None)
            frame.timestamp = t  # the exposure's start: what the brightness was integrated from
            return {"frame": frame}
        img, truth = self._scene.render(self._seq)
        fmt_in = p.input_format or "BGR"
        raw = encode_raw(img, fmt_in) if fmt_in != "BGR" else img
        frame = self._publishable(raw, fmt_in, None)
        # stamped with its frame's time: recorded at it, in Unix time like the frame
        truth = dataclasses.replace(truth, timestamp=frame.timestamp)
        return {"frame": frame, "truth": truth}

    def _publishable(self, raw: np.ndarray, fmt_in: str, dims: tuple[int, int] | None) -> Frame:
        p: CaptureParams = self.params
        w, h = p.size or raw_size(raw, fmt_in, dims)
        frame = self.ctx.new_frame(output_shape(w, h, p.pixel_format), np.uint8, p.pixel_format)
        convert_into(raw, fmt_in, p.pixel_format, frame.data, dims)
        return self._stamped(frame)

    # -- real sources

    def _open(self) -> Reader:
        p: CaptureParams = self.params
        kind, target = self._kind, self._target

        def opener(alert: Callable[[str, str], None], start: int) -> Device:
            if kind == "images":
                assert isinstance(target, str)
                return ImageDevice(target, p.input_format == "GRAY", alert, start)
            return VideoDevice(
                kind,
                target,
                input_format=p.input_format,
                size=p.size,
                fps=p.fps,
                start=start,
                decode_threads=p.decode_threads,
            )

        self._recovery.opening()
        return Reader(
            self.ctx.name,
            opener,
            asyncio.get_running_loop(),
            latest=kind == "camera",
            rewind=p.on_eof == "loop",
            start=self._position,
            # Offline, the source follows its readers: decoding below them (reader.py).
            background=kind != "camera" and p.pacing == "fast" and self._readers_in_workers(),
        )

    def _readers_in_workers(self) -> bool:
        """Every period-1 frame reader of this source runs in a worker process (and one does).

        Then its decoder may run below them. Not with a reader on the loop: the loop's own
        helper threads (OpenCV's pool, spinning between an inline tracker's calls) run at the
        loop's priority and starved a lowered decoder (graphs/video.yaml inline under
        ``--realtime``: 0.95x of a plain OpenCV loop -> 0.69x)."""
        try:
            graph = self.ctx.graph
        except RuntimeError:  # outside a runtime (a node harness): no readers
            return False
        readers = [
            n
            for n in graph.nodes.values()
            if (n.frame_source or "").split(".")[0] == self.ctx.name
            and getattr(n.trigger, "period", 1) == 1
        ]
        return bool(readers) and all(n.spec.placement != "inline" for n in readers)

    def _drop_reader(self) -> None:
        if self._reader is not None:
            self._reader.stop()
            self._abandoned.append(self._reader)
            self._reader = None
        for r in self._abandoned:
            _release(r.unused())
        self._abandoned = [r for r in self._abandoned if r.thread.is_alive()]

    def _failed(self, alert: str, detail: str) -> None:
        """Abandon the reader, then report and schedule a reopen after the backoff (or give
        up: :meth:`SourceRecovery.failed` raises FatalError)."""
        self._drop_reader()
        self._recovery.failed(alert, detail)

    async def _idle(self, until: float | None = None) -> None:
        """Nothing to publish now: free-running nodes wait a little instead of spinning."""
        if self._loop_mode:
            wait = 0.1 if until is None else min(0.1, max(0.0, until - self.ctx.now()))
            await asyncio.sleep(max(wait, 0.001))

    async def _next_frame(self, reader: Reader, first: bool) -> Any:
        """The next frame item of ``reader`` (image, dims, position), handling the alerts,
        native log lines, errors, end of stream and timeouts before it; None if there is
        no frame this activation."""
        p: CaptureParams = self.params
        recovery = self._recovery
        timeout = p.grab_timeout_s
        while True:
            item = await reader.get(timeout)
            if reader is not self._reader:  # dropped meanwhile (teardown)
                return None
            if item is None:
                failure = recovery.timed_out(first, timeout, self._position)
                if failure is not None:
                    self._failed("grab-timeout", failure)
                return None
            kind, value = item
            if kind == ALERT:
                recovery.alert(*value)
            elif kind == LOG:
                recovery.native_log(value)
            elif kind == ERROR:
                self._failed("source-error", value)
                return None
            elif kind == EOF:
                self._drop_reader()
                recovery.end_of_stream(self._seq)
                if p.on_eof == "exit":  # a recording played through the graph: then stop
                    self.ctx.request_stop()
                return None
            else:
                return value

    async def _grab(self) -> dict[str, Any] | None:
        p: CaptureParams = self.params
        recovery = self._recovery
        if recovery.ended:
            await self._idle()
            return None
        if self._reader is None:
            if self.ctx.now() < recovery.retry_at:
                await self._idle(recovery.retry_at)
                return None
            self._reader = self._open()
        reader = self._reader
        value = await self._next_frame(reader, first=reader.delivered == 0)
        if value is None:
            return None
        img, dims, self._position, blank = value
        recovery.frame_read()
        lent: Frame | None = reader.reclaim(blank)
        try:
            if lent is not None and img is lent.data:  # decoded in its slot: no copy
                frame = self._stamped(lent)
                self._held = lent  # the node's link, given back once it is published
            else:
                _release([lent])
                frame = self._publishable(img, p.input_format or "BGR", dims)
        except SourceError as e:
            self._failed("source-error", str(e))
            return None
        self._lend(reader, img)
        recovery.frame_published(first=frame.seq == 0)
        return {"frame": frame}

    def _lend(self, reader: Reader, img: np.ndarray) -> None:
        """Keep ``LEND`` slots with the reader of a file whose frames are published as they
        are decoded (same format, same size): it decodes the next frames into them."""
        p: CaptureParams = self.params
        fmt = p.input_format or "BGR"
        if self._kind != "file" or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            return
        h, w = img.shape[:2]
        if fmt != p.pixel_format or fmt not in ("BGR", "RGB"):
            return
        if p.size is not None and tuple(p.size) != (w, h):
            return
        while reader.lent < LEND:
            # A pool at its bound counts this as a dropped frame, as it would the next one.
            frame = self.ctx.new_frame(img.shape, np.uint8, p.pixel_format)
            if not frame.shared:  # no pool, or every slot held: decoded then copied
                return
            frame.acquire()  # the node's link: the activation lets go of its own at its end
            reader.lend(frame.data, frame)

    def _stamped(self, frame: Frame) -> Frame:
        frame.seq = self._seq
        frame.timestamp = self.ctx.now()
        frame.source = self.ctx.name
        self._seq += 1
        return frame

    def _unhold(self) -> None:
        """The frame returned last time is held by its readers now (and by nobody if it was
        discarded: the activation took a link of its own on it, given back at its end): drop
        the node's link."""
        if self._held is not None:
            self._held.release()
            self._held = None


def _release(frames: list[Any]) -> None:
    for frame in frames:
        if frame is not None:
            frame.release()
