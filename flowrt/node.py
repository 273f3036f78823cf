"""The node base class: a user writes ``process``; the runtime does threads, buffers and timing.

Lifecycle and timing contract
-----------------------------
1. The runtime validates ``params`` against the class's ``Params`` model when the graph is
   loaded, long before anything runs.
2. ``setup()`` runs once before the first activation (in the worker process for
   ``placement: process``/``pool``). Open devices and allocate buffers here, not in
   ``__init__``: a restarted node gets a fresh instance and a fresh ``setup``.
3. ``process(**inputs)`` runs once per activation with one keyword argument per input port.
   It may be a plain function or a coroutine function. It returns the value of the single
   output port, a mapping ``{port: value}`` when there are several, or ``None`` for nothing.
   Its activation is measured from release (the tick) to return; past ``deadline`` it counts
   as a miss. It is never re-entered: while it runs, further frame/timer activations are
   skipped and counted (overrun), and input activations wait in the input buffers.
   An inline ``process`` runs on the event loop and must be short; the runtime reports
   calls that block the loop.
4. ``teardown()`` runs once when the runtime stops or before a restart, even after errors.
5. An exception from ``setup`` or ``process`` (or a hung or dead worker) is a failure: the
   node is restarted, a fresh instance after a doubling back-off, and given up (state
   ``failed``) after ``restart.max_failures`` failures in a row without a completed
   activation (:mod:`flowrt.supervision`), or at once if it raises :class:`FatalError`. A
   problem the node can wait out (a device gone) is better reported with ``ctx.set_error``
   while it keeps running.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import logging
import os
import sys
from collections.abc import Callable, Mapping
from random import Random
from typing import TYPE_CHECKING, Any, ClassVar, Final, Generic, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from .frames import worker_frame

if TYPE_CHECKING:
    from .frames import Frame
    from .graph.spec import Trigger
    from .rtdb import RTDB, RtdbHandle

T = TypeVar("T")

SEED_ENV = "FLOWRT_SEED"
"""Environment variable: the run's seed of ``ctx.random`` (default ``0``); inherited by worker
processes, and stored in a deterministic recording so that replay draws the same numbers."""


def node_seed(name: str, seed: str | None = None) -> int:
    """The seed of node ``name``'s ``ctx.random`` for the run seed ``seed`` (default: the
    ``FLOWRT_SEED`` environment variable, else ``0``).

    A stable hash, not Python's ``hash`` (salted per process): a node gets the same numbers
    in every run, in a worker process as on the loop, and when a recording is replayed.
    """
    run = os.environ.get(SEED_ENV, "0") if seed is None else seed
    digest = hashlib.blake2b(f"{run}:{name}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


class Input(Generic[T]):
    """An input port. ``required`` inputs must be connected and hold a value to activate."""

    def __init__(
        self,
        type_: type[T] | Any = object,
        *,
        required: bool = True,
        policy: str | None = None,
        doc: str = "",
    ) -> None:
        self.type: Any = type_
        self.required = required
        # The edge policy when the graph file names none: e.g. a command multiplexer wants
        # the newest command of each source (latest), not a backlog (the message default).
        self.policy = policy
        self.doc = doc
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return f"Input({getattr(self.type, '__name__', self.type)}, name={self.name!r})"


#: An output's expected rate when it publishes once per activation (the default).
PER_ACTIVATION: Final = "activation"


class Output(Generic[T]):
    """An output port; every connected input gets its own buffer (fan-out).

    ``rate_hz`` is how often the output is expected to publish, for the statistics and the
    recording's stream table (expected vs received, "missing"): ``PER_ACTIVATION`` (the
    default) at the node's own rate, a number of publications per second for an output
    with a rate of its own (a status every second on a node ticking at 100 Hz), ``None``
    for one without a rate (on events: nothing is expected, nothing counted missing). A
    rate that depends on the params comes from :meth:`Node.output_rates`.
    """

    def __init__(
        self,
        type_: type[T] | Any = object,
        *,
        doc: str = "",
        rate_hz: float | Literal["activation"] | None = PER_ACTIVATION,
    ) -> None:
        self.type: Any = type_
        self.doc = doc
        self.rate_hz = rate_hz
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return f"Output({getattr(self.type, '__name__', self.type)}, name={self.name!r})"


class FatalError(Exception):
    """Raise from ``setup`` or ``process`` when restarting the node cannot help (a device
    that retried its bound and is gone, a configuration that cannot work): the node is given
    up at once (state ``failed``, this message as the reason) instead of being restarted.

    Supervision recognises any exception whose ``fatal`` attribute is true, in every
    placement; this class is the ready-made one.
    """

    fatal = True


class NoParams(BaseModel):
    """The params model of a node that takes none: any key given is an error."""

    model_config = ConfigDict(extra="forbid")


def validate_params(
    model: type[BaseModel], data: Mapping[str, Any], context: dict[str, Any] | None = None
) -> BaseModel:
    """``data`` as an instance of a node's params ``model``, a key it has no field for
    refused as pydantic's ``extra="forbid"`` would, unless the model says otherwise
    (``model_config`` with ``extra``): a user's ``class Params(BaseModel)`` ignored a
    misspelt key (``factr: 3`` ran with the default) where the built-in kinds refuse it."""
    unknown = _unknown_params(model, data)
    extra = [{"type": "extra_forbidden", "loc": (k,), "input": data[k]} for k in unknown]
    try:
        params = model.model_validate(dict(data), context=context)
    except ValidationError as e:
        if not extra:
            raise
        raise ValidationError.from_exception_data(e.title, [*e.errors(), *extra]) from None  # type: ignore[list-item]
    if extra:
        raise ValidationError.from_exception_data(model.__name__, extra)  # type: ignore[arg-type]
    return params


def _unknown_params(model: type[BaseModel], data: Mapping[str, Any]) -> list[str]:
    if model.model_config.get("extra") is not None:  # the author chose: forbid, allow, ignore
        return []
    known: set[str] = set()
    for name, f in model.model_fields.items():
        known.add(name)
        known.update(a for a in (f.alias, f.validation_alias) if isinstance(a, str))
    return [k for k in data if k not in known]


class NodeContext:
    """What a running node may ask of the runtime, whatever its placement.

    The runtime passes a richer context on the event loop (publishing, frame pools); in a
    worker process only the local parts are available.
    """

    def __init__(
        self, name: str, logger: logging.Logger | None = None, rtdb: RtdbHandle | None = None
    ) -> None:
        self.name = name
        self.log = logger or logging.getLogger(f"flowrt.node.{name}")
        self._rtdb_handle = rtdb
        self._rtdb: RTDB | None = None
        self._random: Random | None = None

    @property
    def random(self) -> Random:
        """The node's random numbers: seeded from its name and the run's seed
        (:func:`node_seed`), so a run is reproducible and a deterministic replay draws exactly
        what the recorded run drew. A restarted node starts the sequence again."""
        if self._random is None:
            self._random = Random(node_seed(self.name))
        return self._random

    def observe(self, observer: Any) -> None:
        """Let ``observer`` watch every activation and publication of the graph (the
        deterministic recording, :mod:`flowrt.determinism`); only on the event loop."""
        raise RuntimeError("observe() is only available to inline nodes on the event loop")

    def now(self) -> float:
        """Runtime clock, seconds (monotonic; virtual under a test clock)."""
        import time

        return time.monotonic()

    def new_frame(
        self, shape: tuple[int, ...], dtype: Any = np.uint8, pixel_format: str = "BGR"
    ) -> Frame:
        """A writable frame to fill and return; in shared memory when the runtime provides it.

        In a worker process it is a slot the main process lent for this call (see
        :mod:`flowrt.frames.lending`): returned, only its descriptor crosses the socket. Valid
        for the call that made it: once returned it is read-only, and one not returned is reused.
        """
        return worker_frame(shape, dtype, self.name, pixel_format)

    def publish(self, port: str, value: Any) -> None:
        """Publish outside the return path (streaming nodes); only on the event loop."""
        raise RuntimeError("publish() is only available to inline nodes on the event loop")

    def emit(self, event: Any) -> None:
        """Publish a typed event (e.g. a HealthAlert); only on the event loop."""
        raise RuntimeError("emit() is only available to inline nodes on the event loop")

    def stats(self) -> Any:
        """The runtime's statistics (``RuntimeStats``); only on the event loop."""
        raise RuntimeError("stats() is only available to inline nodes on the event loop")

    def elapsed(self) -> float:
        """Seconds since the runtime started (the time base of events); approximate here."""
        return self.now()

    async def wait_readers(self) -> None:
        """Wait until every period-1 frame-triggered reader of this node's frame outputs is
        ready for the next frame (idle, started), whatever its placement.

        A source that paces itself by its readers (``pacing: fast``) awaits this before
        publishing, so that a reader slower than the source is never skipped. Outside a
        runtime there are no readers: it returns at once.
        """

    def request_stop(self) -> None:
        """Ask the runtime to stop; only on the event loop."""
        raise RuntimeError("request_stop() is only available to inline nodes on the event loop")

    @property
    def rtdb(self) -> RTDB:
        """The runtime's real-time database (``flowrt.rtdb.RTDB``), in every placement."""
        if self._rtdb is None:
            if self._rtdb_handle is None:
                raise RuntimeError(f"{self.name}: no RTDB (the node runs outside a Runtime)")
            from .rtdb import RTDB

            self._rtdb = RTDB.attach(self._rtdb_handle)
        return self._rtdb

    @property
    def graph(self) -> Any:
        """The running graph (a :class:`flowrt.Graph`: every node's kind, class and params),
        to read, never to change: for a node that adapts to what else runs (the live view
        requires a token when the graph can drive from its page). Only on the event loop."""
        raise RuntimeError("graph is only available to inline nodes on the event loop")

    def set_mode(self, mode: str) -> None:
        """Switch the runtime to a mode of the graph file; only on the event loop."""
        raise RuntimeError("set_mode() is only available to inline nodes on the event loop")

    @property
    def period(self) -> float | None:
        """The node's timer period in seconds (None unless timer-triggered): e.g. to derive a
        timeout of "three periods" that follows run-time timing changes."""
        return None

    def input_time(self, name: str) -> float | None:
        """When the value input ``name`` holds for this activation was published on its edge
        (runtime clock, seconds, comparable with :meth:`now`); None when it holds no value.

        This is what freshness is judged on (see :mod:`flowrt.freshness`): never the value's
        identity. Known on the event loop (inline nodes); None in a worker process.
        """
        return None

    def input_age(self, name: str, value: Any = None) -> float | None:
        """Seconds since the value of input ``name`` was published; with ``value`` given, the
        older of that and the value's own ``timestamp`` when it is in this clock (a stamp in
        the future is another machine's and is ignored). None when nothing was received."""
        from .freshness import age_of

        return age_of(self.now(), self.input_time(name), value)

    def set_error(self, reason: str) -> None:
        """Mark the node in an error state (a source that cannot open, a bus gone).

        The node keeps running (it may recover and call :meth:`clear_error`); the table shows
        it red with ``reason``, statistics carry it, and a :class:`HealthAlert` is emitted once
        per new reason. Only on the event loop.
        """
        raise RuntimeError("set_error() is only available to inline nodes on the event loop")

    def clear_error(self) -> None:
        """Leave the error state set by :meth:`set_error` (the device is back)."""
        raise RuntimeError("clear_error() is only available to inline nodes on the event loop")

    def set_waiting(self, reason: str | None) -> None:
        """Say the node waits for something outside the graph that is normal to be absent
        (an operator yet to open the page that drives it); ``None``: it no longer waits.

        Not an error: the table shows state ``waiting`` with ``reason``, and a run ending
        while a node waits ends well. Only on the event loop.
        """
        raise RuntimeError("set_waiting() is only available to inline nodes on the event loop")


