"""Graph models: the one description of a graph, whether it came from YAML or from Python.

Everything the runtime needs is here and validated by pydantic, so that a graph that loads
is a graph that can run. Structural checks that need the node classes (ports, cycles, frame
sources) live in :mod:`flowrt.graph._resolve`.
"""

from __future__ import annotations

import ipaddress
import math
import re
from enum import StrEnum
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    field_validator,
    model_validator,
)
from pydantic.functional_validators import AfterValidator, BeforeValidator

from ._schema_forms import short_form_schema, trigger_words

_DURATION = re.compile(r"^\s*(?P<num>[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(?P<unit>us|ms|s)?\s*$")
_UNIT_MS = {"us": 0.001, "ms": 1.0, "s": 1000.0, None: 1.0}


_SECONDS = re.compile(r"^\s*(?P<num>[0-9]*\.?[0-9]+)\s*(?P<unit>[A-Za-z]*)\s*$")
_UNIT_S = {
    "": 1.0,
    "s": 1.0,
    "sec": 1.0,
    "ms": 1e-3,
    "us": 1e-6,
    "m": 60.0,
    "min": 60.0,
    "h": 3600.0,
}


def parse_seconds(text: str) -> float:
    """Read ``90``, ``30s``, ``500ms``, ``10m``, ``1.5min``, ``1h`` as seconds.

    For lengths of time a person types (``--duration``, ``--start``, a recording's
    ``split_duration``): a bare number is seconds here, where in a graph's timing it is
    milliseconds (:func:`parse_duration_ms`), and minutes and hours are allowed.
    """
    m = _SECONDS.match(text)
    unit = m.group("unit").lower() if m else ""
    if m is None or unit not in _UNIT_S:
        raise ValueError(f"{text!r} is not a duration (e.g. 90, 30s, 10m, 1h)")
    s = float(m.group("num")) * _UNIT_S[unit]
    if not math.isfinite(s):
        raise ValueError(f"{text!r} is not a finite duration")
    return s


def parse_duration_ms(value: Any) -> float:
    """Read ``10ms``, ``1.5s``, ``200us`` or a bare number (milliseconds) as milliseconds.

    Only finite durations: a NaN or infinite timer, phase, deadline or watchdog validated
    once and then crashed the clock (``OverflowError``) or failed every call.
    """
    ms: float | None = None
    if isinstance(value, bool):
        raise ValueError("expected a duration such as 10ms, 1.5s or 200us")
    if isinstance(value, int | float):
        try:
            ms = float(value)
        except OverflowError:  # an int beyond a float's range
            ms = math.inf
    elif isinstance(value, str):
        m = _DURATION.match(value)
        if m:
            ms = float(m.group("num")) * _UNIT_MS[m.group("unit")]
    if ms is None:
        raise ValueError(f"expected a duration such as 10ms, 1.5s or 200us, got {value!r}")
    if not math.isfinite(ms):
        shown = repr(value) if len(repr(value)) <= 40 else f"{repr(value)[:30]}... (too large)"
        raise ValueError(f"must be a finite duration, got {shown}")
    return ms


_DURATION_TEXT = Annotated[
    str, Field(pattern=r"^\s*[0-9]*\.?[0-9]+([eE][-+]?[0-9]+)?\s*(us|ms|s)?\s*$")
]
_PARSED_DURATION = BeforeValidator(parse_duration_ms, json_schema_input_type=float | _DURATION_TEXT)
"""A duration with its unit parsed; its JSON Schema takes the number or the text (its form:
the schema accepted ``deadline: fast``, which the loader refuses)."""
DurationMs = Annotated[float, _PARSED_DURATION]
"""A finite duration in milliseconds; YAML may write it with a unit (us, ms, s)."""


# --- the documented ranges ---------------------------------------------------------------
#
# Every duration, rate, count and id of a graph file is finite and within these bounds, so
# that a graph that validates is a graph that runs. TimingOverride carries the same bounds, so
# that a run-time change (a mode, a request to the control endpoint) is checked with the same
# rules: ``TimingOverride.model_validate(change)``. README "Timing ranges".

