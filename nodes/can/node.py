"""The ``can`` node: a CAN bus as ports, decoded and encoded with a DBC file, supervised.

Built on python-can (every interface it has: ``virtual``, ``socketcan``, ``slcan``, ``pcan``,
...) and cantools (DBC, KCD, ARXML: layouts, scaling, cycle times)::

    chassis:
      kind: can
      params:
        interface: virtual          # any python-can interface
        channel: robot
        bitrate: 250000
        dbc: robot.dbc              # beside the graph file, then shipped with flowrt.nodes
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
    A message cantools cannot unpack whole (overlapping signals, as in GM's databases) is
    decoded signal by signal, each as cantools decodes it alone.

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
      ``HealthAlert`` is raised (one for the tick when more than 3 time out together); it
      is valid again with the next good frame. Messages this node transmits are not
      supervised. ``receive`` names the messages the node receives
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

CAN FD
    With ``fd: true`` the interface is opened for CAN FD (python-can's ``fd`` option; give
    ``data_bitrate`` for a real adapter) and the DBC's FD messages (``VFrameFormat``, or more
    than 8 bytes) go out as FD frames, with bit-rate switch unless ``bitrate_switch: false``
    or the DBC's ``CANFD_BRS`` is 0, padded to the next FD length. Received FD frames decode
    alike. An FD message on a node without ``fd: true`` is an encode error (not sent).

Multiplexed messages
    Only the multiplexer and the signals of the branch its value selects are encoded (the
    others keep their values for when their branch is selected again); receiving decodes
    the branch the frame carries. A signal set that cannot be encoded (a value out of range,
    a multiplexer value with no branch) is not sent: counted per message
    (``encode_errors``) and per cause, and reported once per cause (a warning and a
    ``can-encode`` HealthAlert), not once per tick.

Trace
    ``trace: run.blf`` logs every frame of the bus (received and sent) with python-can's
    writers, by suffix: candump ``.log``, ``.asc``, ``.blf``, ``.csv``; ``trace_max_bytes``
    rotates it by size (python-can's ``SizedRotatingLogger``). A thread writes it; frames it
    could not keep up with are counted (``trace_dropped``). ``flowrt can stats run.blf``
    reads it back.

Replay
    ``replay: trace.asc`` (any format python-can reads) sends the frames of a trace onto the
    bus at their recorded timing (to the resolution of the tick), once or ``replay_loop``,
    as they were: FD, bit-rate switch, remote and error frames kept.

Every ``status_ms`` the node publishes a :class:`CanBusStatus` on ``status``: per message
received/sent, rate, age, timeouts, bad counters/checksums/lengths, late sends, validity.
Its bounded summary (:class:`CanBusSummary`: the bus counters, totals over the messages,
how many are invalid and the first few names; the same size for 3 messages or 3000) is kept
in the RTDB record ``<node>.can`` (``flowrt ctl rtdb chassis.can`` while the graph runs
with ``--control``).
The DBC is loaded when the graph is validated: a file that does not parse is one error line;
what cantools' strict loading would refuse is a named warning, once (``strict: true``
refuses). The wire is :mod:`flowrt.nodes.can.bus`, the params :mod:`flowrt.nodes.can.params`,
the DBC handling :mod:`flowrt.nodes.can.dbc`, the port values :mod:`flowrt.nodes.can.values`.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from fractions import Fraction
from typing import Any

from flowrt import HealthAlert, Input, Node, Output, TimerTrigger

from .bus import SERIAL_INTERFACES, CanLink, TraceLog, TraceReplay, one_line
from .dbc import (
    EncodeProblem,
    SignalDecoder,
    acceptance_filters,
    checksum,
    load_dbc,
    message_brs,
    message_is_fd,
)
from .params import CanParams, MessageParams
from .signals import SignalSource, Wave
from .state import MessageState as _Msg
from .transmit import encode, take
from .values import CanBusStatus, CanBusSummary, CanFrame, CanMessage, MessageStatus, summarise

__all__ = [
    "Can",
    "CanBusStatus",
    "CanBusSummary",
    "CanFrame",
    "CanMessage",
    "CanParams",
    "MessageStatus",
    "SignalSource",
    "Wave",
    "checksum",
    "load_dbc",
]

CAN_ERR_BUSOFF = 0x40  # SocketCAN error class bit in an error frame's id (linux/can/error.h)
#: Timeout alerts a tick raises one by one; more messages timing out together are one alert.
ALERTS_PER_TICK = 3


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


# --- the node ---------------------------------------------------------------------------------


class Can(Node):
    """A CAN bus: decoded messages out, messages to encode in (see the module docstring)."""

    swappable = frozenset({"timeout_factor", "max_bad"})  # over the control endpoint: flowrt kinds

    Params = CanParams
    inline_only = True  # its reader thread hands frames to the event loop
    external = True  # received frames are recorded inputs: replay publishes them, sends nothing

    unknown = Output(
        CanFrame, doc="frames with ids the DBC does not know (unknown_output)", rate_hz=None
    )
    frames = Output(CanFrame, doc="every received frame, raw (raw_output)", rate_hz=None)
    status = Output(CanBusStatus, doc="per-message and bus counters every status_ms")

    @classmethod
    def params_inputs(cls, params: Any) -> Mapping[str, Input[Any]]:
        db = load_dbc(params.dbc)
        return {m.name: Input(object, required=False, doc="signals to send") for m in db.messages}

    @classmethod
    def params_outputs(cls, params: Any) -> Mapping[str, Output[Any]]:
        """One per DBC message, expected at its cycle time; an event message (no cycle) or
        one the ``receive`` filter keeps out has no rate: nothing of it is "missing"."""
        db = load_dbc(params.dbc)
        kept = None if params.receive is None else set(params.receive)
        out: dict[str, Output[Any]] = {}
        for m in db.messages:
            cycle = params.cycle_ms(m)
            hz = 1000.0 / cycle if cycle and (kept is None or m.name in kept) else None
            out[m.name] = Output(CanMessage, doc=f"decoded 0x{m.frame_id:X}", rate_hz=hz)
        return out

    @classmethod
    def output_rates(cls, params: Any) -> Mapping[str, float | None]:
        """Each message at its cycle, ``status`` every ``status_ms``, raw frames on events."""
        return {**super().output_rates(params), "status": 1000.0 / params.status_ms}

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
            fd = message_is_fd(m)
            st = _Msg(m, p.cycle_ms(m), opts, fd=fd, brs=fd and p.bitrate_switch and message_brs(m))
            if opts.timeout_ms is not None:
                st.timeout = opts.timeout_ms / 1000
            elif st.cycle:
                st.timeout = p.timeout_factor * st.cycle / 1000
            self.msgs[m.name] = st
            self.by_id[(int(m.frame_id), bool(m.is_extended_frame))] = st
        self.tick = self.default_trigger(p).timer / 1000
        self.started = False  # the first tick decides what this node sends
        self.received = self.sent = self.unknown_count = self.error_frames = 0
        self.bus_off = self.decode_errors = 0
        self.channels: dict[str, int] = {}  # channel -> frames received
        self.unknown_by_channel: dict[str, int] = {}
        self.id_counts: dict[tuple[str, int, bool], int] = {}
        self.encode_causes: dict[tuple[str, str], int] = {}
        self.last_status = 0.0
        self.rtdb: Any = _status_rtdb(self.ctx) if p.status_record else None
        self.keep_status = self.rtdb is not None
        self.replay: TraceReplay | None = None
        self.trace_error = ""
        trace = None
        if p.trace is not None:
            try:
                trace = await asyncio.to_thread(TraceLog, p.trace, p.trace_max_bytes)
            except (OSError, ValueError) as e:  # a folder it cannot write: the bus runs anyway
                self.trace_error = f"CAN trace {p.trace} cannot open: {one_line(e)}"
                self.ctx.log.error("%s: %s", self.ctx.name, self.trace_error)
        self.link = CanLink(
            self.loop,
            self.ctx.name,
            p.interface,
            _bus_kwargs(p, self.db),
            send_thread=(
                p.send_thread if p.send_thread is not None else p.interface in SERIAL_INTERFACES
            ),
            reopen_s=p.reopen_ms / 1000,
            reopen_max_s=p.reopen_max_ms / 1000,
            on_frame=self._on_frame,
            on_error=self.ctx.set_error,
            on_open=self._on_open,
            trace=trace,
        )
        self.link.open()

    async def teardown(self) -> None:
        await self.link.shutdown()

    @property
    def bus(self) -> Any:
        """The open python-can bus, None while it is (re)opening."""
        return self.link.bus

    def _on_open(self, reopened: bool) -> None:
        if reopened:
            self.ctx.log.info("%s: CAN interface reopened", self.ctx.name)
        if self.trace_error:  # the bus is fine, the trace is not: stay red for it
            self.ctx.set_error(self.trace_error)
        else:
            self.ctx.clear_error()

    # --- receive -----------------------------------------------------------------------------

    def _on_frame(self, frame: Any) -> None:
        if self.link.bus is None:
            return
        now = self.ctx.now()
        if frame.is_error_frame:
            self.error_frames += 1
            if frame.arbitration_id & CAN_ERR_BUSOFF:
                self.bus_off += 1
                self.link.lost(self.link.gen, OSError("bus-off"))
            return
        self.received += 1
        chan = None if frame.channel is None else str(frame.channel)
        self.channels[chan or ""] = self.channels.get(chan or "", 0) + 1
        key = (int(frame.arbitration_id), bool(frame.is_extended_id))
        per = (chan or "", *key)
        self.id_counts[per] = self.id_counts.get(per, 0) + 1
        st = self.by_id.get(key)
        data = b"" if frame.is_remote_frame else bytes(frame.data)
        fd, brs = bool(frame.is_fd), bool(frame.bitrate_switch)
        if self.params.raw_output:
            raw = CanFrame(
                key[0], data, key[1], now, float(frame.timestamp), chan, fd, brs,
                bool(frame.is_remote_frame), int(frame.dlc),
            )  # fmt: skip
            self.ctx.publish("frames", raw)
        if st is None:
            self.unknown_count += 1
            self.unknown_by_channel[chan or ""] = self.unknown_by_channel.get(chan or "", 0) + 1
            if self.params.unknown_output:
                out = CanFrame(
                    key[0], data, key[1], now, float(frame.timestamp), chan, fd, brs,
                    bool(frame.is_remote_frame), int(frame.dlc),
                )  # fmt: skip
                self.ctx.publish("unknown", out)
            return
        st.received += 1
        st.window += 1
        if frame.is_remote_frame:  # a request for the message: nothing to decode
            return
        if not st.fits(data):
            st.bad_length += 1
            self._bad(st)
            return
        try:
            signals = _decode(st, data[: st.dbc.length])
        except Exception:
            self.decode_errors += 1
            self._bad(st)
            return
        reason = st.integrity(signals, data)
        if reason:
            self._bad(st)
        else:
            st.fail = max(st.fail - 1, 0)
        st.last_rx = now
        st.timed_out = False
        valid = st.fail < self.params.max_bad
        out = CanMessage(
            st.dbc.name, key[0], dict(signals), data, now, valid, "" if valid else reason,
            float(frame.timestamp), chan, fd, brs,
        )  # fmt: skip
        st.last = out
        self.ctx.publish(st.dbc.name, out)

    def _bad(self, st: _Msg) -> None:
        st.fail = min(st.fail + 1, self.params.max_bad)

    # --- the tick: transmit, supervise, reopen, report --------------------------------------

    def process(self, **inputs: Any) -> None:
        if not self.started:
            self._start(inputs)
        now = self.ctx.now()
        t = self.ctx.elapsed()
        for name, value in inputs.items():
            if value is not None:
                self._take(self.msgs[name], value)
        if self.link.bus is not None:
            self._transmit(t)
            if self.replay is not None:
                self._replay(t)
        elif self.link.reopen_due():
            self.link.on_loop(self.link.open)
        self._supervise(now)
        if t - self.last_status >= self.params.status_ms / 1000:
            self.last_status = t
            status = self.snapshot()
            self.ctx.publish("status", status)
            if self.keep_status:  # on the loop: a `timing: precise` thread keeps its instants
                self.link.on_loop(self._record_status, status)

    def _transmit(self, t: float) -> None:
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

    def _replay(self, t: float) -> None:
        assert self.replay is not None
        for frame in self.replay.due(t, self.tick / 2):
            if self.link.put(frame):
                self.sent += 1
        if self.replay.done:
            self.replay = None

    def _record_status(self, status: CanBusStatus) -> None:
        """Keep the status's bounded summary in the RTDB (``<node>.can``): ``flowrt ctl rtdb
        chassis.can`` shows it while the graph runs. The full table, which grows with the
        DBC, is on ``status`` only: an RTDB value has a size limit, and a status over it
        raised here and restarted the node every ``status_ms`` (issue 38). On the loop only:
        in a precise release thread its locks held the next frames back (4.6 ms, once)."""
        if not self.keep_status:
            return
        try:
            self.rtdb.write(
                f"{self.ctx.name}.can", summarise(status), validity_ms=3 * self.params.status_ms
            )
        except ValueError as e:  # an RTDB made with a smaller max_value: say so once, go on
            self.keep_status = False
            self.ctx.log.warning("%s: status not kept in the RTDB: %s", self.ctx.name, e)

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
            self.replay = TraceReplay(p.replay, p.replay_loop, p.channel, self.ctx.elapsed())

    def _take(self, st: _Msg, value: Any) -> None:
        """Keep an input value for sending; a value that does not fit the message is counted
        (``bad_inputs``) and logged, not raised: one bad producer must not stop the bus."""
        problem = take(st, value)
        if problem and (st.bad_inputs == 1 or st.bad_inputs % 1000 == 0):
            self.ctx.log.warning(
                "%s: input %s (%d so far): %s", self.ctx.name, st.dbc.name, st.bad_inputs, problem
            )

    def _send(self, st: _Msg) -> None:
        import can

        try:
            data = encode(st, self.params.fd)
        except EncodeProblem as e:
            self._encode_failed(st, e)
            return
        self._put(st, can.Message(**self._frame_fields(st), data=data))

    def _frame_fields(self, st: _Msg) -> dict[str, Any]:
        return {
            "arbitration_id": st.dbc.frame_id,
            "is_extended_id": st.dbc.is_extended_frame,
            "is_fd": st.fd,
            "bitrate_switch": st.brs,
            "channel": self.params.channel,
        }

    def _put(self, st: _Msg, msg: Any) -> None:
        if self.link.put(msg):
            self.sent += 1
            st.sent += 1
            st.window += 1

    def _encode_failed(self, st: _Msg, e: EncodeProblem) -> None:
        """Counted per message and per cause; said once per cause (a value out of range every
        tick is one warning and one alert, not one per tick)."""
        st.encode_errors += 1
        key = (st.dbc.name, e.cause)
        n = self.encode_causes.get(key, 0)
        self.encode_causes[key] = n + 1
        if n == 0:
            detail = f"{st.dbc.name} not sent: {e}"
            self.ctx.log.warning("%s: %s", self.ctx.name, detail)
            self.ctx.emit(HealthAlert(self.ctx.elapsed(), self.ctx.name, "can-encode", detail))

    def _supervise(self, now: float) -> None:
        """Timed-out messages are republished invalid, each; the alert is one per message,
        or one for the tick when more time out together (a vehicle's bus gone quiet is one
        event, not 331 lines: the status output has every message's timeouts)."""
        details: list[str] = []
        names: list[str] = []
        for st in self.rxs:
            assert st.timeout is not None
            since = st.last_rx if st.last_rx is not None else self.supervise_from
            if st.timed_out or now - since <= st.timeout:
                continue
            st.timed_out = True
            st.timeouts += 1
            st.last_counter = None
            names.append(f"{st.dbc.name} (0x{st.dbc.frame_id:X})")
            details.append(
                f"{names[-1]} not received for "
                f"{(now - since) * 1000:.0f} ms (timeout {st.timeout * 1000:g} ms)"
            )
            last = st.last
            self.ctx.publish(
                st.dbc.name,
                CanMessage(
                    st.dbc.name,
                    int(st.dbc.frame_id),
                    dict(last.signals) if last else {},
                    last.data if last else b"",
                    # the signals' time; never received: the timeout's (0.0 read as the
                    # machine's boot in a recording's Unix time)
                    last.timestamp if last else now,
                    False,
                    "timeout",
                    last.bus_timestamp if last else 0.0,
                    last.channel if last else None,
                    st.fd,
                    st.brs,
                ),
            )
        if len(details) > ALERTS_PER_TICK:
            details = [
                f"{len(details)} messages not received within their timeouts: "
                f"{', '.join(names[:ALERTS_PER_TICK])}, ... (the status output has each)"
            ]
        for detail in details:
            self.ctx.emit(HealthAlert(self.ctx.elapsed(), self.ctx.name, "can-timeout", detail))

    # --- statistics --------------------------------------------------------------------------

    def snapshot(self) -> CanBusStatus:
        """The bus and per-message counters now (also published on ``status``)."""
        now = self.ctx.now()
        t = self.ctx.elapsed()
        span = max(t - getattr(self, "last_snapshot", 0.0), 1e-9)
        self.last_snapshot = t
        rows = tuple(
            _message_status(st, now, span, self.params.max_bad) for st in self.msgs.values()
        )
        p: CanParams = self.params
        link = self.link
        trace = link.trace
        return CanBusStatus(
            t, p.interface, p.channel, link.bus is not None, self.received, self.sent,
            self.unknown_count, self.error_frames, self.bus_off, link.lost_count, link.reopens,
            link.send_errors, self.decode_errors, rows,
            tuple(sorted(self.channels)), tuple(sorted(self.unknown_by_channel.items())),
            trace.written if trace else 0, trace.dropped if trace else 0,
            tuple((m, c, n) for (m, c), n in sorted(self.encode_causes.items())),
            tuple((c, i, e, n) for (c, i, e), n in sorted(self.id_counts.items())),
            timestamp=now,  # recorded as Unix time, the recording's time base
        )  # fmt: skip


def _status_rtdb(ctx: Any) -> Any:
    """The RTDB that keeps the status record, taken at setup on the loop (its first use
    creates it, ~5 ms: not in a precise release thread); None outside a Runtime."""
    try:
        return ctx.rtdb
    except RuntimeError:  # no RTDB: nothing to keep the record in
        return None


def _decode(st: _Msg, data: bytes) -> Mapping[str, Any]:
    """Physical values as cantools decodes them: the message whole, or (one that cantools
    cannot unpack whole: overlapping signals) each signal alone. A multiplexed message that
    fails (a multiplexer value with no branch) raises: a decode error."""
    if st.by_signal is not None:
        return st.by_signal(data)
    try:
        values: Mapping[str, Any] = st.dbc.decode(data, decode_choices=False)
        return values
    except Exception:
        if st.dbc.is_multiplexed():
            raise
        st.by_signal = SignalDecoder(st.dbc)  # structural: the same for every frame
        return st.by_signal(data)


def _bus_kwargs(p: CanParams, db: Any) -> dict[str, Any]:
    """The keyword arguments of ``can.Bus``: the params' options, channel, rates, FD, filters."""
    kwargs: dict[str, Any] = dict(p.options)
    if p.channel is not None:
        kwargs["channel"] = p.channel
    if p.bitrate is not None:
        kwargs["bitrate"] = p.bitrate
    if p.fd:
        kwargs.setdefault("fd", True)
        if p.data_bitrate is not None:
            kwargs.setdefault("data_bitrate", p.data_bitrate)
    if p.receive is not None and "can_filters" not in kwargs:
        kwargs["can_filters"] = acceptance_filters(db, p.receive)
    return kwargs


def _message_status(st: _Msg, now: float, span: float, max_bad: int) -> MessageStatus:
    """One message's row of the status (and the start of its next rate window)."""
    window, st.window = st.window, 0
    return MessageStatus(
        st.dbc.name, int(st.dbc.frame_id), st.received, st.sent, window / span,
        None if st.last_rx is None else (now - st.last_rx) * 1000,
        st.timeouts, st.bad_counter, st.bad_checksum, st.bad_length, st.late,
        st.bad_inputs, not st.timed_out and st.fail < max_bad, st.encode_errors, st.fd,
    )  # fmt: skip
