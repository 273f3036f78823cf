"""The params of the capture node and their validation: a graph that loads is one that runs.

``source`` is parsed once (:func:`parse_source`) into its kind and target; a missing video
file is a graph error located at ``source`` and file paths become absolute. Durations are
read by the graph's own rule (:func:`flowrt.parse_duration_ms`: ``200ms``, ``1.5s``,
``500us`` or a number of milliseconds, with the same messages). A frame is bounded by the
shared memory its pool takes: a warning above :data:`WARN_FRAME_BYTES`, refused above
:data:`MAX_FRAME_BYTES` unless ``allow_large``.
"""

from __future__ import annotations

import glob
import os
import re
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic.functional_validators import BeforeValidator

from flowrt import parse_duration_ms, resolve_path
from flowrt.files import check_regular_file
from flowrt.graph.spec import MAX_DURATION_MS

from .formats import PACKED, PLANAR, InputFormat, OutputFormat

__all__ = [
    "MAX_FRAME_BYTES",
    "POOL_SLOTS_AT_START",
    "POOL_SLOTS_MAX",
    "SCENES",
    "WARN_FRAME_BYTES",
    "CaptureParams",
    "SourceKind",
    "frame_bytes",
    "parse_source",
    "pool_memory_text",
]

SCENES = ("soccer", "flash")

Ms = Annotated[float, BeforeValidator(parse_duration_ms), Field(gt=0, le=MAX_DURATION_MS)]
"""A positive duration of at most an hour, in milliseconds, read like the graph's durations."""

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
    decode_threads: int = Field(
        1,
        ge=0,
        le=64,
        description="a file's decoding threads (FFmpeg): 1 decodes on the reader thread, "
        "beside the graph; 0: FFmpeg's choice (one per CPU)",
    )
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
        if kind == "images" and not glob.glob(os.path.expanduser(path)):
            where = "" if os.path.isabs(os.path.expanduser(target)) else _relative_hint(info)
            raise ValueError(f"no image file matches {path}{where}")
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
            if fmt in PACKED and w % 2:
                raise ValueError(f"{fmt} needs an even width, got size {w}x{h}")
            if fmt in PLANAR and (w % 2 or h % 2):
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
