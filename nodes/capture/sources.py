"""The devices a capture node reads: cameras and video files (OpenCV), image sequences.

A device is opened, read and released by one reader thread only
(:mod:`flowrt.nodes.capture.reader`); nothing here touches the event loop. ``read()`` blocks
for as long as the driver or decoder does, returns None at the end of a file, and raises
:class:`SourceError` (a message meant for the user) when the device cannot be opened or read.
The synthetic scenes are not devices: the node renders them itself, on its own clock
(:mod:`flowrt.nodes.scene`, :mod:`flowrt.nodes.calibration`).
"""

from __future__ import annotations

import glob
import os
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

__all__ = ["FOURCC", "Device", "ImageDevice", "SourceError", "VideoDevice"]


class SourceError(Exception):
    """A source cannot be opened or read; the message is meant for the user."""


# V4L2 pixel formats requested from a camera whose input_format is set (delivered unconverted).
FOURCC = {
    "YUYV": "YUYV",
    "UYVY": "UYVY",
    "I420": "YU12",
    "NV12": "NV12",
    "GRAY": "GREY",
    "RGB": "RGB3",
}


class Device:
    """What a reader thread reads: ``read()`` returns an array, or None at the end.

    ``position`` is the index in the stream of the next frame ``read()`` returns, so that a
    reopened file or image sequence resumes where it stalled instead of starting over.
    ``into``: an array to decode into when the device can (its shape and type match the
    frame); the returned array is then that very array, else a new one.
    """

    dims: tuple[int, int] | None = None
    rewindable = False
    position = 0

    def read(self, into: np.ndarray | None = None) -> np.ndarray | None:
        raise NotImplementedError

    def release(self) -> None:
        pass


def _open_file(target: str, threads: int) -> Any:
    """A file (or stream URL) through FFmpeg with ``threads`` decoding threads (0: its
    choice); a backend that does not take the setting opens it with its own."""
    if threads > 0:
        cap = cv2.VideoCapture(target, cv2.CAP_FFMPEG, [cv2.CAP_PROP_N_THREADS, threads])
        if cap.isOpened():
            return cap
        cap.release()
    return cv2.VideoCapture(target)


class VideoDevice(Device):
    """A video file or stream (``kind`` ``file``) or a camera (``camera``), through OpenCV.

    A camera is asked for ``input_format`` (delivered raw, unconverted), ``size`` and ``fps``;
    what it grants is in ``dims``. A file reopened after a stall seeks to ``start``.

    ``decode_threads``: FFmpeg's decoding threads for a file (0: its choice, one per CPU).
    One by default: the reader thread already decodes beside the graph, and FFmpeg's own
    threads (woken for every frame) compete with the graph's nodes for the CPUs. Measured on
    the 2-CPU machine with the 720x528 sample clip: one thread 0.30-0.32 ms of CPU per frame,
    FFmpeg's choice 0.36-0.38 ms (a lower wall time alone, 0.23-0.26 ms); graphs/video.yaml
    offline, inline tracker: 1.17x a plain OpenCV loop with one thread, 1.03x with FFmpeg's
    choice (benchmarks/RESULTS.md).
    """

    def __init__(
        self,
        kind: str,
        target: str | int,
        *,
        input_format: str | None = None,
        size: tuple[int, int] | None = None,
        fps: float = 0.0,
        start: int = 0,
        decode_threads: int = 1,
    ) -> None:
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
            cap = _open_file(target, decode_threads)
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
            fmt = input_format
            if fmt in FOURCC:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*FOURCC[fmt]))
            if size is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
            cap.set(cv2.CAP_PROP_FPS, fps)
            if fmt in FOURCC:
                cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
            self.dims = (
                int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            )
        self.cap = cap
        if start > 0 and kind == "file":  # resume after a stall (seeking is best effort)
            cap.set(cv2.CAP_PROP_POS_FRAMES, start)
            self.frames = self.position = start

    def read(self, into: np.ndarray | None = None) -> np.ndarray | None:
        # OpenCV writes into ``into`` when its shape and type fit (a frame's shared-memory
        # slot: no copy on the loop), else it allocates.
        ok, img = self.cap.read() if into is None else self.cap.read(into)
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


class ImageDevice(Device):
    """The image files matching a glob, in sorted order; an unreadable one is reported through
    ``alert`` and skipped, so one bad file does not end the sequence."""

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

    def read(self, into: np.ndarray | None = None) -> np.ndarray | None:
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
