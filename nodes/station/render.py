"""Drawing detections on a frame and encoding both as JPEG: the live view's pictures.

Used by the view's server process (:mod:`flowrt.nodes.station.server`), which encodes what
the display node sends it, once per frame whatever the number of clients.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

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


def label_origin(x: int, y: int, tw: int, th: int, base: int, w: int, h: int) -> tuple[int, int]:
    """Where a label of ``tw`` x ``th`` (+``base``) goes for a box at (x, y): above the box,
    below it when there is no room, and always inside the ``w`` x ``h`` image (near the right
    or bottom edge it moves in; it is never cut off)."""
    ty = y - 3 if y - th - base - 3 >= 0 else y + th + 3
    x = min(max(0, x), max(0, w - tw - 2))
    ty = min(max(th + 1, ty), max(th + 1, h - base))
    return x, ty


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
        x, ty = label_origin(x, y, tw, th, base, w, h)
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