class Node:
    """Base class of every node; subclasses declare ports as class attributes.

    Example::

        class Threshold(Node):
            class Params(BaseModel):
                level: int = 128

            frame = Input(Frame)
            count = Output(int)

            def process(self, frame: Frame) -> int:
                return int((frame.data > self.params.level).sum())
    """

    Params: ClassVar[type[BaseModel]] = NoParams
    inputs: ClassVar[Mapping[str, Input[Any]]] = {}
    outputs: ClassVar[Mapping[str, Output[Any]]] = {}
    any_inputs: ClassVar[Input[Any] | None] = None
    """Set to an ``Input`` to accept inputs of any name with that type (e.g. a display)."""
    inline_only: ClassVar[bool] = False
    """True for nodes that need the event loop (frame pools, servers): placement is checked."""
    swappable: ClassVar[frozenset[str]] = frozenset()
    """The params a swap over the control endpoint (``POST /swap``, ``flowrt ctl swap``) may
    change: an algorithm's, never where data goes (an address, a device, a token, a folder).
    Shown by ``flowrt kinds KIND``; none by default (:mod:`flowrt.control._swap_policy`)."""
    swap_folders: ClassVar[Mapping[str, str]] = {}
    """Path params in ``swappable`` -> the folder param each is confined to (a recorder's
    ``session`` inside its ``path``): relative, without ``..``, resolved under that folder."""
    timing_fixed: ClassVar[bool] = False
    """True for nodes that keep a robot safe (an arbiter, an e-stop): their timing is the
    graph file's (its modes included); the control endpoint refuses to change it (403), as it
    refuses their safety params: a local caller disabling the arbiter left the robot on its
    last command, a Stop on the page no longer reaching it."""
    external: ClassVar[bool] = False
    """True for nodes whose outputs come from outside the graph although they have inputs (a
    CAN bus: frames received while it transmits its inputs). A deterministic recording stores
    their outputs as values, like a source's, and replay publishes those instead of running
    the node (:mod:`flowrt.determinism`)."""

    params: Any
    ctx: NodeContext

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        ins: dict[str, Input[Any]] = {}
        outs: dict[str, Output[Any]] = {}
        for base in reversed(cls.__mro__):
            for key, value in vars(base).items():
                if isinstance(value, Input) and key != "any_inputs":  # not a port of its own
                    ins[key] = value
                elif isinstance(value, Output):
                    outs[key] = value
        cls.inputs = ins
        cls.outputs = outs

    @classmethod
    def default_trigger(cls, params: Any) -> Trigger | None:
        """The trigger used when the graph gives none (e.g. a capture node's own fps)."""
        return None

    @classmethod
    def advise(cls, params: Any) -> list[tuple[str, str]]:
        """Warnings about valid but costly params, as ``(param key, message)``.

        ``flowrt validate`` shows them located at the param (``""``: at ``params``); an
        error belongs in the ``Params`` model instead. E.g. a capture node says how much
        shared memory its frame size will take.
        """
        return []

    @classmethod
    def params_inputs(cls, params: Any) -> Mapping[str, Input[Any]]:
        """Inputs that exist because of the params (a CAN node transmits the messages of its
        DBC file, one input each), beside the class's own; checked when the graph loads."""
        return {}

    @classmethod
    def params_outputs(cls, params: Any) -> Mapping[str, Output[Any]]:
        """Outputs that exist because of the params (a CAN node publishes each message of its
        DBC file on an output named after it), beside the class's own."""
        return {}

    @classmethod
    def output_rates(cls, params: Any) -> Mapping[str, float | None]:
        """Expected publications per second of the outputs that do not publish once per
        activation, by port; None for an output without a rate (event-driven). Outputs not
        named follow the node's activation rate. The runtime's statistics (``output_hz``)
        and the recording's stream table read it.

        Default: each port's ``Output(rate_hz=...)``, the class's and the params' outputs.
        Override it when a rate depends on the params (a CAN node's status every
        ``status_ms``; each DBC message at its cycle time).
        """
        ports = {**cls.outputs, **cls.params_outputs(params)}
        return {n: p.rate_hz for n, p in ports.items() if not isinstance(p.rate_hz, str)}

    @classmethod
    def frame_ports(cls) -> list[str]:
        """Output ports carrying frames: each publication on one is a tick of the frame clock."""
        from .frames import Frame

        return [
            n
            for n, p in cls.outputs.items()
            if isinstance(p.type, type) and issubclass(p.type, Frame)
        ]

    def setup(self) -> Any:
        """Acquire resources; may be async."""

    def process(self, *args: Any, **inputs: Any) -> Any:
        raise NotImplementedError(f"{type(self).__name__}.process")

    def teardown(self) -> Any:
        """Release resources; may be async; runs even after errors."""

    # Optional hooks (looked up by name, so a node defines only what it needs):
    # ``get_state() -> Any`` / ``set_state(state)``: when the node is swapped for a new instance
    # (``Runtime.swap``, ``flowrt ctl swap``/``reload``), the new one receives the old one's
    # state, e.g. a tracker's last position. ``params_changed(old)``: params replaced between
    # activations (a mode's weights); recompute what ``setup`` derived from them.
    # ``on_disable()``: the node was disabled while it runs (``Runtime.set_timing(node,
    # enabled=False)``, a mode): a node that commands a device every tick leaves it safe (a
    # haptic handle's force zeroed); called between calls, never beside one, in the node's
    # own process (:mod:`flowrt.kernel.disabling`).
    # ``report() -> Any``: JSON-able facts about the node (a recorder's per-stream tables),
    # published in ``RuntimeStats.reports`` (``--stats-json``, ``ctl stats --json``).