MIN_TIMER_MS = 0.1
"""Shortest timer period: 100 us (10 kHz). Below it a timerfd interval rounds towards zero
(``1e-9ms`` armed a zero interval: the timer fired once, then never) and no Python node keeps
up anyway."""
MAX_DURATION_MS = 3_600_000.0
"""Longest timer period, phase, deadline, watchdog, back-off: one hour. Longer is a node that
never runs again (``1e300ms``), which is ``enabled: false``."""
MIN_DEADLINE_MS = 0.01
"""Shortest deadline: 10 us, about the resolution at which activations are measured."""
MIN_WATCHDOG_MS = 1.0
"""Shortest watchdog: 1 ms. A call's round trip to a worker process takes tens to hundreds of
microseconds; a ``1us`` watchdog killed every call as hung."""
MAX_FRAME_PERIOD = 100_000
"""Longest frame-trigger period, in frames (83 min at 20 fps)."""
MIN_PRIORITY, MAX_PRIORITY = 1, 99
MAX_CPU_ID = 8191
"""Largest CPU number (Linux's CONFIG_NR_CPUS is at most 8192). A huge id overflowed
``sched_setaffinity`` and restarted the worker forever."""
MAX_QUEUE_SIZE = 100_000
"""Largest queue/lossless edge capacity."""
MAX_SPIN_MS = 10.0
"""Longest busy-poll around an expected activation."""


def _ms(v: float) -> str:
    """``3600000 ms`` rather than ``3.6e+06 ms``; tiny and huge values stay exponents."""
    v = float(v)
    if v.is_integer() and abs(v) < 1e12:
        return f"{int(v)} ms"
    return f"{v:g} ms"


def check_timer_ms(v: float) -> float:
    """A timer period within [MIN_TIMER_MS, MAX_DURATION_MS]."""
    if v <= 0:
        raise ValueError(f"timer period must be positive, got {_ms(v)}")
    if v < MIN_TIMER_MS:
        raise ValueError(
            f"timer period must be at least {_ms(MIN_TIMER_MS)} (100 us), got {_ms(v)}"
        )
    if v > MAX_DURATION_MS:
        raise ValueError(f"timer period must be at most {_ms(MAX_DURATION_MS)} (1 h), got {_ms(v)}")
    return v


def check_phase_ms(v: float) -> float:
    """A timer phase within [0, MAX_DURATION_MS] (and below the period: checked by the graph)."""
    if v < 0:
        raise ValueError(f"phase must be >= 0, got {_ms(v)}")
    if v > MAX_DURATION_MS:
        raise ValueError(f"phase must be at most {_ms(MAX_DURATION_MS)} (1 h), got {_ms(v)}")
    return v


def _positive_duration(v: float, least: float) -> float:
    if v <= 0:
        raise ValueError(f"must be positive, got {_ms(v)}")
    if not least <= v <= MAX_DURATION_MS:
        raise ValueError(
            f"must be between {_ms(least)} and {_ms(MAX_DURATION_MS)} (1 h), got {_ms(v)}"
        )
    return v


def check_deadline_ms(v: float) -> float:
    """A deadline within [MIN_DEADLINE_MS, MAX_DURATION_MS]."""
    return _positive_duration(v, MIN_DEADLINE_MS)


def check_watchdog_ms(v: float) -> float:
    """A watchdog within [MIN_WATCHDOG_MS, MAX_DURATION_MS]."""
    return _positive_duration(v, MIN_WATCHDOG_MS)


def check_frame_period(v: int) -> int:
    """A frame-trigger period within [1, MAX_FRAME_PERIOD] frames."""
    if v <= 0:
        raise ValueError(f"period must be a positive number of frames, got {v}")
    if v > MAX_FRAME_PERIOD:
        raise ValueError(f"period must be at most {MAX_FRAME_PERIOD} frames, got {v}")
    return v


def check_frame_phase(v: int) -> int:
    """A frame-trigger phase within [0, MAX_FRAME_PERIOD) (and below the period)."""
    if v < 0:
        raise ValueError(f"phase must be >= 0, got {v}")
    if v >= MAX_FRAME_PERIOD:
        raise ValueError(f"phase must be less than {MAX_FRAME_PERIOD} frames, got {v}")
    return v


def _bounded_ms(lo: float, hi: float) -> AfterValidator:
    def check(v: float) -> float:
        if not lo <= v <= hi:
            raise ValueError(f"must be between {_ms(lo)} and {_ms(hi)}, got {_ms(v)}")
        return v

    return AfterValidator(check)


