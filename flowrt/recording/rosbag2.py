"""rosbag2 folders: read wherever an MCAP session is, and written by the ``ros2`` profile.

A rosbag2 bag is a folder with ``metadata.yaml`` (``rosbag2_bagfile_information``: the
storage, the files, the topics with their types and counts) and its storage files: MCAP
(``rosbag2_storage_mcap``, read as any MCAP file) or SQLite3 ``.db3`` (read here with the
standard library's ``sqlite3``: tables ``topics``, ``messages`` and, from the Jazzy format
on, ``message_definitions``; older bags carry no definitions, which then come from the type
store ``rosbags`` ships for the standard ROS 2 types).

A bag whose recorder was killed has no ``metadata.yaml``: its ``.mcap``/``.db3`` files are
read all the same. Compressed bags (``compression_mode: file|message``) are refused with the
reason (``ros2 bag convert`` or ``rosbags-convert`` decompresses them).

This module only knows the folder and the SQLite storage; :mod:`.reader` turns what it
returns into the streams and messages of a recording.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "METADATA_FILE",
    "BagError",
    "Db3Topic",
    "bag_files",
    "db3_messages",
    "db3_topics",
    "header_profile",
    "is_db3",
    "metadata_after_repair",
    "write_metadata",
]

METADATA_FILE = "metadata.yaml"
ROSBAG2_VERSION = 9  # what Jazzy writes, and rosbags' Writer; offered_qos_profiles is a list
_SQLITE_MAGIC = b"SQLite format 3\x00"


class BagError(ValueError):
    """A bag folder that cannot be read (compressed, a storage flowrt does not read)."""


def _metadata(folder: Path) -> dict[str, Any] | None:
    import yaml

    meta = folder / METADATA_FILE
    if not meta.is_file():
        return None
    try:
        doc = yaml.safe_load(meta.read_text())
    except OSError as e:
        raise BagError(f"{meta}: not readable: {e.strerror or e}") from None
    except yaml.YAMLError as e:  # one line: pyyaml's message spans five, with a caret
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        raise BagError(f"{meta}: not YAML: {getattr(e, 'problem', None) or e}{where}") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    return info if isinstance(info, dict) else None


def bag_files(folder: Path) -> list[Path] | None:
    """The storage files of a rosbag2 folder in order, or None when it is not a bag.

    Raises :class:`BagError` for a bag flowrt cannot read.
    """
    info = _metadata(folder)
    if info is None:
        db3 = sorted(folder.glob("*.db3"))
        return db3 or None  # a bag without metadata (killed recorder); MCAP ones: a session
    paths = info.get("relative_file_paths") or []
    for key, ok, what in (
        ("compression_mode", isinstance(info.get("compression_mode") or "", str), "a name"),
        ("storage_identifier", isinstance(info.get("storage_identifier", ""), str), "a name"),
        (
            "relative_file_paths",
            isinstance(paths, list) and all(isinstance(p, str) for p in paths),
            "a list of file names",
        ),
    ):
        if not ok:  # a hand-edited file: said, not a TypeError from the lines below
            raise BagError(f"{folder / METADATA_FILE}: {key}: expected {what}")
    if (info.get("compression_mode") or "none").lower() not in ("", "none"):
        raise BagError(
            f"{folder}: a {info.get('compression_format') or '?'}-compressed bag "
            f"({info['compression_mode']} mode): decompress it first (ros2 bag convert)"
        )
    storage = info.get("storage_identifier", "")
    if storage not in ("mcap", "sqlite3"):
        raise BagError(f"{folder}: storage {storage!r} (flowrt reads mcap and sqlite3)")
    names = [Path(p).name for p in paths]
    files = [folder / n for n in names if (folder / n).is_file()]
    if not files:  # paths that do not match the folder's (renamed): what is there
        files = sorted(folder.glob("*.mcap" if storage == "mcap" else "*.db3"))
    if not files and names:  # it said "no .mcap file in this folder" of a bag's missing .db3
        raise BagError(f"{folder}: {', '.join(names)}: missing (named by {METADATA_FILE})")
    return files


def is_db3(path: Path) -> bool:
    """True for a rosbag2 SQLite3 storage file (by its magic, whatever its name)."""
    try:
        with open(path, "rb") as f:
            return f.read(16) == _SQLITE_MAGIC
    except OSError:
        return False


@dataclass
class Db3Topic:
    """One topic of a ``.db3`` file: its schema (a ``mcap`` Schema record), times and sizes."""

    id: int
    name: str
    type: str
    encoding: str
    schema: Any
    times: list[int] = field(default_factory=list)
    bytes: int = 0


def _connect(path: Path) -> sqlite3.Connection:
    # read-only and immutable: a bag being copied or on a read-only medium is still read
    # the replay node reads on a worker thread of its own choosing, one call at a time
    return sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True, check_same_thread=False)


def db3_topics(path: Path, with_times: bool = True) -> dict[int, Db3Topic]:
    """The topics of a ``.db3`` file with their schemas (and every message's time and size)."""
    from mcap.records import Schema

    con = _connect(path)
    try:
        rows = con.execute("SELECT id, name, type, serialization_format FROM topics").fetchall()
        defs = _definitions(con)
        topics: dict[int, Db3Topic] = {}
        for n, (tid, name, typ, fmt) in enumerate(rows, start=1):
            text, encoding = defs.get(typ) or _standard_definition(typ)
            schema = Schema(id=n, name=typ, encoding=encoding, data=text.encode())
            topics[tid] = Db3Topic(tid, name, typ, fmt, schema)
        if with_times:
            q = "SELECT topic_id, timestamp, length(data) FROM messages ORDER BY timestamp"
            for tid, t, size in con.execute(q):
                top = topics.get(tid)
                if top is not None:
                    top.times.append(int(t))
                    top.bytes += int(size or 0)
        return topics
    except sqlite3.DatabaseError as e:
        raise BagError(f"{path}: {e}") from None
    finally:
        con.close()


def db3_last_time(path: Path) -> int | None:
    """The last message's time (ns) in a ``.db3`` file (None: no message, or unreadable)."""
    try:
        con = _connect(path)
        try:
            row = con.execute("SELECT MAX(timestamp) FROM messages").fetchone()
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return None
    return None if row is None or row[0] is None else int(row[0])


def db3_messages(
    path: Path, topics: set[str] | None = None
) -> Iterator[tuple[Db3Topic, int, bytes]]:
    """(topic, log time ns, CDR bytes) of a ``.db3`` file in time order."""
    known = db3_topics(path, with_times=False)
    con = _connect(path)
    try:
        q = "SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id"
        for tid, t, data in con.execute(q):
            top = known.get(tid)
            if top is not None and (topics is None or top.name in topics):
                yield top, int(t), bytes(data)
    finally:
        con.close()


def _definitions(con: sqlite3.Connection) -> dict[str, tuple[str, str]]:
    """type -> (definition, ros2msg|ros2idl) from the ``message_definitions`` table, if any."""
    tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    if "message_definitions" not in tables:
        return {}
    q = "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
    return {t: (text, enc) for t, enc, text in con.execute(q) if text}


def _standard_definition(typ: str) -> tuple[str, str]:
    """A standard type's definition from rosbags' type store; empty when it has none."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.LATEST)
    if typ not in store.fielddefs:
        return "", "ros2msg"
    text, _ = store.generate_msgdef(typ, ros_version=2)
    return text, "ros2msg"


def write_metadata(folder: Path, files: list[Path]) -> Path:
    """Write ``metadata.yaml`` for a bag of finished MCAP ``files`` (the ``ros2`` profile).

    Everything comes from the files' own summaries (channels, schemas, statistics), so the
    metadata says what the files hold, whichever process wrote them.
    """
    import yaml
    from mcap.reader import make_reader

    topics: dict[str, dict[str, Any]] = {}
    per_file: list[tuple[Path, int, int, int]] = []  # path, count, start, end
    for f in files:
        with open(f, "rb") as fh:
            summary = make_reader(fh).get_summary()
        if summary is None or summary.statistics is None:
            raise BagError(f"{f}: no summary (the file was not finished)")
        st = summary.statistics
        per_file.append((f, st.message_count, st.message_start_time, st.message_end_time))
        for cid, ch in summary.channels.items():
            schema = summary.schemas.get(ch.schema_id)
            t = topics.setdefault(
                ch.topic, {"name": ch.topic, "type": schema.name if schema else "", "count": 0}
            )
            t["count"] += st.channel_message_counts.get(cid, 0)
    counted = [p for p in per_file if p[1]]
    start = min((p[2] for p in counted), default=0)
    duration = max((p[3] for p in counted), default=start) - start
    info = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [f.name for f in files],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(p[1] for p in per_file),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t["name"],
                    "type": t["type"],
                    "serialization_format": "cdr",
                    "offered_qos_profiles": [],
                    "type_description_hash": "",
                },
                "message_count": t["count"],
            }
            for t in topics.values()
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": f.name,
                "starting_time": {"nanoseconds_since_epoch": t0 if n else 0},
                "duration": {"nanoseconds": (t1 - t0) if n else 0},
                "message_count": n,
            }
            for f, n, t0, t1 in per_file
        ],
        "custom_data": None,
        "ros_distro": "flowrt",
    }
    path = folder / METADATA_FILE
    tmp = path.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
    tmp.replace(path)
    return path


def header_profile(path: Path) -> str | None:
    """The profile in an MCAP file's header record (``flowrt``, ``ros2``...), None when the
    file is cut before its header ends."""
    from mcap.records import Header
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as f:
            first = next(iter(StreamReader(f, skip_magic=False).records), None)
    except Exception:
        return None
    return first.profile if isinstance(first, Header) else None


def metadata_after_repair(repaired: Path, files: list[Path]) -> Path | None:
    """``metadata.yaml`` for the rosbag2 folder of a repaired ``ros2`` file (the reader's
    ``repair``), from what its files now hold: a killed recorder never wrote it, and rosbags
    does not open a folder without it. The path written, or None.

    Only when the folder is that bag: the file is one of its parts and every part is a
    finished ``ros2`` file. A part still unrepaired (``info --repair`` goes through a
    session's files in turn) leaves it to that part's repair; a ``ros2`` file among files
    of another profile (copied into a folder of its own choosing) makes no bag of them.
    ``files``: the folder's parts, as :func:`.session.mcap_files` lists them.
    """
    folder = repaired.parent
    if repaired not in files or any(header_profile(f) != "ros2" for f in files):
        return None
    if not all(_finished(f) for f in files):
        return None
    try:
        return write_metadata(folder, files)
    except (BagError, OSError):
        return None


def _finished(path: Path) -> bool:
    """True when the file ends with its summary (what :func:`write_metadata` reads)."""
    from mcap.reader import SeekingReader

    try:
        with open(path, "rb") as f:
            return SeekingReader(f).get_summary() is not None
    except Exception:
        return False