def make_node(
    cls: type[Node], params: BaseModel | Mapping[str, Any] | None, ctx: NodeContext
) -> Node:
    """Instantiate a node with validated params and its context, ready for ``setup``."""
    node = cls()
    node.params = (
        params if isinstance(params, BaseModel) else validate_params(cls.Params, params or {})
    )
    node.ctx = ctx
    return node


class NodeFactory:
    """A picklable recipe for a node instance, so a worker process can build its own copy.

    It pickles its class and its params' class by name (module and qualified name, found
    again in the process that unpickles it), and the params as their field values: pickle's
    own way refuses a class that is no longer its module's, which every class of a module
    becomes when ``flowrt ctl reload`` re-imports it in the main process (an inline node's
    reload); the other nodes of that module could then no longer be restarted in a worker.
    """

    def __init__(self, cls: type[Node], params: BaseModel, name: str) -> None:
        self._cls: type[Node] | None = cls
        self._params: BaseModel | None = params
        # Unpickled: the class's name and the params' portable form, resolved by the first
        # call (after the module is imported anew when ``reload`` says so).
        self._cls_ref: _ClassRef = cls
        self._params_state: Any = None
        self.name = name
        self.rtdb: RtdbHandle | None = None  # set by the runtime: where ctx.rtdb attaches
        # ``flowrt ctl reload``: a worker forked from a process that imported the module
        # before the edit must import it anew to run the edited code.
        self.reload = False
        # The ports the graph wired, as the runtime's process knows them: a reload in a
        # worker must keep them (the runtime never sees the edited class to check it).
        self.ports = _ports(cls, params)

    @property
    def cls(self) -> type[Node]:
        """The node's class (in a worker: found by its name the first time it is asked)."""
        if self._cls is None:
            self._cls = _find_class(self._cls_ref)
        return self._cls

    @property
    def params(self) -> BaseModel:
        """The node's params (in a worker: rebuilt for their class found by name)."""
        if self._params is None:
            self._params = _from_portable(self._params_state)
        return self._params

    def __reduce__(self) -> tuple[Any, ...]:
        if self._params is None:  # pickled again before its first call: as it came
            ref, state = self._cls_ref, self._params_state
        else:
            ref, state = _class_ref(self.cls), _portable(self._params)
        return (_unpickle_factory, (ref, state, self.name, self.rtdb, self.reload, self.ports))

    def __call__(self) -> Node:
        if self.reload:
            cls = reimport(self._cls_ref if self._cls is None else self._cls)
            # Rebuilt from the portable form after the re-import: nested models of the
            # edited module get its new classes too.
            state = self._params_state if self._params is None else _portable(self._params)
            params = (
                _construct(cls.Params, state) if isinstance(state, _ModelState) else self.params
            )
            changed = _ports_changed(self.ports, _ports(cls, params))
            if changed:  # as an inline node's reload is refused by the swap's port check
                raise ImportError(
                    f"the edit changes {self.name}'s ports ({changed}): a reload keeps a "
                    "node's ports; restart the graph to wire new ones"
                )
        else:
            cls, params = self.cls, self.params
        return make_node(cls, params, NodeContext(self.name, rtdb=self.rtdb))

    @staticmethod
    def carry_params(cls: type[Node], params: BaseModel) -> BaseModel:
        """``params`` as an instance of ``cls.Params``, the class of a module re-imported
        since they were made: their field values and the fields that were set, taken over
        without validation (``model_construct``). Validating them again would read what a
        validator already converted as if it were written: a duration "200ms" became 0.2 s,
        which read again as milliseconds is 0.2 ms. Fields the edit added get their defaults;
        nested models are rebuilt for the classes their names now find."""
        state = _portable(params)
        if not isinstance(state, _ModelState):
            return params
        return _construct(cls.Params, state)


