"""Pixel formats of the capture node: what a source delivers and what the node publishes.

A raw camera delivers packed 4:2:2 (YUYV, UYVY) or planar 4:2:0 (I420, NV12) buffers, or
BGR/RGB/GRAY; the node publishes BGR, RGB or GRAY. Each (input, output) pair is one
``cv2.cvtColor`` pass, followed by one resize only if the published size differs, written
straight into the published frame (a shared-memory slot when the runtime provides a pool).
:func:`encode_raw` goes the other way, so the synthetic scene can simulate a raw camera.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np

from .sources import SourceError

__all__ = [
    "INPUT_FORMATS",
    "OUTPUT_FORMATS",
    "PACKED",
    "PLANAR",
    "InputFormat",
    "OutputFormat",
    "convert_into",
    "encode_raw",
    "output_shape",
    "raw_size",
]

OutputFormat = Literal["BGR", "RGB", "GRAY"]
InputFormat = Literal["BGR", "RGB", "GRAY", "YUYV", "UYVY", "I420", "NV12"]
OUTPUT_FORMATS: tuple[str, ...] = ("BGR", "RGB", "GRAY")
INPUT_FORMATS: tuple[str, ...] = ("BGR", "RGB", "GRAY", "YUYV", "UYVY", "I420", "NV12")
PACKED = ("YUYV", "UYVY")  # 4:2:2, two bytes per pixel: (h, w, 2)
PLANAR = ("I420", "NV12")  # 4:2:0, Y plane then chroma: (h * 3 / 2, w)

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
# cv2's YUV->GRAY takes the luma plane as it is: video range (16..235). Expanded to full range
# (0..255) so that GRAY from a YUV camera means the same as GRAY from a BGR one.
_VIDEO_TO_FULL = np.clip((np.arange(256) - 16) * 255.0 / 219.0 + 0.5, 0, 255).astype(np.uint8)


def raw_size(raw: np.ndarray, fmt: str, dims: tuple[int, int] | None = None) -> tuple[int, int]:
    """(width, height) of the image a raw buffer in ``fmt`` holds."""
    if fmt in PACKED:
        if raw.ndim == 3 and raw.shape[2] == 2:
            return raw.shape[1], raw.shape[0]
    elif fmt in PLANAR:
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
    if fmt in PACKED:
        shape: tuple[int, ...] = (h, w, 2)
    elif fmt in PLANAR:
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
    luma = output_format == "GRAY" and input_format in (*PACKED, *PLANAR)
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
