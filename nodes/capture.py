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
previous one (``ctx.wait_readers()``), so an offline run processes every frame.

Pixel formats: ``pixel_format`` is what the node publishes (BGR, RGB or GRAY). ``input_format``
is what the source delivers: for a camera, a raw device format (YUYV, UYVY, I420, NV12, or
BGR/RGB/GRAY); for the synthetic scene the rendered image is first encoded to it, which
simulates a raw camera. Decoded files and images are BGR (``RGB`` declares channel-swapped
content, ``GRAY`` reads images as grey). Conversion and resizing happen once, at capture,
straight into the published frame (a shared-memory slot when the runtime provides a pool).

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
"""

from __future__ import annotations

import asyncio
import contextlib
import glob
import math
import os
import re
import sys
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Iterator
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic.functional_validators import BeforeValidator

from flowrt import (
    FatalError,
    Frame,
    HealthAlert,
    LoopTrigger,
    Node,
    Output,
    TimerTrigger,
    resolve_path,
)
from flowrt.files import check_regular_file

from .scene import SceneTruth

__all__ = [
    "INPUT_FORMATS",
    "OUTPUT_FORMATS",
    "Capture",
    "CaptureParams",
    "SourceError",
    "convert_into",
    "encode_raw",
    "parse_source",
]

OutputFormat = Literal["BGR", "RGB", "GRAY"]
InputFormat = Literal["BGR", "RGB", "GRAY", "YUYV", "UYVY", "I420", "NV12"]
OUTPUT_FORMATS: tuple[str, ...] = ("BGR", "RGB", "GRAY")
INPUT_FORMATS: tuple[str, ...] = ("BGR", "RGB", "GRAY", "YUYV", "UYVY", "I420", "NV12")
_PACKED = ("YUYV", "UYVY")  # 4:2:2, two bytes per pixel: (h, w, 2)
_PLANAR = ("I420", "NV12")  # 4:2:0, Y plane then chroma: (h * 3 / 2, w)
SCENES = ("soccer", "flash")

# One cv2.cvtColor code per (input, output) pair: every conversion is a single pass.
_CVT: dict[tuple[str, str], int] = {
    ("BGR", "RGB"): cv2.COLOR_BGR2RGB,
    ("BGR", "GRAY"): cv2.COLOR_BGR2GRAY,
    ("RGB", "BGR"): cv2.COLOR_RGB2BGR,
    ("RGB", "GRAY"): cv2.COLOR_RGB2GRAY,
    ("GRAY", "BGR"): cv2.COLOR_GRAY2BGR,
    ("GRAY", "RGB"): cv2.COLOR_GRAY2RGB,
    ("YUYV", "BGR"): cv2.COLOR_YUV2BGR_YUYV,
    ("YUYV", "RGB"): cv2.COLOR_YUV2RGB_YUYV,
    ("YUYV", "GRAY"): cv2.COLOR_YUV2GRAY_YUYV,
    ("UYVY", "BGR"): cv2.COLOR_YUV2BGR_UYVY,
    ("UYVY", "RGB"): cv2.COLOR_YUV2RGB_UYVY,
    ("UYVY", "GRAY"): cv2.COLOR_YUV2GRAY_UYVY,
    ("I420", "BGR"): cv2.COLOR_YUV2BGR_I420,
    ("I420", "RGB"): cv2.COLOR_YUV2RGB_I420,
    ("I420", "GRAY"): cv2.COLOR_YUV2GRAY_I420,
    ("NV12", "BGR"): cv2.COLOR_YUV2BGR_NV12,
    ("NV12", "RGB"): cv2.COLOR_YUV2RGB_NV12,
    ("NV12", "GRAY"): cv2.COLOR_YUV2GRAY_NV12,
}
# V4L2 pixel formats requested from a camera whose input_format is set (delivered unconverted).
_FOURCC = {
    "YUYV": "YUYV",
    "UYVY": "UYVY",
    "I420": "YU12",
    "NV12": "NV12",
    "GRAY": "GREY",
    "RGB": "RGB3",
}
# cv2's YUV->GRAY takes the luma plane as it is: video range (16..235). Expanded to full range
# (0..255) so that GRAY from a YUV camera means the same as GRAY from a BGR one.
_VIDEO_TO_FULL = np.clip((np.arange(256) - 16) * 255.0 / 219.0 + 0.5, 0, 255).astype(np.uint8)


class SourceError(Exception):
    """A source cannot be opened or read; the message is meant for the user."""


# ---------------------------------------------------------------------- params

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(us|ms|s)?\s*$")
_UNIT_MS = {"us": 0.001, "ms": 1.0, "s": 1000.0, None: 1.0}


def _duration_ms(value: Any) -> Any:
    """``200ms``, ``1.5s``, ``500us`` or a number of milliseconds, like the graph's durations."""
    if isinstance(value, str):
        m = _DURATION.match(value)
        if not m:
            raise ValueError(f"expected a duration such as 200ms, 1.5s or 500us, got {value!r}")
        return float(m.group(1)) * _UNIT_MS[m.group(2)]
    return value