#: A class as a factory pickles it: ``(module, qualified name)``, or the class itself when
#: its name does not find it (a class made in a function: pickle then says why it refuses).
_ClassRef = tuple[str, str] | type


def _lookup(module: Any, qualname: str) -> Any:
    obj = module
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def _class_ref(cls: type) -> _ClassRef:
    """``cls`` by name, if its name finds a class in the module as loaded now."""
    module = sys.modules.get(cls.__module__)
    try:
        found = _lookup(module, cls.__qualname__) if module is not None else None
    except AttributeError:
        found = None
    return (cls.__module__, cls.__qualname__) if isinstance(found, type) else cls


def _find_class(ref: _ClassRef) -> Any:
    """The class ``ref`` names, as the module imported in this process defines it now."""
    if isinstance(ref, type):
        return ref
    module, qualname = ref
    return _lookup(importlib.import_module(module), qualname)


def reimport(ref: _ClassRef) -> type[Node]:
    """The node's class from its module imported anew from disk (imported afresh when this
    process never imported it, re-imported when it did: a worker forked from a process that
    had; ``flowrt ctl reload`` of an inline node, in the runtime's process). A module that
    does not import (the edit has a syntax error, or exits) raises an ImportError of one
    line, which is what the swap that failed shows the user."""
    module, qualname = (ref.__module__, ref.__qualname__) if isinstance(ref, type) else ref
    try:
        loaded = sys.modules.get(module)
        fresh = importlib.reload(loaded) if loaded is not None else importlib.import_module(module)
        cls = _lookup(fresh, qualname)
    except (Exception, SystemExit) as e:  # whatever the module does at import is contained
        if isinstance(e, SyntaxError):
            why = f"{e.msg} ({e.filename}, line {e.lineno})"
        else:
            why = " ".join(str(e).split())
        raise ImportError(f"re-importing {module} failed: {type(e).__name__}: {why}") from None
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise ImportError(f"re-importing {module} failed: {qualname} is no longer a Node class")
    return cls


