"""Render graphs/sample.avi: the clip graphs/video.yaml plays (made here, free to share).

A warm table lamp (the tracker's "candle": amber, a tall cylinder) moves across a dim room
with a window, a table and some texture, at 25 fps for 8 s, 320x240, Motion-JPEG in AVI
(OpenCV writes and reads it without extra codecs). Run ``python graphs/make_sample_video.py``
to render it again; the result is byte-for-byte the same (no randomness).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np

W, H, FPS, SECONDS = 320, 240, 25, 8


def frame(k: int) -> np.ndarray:
    t = k / FPS
    img = np.zeros((H, W, 3), np.uint8)
    img[:] = (38, 34, 30)  # dim wall (BGR)
    yy, xx = np.mgrid[0:H, 0:W]
    img[..., 1] += ((xx // 16 + yy // 16) % 2 * 6).astype(np.uint8)  # wallpaper texture
    cv2.rectangle(img, (210, 30), (300, 110), (120, 110, 95), -1)  # a window
    cv2.line(img, (255, 30), (255, 110), (60, 55, 50), 3)
    cv2.rectangle(img, (0, 170), (W, H), (30, 45, 70), -1)  # the table
    cx = int(W / 2 + 110 * math.sin(2 * math.pi * t / SECONDS))
    cy = 140 + int(8 * math.sin(2 * math.pi * t * 0.7))
    glow = 0.85 + 0.15 * math.sin(2 * math.pi * t * 1.3)  # the flame flickers
    cv2.ellipse(img, (cx, cy + 30), (26, 6), 0, 0, 360, (20, 60, 110), -1)  # its light
    colour = (int(40 * glow), int(170 * glow), int(250 * glow))  # amber (BGR)
    cv2.rectangle(img, (cx - 11, cy - 18), (cx + 11, cy + 24), colour, -1)  # the lamp
    cv2.circle(img, (cx, cy - 24), 5, (200, 230, 255), -1)  # the flame
    return img


def main(path: Path) -> None:
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    if not out.isOpened():
        sys.exit(f"cannot write {path}")
    for k in range(FPS * SECONDS):
        out.write(frame(k))
    out.release()


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).with_name("sample.avi"))