Ms = Annotated[float, BeforeValidator(_duration_ms), Field(gt=0, le=3_600_000)]

# The runtime's frame pool of a capture node: 4 slots allocated at the first frame, growing
# up to 16 while readers hold frames (flowrt.frames.FrameStore.pool).
POOL_SLOTS_AT_START = 4
POOL_SLOTS_MAX = 16
WARN_FRAME_BYTES = 8 * 2**20
"""A frame above this (about 1920x1440 BGR) gets a warning at validate with its memory."""
MAX_FRAME_BYTES = 64 * 2**20
"""A frame above this (about 4730x4730 BGR) is refused unless ``allow_large: true``: a
16384x16384 frame took 3 GB of shared memory, lagged the loop 6.6 s and 15 s to stop."""


def _mib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def frame_bytes(size: tuple[int, int], pixel_format: str) -> int:
    """Bytes of one published frame of ``size`` (width, height) in ``pixel_format``."""
    return size[0] * size[1] * (1 if pixel_format == "GRAY" else 3)


def pool_memory_text(size: tuple[int, int], pixel_format: str) -> str:
    """What a frame of this size costs in the frame pool, for messages."""
    one = frame_bytes(size, pixel_format)
    return (
        f"a {size[0]}x{size[1]} {pixel_format} frame is {_mib(one)}: its frame pool takes "
        f"{_mib(one * POOL_SLOTS_AT_START)} of shared memory at start ({POOL_SLOTS_AT_START} "
        f"slots) and up to {_mib(one * POOL_SLOTS_MAX)} ({POOL_SLOTS_MAX} slots)"
    )


SourceKind = Literal["synthetic", "camera", "file", "images"]
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9_-]*):(.*)$")


def parse_source(source: str) -> tuple[SourceKind, str | int]:
    """Split a ``source`` string into its kind and target; ValueError with a hint if invalid."""
    s = source.strip()
    if not s:
        raise ValueError(
            "source is empty; use synthetic:soccer, camera:N, file:PATH or images:GLOB"
        )
    if "://" in s:  # rtsp://, http://...: a stream FFmpeg opens like a file
        return "file", s
    m = _SCHEME.match(s)
    if m and len(m.group(1)) > 1:
        scheme, rest = m.group(1).lower(), m.group(2).strip()
        if scheme == "synthetic":
            scene = rest or "soccer"
            if scene not in SCENES:
                raise ValueError(
                    f"unknown synthetic scene {scene!r} (available: {', '.join(SCENES)})"
                )
            return "synthetic", scene
        if scheme == "camera":
            if not rest:
                raise ValueError("camera source needs a device: camera:0 or camera:/dev/video0")
            return "camera", int(rest) if rest.isdigit() else rest
        if scheme in ("file", "images"):
            if not rest:
                raise ValueError(f"{scheme} source needs a path: {scheme}:PATH")
            return scheme, rest  # type: ignore[return-value]
        raise ValueError(
            f"unknown source kind {scheme!r}; use synthetic:soccer, camera:N, file:PATH, "
            "images:GLOB or a path"
        )
    if s == "synthetic":
        return "synthetic", "soccer"
    if any(c in s for c in "*?["):
        return "images", s
    return "file", s


def _relative_hint(info: ValidationInfo) -> str:
    ctx = info.context if isinstance(info.context, dict) else {}
    if ctx.get("base_dir") is not None:
        return f" (a relative path resolves against the graph file's directory, {ctx['base_dir']})"
    return f" (a relative path resolves against the current directory, {os.getcwd()})"