@dataclasses.dataclass(frozen=True)
class _ModelState:
    """A pydantic model by name and field values (see :class:`NodeFactory`)."""

    cls: _ClassRef
    values: dict[str, Any]
    fields_set: frozenset[str]
    extra: dict[str, Any] | None
    private: dict[str, Any] | None


def _portable(value: Any) -> Any:
    """``value`` with every pydantic model in it (in lists, tuples and dicts too) replaced
    by its class's name and its field values: it pickles whatever became of its class."""
    if isinstance(value, BaseModel):
        return _ModelState(
            _class_ref(type(value)),
            {k: _portable(v) for k, v in value.__dict__.items()},
            frozenset(value.model_fields_set),
            _portable(value.__pydantic_extra__),
            _portable(value.__pydantic_private__),
        )
    return _inside(value, _portable)


def _from_portable(value: Any) -> Any:
    """What :func:`_portable` made, built again with the classes the names find now."""
    if isinstance(value, _ModelState):
        return _construct(_find_class(value.cls), value)
    return _inside(value, _from_portable)


def _inside(value: Any, each: Callable[[Any], Any]) -> Any:
    """``each`` of a list's, tuple's or dict's items (the same container again), or ``value``."""
    kind = type(value)
    if kind is list or kind is tuple:
        return kind(each(v) for v in value)
    if kind is dict:
        return {k: each(v) for k, v in value.items()}
    return value


