"""What the watchdog reads of a worker: its CPU progress and run-queue wait, from /proc.

A call past its watchdog is killed only when the worker made progress or could run: one that
waited on the run queue was starved of CPU, not hung (see ``Worker._on_hung``).
"""

from __future__ import annotations

import contextlib
import os

_PROC_FDS: dict[tuple[int, str], int] = {}  # (pid, file) -> an open /proc descriptor


def _proc_read(pid: int, name: str) -> bytes:
    """/proc/PID/NAME through a descriptor kept open: ~2 us a read, against ~60 us to open,
    read and close it, which matters at every dispatch of a call that has a watchdog."""
    key = (pid, name)
    fd = _PROC_FDS.get(key)
    if fd is None:
        fd = os.open(f"/proc/{pid}/{name}", os.O_RDONLY | os.O_CLOEXEC)
        _PROC_FDS[key] = fd
    return os.pread(fd, 1024, 0)


def proc_forget(pid: int | None) -> None:
    """Close the /proc descriptors of a worker that is gone."""
    for name in ("schedstat", "stat"):
        fd = _PROC_FDS.pop((pid, name), None) if pid is not None else None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)


def progress_of(pid: int | None, now: float) -> tuple[float, float, float | None] | None:
    """(now, CPU seconds, run-queue wait seconds or None) of a process, from /proc."""
    if pid is None:
        return None
    try:
        cpu_ns, wait_ns, _ = _proc_read(pid, "schedstat").split()
        return now, int(cpu_ns) / 1e9, int(wait_ns) / 1e9
    except (OSError, ValueError):
        pass
    try:
        fields = _proc_read(pid, "stat").rsplit(b")", 1)[1].split()
        ticks = os.sysconf("SC_CLK_TCK")
        return now, (int(fields[11]) + int(fields[12])) / ticks, None  # utime + stime
    except (OSError, ValueError, IndexError):
        return None


def state_of(pid: int | None) -> str:
    """The process state letter of /proc/PID/stat (R runnable, S sleeping, ...), or ''."""
    if pid is None:
        return ""
    try:
        return _proc_read(pid, "stat").rsplit(b")", 1)[1].split()[0].decode()
    except (OSError, IndexError, UnicodeDecodeError):
        return ""