TimerMs = Annotated[float, _PARSED_DURATION, AfterValidator(check_timer_ms)]
PhaseMs = Annotated[float, _PARSED_DURATION, AfterValidator(check_phase_ms)]
DeadlineMs = Annotated[float, _PARSED_DURATION, AfterValidator(check_deadline_ms)]
WatchdogMs = Annotated[float, _PARSED_DURATION, AfterValidator(check_watchdog_ms)]
BackoffMs = Annotated[float, _PARSED_DURATION, _bounded_ms(0, MAX_DURATION_MS)]
SpinMs = Annotated[float, _PARSED_DURATION]
FramePeriod = Annotated[int, AfterValidator(check_frame_period)]
FramePhase = Annotated[int, AfterValidator(check_frame_phase)]
Priority = Annotated[int, Field(ge=MIN_PRIORITY, le=MAX_PRIORITY)]
CpuId = Annotated[int, Field(ge=0, le=MAX_CPU_ID)]


class _Strict(BaseModel):
    # allow_inf_nan=False: every float of a graph file is finite.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class FrameTrigger(_Strict):
    """Activate on the ticks of a frame source: every ``period`` frames, offset by ``phase``.

    The CAMBADA process-manager semantics: on tick ``k`` of the source, the node runs when
    ``k % period == phase``.
    """

    frame: str = Field(
        description="frame source: a node name, or node.port for a node with several"
    )
    period: FramePeriod = 1
    phase: FramePhase = 0


class TimerTrigger(_Strict):
    """Activate every ``timer`` milliseconds, ``phase`` ms after the runtime's time origin."""

    timer: TimerMs
    phase: PhaseMs = 0.0


class InputTrigger(_Strict):
    """Activate when data arrives on the named inputs (``any`` = any input); never re-entrant."""

    input: str | list[str] = "any"


class LoopTrigger(_Strict):
    """Free-running: activate again as soon as the previous activation ends.

    For sources paced by their device (a camera's ``grab`` blocks until the next frame).
    """

    loop: Literal[True] = True


def _trigger_tag(v: Any) -> str | None:
    if isinstance(v, BaseModel):
        return {FrameTrigger: "frame", TimerTrigger: "timer", InputTrigger: "input"}.get(
            type(v), "loop"
        )
    if isinstance(v, dict):
        for key in ("frame", "timer", "input", "loop"):
            if key in v:
                return key
    return None


Trigger = Annotated[
    Annotated[FrameTrigger, Tag("frame")]
    | Annotated[TimerTrigger, Tag("timer")]
    | Annotated[InputTrigger, Tag("input")]
    | Annotated[LoopTrigger, Tag("loop")],
    Discriminator(
        _trigger_tag,
        custom_error_type="trigger",
        custom_error_message="a trigger needs one of the keys frame, timer, input or loop",
    ),
]


class Placement(StrEnum):
    inline = "inline"
    process = "process"
    pool = "pool"


class MissPolicy(StrEnum):
    """What happens to the result of an activation that missed its deadline."""

    continue_ = "continue"  # soft deadline: the late result is still delivered
    discard = "discard"  # firm deadline: the late result is dropped (and counted)


class EdgePolicy(StrEnum):
    latest = "latest"
    queue = "queue"
    lossless = "lossless"


def node_dot_port(v: str) -> str:
    """``node.port``: one dot, both sides non-empty."""
    if v.count(".") != 1 or not all(v.split(".")):
        raise ValueError(f"expected node.port, got {v!r}")
    return v


class InputSpec(_Strict):
    """Where an input reads from and how its buffer behaves."""

    __get_pydantic_json_schema__ = classmethod(
        short_form_schema("short form: the node.port that feeds it")
    )

    source: str = Field(alias="from", description="node.port that feeds this input")
    policy: EdgePolicy | None = None  # None: latest for frames, queue for messages
    size: int = Field(
        default=8, ge=1, le=MAX_QUEUE_SIZE, description="capacity of queue/lossless buffers"
    )

    model_config = ConfigDict(
        extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False
    )

    @model_validator(mode="before")
    @classmethod
    def _short_form(cls, data: Any) -> Any:
        if isinstance(data, str):
            return {"from": data}
        return data

    @field_validator("source")
    @classmethod
    def _node_dot_port(cls, v: str) -> str:
        if "." not in v and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_\-]*", v):
            return v  # a bare name: an import's output (checked where imports are known)
        return node_dot_port(v)

    @property
    def node(self) -> str:
        return self.source.split(".")[0]

    @property
    def port(self) -> str:
        return self.source.split(".")[1] if "." in self.source else "output"


