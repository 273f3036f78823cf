"""Reading a file a user named: only regular files, sizes checked before reading.

Every path a graph or a command takes may be ``/dev/zero`` (endless), a FIFO (``open`` blocks
until a writer comes) or a 1 GiB file where a 10 KB one was meant: read naively, each is a
hang or gigabytes of memory. Here a file is opened without blocking, checked to be a regular
file by ``fstat`` on the open descriptor (no race with a rename), and read only when its size
is within the caller's limit.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["NotARegularFile", "check_regular_file", "file_problem", "read_bytes", "read_text"]


class NotARegularFile(OSError):
    """A path that is a device, a FIFO, a socket or a directory, or a file over the limit;
    ``strerror`` is one line meant for the user."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.strerror = message


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_regular_file(path: str | Path, max_bytes: int | None = None) -> int:
    """The size of ``path`` if it is a regular file within ``max_bytes``; else raises
    :class:`NotARegularFile` (or ``OSError`` when it cannot be read). Never blocks."""
    st = os.stat(path)  # follows links: a link to /dev/zero is a device
    return _checked(path, st, max_bytes)


def _checked(path: str | Path, st: os.stat_result, max_bytes: int | None) -> int:
    if not stat.S_ISREG(st.st_mode):
        raise NotARegularFile(f"{path} is {_kind(st.st_mode)}, not a regular file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise NotARegularFile(
            f"{path} is {st.st_size} bytes, more than the {max_bytes} accepted here"
        )
    return int(st.st_size)


def file_problem(path: str | Path, max_bytes: int | None = None) -> str | None:
    """Why ``path`` cannot be read as a regular file within ``max_bytes`` (one line, the path
    in it), or None when it can."""
    try:
        check_regular_file(path, max_bytes)
    except FileNotFoundError:
        return f"{path}: no such file"
    except NotARegularFile as e:
        return str(e)
    except OSError as e:
        return f"{path}: {e.strerror or e}"
    return None


def read_bytes(path: str | Path, max_bytes: int) -> bytes:
    """The whole regular file at ``path``, at most ``max_bytes`` (else NotARegularFile)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        size = _checked(path, os.fstat(fd), max_bytes)
        os.set_blocking(fd, True)
        chunks: list[bytes] = []
        got = 0
        while got <= size:  # a file growing while read is cut at the limit, not followed
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - got))
            if not chunk:
                break
            chunks.append(chunk)
            got += len(chunk)
            if got > max_bytes:
                raise NotARegularFile(f"{path} grew past {max_bytes} bytes while read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_text(path: str | Path, max_bytes: int, encoding: str = "utf-8") -> str:
    """:func:`read_bytes` decoded (``UnicodeDecodeError`` when it is not ``encoding``)."""
    return read_bytes(path, max_bytes).decode(encoding)
