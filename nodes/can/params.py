"""The ``can`` node's params: the bus, the DBC and per-message options, checked against the
DBC when the graph is validated (names of messages and signals, a checksum that is one
byte, a strict-refused DBC with ``strict: true``); paths resolve beside the graph file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from flowrt import resolve_path
from flowrt.analysis.can_frames import bit_rate
from flowrt.graph.diagnostics import did_you_mean

from .dbc import dbc_warnings, load_dbc

__all__ = ["BitRate", "CanParams", "MessageParams"]

#: The node's own outputs, which no DBC message may be named after.
NODE_OUTPUTS = frozenset({"unknown", "status", "frames"})

#: A bit rate in a graph file: 250000, 500k, 1e6, 2M (whole bit/s, 1k..20M).
BitRate = Annotated[int, BeforeValidator(bit_rate)]


class MessageParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    cycle_ms: float | None = Field(
        default=None, ge=0, description="period; overrides GenMsgCycleTime (0: event-driven)"
    )
    phase_ms: float | None = Field(default=None, ge=0, description="transmit offset in the cycle")
    timeout_ms: float | None = Field(
        default=None, gt=0, description="receive timeout (default timeout_factor x cycle)"
    )
    counter: str | None = Field(default=None, description="rolling counter signal")
    checksum: str | None = Field(default=None, description="checksum signal (one byte)")
    checksum_kind: Literal["xor", "sum", "crc8"] = "xor"


class CanParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    interface: str = Field(default="virtual", description="a python-can interface name")
    channel: str | None = Field(default=None, description="bus channel, e.g. can0, /dev/ttyACM0")
    bitrate: BitRate | None = Field(
        default=None, description="bit/s (250000, 500k, 1M), passed to the interface"
    )
    fd: bool = Field(default=False, description="open the bus for CAN FD and send FD messages so")
    bitrate_switch: bool = Field(
        default=True, description="FD frames with bit-rate switch (unless the DBC's CANFD_BRS=0)"
    )
    data_bitrate: BitRate | None = Field(
        default=None, description="CAN FD data-phase bit/s (2M), passed to the interface"
    )
    dbc: str = Field(
        description="CAN database: .dbc, .kcd, .arxml (beside the graph file, then flowrt.nodes)"
    )
    strict: bool = Field(
        default=False, description="refuse a DBC that cantools' strict loading refuses"
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="more keyword arguments for can.Bus"
    )
    messages: dict[str, MessageParams] = Field(default_factory=dict)
    receive: list[str] | None = Field(
        default=None,
        description="the messages to receive, supervise and let through the interface's "
        "filters (default: all, supervising those it does not send)",
    )
    timeout_factor: float = Field(default=10.0, gt=0, description="timeout in cycles")
    max_bad: int = Field(default=5, ge=1, description="bad frames before a message is invalid")
    unknown_output: bool = Field(default=False, description="publish unknown ids on 'unknown'")
    raw_output: bool = Field(
        default=False,
        description="publish every received frame on 'frames' (id, extended, fd, remote, dlc, "
        "data): a recording's raw CAN channel",
    )
    tick_ms: float | None = Field(default=None, gt=0, description="default: gcd of the cycles")
    reopen_ms: float = Field(default=100.0, gt=0, description="first reopen backoff")
    reopen_max_ms: float = Field(default=5000.0, gt=0, description="longest reopen backoff")
    status_ms: float = Field(default=1000.0, gt=0, description="status output period")
    status_record: bool = Field(
        default=True,
        description="also keep a bounded summary of the status (CanBusSummary) in the RTDB "
        "record '<node>.can'",
    )
    send_thread: bool | None = Field(
        default=None, description="write frames from a thread (default: serial interfaces)"
    )
    replay: str | None = Field(default=None, description="a trace to send at its timing")
    replay_loop: bool = Field(default=False, description="replay the trace over and over")
    trace: str | None = Field(
        default=None, description="log the bus to this file: .log (candump), .asc, .blf, .csv"
    )
    trace_max_bytes: int = Field(
        default=0, ge=0, description="rotate the trace at this size (0: one file)"
    )

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, v: str) -> str:
        from can.interfaces import BACKENDS

        if v not in BACKENDS:
            hint = did_you_mean(v, BACKENDS)
            known = "" if hint else f" (known: {', '.join(sorted(BACKENDS))})"
            raise ValueError(f"unknown python-can interface {v!r}{hint or known}")
        return v

    @field_validator("dbc")
    @classmethod
    def _parses(cls, v: str, info: ValidationInfo) -> str:
        """Beside the graph file (or the working directory), else shipped with flowrt.nodes."""
        near = resolve_path(v, info)
        if Path(near).is_file():
            v = near
        elif Path(v).is_absolute() or not (Path(__file__).resolve().parent.parent / v).is_file():
            raise ValueError(f"{v}: no such file (looked for {near} and in flowrt.nodes)")
        load_dbc(v)
        return v

    @field_validator("trace", "replay")
    @classmethod
    def _beside_the_graph(cls, v: str | None, info: ValidationInfo) -> str | None:
        return None if v is None else resolve_path(v, info)

    @field_validator("trace")
    @classmethod
    def _trace_format(cls, v: str | None) -> str | None:
        if v is not None and Path(v).suffix.lower() not in (".log", ".asc", ".blf", ".csv"):
            raise ValueError(f"trace {v!r}: give a .log, .asc, .blf or .csv file")
        return v

    @model_validator(mode="after")
    def _names(self) -> CanParams:
        db = load_dbc(self.dbc)
        if self.strict and dbc_warnings(self.dbc):
            raise ValueError(f"{self.dbc}: refused by strict loading: {dbc_warnings(self.dbc)[0]}")
        names = {m.name for m in db.messages}
        for name in [*self.messages, *(self.receive or [])]:
            if name not in names:
                raise ValueError(
                    f"{name!r} is not a message of {self.dbc}{did_you_mean(name, names)}"
                )
        clash = names & NODE_OUTPUTS
        if clash:
            raise ValueError(f"message names clash with the node's outputs: {sorted(clash)}")
        for name, opts in self.messages.items():
            _check_message_options(db.get_message_by_name(name), opts)
        if self.replay is not None and not Path(self.replay).is_file():
            raise ValueError(f"replay: {self.replay}: no such file")
        return self

    def cycle_ms(self, msg: Any) -> float | None:
        opts = self.messages.get(msg.name)
        if opts is not None and opts.cycle_ms is not None:
            return opts.cycle_ms or None
        return float(msg.cycle_time) if msg.cycle_time else None


def _check_message_options(msg: Any, opts: MessageParams) -> None:
    sigs = {s.name: s for s in msg.signals}
    for what in ("counter", "checksum"):
        sig = getattr(opts, what)
        if sig is not None and sig not in sigs:
            raise ValueError(f"{msg.name}: {what} signal {sig!r} is not in the message")
    if opts.checksum is not None:
        s = sigs[opts.checksum]
        aligned = s.start % 8 == (0 if s.byte_order == "little_endian" else 7)
        if s.length != 8 or not aligned:
            raise ValueError(f"{msg.name}: checksum {s.name!r} must be one whole byte")
