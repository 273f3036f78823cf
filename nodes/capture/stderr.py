"""What C libraries print on stderr while a capture device opens, collected for its log.

:func:`native_stderr` around an open; :func:`message_kind` tells repeated lines apart, so the
node logs each kind once at INFO and its repeats at DEBUG.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator

__all__ = ["REDIRECT_MAX", "STDERR_LOCK", "message_kind", "native_stderr"]

STDERR_LOCK = threading.Lock()  # fd 2 is the process's: one redirection at a time
REDIRECT_MAX = 3.0  # seconds: fd 2 is given back then even if the open has not returned
# What differs between two lines saying the same: OpenCV's "[ WARN:3@0.618]" prefix
# (thread and time) and FFmpeg's "@ 0x55d0..." context addresses.
_NOISE = re.compile(r"^\[\s*\w+:\d+@[\d.]+\]\s*|0x[0-9a-fA-F]+")


class _Redirect:
    """fd 2 pointed at a temporary file; given back exactly once: when the open returns, or
    after ``REDIRECT_MAX`` by a timer if the driver hangs in it (a hung open must not keep
    the process's stderr, nor the other sources' opens, forever)."""

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._restored = False
        self.tmp = tempfile.TemporaryFile()  # noqa: SIM115 (closed in close())
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        self.saved = os.dup(2)
        os.dup2(self.tmp.fileno(), 2)
        self.timer = threading.Timer(REDIRECT_MAX, self.restore)
        self.timer.daemon = True
        self.timer.start()

    def restore(self) -> None:
        with self._mutex:
            if self._restored:
                return
            self._restored = True
            os.dup2(self.saved, 2)
            os.close(self.saved)
            STDERR_LOCK.release()

    def close(self) -> list[str]:
        self.timer.cancel()
        self.restore()
        self.tmp.seek(0)
        text = self.tmp.read().decode(errors="replace")
        self.tmp.close()
        return [line.rstrip() for line in text.splitlines() if line.strip()]


@contextlib.contextmanager
def native_stderr(lines: list[str]) -> Iterator[None]:
    """Collect what C libraries (OpenCV, V4L2, FFmpeg) print on file descriptor 2 meanwhile.

    OpenCV and FFmpeg write their warnings straight to fd 2, past Python's logging, so they
    would land raw between the lines of the status table. Around a device open (where they
    say why it failed) fd 2 is pointed at a temporary file, and the lines go to the node's
    log instead. Whatever another thread writes to stderr in that window (milliseconds; at
    most ``REDIRECT_MAX``) is logged there too, not lost. Should another source be opening
    for longer than that, this open is not redirected rather than waited for.
    """
    redirect: _Redirect | None = None
    if STDERR_LOCK.acquire(timeout=REDIRECT_MAX):
        try:
            redirect = _Redirect()
        except OSError:
            STDERR_LOCK.release()
    try:
        yield
    finally:
        if redirect is not None:
            lines.extend(redirect.close())


def message_kind(line: str) -> str:
    """``line`` without what differs between two lines that say the same thing."""
    return _NOISE.sub("", line)