class RestartPolicy(_Strict):
    """When a node that raised is started again, and how long to wait (doubling each time)."""

    policy: Literal["always", "on-failure", "never"] = "on-failure"
    backoff: BackoffMs = 100.0
    max_backoff: BackoffMs = 5000.0
    max_restarts: int | None = Field(default=None, ge=0, le=1_000_000_000)
    max_failures: int | None = Field(
        default=10,
        ge=1,
        le=1_000_000_000,
        description="consecutive failures without a completed activation in between (a crash "
        "loop) after which the node is given up and marked failed; null: never give up",
    )
    max_start_failures: int | None = Field(
        default=3,
        ge=1,
        le=1_000_000_000,
        description="consecutive failures of a node that has never completed an activation "
        "(a module a worker cannot import, a file that is not there) after which it is given "
        "up and marked failed (within about a second); null: only max_failures applies",
    )


class NodeSpec(_Strict):
    """One node of the graph: what it is, when it runs, where, and what it reads."""

    kind: str
    params: dict[str, Any] = Field(default_factory=dict)
    trigger: Trigger | None = Field(default=None, json_schema_extra=trigger_words)
    deadline: DeadlineMs | None = None
    miss_policy: MissPolicy = MissPolicy.continue_
    priority: Priority = 10
    placement: Placement = Placement.inline
    enabled: bool = True
    timing: Literal["normal", "precise"] = Field(
        default="normal",
        description="precise: released from a thread of its own sleeping to each instant "
        "(timer-triggered nodes only; costs a thread, and CPU while spinning with spin:)",
    )
    watchdog: WatchdogMs | None = None
    restart: RestartPolicy = RestartPolicy()
    inputs: dict[str, InputSpec] = Field(default_factory=dict)
    cpus: list[CpuId] | None = Field(
        default=None, min_length=1, description="CPUs its worker process may run on"
    )
    spin: SpinMs | None = Field(
        default=None,
        description="its worker busy-polls this long before (and after) each expected "
        "activation; with timing: precise, its release thread spins this long before each",
    )
    pipeline: int | None = Field(
        default=None,
        ge=1,
        le=64,
        description="activations in flight to its worker when its trigger inputs are queues "
        "(default 4; 1: one call at a time), or when it is a period-1 frame reader of a "
        "pacing: fast source (default 2); other latest inputs always have one",
    )
    wcet: DurationMs | None = Field(
        default=None,
        description="execution-time budget (worst case) for flowrt check and admission control",
    )

    @field_validator("trigger", mode="before")
    @classmethod
    def _trigger_shorthand(cls, v: Any) -> Any:
        if v == "loop":
            return {"loop": True}
        if v == "input":
            return {"input": "any"}
        return v

    @field_validator("wcet")
    @classmethod
    def _wcet_finite(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"must be a finite positive duration, got {v:g} ms")
        return v

    @field_validator("spin")
    @classmethod
    def _spin_range(cls, v: float | None) -> float | None:
        if v is not None and not 0 < v <= MAX_SPIN_MS:
            raise ValueError(f"must be in (0, {MAX_SPIN_MS:g} ms], got {v:g} ms")
        return v

    @field_validator("cpus")
    @classmethod
    def _cpu_ids(cls, v: list[int] | None) -> list[int] | None:
        if v is not None:
            if any(c < 0 for c in v):
                raise ValueError("CPU numbers start at 0")
            if len(set(v)) != len(v):
                raise ValueError("a CPU is listed twice")
        return v


class ModeSpec(_Strict):
    """A named set of timing overrides (e.g. attacker / defender), applied as one change."""

    nodes: dict[str, NodeOverride] = Field(default_factory=dict)


