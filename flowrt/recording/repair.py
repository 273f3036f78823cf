"""Repair of a damaged MCAP file: what can be read of it rewritten as a complete file.

A recording cut by a crash or a full disk has no summary and may end inside a chunk. Every
record that still reads (:func:`flowrt.recording.reader._records`, chunks checked by their
CRC) is written again in order to a new file, which takes the original's name; the original
is kept beside it, never overwritten. The repaired file carries a ``flowrt.repair`` metadata
record (:data:`REPAIR_METADATA`: the damage, the messages kept), by which a reader knows what
it holds was cut (a deterministic log so repaired never replays "identical").
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path
from typing import Any

from .inuse import being_recorded
from .reader import Recording, _records
from .rosbag2 import BagError, is_db3

__all__ = ["REPAIR_METADATA", "repair"]

REPAIR_METADATA = "flowrt.repair"
"""The metadata record a repaired file carries: ``damage`` and ``messages_kept``."""


def repair(path: str | Path) -> tuple[Path, int, Path]:
    """Rewrite what can be read of ``path`` as a complete file; keep the original.

    The original is renamed ``NAME.damaged.mcap`` (``NAME.damaged-2.mcap``... when that is
    taken: an original is never overwritten); the repaired file takes its name. Returns (the
    repaired file, messages kept, where the original is kept). An ``OSError`` (a read-only
    folder, a full disk) leaves the original untouched and no partial file behind.

    The repaired file keeps the original's header profile (rosbags refuses a ``ros2`` file
    of another). A killed ``ros2`` recording never wrote the folder's ``metadata.yaml``,
    without which rosbags does not open it: the repair writes it (:mod:`.rosbag2`).
    """
    from .rosbag2 import header_profile, metadata_after_repair

    p = Path(path)
    if is_db3(p):  # it would be renamed .damaged.mcap and replaced by an empty MCAP file
        raise OSError(errno.EINVAL, "a rosbag2 SQLite3 file: flowrt repairs MCAP files only")
    if being_recorded(p):  # its writer would go on in the renamed file, this one cut short
        raise OSError(errno.EBUSY, "still being recorded (a recorder writes it)")
    rec, tmp, profile = Recording(p), p.with_name(p.stem + ".repairing.mcap"), header_profile(p)
    profile = "flowrt" if profile is None else profile  # cut inside its header: flowrt's
    try:
        kept = _write_repaired(p, rec, tmp, profile)
        damaged = _free_name(p.with_name(p.stem + ".damaged.mcap"))
        os.rename(p, damaged)  # a free name: the original is kept, never overwritten
        try:
            os.replace(tmp, p)
        except OSError:
            os.rename(damaged, p)
            raise
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    if profile == "ros2":  # a folder that is no bag flowrt reads (BagError): no metadata
        from .session import mcap_files

        with contextlib.suppress(BagError):
            metadata_after_repair(p, mcap_files(p.parent))
    return p, kept, damaged


def _free_name(path: Path) -> Path:
    """``path``, or ``STEM-2.mcap``, ``STEM-3.mcap``...: the first that does not exist."""
    n = 2
    candidate = path
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
        n += 1
    return candidate


def _write_repaired(p: Path, rec: Any, tmp: Path, header_profile: str) -> int:
    from mcap.records import Attachment, Channel, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    kept = 0
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    schemas: dict[int, Any] = {}
    with open(tmp, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile=header_profile, library="flowrt repair")
        for r in _records(p, rec, emit_chunks=False):
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                s = schemas.get(r.schema_id)
                if s is not None and r.schema_id not in schema_ids:
                    schema_ids[r.schema_id] = w.register_schema(s.name, s.encoding, s.data)
                channel_ids[r.id] = w.register_channel(
                    r.topic, r.message_encoding, schema_ids.get(r.schema_id, 0), r.metadata
                )
            elif isinstance(r, Message) and r.channel_id in channel_ids:
                w.add_message(
                    channel_ids[r.channel_id], r.log_time, r.data, r.publish_time, r.sequence
                )
                kept += 1
            elif isinstance(r, Metadata):
                w.add_metadata(r.name, r.metadata)
            elif isinstance(r, Attachment):
                w.add_attachment(r.create_time, r.log_time, r.name, r.media_type, r.data)
        w.add_metadata(
            REPAIR_METADATA,
            {"damage": rec.damage or "not closed cleanly", "messages_kept": str(kept)},
        )
        w.finish()  # type: ignore[no-untyped-call]
        f.flush()
        os.fsync(f.fileno())
    return kept
