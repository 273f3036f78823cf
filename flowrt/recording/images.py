"""Image messages of other tools as pixels: ROS 1/ROS 2 ``sensor_msgs`` and Foxglove's.

A replayed image becomes a :class:`~flowrt.Frame` in the runtime's pool, so a ``tracker``
cannot tell a rosbag2 camera from a live one. The message has been made plain first
(:mod:`.plain`), so one function serves every encoding family (CDR, ROS 1, protobuf, JSON).

Pixel encodings (``sensor_msgs/msg/Image.encoding``, ``foxglove.RawImage.encoding``):

=====================================  ==========================================
``bgr8``, ``8UC3``                      BGR uint8
``rgb8``                                RGB uint8
``bgra8`` / ``rgba8``                   BGR / RGB uint8, alpha dropped
``mono8``, ``8UC1``                     GRAY uint8
``mono16``, ``16UC1``                   GRAY uint16 (``is_bigendian`` honoured)
``bayer_rggb8`` ``bggr8`` ``gbrg8``     demosaiced to BGR uint8 (OpenCV, with
``grbg8``                               cv_bridge's pattern names)
``uyvy``/``yuv422``, ``yuyv``/          BGR uint8
``yuv422_yuy2``
=====================================  ==========================================

A compressed image (``sensor_msgs/msg/CompressedImage``, ``foxglove.CompressedImage``) is
decoded by OpenCV: JPEG/PNG colour as BGR, grey as GRAY.

The frame's time is the message's own stamp (``header.stamp``, Foxglove's ``timestamp``) when
it has one, else the log time (:func:`stamp_ns`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["IMAGE_SCHEMAS", "is_image_schema", "pixels_of", "stamp_ns"]

RAW_SCHEMAS = {
    "sensor_msgs/msg/Image",
    "sensor_msgs/Image",
    "foxglove_msgs/msg/RawImage",
    "foxglove_msgs/RawImage",
    "foxglove.RawImage",
}
COMPRESSED_SCHEMAS = {
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/CompressedImage",
    "foxglove_msgs/msg/CompressedImage",
    "foxglove_msgs/CompressedImage",
    "foxglove.CompressedImage",
}
IMAGE_SCHEMAS = RAW_SCHEMAS | COMPRESSED_SCHEMAS

# cv_bridge's mapping: OpenCV names a Bayer pattern by its second row's first two pixels.
_BAYER = {
    "bayer_rggb8": "COLOR_BayerBG2BGR",
    "bayer_bggr8": "COLOR_BayerRG2BGR",
    "bayer_gbrg8": "COLOR_BayerGR2BGR",
    "bayer_grbg8": "COLOR_BayerGB2BGR",
}
_YUV = {
    "uyvy": "COLOR_YUV2BGR_UYVY",
    "yuv422": "COLOR_YUV2BGR_UYVY",
    "yuyv": "COLOR_YUV2BGR_YUYV",
    "yuv422_yuy2": "COLOR_YUV2BGR_YUYV",
}
# encoding -> (channels, dtype, flowrt pixel format, channels kept)
_DIRECT: dict[str, tuple[int, Any, str, int]] = {
    "bgr8": (3, np.uint8, "BGR", 3),
    "8UC3": (3, np.uint8, "BGR", 3),
    "rgb8": (3, np.uint8, "RGB", 3),
    "bgra8": (4, np.uint8, "BGR", 3),
    "8UC4": (4, np.uint8, "BGR", 3),
    "rgba8": (4, np.uint8, "RGB", 3),
    "mono8": (1, np.uint8, "GRAY", 1),
    "8UC1": (1, np.uint8, "GRAY", 1),
    "mono16": (1, np.uint16, "GRAY", 1),
    "16UC1": (1, np.uint16, "GRAY", 1),
}


def is_image_schema(name: str) -> bool:
    """True for a schema whose messages replay as frames."""
    return name in IMAGE_SCHEMAS


def pixels_of(schema_name: str, msg: dict[str, Any]) -> tuple[np.ndarray, str]:
    """(pixels, flowrt pixel format) of a plain image message; ValueError when it cannot be."""
    import cv2

    data = msg.get("data") or b""
    if isinstance(data, str):  # a JSON-encoded Foxglove image: base64 pixels
        import base64

        data = base64.b64decode(data)
    buf = np.frombuffer(bytes(data) if not isinstance(data, bytes) else data, np.uint8)
    if schema_name in COMPRESSED_SCHEMAS:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"cannot decode a {msg.get('format', '?')!r} compressed image")
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return img, "GRAY" if img.ndim == 2 else "BGR"
    enc = str(msg.get("encoding", ""))
    h, w = int(msg.get("height", 0)), int(msg.get("width", 0))
    step = int(msg.get("step", 0))
    if h <= 0 or w <= 0:
        raise ValueError(f"an image of {w}x{h} pixels")
    if enc in _BAYER or enc in _YUV:
        per_pixel = 1 if enc in _BAYER else 2
        rows = _rows(buf, h, step or w * per_pixel, w * per_pixel)
        src = rows if enc in _BAYER else rows.reshape(h, w, 2)
        code = getattr(cv2, _BAYER.get(enc) or _YUV[enc])
        return cv2.cvtColor(np.ascontiguousarray(src), code), "BGR"
    spec = _DIRECT.get(enc)
    if spec is None:
        raise ValueError(f"unsupported image encoding {enc!r}")
    channels, dtype, fmt, keep = spec
    itemsize = np.dtype(dtype).itemsize
    rows = _rows(buf, h, step or w * channels * itemsize, w * channels * itemsize)
    px = rows.view(np.dtype(dtype).newbyteorder(">" if msg.get("is_bigendian") else "<"))
    px = px.astype(dtype, copy=False)
    px = px.reshape(h, w) if channels == 1 else px.reshape(h, w, channels)[:, :, :keep]
    return px, fmt


def _rows(buf: np.ndarray, h: int, step: int, row_bytes: int) -> np.ndarray:
    """The ``h`` rows of ``row_bytes`` each out of a buffer of ``step``-byte rows."""
    if step < row_bytes or buf.size < step * (h - 1) + row_bytes:
        raise ValueError(
            f"an image of {h} rows of {row_bytes} bytes (step {step}) in {buf.size} bytes"
        )
    if buf.size < step * h:  # the last row's padding left out: pad it back
        buf = np.concatenate([buf, np.zeros(step * h - buf.size, np.uint8)])
    return buf[: step * h].reshape(h, step)[:, :row_bytes]


def stamp_ns(msg: dict[str, Any]) -> int | None:
    """The message's own time, ns (ROS 2 ``sec``/``nanosec``, ROS 1 ``secs``/``nsecs``,
    protobuf ``seconds``/``nanos``), or None when it has none or it is zero."""
    header = msg.get("header")
    t = header.get("stamp") if isinstance(header, dict) else msg.get("timestamp")
    if not isinstance(t, dict):
        return None
    sec = t.get("sec", t.get("secs", t.get("seconds")))
    nsec = t.get("nanosec", t.get("nsecs", t.get("nsec", t.get("nanos", 0))))
    if not isinstance(sec, int) or not isinstance(nsec, int):
        return None
    ns = sec * 1_000_000_000 + nsec
    return ns if ns > 0 else None
