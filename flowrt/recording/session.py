"""Sessions: ``recordings/drive_001/`` (next free number), and what a recording says about itself.

A session folder holds the MCAP file (or its parts, :mod:`.split`) and ``streams.json`` (the
per-stream report): nothing a user could lose by copying the folder. Each file says how it
was made: metadata ``flowrt`` (version, host, start time, graph name, Python), attachments
``graph.yaml`` (the graph file's text, when known) and ``timing.json`` (every node's trigger,
period, deadline, priority and placement at the start), and at a clean stop (in the last
file) ``streams.json`` again.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import platform
import re
import socket
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .rosbag2 import METADATA_FILE, bag_files

__all__ = [
    "SESSION_FILE",
    "SESSION_NAME",
    "check_writable",
    "mcap_files",
    "new_session",
    "session_metadata",
]

SESSION_FILE = "streams.json"
SESSION_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}\Z")  # \Z: "$" took "abc\n" too
"""A session prefix (and a session folder's name): no path separator, no dot, bounded."""
_NAME = SESSION_NAME
_PART = re.compile(r"^(.*)_(\d+)\.mcap$")


def check_writable(root: str | Path) -> str | None:
    """None if sessions can be created under ``root`` (made if missing), else why not."""
    path = Path(root)
    if path.exists() and not path.is_dir():
        return f"{path} is not a directory"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"cannot create {path}: {e.strerror or e}"
    try:
        with tempfile.NamedTemporaryFile(dir=path, prefix=".flowrt-write-test-"):
            pass
    except OSError as e:
        return f"{path} is not writable: {e.strerror or e}"
    return None


def new_session(root: str | Path, name: str = "rec") -> Path:
    """Create ``root/NAME_NNN`` with the next free number (``drive_001``, ``drive_002``...)."""
    if not _NAME.match(name):
        raise ValueError(f"session name {name!r}: use letters, digits, _ and -")
    base = Path(root)
    base.mkdir(parents=True, exist_ok=True)
    pattern = re.compile(rf"^{re.escape(name)}_(\d+)$")
    taken = [int(m.group(1)) for p in base.iterdir() if (m := pattern.match(p.name))]
    n = max(taken, default=0) + 1
    while True:  # another recorder may take a number at the same moment: try the next one
        path = base / f"{name}_{n:03d}"
        try:
            path.mkdir()
            return path
        except FileExistsError:
            n += 1


def mcap_files(path: str | Path) -> list[Path]:
    """The MCAP file(s) of a session folder in part order, or the file itself.

    A rosbag2 folder gives its storage files (``.mcap`` or ``.db3``, :mod:`.rosbag2`); one
    that flowrt cannot read raises :class:`~.rosbag2.BagError` with the reason.

    Parts sort by their number (``_999`` before ``_1000``); the originals that ``info
    --repair`` kept (``*.damaged.mcap``) and its unfinished output are not parts.
    """
    p = Path(path)
    if p.name == METADATA_FILE and p.is_file():  # a bag named by its metadata: the folder
        p = p.parent
    if not p.is_dir():
        return [p]
    bag = bag_files(p)  # a rosbag2 folder: its files, as metadata.yaml lists them
    if bag is not None:
        return bag
    files = [
        f
        for f in p.glob("*.mcap")
        if not f.name.endswith(".repairing.mcap") and ".damaged" not in f.name
    ]
    recordings = sorted({_part_key(f)[0] for f in files})
    if len(recordings) > 1:  # read as one: "duration 95791334 s" from files years apart
        names = ", ".join(sorted(f.name for f in files)[:4]) + (", ..." if len(files) > 4 else "")
        raise ValueError(
            f"{p}: {len(recordings)} recordings, not one session ({names}): give one file"
        )
    return sorted(files, key=_part_key)


def not_a_recording(path: Path) -> str | None:
    """Why ``path`` is no recording flowrt reads (None: it is MCAP, a rosbag2 SQLite3
    file, or an MCAP cut inside its magic, killed at creation: repairable). The command
    line and the ``replay`` node say the same (the node said "InvalidMagic" of a ROS 1 bag,
    "replayed up to the damage at byte 0" of a text file)."""
    from .rosbag2 import is_db3

    if is_db3(path):  # a rosbag2 SQLite3 file: read through the same reader
        return None
    magic = b"\x89MCAP0\r\n"
    with open(path, "rb") as f:
        head = f.read(13)
    if head.startswith(b"#ROSBAG V"):
        return "a ROS 1 bag, not read: convert it with rosbags-convert (pip install rosbags)"
    if not head and path.suffix != ".mcap":  # (a 0-byte .db3 was "not an MCAP file")
        return "an empty file (0 bytes): no recording in it"
    if not magic.startswith(head[:8]):
        return "not an MCAP file"
    return None


def sessions_hint(folder: Path, shown: Callable[[str], str] = str) -> str:
    """A folder of recording sessions (``-o recordings/``) named to the user: which to give
    (``shown``: how a name is printed)."""
    try:
        sessions = sorted(d.name for d in folder.iterdir() if d.is_dir() and _a_recording(d))
    except OSError:
        return ""
    if not sessions:
        return ""
    names = ", ".join(shown(n) for n in sessions[-3:])
    more = f" and {len(sessions) - 3} more" if len(sessions) > 3 else ""
    last = shown(str(folder / sessions[-1]))
    return f" (it holds sessions: {names}{more}; give one, e.g. {last})"


def _a_recording(folder: Path) -> bool:
    """A session folder, or a rosbag2 one (MCAP or SQLite3 storage)."""
    return (
        any(folder.glob("*.mcap"))
        or any(folder.glob("*.db3"))
        or (folder / METADATA_FILE).is_file()
    )


def missing_parts(path: str | Path, files: list[Path]) -> list[str]:
    """The parts a split session folder lacks (``rec_001_001.mcap`` between ``_000`` and
    ``_002``, or ``_000`` itself): a deleted or never-copied part was read as a whole
    recording with a long gap (``flowrt info`` exit 0, a replay "identical"). Only the
    folder's own parts count (``NAME/NAME_NNN.mcap``); a missing last part cannot be told."""
    folder = Path(path)
    if not folder.is_dir():
        return []
    numbers: list[int] = []
    width = 3
    for f in files:
        m = _PART.match(f.name)
        if m is not None and m.group(1) == folder.name:
            numbers.append(int(m.group(2)))
            width = len(m.group(2))
    if not numbers:
        return []
    have = set(numbers)
    return [f"{folder.name}_{n:0{width}d}.mcap" for n in range(max(have)) if n not in have]


def _part_key(path: Path) -> tuple[str, int]:
    m = _PART.match(path.name)
    return (m.group(1), int(m.group(2))) if m else (path.stem, -1)


def session_metadata(
    graph: str, started: float, extra: dict[str, str] | None = None
) -> dict[str, dict[str, str]]:
    """The ``flowrt`` metadata record: who recorded, where, when, which graph."""
    from ..version import __version__

    meta = {
        "flowrt_version": __version__,
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "pid": str(os.getpid()),
        "start_time": dt.datetime.fromtimestamp(started, dt.UTC).isoformat(),
        "graph": graph,
    }
    meta.update(extra or {})
    return {"flowrt": meta}


def timing_json(stats: Any) -> bytes:
    """Every node's timing at the start, from a ``RuntimeStats`` snapshot (JSON)."""
    import json

    nodes = []
    with contextlib.suppress(Exception):
        for n in stats.nodes:
            nodes.append(
                {
                    "name": n.name,
                    "kind": n.kind,
                    "placement": n.placement,
                    "trigger": n.trigger,
                    "period": n.period,
                    "priority": n.priority,
                    "deadline_ms": n.deadline_ms,
                    "enabled": n.enabled,
                }
            )
    return json.dumps({"graph": getattr(stats, "graph", ""), "nodes": nodes}, indent=1).encode()