class TimingOverride(_Strict):
    """The run-time adjustable part of a node's timing; unset fields keep their value.

    Validated with the graph files' ranges (``TimingOverride.model_validate(change)``), so a
    change from a mode, the control endpoint or the API can be checked whole before any of
    it is applied. Whether it fits the node's trigger (frames take period/phase, timers ms)
    is checked against the graph (``flowrt.graph._resolve`` /
    ``flowrt.kernel.timing.TimingChange.problems``).
    """

    period: FramePeriod | None = None
    phase: FramePhase | None = None
    timer: TimerMs | None = None
    timer_phase: PhaseMs | None = Field(
        default=None, description="phase of a timer-triggered node, ms (below its timer)"
    )
    deadline: DeadlineMs | None = None
    priority: Priority | None = None
    enabled: bool | None = None


class NodeOverride(TimingOverride):
    """A mode's change to one node: its timing, and params merged over the graph file's.

    Params are merged key by key, into nested mappings too, so a mode can change one weight
    of an arbiter (``sources: {avoid: {weight: 3}}``) and keep the rest.
    """

    params: dict[str, Any] | None = None


ModeSpec.model_rebuild()


def merge_params(base: dict[str, Any], override: dict[str, Any] | None) -> dict[str, Any]:
    """``override`` over ``base``, recursively for mappings (a mode's params over the graph's)."""
    out = dict(base)
    for key, value in (override or {}).items():
        old = out.get(key)
        out[key] = (
            merge_params(old, value) if isinstance(old, dict) and isinstance(value, dict) else value
        )
    return out


class OverloadSpec(_Strict):
    """Overload control: shed the lowest-priority work under load, restore it when load falls.

    Every ``interval`` the controller looks at the window since its last look. It is
    *overloaded* when any configured measure is above its threshold and *calm* when every one
    is below ``hysteresis`` times its threshold (in between it does nothing). Overloaded: one
    shedding step per interval — the lowest-priority sheddable node gets its period doubled
    (frame or timer trigger), up to ``max_slowdown`` times its own; only when no node can be
    slowed further is the lowest-priority one disabled. Calm for ``restore_after``: one step
    undone per interval, the last one first. Never shed: frame sources, nodes in ``protect``,
    nodes at or above ``protect_priority`` (default: the highest priority among the nodes that
    could be shed), input- and loop-triggered nodes.
    """

    interval: DurationMs = Field(
        default=500.0, gt=0, le=MAX_DURATION_MS, description="evaluation window, ms"
    )
    loop_lag_ms: float | None = Field(
        default=5.0, gt=0, description="mean lateness of a 10 ms probe timer over the window, ms"
    )
    cpu_percent: float | None = Field(
        default=None, gt=0, le=100, description="system-wide CPU use over the window, % (psutil)"
    )
    miss_rate: float | None = Field(
        default=0.05, gt=0, le=1, description="deadline misses / activations, nodes with a deadline"
    )
    hysteresis: float = Field(default=0.5, gt=0, lt=1)
    restore_after: DurationMs = Field(
        default=2000.0, ge=0, le=MAX_DURATION_MS, description="calm this long, ms"
    )
    max_slowdown: int = Field(
        default=4, ge=1, le=MAX_FRAME_PERIOD, description="longest period, times the node's own"
    )
    disable: bool = Field(default=True, description="disable nodes once none can be slowed further")
    protect: list[str] = Field(default_factory=list, description="nodes never shed")
    protect_priority: int | None = Field(default=None, ge=1, le=99)


class QosSpec(_Strict):
    """Quality-of-service settings of the runtime (``qos:`` in a graph file)."""

    overload: OverloadSpec | None = None


def _node_name(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_\-]*", name):
        raise ValueError("use letters, digits, _ and -, starting with a letter or _")
    return name


# Checked as a key, so that an error points at the offending name, not at `nodes:`.
NodeName = Annotated[str, AfterValidator(_node_name)]


_ENDPOINT = re.compile(
    r"^(?P<proto>tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/(?P<addr>[^#?]+)"
    r"(?P<rest>[#?].*)?$"
)
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(?P<port>[0-9]{1,5})$")


def _endpoint(v: str) -> str:
    """A Zenoh endpoint such as ``tcp/127.0.0.1:7447`` (protocol/address, optional #config)."""
    m = _ENDPOINT.match(v)
    if not m:
        raise ValueError(
            f"not a Zenoh endpoint: {v!r} (expected e.g. tcp/127.0.0.1:7447 or tls/host:7447)"
        )
    if m.group("proto") in ("tcp", "udp", "tls", "quic", "ws"):
        hp = _HOST_PORT.match(m.group("addr"))
        if not hp or not 0 <= int(hp.group("port")) <= 65535:
            raise ValueError(f"{v!r}: expected host:port with a port in 0..65535")
    return v


