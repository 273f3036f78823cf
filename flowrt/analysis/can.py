"""CAN bus analysis: worst-case frame lengths, utilisation and worst-case response times.

The response-time analysis is the revised one of R. I. Davis, A. Burns, R. J. Bril and
J. J. Lukkien, "Controller Area Network (CAN) schedulability analysis: Refuted, revisited
and revised", Real-Time Systems 35(3):239-272, 2007. CAN arbitrates by identifier, so the
bus behaves as one global fixed-priority *non-preemptive* queue: a message waits for the
frame already on the wire (blocking), then for every higher-priority frame queued before it
wins arbitration (interference). Tindell's original 1994 analysis looked only at the first
instance of a message after the critical instant; Davis et al. showed that a later instance
in the same priority level-m busy period can have a longer response time (their example:
the analysis said 3 ms, the bus gives 3.5 ms, past a 3.25 ms deadline). So, per message m:

- transmission time ``C_m = frame_bits(n) * tau_bit`` with the worst case of bit stuffing
  and the 3-bit interframe space (Davis et al. eq. 2):
  ``47 + 8n + floor((34 + 8n - 1) / 4)`` bits for 11-bit identifiers and
  ``67 + 8n + floor((54 + 8n - 1) / 4)`` for 29-bit ones;
- blocking ``B_m = max C_k`` over lower-priority messages k (0 for the lowest);
- busy period ``t = B_m + sum_{k in hep(m)} ceil((t + J_k) / T_k) C_k`` (eq. 12);
- number of instances in it ``Q_m = ceil((t_m + J_m) / T_m)`` (eq. 13);
- for every instance q in 0..Q_m-1 the queuing delay
  ``w(q) = B_m + q C_m + sum_{k in hp(m)} ceil((w + J_k + tau_bit) / T_k) C_k`` (eq. 15)
  and response time ``R(q) = J_m + w(q) - q T_m + C_m`` (eq. 16); ``R_m = max_q R(q)``.

``J`` is the queuing jitter (the variation of the instant a message is queued relative to
its period, e.g. from the task that queues it). Error recovery overhead is not modelled
(an error-free bus). Messages without a period (event-driven) block lower-priority
messages (they are in ``B``) but cannot be analysed themselves nor bound the interference
they cause to lower-priority messages: they are reported as not analysed, with the messages
they can delay without bound. Given a minimum inter-arrival time (``sporadic``), such a
message is analysed as Davis et al.'s sporadic message: ``T`` is that minimum time.

CAN FD messages (ISO 11898-1:2015) take their frame length from
:mod:`flowrt.analysis.can_frames` and ``C = arbitration bits / nominal rate + data bits /
data rate``; an FD message with bit-rate switch and no data bit rate is not analysed (its
no-BRS length, an upper bound, still counts as interference and blocking).

Pure functions over :class:`CanMessageTiming`; the DBC reading is :func:`timings_from_dbc`,
which takes a loaded cantools database (no runtime imports).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .can_frames import fd_frame_bits, frame_bits

__all__ = [
    "NO_DATA_BITRATE",
    "BusAnalysis",
    "CanMessageTiming",
    "MessageResult",
    "analyse_bus",
    "frame_bits",
    "response_time",
    "timings_from_dbc",
]

_MAX_ITER = 100_000
#: The note of an FD message with bit-rate switch analysed without a data bit rate.
NO_DATA_BITRATE = "CAN FD with bit-rate switch: no data bit rate"
#: Most instances of a message in its busy period that are examined (eq. 13): a queuing jitter
#: of days against a period of milliseconds would otherwise take hours; past it the message
#: is reported unbounded.
MAX_INSTANCES = 10_000


@dataclass(frozen=True)
class CanMessageTiming:
    """A message as the analysis sees it. ``period_ms`` None: event-driven (not analysed).

    The identifier is the priority: lower id wins arbitration. Standard and extended ids
    are compared as CAN does on the wire (the 11 base bits first, a standard frame beating
    an extended one with the same base id).
    """

    name: str
    id: int
    dlc: int
    period_ms: float | None
    extended: bool = False
    deadline_ms: float | None = None  # None: the period
    jitter_ms: float = 0.0
    fd: bool = False  # CAN FD (ISO 11898-1:2015)
    brs: bool = False  # FD with bit-rate switch: the data phase at the data bit rate
    sporadic: bool = False  # period_ms is a minimum inter-arrival time, not a cycle

    def priority_key(self) -> tuple[int, int, int]:
        """Arbitration order (smaller wins): base id, then RTR/IDE (standard first), then the
        18 extension bits."""
        if self.extended:
            return (self.id >> 18, 1, self.id & 0x3FFFF)
        return (self.id, 0, 0)


@dataclass(frozen=True)
class MessageResult:
    timing: CanMessageTiming
    frame_bits: int
    c_ms: float  # transmission time
    blocking_ms: float
    busy_period_ms: float | None
    instances: int | None  # Q_m, instances in the busy period
    wcrt_ms: float | None  # None: not analysed (no period) or unbounded (busy period diverges)
    deadline_ms: float | None
    schedulable: bool | None  # None: not analysed
    arbitration_bits: int = 0  # FD: bits at the nominal rate (classic: all of them)
    data_bits: int = 0  # FD: bits at the data rate with BRS
    note: str = ""  # why not analysed
    delays: tuple[str, ...] = ()  # not analysed: lower-priority messages it can delay unboundedly

    @property
    def name(self) -> str:
        return self.timing.name


@dataclass(frozen=True)
class BusAnalysis:
    """The bus as a whole: load, each message's result, and the verdict.

    ``bits_per_s`` is the load in nominal bit times per second, ``utilisation * bitrate``:
    an FD data phase at ``data_bitrate`` counts ``bitrate / data_bitrate`` of a nominal bit
    per bit, so the figure and the utilisation always agree. ``arbitration_bits_per_s`` and
    ``data_bits_per_s`` are the bits actually sent in each phase.

    Without a data bit rate an FD message with bit-rate switch has no known length: it
    counts at its no-BRS length in ``utilisation`` (an upper bound) and at its arbitration
    phase only in ``utilisation_min`` (a lower bound, the data phase taken as instant).
    """

    bitrate: int
    bits_per_s: float  # nominal bit times per second of the periodic messages
    utilisation: float  # sum of C/T: the share of the bus' time (an upper bound, see above)
    messages: list[MessageResult]  # in priority order, highest first
    data_bitrate: int | None = None
    utilisation_min: float | None = None  # None: the same as utilisation (every length known)
    arbitration_bits_per_s: float = 0.0
    data_bits_per_s: float = 0.0

    @property
    def not_analysed(self) -> list[MessageResult]:
        return [m for m in self.messages if m.schedulable is None]

    @property
    def schedulable(self) -> bool | None:
        """True when every analysed message meets its deadline and the bus is not over-full;
        False when one misses it or the utilisation is over 100 % even at its lower bound;
        None (unknown) when nothing could be analysed, or the utilisation may or may not be
        over 100 % (the FD data phase at an unknown rate). Event-driven messages do not count.
        """
        if any(m.schedulable is False for m in self.messages):
            return False
        low = self.utilisation if self.utilisation_min is None else self.utilisation_min
        if low > 1.0 + 1e-12:
            return False
        if not any(m.schedulable for m in self.messages) or self.utilisation > 1.0 + 1e-12:
            return None
        return True

    @property
    def verdict_reason(self) -> str:
        """Why the verdict is no or unknown ("" when schedulable)."""
        misses = [m.name for m in self.messages if m.schedulable is False]
        if misses:
            more = f" and {len(misses) - 3} more" if len(misses) > 3 else ""
            return (
                f"{len(misses)} message(s) can miss their deadline: {', '.join(misses[:3])}{more}"
            )
        low = self.utilisation if self.utilisation_min is None else self.utilisation_min
        if low > 1.0 + 1e-12:
            return f"utilisation {100 * low:.2f} % is over 100 %"
        no_rate = sum(1 for m in self.not_analysed if m.note == NO_DATA_BITRATE)
        if not any(m.schedulable for m in self.messages):
            if not self.messages:
                return "no messages"
            why = (
                f"{no_rate} CAN FD message(s) with bit-rate switch and no data bit rate "
                "(give --data-bitrate or the DBC's BaudrateCANFD)"
                if no_rate
                else "no message has a cycle time (give --period or --sporadic)"
            )
            return f"nothing could be analysed: {why}"
        if self.utilisation > 1.0 + 1e-12:
            return (
                f"utilisation between {100 * low:.2f} % and {100 * self.utilisation:.2f} % "
                f"({no_rate} CAN FD message(s) with bit-rate switch and no data bit rate)"
            )
        return ""

    def to_json(self) -> dict[str, Any]:
        """The ``flowrt can analyse --json`` document: ids integers, times ms floats."""
        return {
            "bitrate": self.bitrate,
            "data_bitrate": self.data_bitrate,
            "utilisation": self.utilisation,
            "utilisation_min": self.utilisation_min,
            "bits_per_s": self.bits_per_s,
            "arbitration_bits_per_s": self.arbitration_bits_per_s,
            "data_bits_per_s": self.data_bits_per_s,
            "schedulable": self.schedulable,
            "reason": self.verdict_reason,
            "not_analysed_count": len(self.not_analysed),
            "messages": [
                {
                    "name": m.name,
                    "id": m.timing.id,
                    "extended": m.timing.extended,
                    "dlc": m.timing.dlc,
                    "period_ms": _f(m.timing.period_ms),
                    "frame_bits": m.frame_bits,
                    "c_ms": m.c_ms,
                    "blocking_ms": m.blocking_ms,
                    "jitter_ms": float(m.timing.jitter_ms),
                    "busy_period_ms": m.busy_period_ms,
                    "instances": m.instances,
                    "wcrt_ms": m.wcrt_ms,
                    "deadline_ms": _f(m.deadline_ms),
                    "schedulable": m.schedulable,
                    "fd": m.timing.fd,
                    "brs": m.timing.brs,
                    "sporadic": m.timing.sporadic,
                    "arbitration_bits": m.arbitration_bits,
                    "data_bits": m.data_bits,
                }
                for m in self.messages
            ],
            "not_analysed": [
                {"name": m.name, "reason": m.note, "c_ms": m.c_ms, "delays": list(m.delays)}
                for m in self.not_analysed
            ],
        }


def _f(x: float | None) -> float | None:
    return None if x is None else float(x)


def response_time(
    c: float,
    t: float,
    j: float,
    blocking: float,
    higher: Sequence[tuple[float, float, float]],
    tau_bit: float,
) -> tuple[float | None, float | None, int | None]:
    """Worst-case response time of one message (Davis et al. 2007, eqs. 12-16).

    ``higher`` holds (C, T, J) of every higher-priority periodic message. Times in any one
    unit. Returns (R, busy period, Q), all None when the busy period does not end (the
    level-m utilisation is >= 1, or the iteration did not converge).
    """
    hep = [*higher, (c, t, j)]
    if sum(ck / tk for ck, tk, _ in hep) >= 1.0:
        return None, None, None
    busy = blocking + sum(ck for ck, _, _ in hep)
    for _ in range(_MAX_ITER):
        nxt = blocking + sum(math.ceil((busy + jk) / tk - 1e-12) * ck for ck, tk, jk in hep)
        if nxt <= busy + 1e-12:
            break
        busy = nxt
    else:
        return None, None, None
    q_count = max(1, math.ceil((busy + j) / t - 1e-12))
    if q_count > MAX_INSTANCES:
        return None, None, None
    worst = 0.0
    w = blocking
    for q in range(q_count):
        w = max(w, blocking + q * c)
        for _ in range(_MAX_ITER):
            nxt = (
                blocking
                + q * c
                + sum(math.ceil((w + jk + tau_bit) / tk - 1e-12) * ck for ck, tk, jk in higher)
            )
            if nxt <= w + 1e-12:
                break
            w = nxt
        else:
            return None, None, None
        worst = max(worst, j + w - q * t + c)
    return worst, busy, q_count


def _frame(m: CanMessageTiming, tau_ms: float, data_bitrate: int | None) -> tuple[int, int, float]:
    """(arbitration bits, data bits, C in ms) of one message; FD with BRS needs the data rate
    (None: the no-BRS length, an upper bound)."""
    if not m.fd:
        bits = frame_bits(m.dlc, m.extended)
        return bits, 0, bits * tau_ms
    fd = fd_frame_bits(m.dlc, m.extended, m.brs)
    if m.brs and data_bitrate is not None:
        return fd.arbitration, fd.data, fd.arbitration * tau_ms + fd.data * 1000.0 / data_bitrate
    return fd.arbitration, fd.data, fd.total * tau_ms


def analyse_bus(
    messages: Iterable[CanMessageTiming], bitrate: int, data_bitrate: int | None = None
) -> BusAnalysis:
    """Frame lengths, utilisation and worst-case response times of a message set."""
    if bitrate <= 0:
        raise ValueError(f"bitrate must be positive, got {bitrate}")
    if data_bitrate is not None and data_bitrate < bitrate:
        raise ValueError(f"the data bit rate {data_bitrate} is below the nominal {bitrate}")
    msgs = sorted(messages, key=CanMessageTiming.priority_key)
    tau_ms = 1000.0 / bitrate
    frames = [_frame(m, tau_ms, data_bitrate) for m in msgs]
    bits = [a + d for a, d, _ in frames]
    cs = [c for _, _, c in frames]
    periodic = [(f, m) for f, m in zip(frames, msgs, strict=True) if m.period_ms]
    util = sum(c / float(m.period_ms or 1) for (_, _, c), m in periodic)
    unknown = [(d, m) for (_, d, _), m in periodic if m.fd and m.brs and data_bitrate is None]
    util_min = None
    if unknown:  # their data phase at an unknown rate: at least their arbitration phase
        util_min = util - sum(d * tau_ms / float(m.period_ms or 1) for d, m in unknown)
    arb_bps = sum(a * 1000.0 / float(m.period_ms or 1) for (a, _, _), m in periodic)
    data_bps = sum(d * 1000.0 / float(m.period_ms or 1) for (_, d, _), m in periodic)
    results: list[MessageResult] = []
    for i, m in enumerate(msgs):
        blocking = max(cs[i + 1 :], default=0.0)
        deadline = m.deadline_ms if m.deadline_ms is not None else m.period_ms
        arb, data = frames[i][0], frames[i][1]
        if m.period_ms is None:
            lower = tuple(h.name for h in msgs[i + 1 :] if h.period_ms is not None)
            note = "no cycle time"
            results.append(
                MessageResult(
                    m, bits[i], cs[i], blocking, None, None, None, deadline, None,
                    arb, data, note, lower,
                )
            )  # fmt: skip
            continue
        if m.fd and m.brs and data_bitrate is None:
            note = NO_DATA_BITRATE
            results.append(
                MessageResult(
                    m, bits[i], cs[i], blocking, None, None, None, deadline, None, arb, data, note
                )
            )
            continue
        higher = [
            (cs[k], float(h.period_ms), float(h.jitter_ms))
            for k, h in enumerate(msgs[:i])
            if h.period_ms is not None
        ]
        r, busy, q = response_time(
            cs[i], float(m.period_ms), float(m.jitter_ms), blocking, higher, tau_ms
        )
        ok = r is not None and deadline is not None and r <= deadline + 1e-9
        results.append(
            MessageResult(m, bits[i], cs[i], blocking, busy, q, r, deadline, ok, arb, data)
        )
    return BusAnalysis(
        bitrate, util * bitrate, util, results, data_bitrate, util_min, arb_bps, data_bps
    )


def timings_from_dbc(
    db: Any,
    *,
    periods: Mapping[str, float] | None = None,
    deadlines: Mapping[str, float] | None = None,
    jitters: Mapping[str, float] | None = None,
    sporadic: Mapping[str, float] | None = None,
) -> list[CanMessageTiming]:
    """The messages of a loaded cantools database, their period from ``GenMsgCycleTime``
    (``cycle_time``) unless ``periods`` overrides it by message name. A message without a
    cycle time is sporadic with the minimum inter-arrival time ``sporadic`` gives (else the
    DBC's ``GenMsgDelayTime``), and event-driven (not analysed) without one. FD-ness comes
    from the DBC (``VFrameFormat``, or more than 8 bytes) and BRS from ``CANFD_BRS``."""
    from .can_database import message_attribute, message_brs, message_is_fd

    periods = periods or {}
    deadlines = deadlines or {}
    jitters = jitters or {}
    sporadic = sporadic or {}
    names = {m.name for m in db.messages}
    for what, table in (
        ("period", periods),
        ("deadline", deadlines),
        ("jitter", jitters),
        ("sporadic", sporadic),
    ):
        for name in table:
            if name not in names:
                raise KeyError(f"{what} given for {name!r}, which is not a message of the DBC")
    out: list[CanMessageTiming] = []
    for m in db.messages:
        period = periods.get(m.name, m.cycle_time or None)
        is_sporadic = False
        if not period:
            gap = sporadic.get(m.name, _positive(message_attribute(m, "GenMsgDelayTime")))
            if gap:
                period, is_sporadic = gap, True
        fd = message_is_fd(m)
        out.append(
            CanMessageTiming(
                name=m.name,
                id=int(m.frame_id),
                dlc=int(m.length),
                period_ms=float(period) if period else None,
                extended=bool(m.is_extended_frame),
                deadline_ms=deadlines.get(m.name),
                jitter_ms=float(jitters.get(m.name, 0.0)),
                fd=fd,
                brs=fd and message_brs(m),
                sporadic=is_sporadic,
            )
        )
    return out


def _positive(value: Any) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) and x > 0 else None