class CaptureParams(BaseModel):
    """Params of the ``capture`` node (see the module documentation)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    source: str = Field(
        "synthetic:soccer",
        description="synthetic:soccer | camera:N | camera:/dev/videoN | file:PATH | images:GLOB",
    )
    fps: float = Field(
        20.0, ge=0.001, le=1000, description="frame rate (realtime pacing; requested from cameras)"
    )
    size: tuple[int, int] | None = Field(
        None, description="output [width, height]; resized once at capture"
    )
    pixel_format: OutputFormat = "BGR"
    input_format: InputFormat | None = Field(
        None, description="what the source delivers (raw cameras)"
    )
    pacing: Literal["realtime", "fast"] = "realtime"
    on_eof: Literal["stop", "loop", "exit"] = "stop"
    seed: int = Field(0, ge=0)
    clutter: float = Field(
        0.3, ge=0.0, le=1.0, description="synthetic scene: noise, lighting, distractors"
    )
    flash_on: Ms = Field(100.0, gt=0, description="synthetic:flash: the LED is on this long")
    flash_period: Ms = Field(1000.0, gt=0, description="synthetic:flash: every this long")
    grab_timeout: Ms | None = Field(None, description="ms; default two frame periods")
    open_timeout: Ms = 5000.0
    backoff: Ms = 200.0
    max_backoff: Ms = 5000.0
    max_retries: int | None = Field(
        None, ge=0, description="consecutive failed reopens before giving up"
    )
    allow_large: bool = Field(
        False,
        description=f"accept a frame above {MAX_FRAME_BYTES // 2**20} MiB (its pool takes "
        f"{POOL_SLOTS_AT_START} to {POOL_SLOTS_MAX} times that in shared memory)",
    )

    @field_validator("source")
    @classmethod
    def _check_source(cls, v: str, info: ValidationInfo) -> str:
        """A ``file:`` that is not there is a graph error, located at this param; file and
        image paths become absolute (relative ones resolve against the graph file's
        directory), so the graph runs the same from any working directory."""
        kind, target = parse_source(v)
        if kind not in ("file", "images") or not isinstance(target, str) or "://" in target:
            return v
        path = resolve_path(target, info)
        if kind == "file":
            if not os.path.exists(path):
                where = "" if os.path.isabs(os.path.expanduser(target)) else _relative_hint(info)
                raise ValueError(f"video file not found: {path}{where}")
            if os.path.isdir(path):
                raise ValueError(
                    f"{path} is a directory, not a video file (for images use images:GLOB)"
                )
            try:  # a device or a FIFO would block or never end: only regular files
                check_regular_file(path)
            except OSError as e:
                raise ValueError(f"video file: {e.strerror or e}") from None
        return f"{kind}:{path}"

    @field_validator("size")
    @classmethod
    def _check_size(cls, v: tuple[int, int] | None) -> tuple[int, int] | None:
        if v is not None and (v[0] < 2 or v[1] < 2 or v[0] > 16384 or v[1] > 16384):
            raise ValueError(f"size must be [width, height] in 2..16384, got {list(v)}")
        return v

    @field_validator("input_format")
    @classmethod
    def _check_input_format(cls, fmt: str | None, info: ValidationInfo) -> str | None:
        source = info.data.get("source")
        if source is None:  # the source itself is invalid: reported there
            return fmt
        kind, _ = parse_source(source)
        if fmt is not None:
            if kind == "file" and fmt not in ("BGR", "RGB"):
                raise ValueError(
                    f"{fmt} needs a raw source (camera: or synthetic:); "
                    "decoded video is BGR (or RGB for channel-swapped content)"
                )
            if kind == "images" and fmt not in ("BGR", "RGB", "GRAY"):
                raise ValueError(f"{fmt} needs a raw source (camera: or synthetic:)")
        if kind == "synthetic":
            w, h = info.data.get("size") or (320, 240)
            if fmt in _PACKED and w % 2:
                raise ValueError(f"{fmt} needs an even width, got size {w}x{h}")
            if fmt in _PLANAR and (w % 2 or h % 2):
                raise ValueError(f"{fmt} needs an even width and height, got size {w}x{h}")
        return fmt

    @field_validator("max_backoff")
    @classmethod
    def _check_backoff(cls, v: float, info: ValidationInfo) -> float:
        if v < info.data.get("backoff", 0.0):
            raise ValueError("max_backoff must be >= backoff")
        return v

    @model_validator(mode="after")
    def _check_scene_size(self) -> CaptureParams:
        w, h = self.size or (320, 240)
        if self.kind()[0] == "synthetic" and (w < 32 or h < 24):
            raise ValueError(f"the synthetic scene needs a size of at least 32x24, got {w}x{h}")
        if (
            self.size is not None
            and frame_bytes(self.size, self.pixel_format) > MAX_FRAME_BYTES
            and not self.allow_large
        ):
            raise ValueError(
                f"{pool_memory_text(self.size, self.pixel_format)}; above the "
                f"{MAX_FRAME_BYTES // 2**20} MiB limit of one frame: set allow_large: true "
                "to accept it"
            )
        return self

    def kind(self) -> tuple[SourceKind, str | int]:
        return parse_source(self.source)

    @property
    def period_s(self) -> float:
        return 1.0 / self.fps

    @property
    def grab_timeout_s(self) -> float:
        return (self.grab_timeout / 1000) if self.grab_timeout is not None else 2.0 / self.fps


# ---------------------------------------------------------------------- pixel formats


def raw_size(raw: np.ndarray, fmt: str, dims: tuple[int, int] | None = None) -> tuple[int, int]:
    """(width, height) of the image a raw buffer in ``fmt`` holds."""
    if fmt in _PACKED:
        if raw.ndim == 3 and raw.shape[2] == 2:
            return raw.shape[1], raw.shape[0]
    elif fmt in _PLANAR:
        if raw.ndim == 2 and raw.shape[0] % 3 == 0 and dims is None:
            return raw.shape[1], raw.shape[0] * 2 // 3
    else:
        return raw.shape[1], raw.shape[0]
    if dims is None:
        raise SourceError(
            f"a flat {fmt} buffer of {raw.size} bytes needs the device's width and height"
        )
    return dims


def _shape_raw(raw: np.ndarray, fmt: str, w: int, h: int) -> np.ndarray:
    """View a raw buffer with the shape cv2.cvtColor expects for ``fmt``."""
    if fmt in _PACKED:
        shape: tuple[int, ...] = (h, w, 2)
    elif fmt in _PLANAR:
        shape = (h * 3 // 2, w)
    elif fmt == "GRAY":
        shape = (h, w) if raw.ndim != 3 else (h, w, 1)
    else:
        shape = (h, w, 3)
    if raw.dtype != np.uint8:
        raise SourceError(f"expected 8-bit {fmt} data, got {raw.dtype}")
    if raw.size != math.prod(shape):
        raise SourceError(f"a raw frame of {raw.size} bytes does not fit {fmt} at {w}x{h}")
    return raw.reshape(shape)


def output_shape(width: int, height: int, fmt: str) -> tuple[int, ...]:
    return (height, width) if fmt == "GRAY" else (height, width, 3)


def convert_into(
    raw: np.ndarray,
    input_format: str,
    output_format: str,
    out: np.ndarray,
    dims: tuple[int, int] | None = None,
) -> np.ndarray:
    """Convert ``raw`` (in ``input_format``) to ``output_format`` and resize it into ``out``.

    One cvtColor pass, then one resize only if ``out`` has another size; written in place
    when no resize is needed. ``dims`` is the (width, height) of a flat raw device buffer.
    """
    w, h = raw_size(raw, input_format, dims)
    src = _shape_raw(raw, input_format, w, h)
    oh, ow = out.shape[:2]
    if input_format == "GRAY" and src.ndim == 3:
        src = src[..., 0]
    code = _CVT.get((input_format, output_format))
    luma = output_format == "GRAY" and input_format in (*_PACKED, *_PLANAR)
    if (ow, oh) == (w, h):
        if code is None:
            np.copyto(out, src.reshape(out.shape))
        else:
            cv2.cvtColor(src, code, dst=out)
    else:
        converted = src if code is None else cv2.cvtColor(src, code)
        interp = cv2.INTER_AREA if ow * oh < w * h else cv2.INTER_LINEAR
        cv2.resize(converted, (ow, oh), dst=out, interpolation=interp)
    if luma:
        cv2.LUT(out, _VIDEO_TO_FULL, dst=out)
    return out


def encode_raw(bgr: np.ndarray, fmt: str) -> np.ndarray:
    """Encode a BGR image to a raw format, as a camera would deliver it (BT.601, video range)."""
    if fmt == "BGR":
        return bgr
    if fmt == "RGB":
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if fmt == "GRAY":
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if fmt == "YUYV":
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUYV)
    if fmt == "UYVY":
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_UYVY)
    i420 = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)
    if fmt == "I420":
        return i420
    if fmt == "NV12":
        h, w = bgr.shape[:2]
        n = h * w // 4
        chroma = i420[h:].reshape(-1)
        nv12 = i420.copy()
        inter = nv12[h:].reshape(-1)
        inter[0::2] = chroma[:n]
        inter[1::2] = chroma[n:]
        return nv12
    raise ValueError(f"unsupported pixel format {fmt!r}; supported: {', '.join(INPUT_FORMATS)}")


# ---------------------------------------------------------------------- devices (reader thread)


class _Device:
    """What a reader thread reads: ``read()`` returns an array, or None at the end.

    ``position`` is the index in the stream of the next frame ``read()`` returns, so that a
    reopened file or image sequence resumes where it stalled instead of starting over.
    """

    dims: tuple[int, int] | None = None
    rewindable = False
    position = 0

    def read(self) -> np.ndarray | None:
        raise NotImplementedError

    def release(self) -> None:
        pass


class _VideoDevice(_Device):
    def __init__(self, kind: str, target: str | int, params: CaptureParams, start: int = 0) -> None:
        self.kind = kind
        self.target = target
        self.frames = 0
        self.rewindable = kind == "file"
        if kind == "file":
            assert isinstance(target, str)
            if "://" not in target and not os.path.exists(target):
                raise SourceError(f"video file not found: {target}")
            if "://" not in target and os.path.isdir(target):
                raise SourceError(
                    f"{target} is a directory, not a video file (for images use images:GLOB)"
                )
            cap = cv2.VideoCapture(target)
            if not cap.isOpened():
                cap.release()
                raise SourceError(
                    f"cannot open {target} as a video "
                    "(corrupt file, or a format OpenCV/FFmpeg cannot read)"
                )
        else:
            if isinstance(target, str) and not os.path.exists(target):
                raise SourceError(f"camera device {target} does not exist")
            cap = cv2.VideoCapture(target)
            if not cap.isOpened():
                cap.release()
                raise SourceError(
                    f"cannot open camera {target} (no such device, in use, or no permission)"
                )
            fmt = params.input_format
            if fmt in _FOURCC:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*_FOURCC[fmt]))
            if params.size is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, params.size[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, params.size[1])
            cap.set(cv2.CAP_PROP_FPS, params.fps)
            if fmt in _FOURCC:
                cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
            self.dims = (
                int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            )
        self.cap = cap
        if start > 0 and kind == "file":  # resume after a stall (seeking is best effort)
            cap.set(cv2.CAP_PROP_POS_FRAMES, start)
            self.frames = self.position = start

    def read(self) -> np.ndarray | None:
        ok, img = self.cap.read()
        if not ok or img is None:
            if self.kind == "camera":
                raise SourceError(
                    f"camera {self.target}: read failed (device unplugged or stalled?)"
                )
            if self.frames == 0:
                raise SourceError(
                    f"{self.target} opened but no frame could be decoded (corrupt or empty video)"
                )
            return None
        self.frames += 1
        self.position += 1
        return img

    def release(self) -> None:
        self.cap.release()


class _ImageDevice(_Device):
    rewindable = True

    def __init__(
        self, pattern: str, grey: bool, alert: Callable[[str, str], None], start: int = 0
    ) -> None:
        self.files = sorted(glob.glob(os.path.expanduser(pattern)))
        if not self.files:
            raise SourceError(f"no image files match {pattern!r}")
        self.flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
        self.alert = alert
        self.index = min(start, len(self.files))
        self.good = self.index  # resuming: the files before were read already

    def read(self) -> np.ndarray | None:
        while self.index < len(self.files):
            path = self.files[self.index]
            self.index += 1
            img = cv2.imread(path, self.flag)
            if img is None:
                self.alert("source-error", f"cannot read image {path} (skipped)")
                continue
            self.good += 1
            self.position = self.index
            return img
        if self.good == 0:
            raise SourceError(
                f"none of the {len(self.files)} files matching the pattern is a readable image"
            )
        return None


_FRAME, _EOF, _ERROR, _ALERT, _LOG = "frame", "eof", "error", "alert", "log"

_STDERR_LOCK = threading.Lock()  # fd 2 is the process's: one redirection at a time
_REDIRECT_MAX = 3.0  # seconds: fd 2 is given back then even if the open has not returned
# What differs between two lines saying the same: OpenCV's "[ WARN:3@0.618]" prefix
# (thread and time) and FFmpeg's "@ 0x55d0..." context addresses.
_NOISE = re.compile(r"^\[\s*\w+:\d+@[\d.]+\]\s*|0x[0-9a-fA-F]+")


class _Redirect:
    """fd 2 pointed at a temporary file; given back exactly once: when the open returns, or
    after ``_REDIRECT_MAX`` by a timer if the driver hangs in it (a hung open must not keep
    the process's stderr, nor the other sources' opens, forever)."""

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._restored = False
        self.tmp = tempfile.TemporaryFile()  # noqa: SIM115 (closed in close())
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        self.saved = os.dup(2)
        os.dup2(self.tmp.fileno(), 2)
        self.timer = threading.Timer(_REDIRECT_MAX, self.restore)
        self.timer.daemon = True
        self.timer.start()

    def restore(self) -> None:
        with self._mutex:
            if self._restored:
                return
            self._restored = True
            os.dup2(self.saved, 2)
            os.close(self.saved)
            _STDERR_LOCK.release()

    def close(self) -> list[str]:
        self.timer.cancel()
        self.restore()
        self.tmp.seek(0)
        text = self.tmp.read().decode(errors="replace")
        self.tmp.close()
        return [line.rstrip() for line in text.splitlines() if line.strip()]


@contextlib.contextmanager
def _native_stderr(lines: list[str]) -> Iterator[None]:
    """Collect what C libraries (OpenCV, V4L2, FFmpeg) print on file descriptor 2 meanwhile.

    OpenCV and FFmpeg write their warnings straight to fd 2, past Python's logging, so they
    would land raw between the lines of the status table. Around a device open (where they
    say why it failed) fd 2 is pointed at a temporary file, and the lines go to the node's
    log instead. Whatever another thread writes to stderr in that window (milliseconds; at
    most ``_REDIRECT_MAX``) is logged there too, not lost. Should another source be opening
    for longer than that, this open is not redirected rather than waited for.
    """
    redirect: _Redirect | None = None
    if _STDERR_LOCK.acquire(timeout=_REDIRECT_MAX):
        try:
            redirect = _Redirect()
        except OSError:
            _STDERR_LOCK.release()
    try:
        yield
    finally:
        if redirect is not None:
            lines.extend(redirect.close())


class _Reader:
    """A daemon thread that owns one device: opens, reads ahead and releases it.

    Items go to a deque that the event loop takes from; ``latest`` keeps only the newest
    (cameras: an old frame is worthless), otherwise the thread reads at most ``depth`` frames
    ahead (files: decoding is smoothed, nothing is skipped). The thread alone touches the
    device, so abandoning a reader stuck in a driver call is safe: it releases the device
    whenever the call returns.
    """

    def __init__(
        self,
        name: str,
        opener: Callable[[Callable[[str, str], None], int], _Device],
        loop: asyncio.AbstractEventLoop,
        *,
        latest: bool,
        depth: int = 2,
        rewind: bool = False,
        start: int = 0,
    ) -> None:
        self._opener = opener
        self._start = start
        self._loop = loop
        self._latest = latest
        self._depth = depth
        self._rewind = rewind
        self._items: deque[tuple[str, Any]] = deque()
        self._cond = threading.Condition()
        self._waiter: asyncio.Future[None] | None = None
        self._stop = False
        self.delivered = 0
        self.thread = threading.Thread(target=self._run, name=f"flowrt-capture-{name}", daemon=True)
        self.thread.start()

    # -- thread side

    def _push(self, kind: str, value: Any) -> None:
        with self._cond:
            if self._stop:
                return
            if kind == _FRAME and self._latest:
                for i, queued in enumerate(self._items):
                    if queued[0] == _FRAME:  # keep only the newest frame
                        del self._items[i]
                        break
            self._items.append((kind, value))
            waiter = self._waiter
        if waiter is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nobody is waiting
                self._loop.call_soon_threadsafe(_wake, waiter)

    def _alert(self, alert: str, detail: str) -> None:
        self._push(_ALERT, (alert, detail))

    def _room(self) -> bool:
        with self._cond:
            while not self._stop and not self._latest:
                if sum(1 for i in self._items if i[0] == _FRAME) < self._depth:
                    break
                self._cond.wait()
            return not self._stop

    def _open(self, start: int) -> _Device:
        lines: list[str] = []
        try:
            with _native_stderr(lines):
                return self._opener(self._alert, start)
        finally:
            if lines:
                self._push(_LOG, lines)

    def _run(self) -> None:
        dev: _Device | None = None
        try:
            dev = self._open(self._start)
            while self._room():
                img = dev.read()
                if img is None:
                    if not (self._rewind and dev.rewindable):
                        self._push(_EOF, None)
                        return
                    dev.release()
                    dev = None
                    dev = self._open(0)
                    continue
                self._push(_FRAME, (img, dev.dims, dev.position))
        except SourceError as e:
            self._push(_ERROR, str(e))
        except Exception as e:  # a driver or decoder error: report it, never kill silently
            self._push(_ERROR, f"{type(e).__name__}: {e}")
        finally:
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.release()

    # -- loop side

    def take(self) -> tuple[str, Any] | None:
        with self._cond:
            if not self._items:
                return None
            item = self._items.popleft()
            self._cond.notify()
        if item[0] == _FRAME:
            self.delivered += 1
        return item

    async def get(self, wait: float) -> tuple[str, Any] | None:
        """The next item, or None after ``wait`` seconds without one."""
        item = self.take()
        if item is not None or wait <= 0:
            return item
        with self._cond:
            if not self._items:
                self._waiter = self._loop.create_future()
            waiter = self._waiter
        if waiter is not None:
            try:
                await asyncio.wait_for(waiter, wait)
            except TimeoutError:
                pass
            finally:
                with self._cond:
                    self._waiter = None
        return self.take()

    def stop(self) -> None:
        """Ask the thread to end; it releases the device as soon as its current call returns."""
        with self._cond:
            self._stop = True
            self._items.clear()
            self._cond.notify_all()


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


# ---------------------------------------------------------------------- the node


class Capture(Node):
    """A frame source: camera, video file, image sequence or the synthetic soccer scene.

    Outputs ``frame`` (each publication is a tick of this node's frame clock) and ``truth``
    (the synthetic scene's :class:`~flowrt.nodes.scene.SceneTruth` of that frame; nothing for
    real sources). Runs inline: it needs the runtime's frame pool and event stream.
    """

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
        self._t0 = self.ctx.now()
        self._scene: Any = None
        self._reader: _Reader | None = None
        self._abandoned: list[_Reader] = []
        self._opened_at = 0.0
        self._retry_at = 0.0
        self._backoff = p.backoff / 1000
        self._failures = 0  # consecutive failed (re)opens
        self.reopens = 0  # failed opens and reads in all: each one is followed by a reopen
        self._last_error = ""
        self._native_seen: set[str] = set()
        self._troubled = False  # a problem was reported and frames have not flowed since
        self._ended = False  # end of stream with on_eof: stop, or gave up
        self._last_problem = ("", "")
        self._position = 0  # where a reopened file or image sequence resumes
        self._last_frame_at = 0.0
        self._stalled = False  # a slow file/image read was reported, not yet a failure
        if self._kind == "synthetic" and p.kind()[1] == "flash":
            from .calibration import FlashScene

            w, h = p.size or (320, 240)
            self._scene = FlashScene(w, h, p.flash_on / 1000, p.flash_period / 1000)
        elif self._kind == "synthetic":
            from .scene import SoccerScene

            w, h = p.size or (320, 240)
            self._scene = SoccerScene(w, h, seed=p.seed, clutter=p.clutter, fps=p.fps)

    async def teardown(self) -> None:
        if self._scene is None and self._seq == 0:  # the run's verdict: this source failed
            p: CaptureParams = self.params
            why = (
                f" ({self.reopens} attempt{'' if self.reopens == 1 else 's'} failed; "
                f"last error: {self._last_error})"
                if self.reopens
                else ""
            )
            with contextlib.suppress(RuntimeError):
                self.ctx.set_error(f"{p.source}: never delivered a frame{why}")
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
        stuck = [r.thread.name for r in readers if r.thread.is_alive()]
        if stuck:
            self.ctx.log.warning(
                "%s: %d reader thread(s) still blocked in the device at teardown (left behind)",
                self.ctx.name,
                len(stuck),
            )

    async def process(self) -> dict[str, Any] | None:
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
        return {"frame": frame, "truth": truth}

    def _publishable(self, raw: np.ndarray, fmt_in: str, dims: tuple[int, int] | None) -> Frame:
        p: CaptureParams = self.params
        w, h = p.size or raw_size(raw, fmt_in, dims)
        frame = self.ctx.new_frame(output_shape(w, h, p.pixel_format), np.uint8, p.pixel_format)
        convert_into(raw, fmt_in, p.pixel_format, frame.data, dims)
        frame.seq = self._seq
        frame.timestamp = self.ctx.now()
        frame.source = self.ctx.name
        self._seq += 1
        return frame

    # -- real sources

    def _alert(self, alert: str, detail: str, severity: str = "warning", note: str = "") -> None:
        """Emit a HealthAlert; log it too, unless it repeats the previous problem."""
        t = self.ctx.elapsed()
        with contextlib.suppress(RuntimeError):  # emit() exists only on the event loop
            self.ctx.emit(
                HealthAlert(t, self.ctx.name, alert=alert, detail=detail + note, severity=severity)
            )
        if (alert, detail) != self._last_problem or severity == "info":
            log = self.ctx.log.info if severity == "info" else self.ctx.log.warning
            log("%s: %s: %s%s", self.ctx.name, alert, detail, note)
        self._last_problem = (alert, detail)

    def _native_log(self, lines: list[str]) -> None:
        """OpenCV's and FFmpeg's own messages: in this node's log, each kind once at INFO."""
        for line in lines:
            key = _NOISE.sub("", line)
            first = key not in self._native_seen
            if first and len(self._native_seen) < 256:
                self._native_seen.add(key)
            log = self.ctx.log.info if first else self.ctx.log.debug
            log("%s: opencv: %s", self.ctx.name, line)

    def _open(self) -> _Reader:
        p: CaptureParams = self.params
        kind, target = self._kind, self._target

        def opener(alert: Callable[[str, str], None], start: int) -> _Device:
            if kind == "images":
                assert isinstance(target, str)
                return _ImageDevice(target, p.input_format == "GRAY", alert, start)
            return _VideoDevice(kind, target, p, start)

        self._opened_at = self._last_frame_at = self.ctx.now()
        self._stalled = False
        return _Reader(
            self.ctx.name,
            opener,
            asyncio.get_running_loop(),
            latest=kind == "camera",
            rewind=p.on_eof == "loop",
            start=self._position,
        )

    def _drop_reader(self) -> None:
        if self._reader is not None:
            self._reader.stop()
            self._abandoned.append(self._reader)
            self._reader = None
        self._abandoned = [r for r in self._abandoned if r.thread.is_alive()]

    def _failed(self, alert: str, detail: str) -> None:
        """Report, abandon the reader and schedule a reopen after the backoff (or give up)."""
        p: CaptureParams = self.params
        self._drop_reader()
        self._troubled = True
        self._failures += 1
        self.reopens += 1
        self._last_error = detail
        if p.max_retries is not None and self._failures > p.max_retries:
            self._alert(alert, detail, "error")
            self._alert(
                "source-gave-up", f"{self._failures} consecutive failures; no more retries", "error"
            )
            self._ended = True
        else:
            self._alert(
                alert,
                detail,
                "error",
                f"; reopening in {self._backoff * 1000:.0f} ms (attempt {self.reopens + 1})",
            )
        with contextlib.suppress(RuntimeError):  # red in the table, with the reason
            self.ctx.set_error(detail)
        if self._ended:  # retries exhausted: the node is failed for good (supervision)
            raise FatalError(
                f"{p.source}: {self._failures} consecutive failures, max_retries "
                f"{p.max_retries} exhausted; last error: {detail}"
            )
        self._retry_at = self.ctx.now() + self._backoff
        self._backoff = min(self._backoff * 2, max(p.max_backoff, p.backoff) / 1000)

    async def _idle(self, until: float | None = None) -> None:
        """Nothing to publish now: free-running nodes wait a little instead of spinning."""
        if self._loop_mode:
            wait = 0.1 if until is None else min(0.1, max(0.0, until - self.ctx.now()))
            await asyncio.sleep(max(wait, 0.001))

    def _timed_out(self, first: bool, timeout: float) -> None:
        """No frame within the grab timeout.

        A camera that stalls is reopened at once. A file or image sequence that is slow
        (a huge frame, a network share) is reported and given until ``open_timeout`` before
        it is reopened, resuming at the frame it stalled on rather than starting over.
        """
        p: CaptureParams = self.params
        now = self.ctx.now()
        if first:
            if now - self._opened_at < p.open_timeout / 1000:
                return  # still opening: no frame this time, not yet a failure
            what = f"no first frame within {p.open_timeout:g} ms of opening {p.source}"
            self._failed("grab-timeout", what)
            return
        if self._kind == "camera":
            self._failed("grab-timeout", f"no frame from {p.source} within {timeout * 1000:g} ms")
            return
        stalled = now - self._last_frame_at
        if stalled >= p.open_timeout / 1000:
            what = (
                f"no frame from {p.source} for {stalled * 1000:.0f} ms; "
                f"resuming at frame {self._position}"
            )
            self._failed("grab-timeout", what)
        elif not self._stalled:
            self._stalled = self._troubled = True
            self._alert(
                "grab-timeout", f"no frame from {p.source} within {timeout * 1000:g} ms; waiting"
            )

    async def _grab(self) -> dict[str, Any] | None:
        p: CaptureParams = self.params
        if self._ended:
            await self._idle()
            return None
        if self._reader is None:
            if self.ctx.now() < self._retry_at:
                await self._idle(self._retry_at)
                return None
            self._reader = self._open()
        reader = self._reader
        first = reader.delivered == 0
        timeout = p.grab_timeout_s
        while True:
            item = await reader.get(timeout)
            if reader is not self._reader:  # dropped meanwhile (teardown)
                return None
            if item is None:
                self._timed_out(first, timeout)
                return None
            kind, value = item
            if kind == _ALERT:
                self._alert(*value)
                continue
            if kind == _LOG:
                self._native_log(value)
                continue
            if kind == _ERROR:
                self._failed("source-error", value)
                return None
            if kind == _EOF:
                self._drop_reader()
                self._ended = True
                self._alert(
                    "end-of-stream", f"{p.source}: end of stream after {self._seq} frames", "info"
                )
                if p.on_eof == "exit":  # a recording played through the graph: then stop
                    self.ctx.request_stop()
                return None
            break
        img, dims, self._position = value
        self._last_frame_at = self.ctx.now()
        self._stalled = False
        try:
            frame = self._publishable(img, p.input_format or "BGR", dims)
        except SourceError as e:
            self._failed("source-error", str(e))
            return None
        if self._troubled or frame.seq == 0:  # (the first frame also clears an error left
            # by a previous instance: a swap or restart after "never delivered a frame")
            with contextlib.suppress(RuntimeError):
                self.ctx.clear_error()
        if self._troubled:
            self._troubled = False
            self._alert("source-recovered", f"{p.source}: frames flowing again", "info")
        self._failures = 0
        self._backoff = p.backoff / 1000
        return {"frame": frame}