def _loopback_host(host: str) -> bool:
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_key_expr(v: str, *, wildcards: bool) -> str:
    """A Zenoh key expression: ``/``-separated non-empty chunks, no ``#`` or ``?``; ``*`` and
    ``**`` (whole chunks) only where a set of keys is meant (imports), not for exports."""
    if not v or v.startswith("/") or v.endswith("/"):
        raise ValueError(f"invalid key expression {v!r}: no leading or trailing /")
    for chunk in v.split("/"):
        if not chunk:
            raise ValueError(f"invalid key expression {v!r}: empty chunk (//)")
        if any(c in chunk for c in "#?$"):
            raise ValueError(f"invalid key expression {v!r}: # ? and $ are reserved")
        if "*" in chunk and (chunk not in ("*", "**") or not wildcards):
            raise ValueError(
                f"invalid key expression {v!r}: "
                + ("* and ** must be whole chunks" if wildcards else "name one key, no * or **")
            )
    return v


def _export_key(v: str) -> str:
    return check_key_expr(v, wildcards=False)


#: Zenoh config keys that only time the link (leases, reconnection): they reach no other peer.
TIMING_KEYS = frozenset(
    {
        "transport/link/tx/lease",
        "transport/link/tx/keep_alive",
        "connect/retry",
        "connect/timeout_ms",
        "listen/retry",
        "listen/timeout_ms",
    }
)


class ZenohSpec(_Strict):
    """The Zenoh session of a graph that spans machines (``zenoh:`` in a graph file).

    Defaults keep a robot's graph to itself: listen on loopback only, no multicast or gossip
    scouting; peers are named explicitly. Everything else is Zenoh's own configuration
    (``config``: json5 paths such as ``transport/link/tls/root_ca_certificate``, or a whole
    ``config_file``), for TLS, access control and routers.
    """

    mode: Literal["peer", "client"] = "peer"
    listen: list[Annotated[str, AfterValidator(_endpoint)]] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:0"]
    )
    connect: list[Annotated[str, AfterValidator(_endpoint)]] = Field(default_factory=list)
    scouting: bool = Field(default=False, description="multicast and gossip scouting")
    config: dict[str, Any] = Field(default_factory=dict, description="more Zenoh config keys")
    config_file: str | None = None
    control: Annotated[str, AfterValidator(_export_key)] | None = Field(
        default=None, description="key of a queryable forwarding `flowrt ctl` (see README)"
    )

    def beyond_loopback(self) -> bool:
        """Whether peers other than this host's may reach the session: a listen or connect
        endpoint that is not loopback, scouting, or configuration flowrt does not read (the
        link's timing, :data:`TIMING_KEYS`, opens nothing and is read as harmless)."""
        if self.scouting or self.config_file:
            return True
        if any(key not in TIMING_KEYS for key in self.config):
            return True
        for endpoint in (*self.listen, *self.connect):
            m = _ENDPOINT.match(endpoint)
            if m is None or m.group("proto") == "serial":
                return True
            if m.group("proto") in ("unixsock-stream", "unixpipe"):
                continue  # a local socket or pipe
            hp = _HOST_PORT.match(m.group("addr"))
            if hp is None or not _loopback_host(hp.group("host")):
                return True
        return False


class ExportSpec(_Strict):
    """An output published under a Zenoh key (``export: {key: node.port}``)."""

    __get_pydantic_json_schema__ = classmethod(
        short_form_schema("short form: the node.port to publish")
    )

    source: str = Field(alias="from", description="node.port to publish")
    encoding: Literal["raw", "jpeg", "png"] = Field(
        default="raw", description="frames: raw pixels with a header, or JPEG/PNG"
    )
    quality: int = Field(default=90, ge=1, le=100, description="JPEG quality")
    policy: EdgePolicy | None = None  # latest for frames, queue for messages
    size: int = Field(default=16, ge=1, le=100_000)

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    @model_validator(mode="before")
    @classmethod
    def _short_form(cls, data: Any) -> Any:
        return {"from": data} if isinstance(data, str) else data

    @field_validator("source")
    @classmethod
    def _node_dot_port(cls, v: str) -> str:
        return node_dot_port(v)

    @property
    def node(self) -> str:
        return self.source.split(".")[0]

    @property
    def port(self) -> str:
        return self.source.split(".")[1]


