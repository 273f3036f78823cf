"""The ``can`` node: a CAN bus as ports, decoded and encoded with a DBC file, supervised.

Built on python-can (every interface it has: ``virtual``, ``socketcan``, ``slcan``, ``pcan``,
...) and cantools (DBC, KCD, ARXML: layouts, scaling, cycle times)::

    chassis:
      kind: can
      params:
        interface: virtual          # any python-can interface
        channel: robot
        bitrate: 250000
        dbc: robot.dbc              # looked up in the working directory, then in flowrt.nodes
        messages:                   # per-message options, all optional
          WheelSpeeds: {counter: Counter, checksum: Checksum, checksum_kind: xor}
          MotorSetpoints: {cycle_ms: 20, phase_ms: 5}
      inputs: {MotorSetpoints: control.setpoints}   # messages to transmit, by DBC name

Receive
    A reader thread (never the event loop) takes frames from the bus and hands them to the
    loop. Each frame whose id the DBC knows is decoded into physical values and published
    on the output named after the message, as a :class:`CanMessage` (signals, raw id/data,
    receive time on the runtime clock, ``valid``). Connect it to an ``rtdb`` node to keep it
    in the RTDB. Frames with other ids are counted (``unknown``) and, with
    ``unknown_output: true``, published raw on the ``unknown`` output (:class:`CanFrame`).
    A frame whose length differs from the DBC's is counted (``bad_length``), not decoded.

Transmit
    Every input named after a DBC message is encoded with the DBC from the latest value
    received on it (a mapping of signal values, or a :class:`CanMessage`; signals left out
    keep their last value, or the DBC's initial value). Messages with a cycle time
    (``GenMsgCycleTime``, or ``cycle_ms``) are sent by flowrt's own timer scheduler: the
    node's default trigger is a timer at the gcd of the cycle times (``tick_ms`` to change
    it), and each message goes out on the ticks of its cycle, offset by its phase (given as
    ``phase_ms``, else spread over the cycle by identifier so that messages of the same
    rate do not all queue on the same tick). Not python-can's ``send_periodic`` (one thread
    per message, whose wake-ups drift under load). Messages without a cycle time are sent
    once per new input value, on the next tick. A configured counter signal is incremented
    and a configured checksum computed on every send. A tick that runs past the node's
    ``deadline`` is a deadline miss like any other; a cycle skipped altogether (the tick
    came a whole cycle late) is counted (``late``). On serial interfaces (``slcan`` and the
    like, where a write waits for the wire) frames are written by a sender thread.

Supervision (as opendbc does for cars)
    - A periodic message not received within ``timeout_factor`` (10) times its cycle (or its
      ``timeout_ms``) is republished with ``valid: false`` and ``reason: timeout`` and a
      ``HealthAlert`` is raised; it is valid again with the next good frame. Messages this
      node transmits are not supervised. ``receive`` names the messages the node receives
      at all: only those are supervised, and acceptance filters keep the others out (in
      the adapter where it has them, else in python-can's reader), as an ECU filters.
    - With a ``counter`` signal, a counter that is not the previous one plus one (skipped or
      repeated) is counted; with a ``checksum`` signal (one byte; ``xor``, ``sum`` or
      SAE J1850 ``crc8`` over the other bytes), a mismatch is counted. Each bad frame adds
      one to a failure count, each good one takes one off; at ``max_bad`` (5) the message is
      invalid until good frames bring the count back down.
    - Error frames are counted, bus-off error frames too (SocketCAN's CAN_ERR_BUSOFF), and
      bus-off reopens the interface. An interface that fails (an unplugged adapter, a closed
      serial port) is counted, the node enters the error state (``ctx.set_error``: red in the
      table, a HealthAlert) and reopens it with exponential backoff (``reopen_ms`` up to
      ``reopen_max_ms``), in a thread: opening an adapter may take seconds. Nothing raises.

Replay
    ``replay: trace.asc`` (any format python-can reads) sends the frames of a trace onto the
    bus at their recorded timing (to the resolution of the tick), once or ``replay_loop``.

Every ``status_ms`` the node publishes a :class:`CanBusStatus` on ``status``: per message
received/sent, rate, age, timeouts, bad counters/checksums/lengths, late sends, validity;
it is also kept in the RTDB record ``<node>.can`` (``flowrt ctl rtdb chassis.can`` while
the graph runs with ``--control``).
The DBC is loaded when the graph is validated: a file that does not parse is one error line.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import os
import queue
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from flowrt import HealthAlert, Input, Node, Output, TimerTrigger

__all__ = [
    "Can",
    "CanBusStatus",
    "CanFrame",
    "CanMessage",
    "CanParams",
    "MessageStatus",
    "SignalSource",
]

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x40  # SocketCAN error class bit in an error frame's id (linux/can/error.h)
_SERIAL_INTERFACES = {"slcan", "serial", "robotell", "seeedstudio", "cantact", "gs_usb"}


# --- values on the ports -------------------------------------------------------------------


@dataclass(frozen=True)
class CanMessage:
    """A decoded message: physical signal values plus the raw frame and its validity."""

    name: str
    id: int
    signals: dict[str, Any]
    data: bytes
    timestamp: float  # runtime clock (s) when the frame reached the loop: RTDB-comparable
    valid: bool = True
    reason: str = ""  # why not valid: timeout, counter, checksum
    bus_timestamp: float = 0.0  # the interface's own timestamp

    def __getitem__(self, signal: str) -> Any:
        return self.signals[signal]


@dataclass(frozen=True)
class CanFrame:
    """A raw frame (an id the DBC does not know)."""

    id: int
    data: bytes
    extended: bool
    timestamp: float
    bus_timestamp: float = 0.0


@dataclass(frozen=True)
class MessageStatus:
    name: str
    id: int
    received: int
    sent: int
    rate_hz: float  # over the last status interval (received + sent)
    age_ms: float | None  # since the last frame received
    timeouts: int
    bad_counter: int
    bad_checksum: int
    bad_length: int
    late: int
    bad_inputs: int  # input values that did not fit the message (not sent)
    valid: bool


@dataclass(frozen=True)
class CanBusStatus:
    t: float  # seconds since the runtime started
    interface: str
    channel: str | None
    open: bool
    received: int
    sent: int
    unknown: int
    error_frames: int
    bus_off: int
    interface_lost: int
    reopens: int
    send_errors: int
    decode_errors: int
    messages: tuple[MessageStatus, ...]


# --- params ----------------------------------------------------------------------------------


def _dbc_path(path: str) -> Path:
    p = Path(path)
    if p.is_file():
        return p
    shipped = Path(__file__).resolve().parent / path
    if not p.is_absolute() and shipped.is_file():
        return shipped
    raise ValueError(f"{path}: no such file (looked in {os.getcwd()} and the flowrt.nodes package)")


@functools.lru_cache(maxsize=16)
def _load(path: str, mtime_ns: int) -> Any:
    import cantools

    try:
        return cantools.database.load_file(path, strict=True)
    except Exception as e:  # cantools raises parser, value and key errors of several kinds
        text = " ".join(str(e).split()) or type(e).__name__
        raise ValueError(f"{path}: not a valid CAN database: {text}") from None


def load_dbc(path: str) -> Any:
    """The cantools database of ``path`` (cached while the file is unchanged)."""
    p = _dbc_path(path)
    return _load(str(p), p.stat().st_mtime_ns)


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
    bitrate: int | None = Field(default=None, gt=0, description="bit/s, passed to the interface")
    dbc: str = Field(description="CAN database: .dbc, .kcd, .arxml (cwd, then flowrt.nodes)")
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
    tick_ms: float | None = Field(default=None, gt=0, description="default: gcd of the cycles")
    reopen_ms: float = Field(default=100.0, gt=0, description="first reopen backoff")
    reopen_max_ms: float = Field(default=5000.0, gt=0)
    status_ms: float = Field(default=1000.0, gt=0, description="status output period")
    status_record: bool = Field(
        default=True, description="also keep the status in the RTDB record '<node>.can'"
    )
    send_thread: bool | None = Field(
        default=None, description="write frames from a thread (default: serial interfaces)"
    )
    replay: str | None = Field(default=None, description="a trace to send at its timing")
    replay_loop: bool = False

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, v: str) -> str:
        from can.interfaces import BACKENDS

        if v not in BACKENDS:
            raise ValueError(
                f"unknown python-can interface {v!r} (known: {', '.join(sorted(BACKENDS))})"
            )
        return v

    @field_validator("dbc")
    @classmethod
    def _parses(cls, v: str) -> str:
        load_dbc(v)
        return v

    @model_validator(mode="after")
    def _names(self) -> CanParams:
        db = load_dbc(self.dbc)
        names = {m.name for m in db.messages}
        for name in [*self.messages, *(self.receive or [])]:
            if name not in names:
                raise ValueError(f"{name!r} is not a message of {self.dbc}")
        clash = names & set(Can.outputs)
        if clash:
            raise ValueError(f"message names clash with the node's outputs: {sorted(clash)}")
        for name, opts in self.messages.items():
            msg = db.get_message_by_name(name)
            sigs = {s.name: s for s in msg.signals}
            for what in ("counter", "checksum"):
                sig = getattr(opts, what)
                if sig is not None and sig not in sigs:
                    raise ValueError(f"{name}: {what} signal {sig!r} is not in the message")
            if opts.checksum is not None:
                s = sigs[opts.checksum]
                aligned = s.start % 8 == (0 if s.byte_order == "little_endian" else 7)
                if s.length != 8 or not aligned:
                    raise ValueError(f"{name}: checksum {s.name!r} must be one whole byte")
        if self.replay is not None and not Path(self.replay).is_file():
            raise ValueError(f"replay: {self.replay}: no such file")
        return self

    def cycle_ms(self, msg: Any) -> float | None:
        opts = self.messages.get(msg.name)
        if opts is not None and opts.cycle_ms is not None:
            return opts.cycle_ms or None
        return float(msg.cycle_time) if msg.cycle_time else None


def _gcd_ms(values: list[float]) -> float:
    """gcd of durations in ms, at 0.1 ms resolution, at least 1 ms."""
    g = Fraction(0)
    for v in values:
        f = Fraction(round(v * 10), 10)
        g = (
            Fraction(
                math.gcd(g.numerator * f.denominator, f.numerator * g.denominator),
                g.denominator * f.denominator,
            )
            if g
            else f
        )
    return max(float(g), 1.0) if g else 100.0


# --- checksums (what the vehicles use; python-can and cantools compute none) -----------------


def _crc8_j1850(data: bytes) -> int:
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def checksum(kind: str, data: bytes, skip: int) -> int:
    """Checksum of ``data`` without its byte ``skip`` (where the checksum itself goes)."""
    rest = bytes(b for i, b in enumerate(data) if i != skip)
    if kind == "xor":
        x = 0
        for b in rest:
            x ^= b
        return x
    if kind == "sum":
        return sum(rest) & 0xFF
    return _crc8_j1850(rest)


# --- per-message state -----------------------------------------------------------------------


@dataclass
class _Msg:
    dbc: Any  # cantools Message
    cycle: float | None  # ms
    opts: MessageParams
    timeout: float | None = None  # s
    # receive
    received: int = 0
    last_rx: float | None = None
    last: CanMessage | None = None
    timed_out: bool = False
    fail: int = 0
    last_counter: int | None = None
    bad_counter: int = 0
    bad_checksum: int = 0
    bad_length: int = 0
    timeouts: int = 0
    # transmit
    tx: bool = False
    value: dict[str, Any] = field(default_factory=dict)
    have_value: bool = False
    fresh: bool = False
    due: float = 0.0  # seconds since start
    counter: int = 0
    sent: int = 0
    late: int = 0
    bad_inputs: int = 0
    window: int = 0  # frames since the last status

    @property
    def checksum_byte(self) -> int | None:
        if self.opts.checksum is None:
            return None
        return int(self.dbc.get_signal_by_name(self.opts.checksum).start // 8)


# --- the node ---------------------------------------------------------------------------------


class Can(Node):
    """A CAN bus: decoded messages out, messages to encode in (see the module docstring)."""

    Params = CanParams
    inline_only = True  # its reader thread hands frames to the event loop

    unknown = Output(CanFrame, doc="frames with ids the DBC does not know (unknown_output)")
    status = Output(CanBusStatus, doc="per-message and bus counters every status_ms")

    @classmethod
    def params_inputs(cls, params: Any) -> Mapping[str, Input[Any]]:
        db = load_dbc(params.dbc)
        return {m.name: Input(object, required=False, doc="signals to send") for m in db.messages}

    @classmethod
    def params_outputs(cls, params: Any) -> Mapping[str, Output[Any]]:
        db = load_dbc(params.dbc)
        return {m.name: Output(CanMessage, doc=f"decoded 0x{m.frame_id:X}") for m in db.messages}

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        if params.tick_ms is not None:
            return TimerTrigger(timer=params.tick_ms)
        db = load_dbc(params.dbc)
        times: list[float] = []
        for m in db.messages:
            c = params.cycle_ms(m)
            if c:
                times.append(c)
                opts = params.messages.get(m.name)
                if opts is not None and opts.phase_ms:
                    times.append(opts.phase_ms)
        return TimerTrigger(timer=_gcd_ms(times) if times else 100.0)

    # --- lifecycle ---------------------------------------------------------------------------

    async def setup(self) -> None:
        p: CanParams = self.params
        self.loop = asyncio.get_running_loop()
        self.db = load_dbc(p.dbc)
        self.msgs: dict[str, _Msg] = {}
        self.by_id: dict[tuple[int, bool], _Msg] = {}
        for m in self.db.messages:
            opts = p.messages.get(m.name, MessageParams())
            st = _Msg(m, p.cycle_ms(m), opts)
            if opts.timeout_ms is not None:
                st.timeout = opts.timeout_ms / 1000
            elif st.cycle:
                st.timeout = p.timeout_factor * st.cycle / 1000
            self.msgs[m.name] = st
            self.by_id[(int(m.frame_id), bool(m.is_extended_frame))] = st
        self.tick = self.default_trigger(p).timer / 1000
        self.started = False  # the first tick decides what this node sends
        self.received = self.sent = self.unknown_count = self.error_frames = 0
        self.bus_off = self.lost = self.reopens = self.send_errors = self.decode_errors = 0
        self.bus: Any = None
        self.gen = 0  # bumped at every close: a reader of an old bus stops
        self.opens = 0
        self.closed = False
        self.opening: asyncio.Future[Any] | None = None
        self.backoff = p.reopen_ms / 1000
        self.reopen_at = 0.0
        self.threads: list[threading.Thread] = []
        self.txq: queue.SimpleQueue[Any] | None = None
        self.last_status = 0.0
        self.keep_status = p.status_record
        self.replay_iter: Iterator[Any] | None = None
        self.replay_t0 = 0.0
        self.replay_next: Any = None
        self.use_send_thread = (
            p.send_thread if p.send_thread is not None else p.interface in _SERIAL_INTERFACES
        )
        self._open()

    async def teardown(self) -> None:
        self.closed = True
        self._close()
        threads, self.threads = self.threads, []
        for t in threads:
            await asyncio.to_thread(t.join, 2.0)

    # --- the bus -----------------------------------------------------------------------------

    def _open(self) -> None:
        """Open the interface in a thread (an adapter may take seconds); never raises."""
        if self.opening is not None or self.bus is not None:
            return
        p: CanParams = self.params
        kwargs: dict[str, Any] = dict(p.options)
        if p.channel is not None:
            kwargs["channel"] = p.channel
        if p.bitrate is not None:
            kwargs["bitrate"] = p.bitrate
        if p.receive is not None and "can_filters" not in kwargs:
            kwargs["can_filters"] = self._filters(p.receive)

        def open_bus() -> Any:
            import can

            return can.Bus(interface=p.interface, **kwargs)

        self.opening = self.loop.run_in_executor(None, open_bus)
        self.opening.add_done_callback(self._opened)

    def _opened(self, fut: asyncio.Future[Any]) -> None:
        self.opening = None
        if fut.cancelled():
            return
        exc = fut.exception()
        if exc is not None:
            self._failed_open(exc)
            return
        bus = fut.result()
        if self.closed:
            bus.shutdown()
            return
        self.bus = bus
        self.gen += 1
        gen = self.gen
        if self.opens:
            self.reopens += 1
            self.ctx.log.info("%s: CAN interface reopened", self.ctx.name)
        self.opens += 1
        self.backoff = self.params.reopen_ms / 1000
        self.ctx.clear_error()
        reader = threading.Thread(
            target=self._reader, args=(bus, gen), name=f"can-rx {self.ctx.name}", daemon=True
        )
        self.threads = [t for t in self.threads if t.is_alive()]
        self.threads.append(reader)
        reader.start()
        if self.use_send_thread:
            self.txq = queue.SimpleQueue()
            writer = threading.Thread(
                target=self._writer,
                args=(bus, gen, self.txq),
                name=f"can-tx {self.ctx.name}",
                daemon=True,
            )
            self.threads.append(writer)
            writer.start()

    def _filters(self, names: list[str]) -> list[dict[str, Any]]:
        """Acceptance filters for the messages this node receives (in the adapter where it
        has them, else in python-can before the frame reaches this node)."""
        out = []
        for name in names:
            m = self.db.get_message_by_name(name)
            ext = bool(m.is_extended_frame)
            out.append(
                {"can_id": m.frame_id, "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext}
            )
        # none at all: a filter no frame matches (an empty list would accept everything)
        return out or [{"can_id": 0, "can_mask": 0x1FFFFFFF, "extended": True}]

    def _failed_open(self, exc: BaseException) -> None:
        p: CanParams = self.params
        where = f"{p.interface}:{p.channel}" if p.channel else p.interface
        self.ctx.set_error(f"CAN interface {where} cannot open: {_one_line(exc)}")
        self.reopen_at = self.loop.time() + self.backoff
        self.backoff = min(self.backoff * 2, p.reopen_max_ms / 1000)

    def _close(self) -> None:
        """Let go of the bus: its threads see the generation change and shut it down."""
        self.gen += 1
        self.bus = None
        if self.txq is not None:
            self.txq.put(None)
            self.txq = None

    def _reader(self, bus: Any, gen: int) -> None:
        call = self.loop.call_soon_threadsafe
        try:
            while self.gen == gen:
                try:
                    msg = bus.recv(0.05)
                except Exception as exc:
                    if self.gen == gen:
                        call(self._lost, gen, exc)
                    return
                if msg is not None and self.gen == gen:
                    call(self._on_frame, msg)
        except RuntimeError:  # the loop closed under us at shutdown
            return
        finally:
            try:
                bus.shutdown()
            except Exception as exc:  # an adapter already gone
                log.debug("CAN bus shutdown: %s", exc)

    def _writer(self, bus: Any, gen: int, q: queue.SimpleQueue[Any]) -> None:
        while True:
            msg = q.get()
            if msg is None or self.gen != gen:
                return
            try:
                bus.send(msg)
            except Exception as exc:
                try:
                    self.loop.call_soon_threadsafe(self._send_failed, gen, exc)
                except RuntimeError:
                    return

    def _lost(self, gen: int, exc: BaseException) -> None:
        if gen != self.gen or self.bus is None:
            return
        p: CanParams = self.params
        self.lost += 1
        where = f"{p.interface}:{p.channel}" if p.channel else p.interface
        self.ctx.set_error(f"CAN interface {where} lost: {_one_line(exc)}")
        self._close()
        self.reopen_at = self.loop.time() + self.backoff
        self.backoff = min(self.backoff * 2, p.reopen_max_ms / 1000)

    def _send_failed(self, gen: int, exc: BaseException) -> None:
        self.send_errors += 1
        if isinstance(exc, OSError) or "serial" in type(exc).__module__:
            self._lost(gen, exc)
        elif self.send_errors == 1 or self.send_errors % 1000 == 0:
            self.ctx.log.warning(
                "%s: CAN send failed (%d): %s", self.ctx.name, self.send_errors, _one_line(exc)
            )

    # --- receive -----------------------------------------------------------------------------

    def _on_frame(self, frame: Any) -> None:
        if self.bus is None:
            return
        now = self.ctx.now()
        if frame.is_error_frame:
            self.error_frames += 1
            if frame.arbitration_id & CAN_ERR_BUSOFF:
                self.bus_off += 1
                self._lost(self.gen, OSError("bus-off"))
            return
        self.received += 1
        key = (int(frame.arbitration_id), bool(frame.is_extended_id))
        st = self.by_id.get(key)
        data = bytes(frame.data)
        if st is None:
            self.unknown_count += 1
            if self.params.unknown_output:
                self.ctx.publish(
                    "unknown", CanFrame(key[0], data, key[1], now, float(frame.timestamp))
                )
            return
        st.received += 1
        st.window += 1
        if len(data) != st.dbc.length:
            st.bad_length += 1
            self._bad(st)
            return
        try:
            signals = st.dbc.decode(data, decode_choices=False)
        except Exception:
            self.decode_errors += 1
            self._bad(st)
            return
        reason = self._integrity(st, signals, data)
        if reason:
            self._bad(st)
        else:
            st.fail = max(st.fail - 1, 0)
        st.last_rx = now
        st.timed_out = False
        valid = st.fail < self.params.max_bad
        out = CanMessage(
            st.dbc.name,
            key[0],
            dict(signals),
            data,
            now,
            valid,
            "" if valid else reason,
            float(frame.timestamp),
        )
        st.last = out
        self.ctx.publish(st.dbc.name, out)

    def _bad(self, st: _Msg) -> None:
        st.fail = min(st.fail + 1, self.params.max_bad)

    def _integrity(self, st: _Msg, signals: Mapping[str, Any], data: bytes) -> str:
        reason = ""
        opts = st.opts
        if opts.counter is not None:
            sig = st.dbc.get_signal_by_name(opts.counter)
            raw = round((signals[opts.counter] - sig.offset) / sig.scale)
            if st.last_counter is not None and raw != (st.last_counter + 1) % (1 << sig.length):
                st.bad_counter += 1
                reason = "counter"
            st.last_counter = raw
        idx = st.checksum_byte
        if idx is not None and checksum(opts.checksum_kind, data, idx) != data[idx]:
            st.bad_checksum += 1
            reason = "checksum"
        return reason

    # --- the tick: transmit, supervise, reopen, report --------------------------------------

    def process(self, **inputs: Any) -> None:
        if not self.started:
            self._start(inputs)
        now = self.ctx.now()
        t = self.ctx.elapsed()
        for name, value in inputs.items():
            if value is not None:
                self._take(self.msgs[name], value)
        if self.bus is not None:
            half = min(self.tick / 2, 0.0005)  # timer releases are never early
            for st in self.txs:
                if not st.have_value:  # nothing to send yet: keep to the cycle's grid
                    while st.cycle and st.due <= t + half:
                        st.due += st.cycle / 1000
                    continue
                if st.cycle:
                    if t + half < st.due:
                        continue
                    self._send(st)
                    st.due += st.cycle / 1000
                    while st.due <= t - half:  # cycles that could not go out: say so
                        st.due += st.cycle / 1000
                        st.late += 1
                elif st.fresh:
                    self._send(st)
                    st.fresh = False
            if self.replay_iter is not None:
                self._replay(t)
        elif self.opening is None and self.loop.time() >= self.reopen_at:
            self._open()
        self._supervise(now)
        if t - self.last_status >= self.params.status_ms / 1000:
            self.last_status = t
            status = self.snapshot()
            self.ctx.publish("status", status)
            if self.keep_status:
                self._record_status(status)

    def _record_status(self, status: CanBusStatus) -> None:
        """Keep the status in the RTDB (``<node>.can``): ``flowrt ctl rtdb chassis.can``
        shows it while the graph runs."""
        try:
            db = self.ctx.rtdb
        except RuntimeError:  # no RTDB (outside a Runtime): nothing to keep it in
            self.keep_status = False
            return
        db.write(f"{self.ctx.name}.can", status, validity_ms=3 * self.params.status_ms)

    def _start(self, inputs: Mapping[str, Any]) -> None:
        self.started = True
        p: CanParams = self.params
        t = self.ctx.elapsed()
        txs = sorted((self.msgs[n] for n in inputs), key=lambda s: s.dbc.frame_id)
        for i, st in enumerate(txs):
            st.tx = True
            if st.cycle:
                phase = st.opts.phase_ms
                if phase is None:  # spread same-rate messages over the ticks of the cycle
                    phase = (i * self.tick * 1000) % st.cycle
                k = math.ceil((t - phase / 1000) / (st.cycle / 1000) - 1e-9)
                st.due = phase / 1000 + max(k, 0) * st.cycle / 1000
        self.txs = txs
        watched = set(p.receive) if p.receive is not None else None
        self.rxs = [
            st
            for st in self.msgs.values()
            if st.timeout is not None and (not st.tx if watched is None else st.dbc.name in watched)
        ]
        self.supervise_from = self.ctx.now()
        if p.replay is not None:
            self._open_replay()

    def _take(self, st: _Msg, value: Any) -> None:
        """Keep an input value for sending; a value that does not fit the message is counted
        (``bad_inputs``) and logged, not raised: one bad producer must not stop the bus."""
        signals = value.signals if isinstance(value, CanMessage) else value
        problem = ""
        if not isinstance(signals, Mapping):
            problem = f"expected a mapping of signal values, got {type(value).__name__}"
        else:
            names = {s.name for s in st.dbc.signals}
            unknown = sorted(set(signals) - names)
            if unknown:
                problem = f"no signal {', '.join(map(repr, unknown))}"
        if problem:
            st.bad_inputs += 1
            if st.bad_inputs == 1 or st.bad_inputs % 1000 == 0:
                self.ctx.log.warning(
                    "%s: input %s (%d so far): %s",
                    self.ctx.name,
                    st.dbc.name,
                    st.bad_inputs,
                    problem,
                )
            return
        if not st.have_value:
            st.value = {s.name: (s.initial if s.initial is not None else 0) for s in st.dbc.signals}
        st.value.update(signals)
        st.have_value = True
        st.fresh = True

    def _send(self, st: _Msg) -> None:
        import can

        opts = st.opts
        values = st.value
        if opts.counter is not None:
            sig = st.dbc.get_signal_by_name(opts.counter)
            values = {**values, opts.counter: st.counter * sig.scale + sig.offset}
            st.counter = (st.counter + 1) % (1 << sig.length)
        if opts.checksum is not None:
            values = {**values, opts.checksum: 0}
        try:
            data = bytearray(st.dbc.encode(values, strict=True))
        except Exception as e:
            self.send_errors += 1
            self.ctx.log.warning("%s: cannot encode %s: %s", self.ctx.name, st.dbc.name, e)
            return
        idx = st.checksum_byte
        if idx is not None:
            data[idx] = checksum(opts.checksum_kind, bytes(data), idx)
        msg = can.Message(
            arbitration_id=st.dbc.frame_id, data=data, is_extended_id=st.dbc.is_extended_frame
        )
        if self._put(msg):
            st.sent += 1
            st.window += 1

    def _put(self, msg: Any) -> bool:
        if self.txq is not None:
            self.txq.put(msg)
        else:
            try:
                self.bus.send(msg)
            except Exception as exc:
                self._send_failed(self.gen, exc)
                return False
        self.sent += 1
        return True

    def _supervise(self, now: float) -> None:
        for st in self.rxs:
            assert st.timeout is not None
            since = st.last_rx if st.last_rx is not None else self.supervise_from
            if st.timed_out or now - since <= st.timeout:
                continue
            st.timed_out = True
            st.timeouts += 1
            st.last_counter = None
            detail = (
                f"{st.dbc.name} (0x{st.dbc.frame_id:X}) not received for "
                f"{(now - since) * 1000:.0f} ms (timeout {st.timeout * 1000:g} ms)"
            )
            self.ctx.emit(HealthAlert(self.ctx.elapsed(), self.ctx.name, "can-timeout", detail))
            last = st.last
            self.ctx.publish(
                st.dbc.name,
                CanMessage(
                    st.dbc.name,
                    int(st.dbc.frame_id),
                    dict(last.signals) if last else {},
                    last.data if last else b"",
                    last.timestamp if last else 0.0,
                    False,
                    "timeout",
                    last.bus_timestamp if last else 0.0,
                ),
            )

    # --- replay ------------------------------------------------------------------------------

    def _open_replay(self) -> None:
        import can

        self.replay_iter = iter(can.LogReader(self.params.replay))
        self.replay_t0 = self.ctx.elapsed()
        self.replay_first: float | None = None
        self.replay_next = next(self.replay_iter, None)

    def _replay(self, t: float) -> None:
        while self.replay_next is not None:
            msg = self.replay_next
            if self.replay_first is None:
                self.replay_first = float(msg.timestamp)
            if float(msg.timestamp) - self.replay_first > t - self.replay_t0 + self.tick / 2:
                return
            if not msg.is_error_frame:
                import can

                self._put(
                    can.Message(
                        arbitration_id=msg.arbitration_id,
                        data=msg.data,
                        is_extended_id=msg.is_extended_id,
                    )
                )
            self.replay_next = next(self.replay_iter, None)
        if self.params.replay_loop:
            self._open_replay()
        else:
            self.replay_iter = None

    # --- statistics --------------------------------------------------------------------------

    def snapshot(self) -> CanBusStatus:
        """The bus and per-message counters now (also published on ``status``)."""
        now = self.ctx.now()
        t = self.ctx.elapsed()
        span = max(t - getattr(self, "last_snapshot", 0.0), 1e-9)
        self.last_snapshot = t
        rows = []
        for st in self.msgs.values():
            rows.append(
                MessageStatus(
                    st.dbc.name,
                    int(st.dbc.frame_id),
                    st.received,
                    st.sent,
                    st.window / span,
                    None if st.last_rx is None else (now - st.last_rx) * 1000,
                    st.timeouts,
                    st.bad_counter,
                    st.bad_checksum,
                    st.bad_length,
                    st.late,
                    st.bad_inputs,
                    not st.timed_out and st.fail < self.params.max_bad,
                )
            )
            st.window = 0
        p: CanParams = self.params
        return CanBusStatus(
            t,
            p.interface,
            p.channel,
            self.bus is not None,
            self.received,
            self.sent,
            self.unknown_count,
            self.error_frames,
            self.bus_off,
            self.lost,
            self.reopens,
            self.send_errors,
            self.decode_errors,
            tuple(rows),
        )


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# --- a signal source, for examples, tests and benchmarks ----------------------------------


class Wave(BaseModel):
    model_config = ConfigDict(extra="forbid")
    wave: Literal["const", "sine", "ramp", "count"] = "const"
    value: float = Field(default=0.0, description="const value, or the offset of the others")
    amplitude: float = 1.0
    period_s: float = Field(default=1.0, gt=0)
    modulo: int = Field(default=256, ge=1, description="count wraps here")


class SignalSourceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    signals: dict[str, Wave] = Field(description="signal name -> waveform")
    rate_ms: float = Field(default=100.0, gt=0, description="default timer trigger")


class SignalSource(Node):
    """Signal values for a ``can`` node input, from simple waveforms (a simulated sensor).

    Outputs a mapping ``{signal: value}`` per activation (default trigger: ``rate_ms``):
    ``const`` value, ``sine``/``ramp`` of ``amplitude`` and ``period_s`` around ``value``, or
    ``count`` (0, 1, 2, ... modulo ``modulo``), with the runtime clock as time base.
    """

    Params = SignalSourceParams
    values = Output(dict, doc="signal name -> value")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        return TimerTrigger(timer=params.rate_ms)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> dict[str, float]:
        t = self.ctx.elapsed()
        out: dict[str, float] = {}
        for name, w in self.params.signals.items():
            if w.wave == "const":
                out[name] = w.value
            elif w.wave == "sine":
                out[name] = w.value + w.amplitude * math.sin(2 * math.pi * t / w.period_s)
            elif w.wave == "ramp":
                out[name] = w.value + w.amplitude * ((t / w.period_s) % 1.0)
            else:
                out[name] = float(self.n % w.modulo)
        self.n += 1
        return out
