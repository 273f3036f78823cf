"""A recording file while its writer writes it: held, so that no one else takes it for damaged.

A file being recorded has no summary yet, which is what a killed recorder's file looks like:
``flowrt info`` called a live session "not closed cleanly", and ``info --repair`` renamed
it ``.damaged.mcap`` under its writer, which went on writing the renamed file while a copy
cut at that instant took the session's name. The writer holds an advisory lock (``flock``)
on the file for as long as it writes it; the kernel drops it when the file is closed, so a
killed writer's file is free at once.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

__all__ = ["being_recorded", "hold"]


def hold(fd: int) -> None:
    """Mark the open file ``fd`` as being written (until it is closed); best effort."""
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


def being_recorded(path: str | Path) -> bool:
    """True while a writer holds ``path`` (see :func:`hold`)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # (closing drops a lock taken here)
    return False