class ImportSpec(_Strict):
    """A remote stream used as a local output (``import: {name: key}``): a node named ``name``
    with the stream as output ``output`` (and the link's state changes as ``state``)."""

    __get_pydantic_json_schema__ = classmethod(
        short_form_schema("short form: the Zenoh key expression")
    )

    key: str
    period: DurationMs | None = Field(
        default=None, gt=0, le=3_600_000, description="expected period; default: measured"
    )
    stale_after: Annotated[float, Field(gt=0, le=1000)] | Literal["never"] = Field(
        default=5.0,
        description="periods without a message: stale; never: a stream that may be silent "
        "for any time (commands sent now and then)",
    )
    stale: Literal["error", "state"] = Field(
        default="error",
        description="what stale means: error (the import's node in error until it resumes; "
        "a run that ends stale exits 1) or state (a link that drops: one alert per outage, "
        "the time down counted in the node's report, the run unaffected)",
    )
    size: int = Field(default=16, ge=1, le=100_000, description="hand-over queue (messages)")
    frames: bool = Field(
        default=False, description="the stream carries frames: a frame source (ticks)"
    )
    max_bytes: int | None = Field(
        default=None,
        ge=1,
        le=1 << 30,
        description="largest message accepted (payload bytes); default 64 MiB for frames, "
        "1 MiB for messages: a larger one is dropped, counted, never decoded",
    )
    format: Literal["flowrt", "json", "bytes", "jpeg", "png", "raw"] = Field(
        default="flowrt",
        description="what a publisher sends: flowrt (a flowrt export, with its header), or "
        "the payload alone from a plain Zenoh program: json, bytes, jpeg, png, or raw pixels "
        "(with shape and dtype); see docs/zenoh.md",
    )
    shape: tuple[int, ...] | None = Field(
        default=None, description="format raw: the frame's shape, e.g. [480, 640, 3]"
    )
    dtype: Literal["uint8", "uint16", "int16", "float32"] = Field(
        default="uint8", description="format raw: the pixels' type"
    )
    max_pixels: int = Field(
        default=8192 * 8192,
        ge=1,
        le=1 << 30,
        description="largest frame accepted (width x height), checked from the image "
        "header before any decoding",
    )

    @model_validator(mode="before")
    @classmethod
    def _short_form(cls, data: Any) -> Any:
        return {"key": data} if isinstance(data, str) else data

    @model_validator(mode="after")
    def _format(self) -> ImportSpec:
        """Images from a plain program are frames; raw pixels need their shape."""
        if self.format in ("jpeg", "png", "raw") and not self.frames:
            object.__setattr__(self, "frames", True)
        if self.format == "raw" and (self.shape is None or len(self.shape) not in (2, 3)):
            raise ValueError("format raw needs shape: [height, width] or [height, width, channels]")
        if self.format in ("json", "bytes") and self.frames:
            raise ValueError(f"format {self.format} carries messages, not frames")
        return self

    @property
    def byte_limit(self) -> int:
        """The byte limit in force: ``max_bytes``, or the default for the stream's kind."""
        if self.max_bytes is not None:
            return self.max_bytes
        return (64 << 20) if self.frames else (1 << 20)

    @field_validator("key")
    @classmethod
    def _key(cls, v: str) -> str:
        return check_key_expr(v, wildcards=False)


class GraphSpec(_Strict):
    """A whole graph. ``nodes`` keeps file order, which is also the tie-break for priority."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    name: str = "graph"
    description: str = ""
    nodes: dict[NodeName, NodeSpec]
    modes: dict[str, ModeSpec] = Field(default_factory=dict)
    initial_mode: str | None = None
    qos: QosSpec = Field(default_factory=QosSpec)
    zenoh: ZenohSpec | None = Field(default=None, description="several machines: see README")
    exports: dict[Annotated[str, AfterValidator(_export_key)], ExportSpec] = Field(
        default_factory=dict, alias="export"
    )
    imports: dict[NodeName, ImportSpec] = Field(default_factory=dict, alias="import")
    control_allow_kinds: list[str] = Field(
        default_factory=list,
        description="node kinds the control endpoint may swap a node to, besides the kinds "
        "the graph already uses (see README: the control endpoint)",
    )
