"""The ``recorder`` node's parameters: folders, file layout, writer and profile."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from flowrt import resolve_path
from flowrt.recording import parse_duration, parse_size
from flowrt.recording.session import SESSION_NAME


class RecorderParams(BaseModel):
    """What a recorder is told (a graph's ``params``); the node lives in :mod:`.recorder`.

    Kept apart from the node so the hot path and the session handling read without eighty
    lines of fields between them; ``flowrt kinds recorder`` shows the same fields."""

    model_config = ConfigDict(extra="forbid")
    path: str = Field(
        default="recordings",
        description="folder of the sessions (relative: beside the graph file)",
    )
    name: str = Field(default="rec", description="session prefix: NAME_001, NAME_002 ...")
    session: str | None = Field(
        default=None, description="an existing empty folder to record into (the CLI's)"
    )
    start: bool = Field(default=True, description="record from the start (else: ctl)")

    @field_validator("name", mode="after")
    @classmethod
    def _a_session_prefix(cls, v: str) -> str:
        """Refused here, at load or swap, not only when a recording starts (as a graph's
        every other mistake): NAME_001 must be one plain folder name."""
        if not SESSION_NAME.match(v):
            raise ValueError(f"{_shown(v)}: letters, digits, _ and - (at most 64)")
        return v

    @field_validator("path", "session", mode="before")
    @classmethod
    def _a_folder_name(cls, v: Any) -> Any:
        """A folder that can be made (each part at most 255 bytes) and named on one line."""
        if isinstance(v, str):
            if any(ord(c) < 32 or c == "\x7f" for c in v):
                raise ValueError(f"{_shown(v)}: a control character (a newline?) in a folder name")
            if any(len(part.encode()) > 255 for part in v.split("/")):
                raise ValueError(f"{_shown(v)}: a folder name is at most 255 bytes")
        return v

    @field_validator("path", "session", mode="after")
    @classmethod
    def _beside_the_graph(cls, v: str | None, info: ValidationInfo) -> str | None:
        """Relative folders resolve against the graph file's folder, as every path of a
        graph does: the recording lands in the same place from any working directory."""
        return None if v is None else resolve_path(v, info)

    images: dict[str, Literal["raw", "jpeg", "png"]] = Field(
        default_factory=dict, description="per topic: raw (RawImage), jpeg or png"
    )
    compression: Literal["none", "lz4", "zstd"] = "none"
    chunk_size: int = Field(default=4 << 20, ge=1024)
    flush_interval: float = Field(
        default=1.0, gt=0, description="s: a chunk is finished at least this often"
    )
    max_frames: int = Field(
        default=8, ge=1, description="frames waiting to be copied off their slots, per stream"
    )
    direct_io: bool = Field(
        default=True, description="O_DIRECT writes where possible: past a slow page cache"
    )
    crc: bool = Field(default=True, description="chunk CRCs: damage found; off halves the CPU cost")
    writer: Literal["process", "thread"] = Field(
        default="process",
        description="process: a writer process reading frames from shared memory; "
        "thread: writer threads in the runtime's process",
    )
    writer_priority: Literal["normal", "idle"] = Field(
        default="normal",
        description="idle: the writer process only takes CPU time nobody else wants; "
        "the loop's timers never wait for it, but under load it falls behind (counted)",
    )
    split_size: int | None = Field(
        default=None, description="start a new file past this size: 4GiB, 500MB, bytes"
    )
    split_duration: float | None = Field(
        default=None, description="start a new file after this long: 10m, 30s, seconds"
    )
    annotations: bool = Field(
        default=True, description="detections also as ImageAnnotations on their camera"
    )
    graph_file: str | None = Field(default=None, description="attached as graph.yaml")
    profile: Literal["flowrt", "ros2"] = Field(
        default="flowrt",
        description="ros2: a rosbag2 folder (metadata.yaml, CDR messages, ros2msg schemas)",
    )

    @model_validator(mode="after")
    def _priority_of_a_process(self) -> RecorderParams:
        """A priority is the writer process's: threads share the loop's process."""
        if self.writer_priority != "normal" and self.writer != "process":
            raise ValueError("writer_priority idle needs writer: process")
        return self

    @field_validator("split_size", mode="before")
    @classmethod
    def _size(cls, v: Any) -> Any:
        return None if v is None else parse_size(str(v))

    @field_validator("split_duration", mode="before")
    @classmethod
    def _duration(cls, v: Any) -> Any:
        return None if v is None else parse_duration(str(v))

    log_report: bool = Field(default=True, description="log the table when a recording stops")
    deterministic: bool = Field(
        default=False,
        description="also record what a deterministic replay needs (activations, digests)",
    )


def _shown(v: str) -> str:
    """A refused value in a one-line message (a 300-character name, cut)."""
    return repr(v) if len(v) <= 60 else repr(v[:60]) + "..."