def _construct(model: type[BaseModel], state: _ModelState) -> BaseModel:
    """An instance of ``model`` with ``state``'s values, not validated again (their class may
    be an edited one: fields it no longer has are left out, new ones get their defaults)."""
    names = set(model.model_fields)
    values = {k: _from_portable(v) for k, v in state.values.items() if k in names}
    extra = _from_portable(state.extra) if state.extra else {}
    if model.model_config.get("extra") == "allow":
        names |= set(extra)
        values = {**extra, **values}
    built = model.model_construct(_fields_set=set(state.fields_set & names), **values)
    private = _from_portable(state.private) if state.private else None
    if private and built.__pydantic_private__ is not None:
        known = getattr(model, "__private_attributes__", {})
        built.__pydantic_private__.update({k: v for k, v in private.items() if k in known})
    return built


def _unpickle_factory(
    ref: _ClassRef,
    state: Any,
    name: str,
    rtdb: RtdbHandle | None,
    reload: bool,
    ports: tuple[frozenset[str], frozenset[str]],
) -> NodeFactory:
    """A factory from its pickled parts; its class and params are found at its first call."""
    factory = NodeFactory.__new__(NodeFactory)
    factory._cls, factory._params = None, None
    factory._cls_ref, factory._params_state = ref, state
    factory.name, factory.rtdb, factory.reload, factory.ports = name, rtdb, reload, ports
    return factory


def _ports(cls: type[Node], params: Any) -> tuple[frozenset[str], frozenset[str]]:
    """(input names, output names) of a node of ``cls`` with ``params``."""
    outputs = {*cls.outputs, *cls.params_outputs(params)}
    return frozenset(cls.inputs), frozenset(outputs)


def _ports_changed(
    old: tuple[frozenset[str], frozenset[str]], new: tuple[frozenset[str], frozenset[str]]
) -> str:
    """What differs, in words ("outputs +result -out"); empty when nothing does."""
    said = []
    for what, a, b in (("inputs", old[0], new[0]), ("outputs", old[1], new[1])):
        diff = [f"+{p}" for p in sorted(b - a)] + [f"-{p}" for p in sorted(a - b)]
        if diff:
            said.append(f"{what} {' '.join(diff)}")
    return "; ".join(said)
