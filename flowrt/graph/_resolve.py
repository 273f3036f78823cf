"""A validated, resolved graph: node classes found, params parsed, triggers and edges settled.

``spec`` says what the user wrote; ``Graph`` is what will run. All structural checks happen
here, every problem collected with its location, so a bad graph never reaches the runtime.
"""

from __future__ import annotations

import inspect
import os
from collections import deque
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from math import gcd
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError, ValidationInfo

from ..frames import Frame
from ..node import Node
from ..node import validate_params as params_of
from ._exports import check_exports
from ._loading import Locations, check_text, pydantic_diagnostics, read_graph_file
from ._ports import checked_type as checked_type  # where the kernel imports it from
from ._ports import is_compatible, node_ports, ports_unknown, type_name
from ._registry import KindError, NotImported, resolve_kind
from .diagnostics import Diagnostic, GraphError, Severity, closest, did_you_mean
from .spec import (
    EdgePolicy,
    FrameTrigger,
    GraphSpec,
    InputSpec,
    InputTrigger,
    NodeSpec,
    TimerTrigger,
    Trigger,
    merge_params,
)

PARAMS_BASE_DIR = "base_dir"
"""Key of the validation context that a node's params model is validated with: the graph
file's directory (a ``Path``), or None for a graph built in Python."""


def resolve_path(path: str, info: ValidationInfo) -> str:
    """A path written in a node's params, made absolute the way users expect.

    For use in a params model's validator (``info`` is pydantic's ``ValidationInfo``): a
    relative path in a graph file resolves against the graph file's directory, so that a
    graph runs the same from any working directory; in a graph built in Python (no graph
    file) against the current directory, like ``open()``. ``~`` is expanded.
    """
    expanded = os.path.expanduser(path)
    if os.path.isabs(expanded):
        return expanded
    context = info.context if isinstance(info.context, Mapping) else {}
    base = context.get(PARAMS_BASE_DIR)
    return os.path.abspath(os.path.join(base if base is not None else os.getcwd(), expanded))


@dataclass(frozen=True)
class Edge:
    """A connection from ``src.port`` to ``dst.port`` with the reader's buffer policy."""

    src: str
    src_port: str
    dst: str
    dst_port: str
    policy: EdgePolicy
    size: int

    @property
    def name(self) -> str:
        return f"{self.src}.{self.src_port}->{self.dst}.{self.dst_port}"


@dataclass
class ResolvedNode:
    name: str
    spec: NodeSpec
    cls: type[Node]
    params: BaseModel
    trigger: Trigger
    order: int  # position in the file: tie-break after priority

    @property
    def frame_source(self) -> str | None:
        """``node.port`` whose ticks activate this node, for frame triggers."""
        if isinstance(self.trigger, FrameTrigger):
            return self.trigger.frame
        return None


@dataclass
class Graph:
    spec: GraphSpec
    nodes: dict[str, ResolvedNode]
    edges: list[Edge]
    warnings: list[Diagnostic] = field(default_factory=list)
    file: str = "<python>"
    base_dir: Path | None = None  # the graph file's directory: where relative params resolve
    not_imported: dict[str, str] = field(default_factory=dict)
    """Nodes whose dotted-path kind was not imported (``import_kinds=False``): name -> kind.
    Their params, ports and triggers are unchecked and they are not in ``nodes``."""

    def validate_params(self, cls: type[Node], data: Mapping[str, Any]) -> BaseModel:
        """Validate params for ``cls`` as the graph file's own were (relative paths resolve
        against its directory): for params changed at run time by a mode, a swap or the API."""
        return params_of(cls.Params, data, {PARAMS_BASE_DIR: self.base_dir})

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        kinds: Mapping[str, type[Node]] | None = None,
        *,
        import_kinds: bool = True,
    ) -> Graph:
        """Load a graph file; relative paths in its params resolve against its directory."""
        base_dir = Path(path).resolve().parent
        return cls.from_text(
            read_graph_file(path), str(path), kinds, base_dir=base_dir, import_kinds=import_kinds
        )

    @classmethod
    def from_text(
        cls,
        text: str,
        file: str = "<graph>",
        kinds: Mapping[str, type[Node]] | None = None,
        *,
        base_dir: Path | None = None,
        import_kinds: bool = True,
    ) -> Graph:
        loaded = check_text(text, file)
        if loaded.spec is None:
            raise GraphError(loaded.errors)
        # Structural checks run even when some nodes failed, so every problem is listed at once.
        return resolve(
            loaded.spec,
            loaded.locs,
            kinds,
            earlier=loaded.errors,
            invalid_nodes=loaded.invalid_nodes,
            set_aside=loaded.set_aside,
            base_dir=base_dir,
            import_kinds=import_kinds,
        )

    def frame_port(self, source: str) -> str:
        """Normalise a frame trigger's source (``cam`` or ``cam.frame``) to ``cam.frame``."""
        if "." in source:
            return source
        return f"{source}.{self.nodes[source].cls.frame_ports()[0]}"

    def frame_interval_ms(self, source: str) -> float | None:
        """Nominal time between ticks of a frame source, when its own trigger is a timer."""
        node = self.nodes.get(source.split(".")[0])
        if node is None:
            return None
        if isinstance(node.trigger, TimerTrigger):
            return node.trigger.timer
        if isinstance(node.trigger, FrameTrigger):
            inner = self.frame_interval_ms(node.trigger.frame)
            return None if inner is None else inner * node.trigger.period
        fps = getattr(node.params, "fps", None)
        return 1000.0 / fps if isinstance(fps, int | float) and fps > 0 else None


def importable(folder: Path) -> None:
    """Put a graph file's folder on the import path, so its ``module:Class`` kinds import
    without ``PYTHONPATH=.`` (as ``python script.py`` finds modules beside the script).

    Appended, not prepended: a file beside the graph never shadows flowrt, numpy or the
    standard library. Worker processes start with the main process's ``sys.path``.
    """
    import sys

    entry = str(folder)
    if entry not in sys.path:
        sys.path.append(entry)


@dataclass
class _Resolution:
    """What the steps of :func:`resolve` share: the spec, what was found so far, and the
    diagnostics. Each step adds to it; none raises (every problem is collected)."""

    spec: GraphSpec
    locs: Locations
    kinds: Mapping[str, type[Node]] | None
    base_dir: Path | None
    import_kinds: bool
    invalid_nodes: Collection[str]
    diags: list[Diagnostic]
    classes: dict[str, type[Node]] = field(default_factory=dict)
    params: dict[str, BaseModel] = field(default_factory=dict)
    not_imported: dict[str, str] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    triggers: dict[str, Trigger] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        """Every node name the file gave, the ones dropped as invalid too."""
        return [*self.spec.nodes, *self.invalid_nodes]

    def at(self, path: tuple[str | int, ...], msg: str, sev: Severity = Severity.error) -> None:
        self.diags.append(self.locs.diag(path, msg, sev))


def resolve(
    spec: GraphSpec,
    locs: Locations | None = None,
    kinds: Mapping[str, type[Node]] | None = None,
    *,
    earlier: Iterable[Diagnostic] = (),
    invalid_nodes: Collection[str] = (),
    set_aside: Mapping[str, tuple[str, Mapping[str, Any]]] | None = None,
    base_dir: Path | None = None,
    import_kinds: bool = True,
) -> Graph:
    """Check everything that needs the node classes; raise GraphError with all problems.

    ``earlier`` are problems already found while loading, reported together with these;
    ``invalid_nodes`` were dropped from ``spec`` by then, so references to them are not
    reported again as unknown nodes (``set_aside``: their kind and params, still checked).
    ``base_dir`` is the graph file's directory, handed to
    the params models as validation context (see :func:`resolve_path`). ``import_kinds=False``
    leaves dotted-path kinds unimported (their nodes unchecked, listed in
    ``Graph.not_imported``).

    The steps, in order: kinds and params, edges, triggers and placement, exports, cycles
    and frame chains, modes and QoS, then deadlines once nothing else is wrong.
    """
    locs = locs or Locations("<python>")
    r = _Resolution(spec, locs, kinds, base_dir, import_kinds, invalid_nodes, list(earlier))
    r.spec = _with_imports(spec, r.at)  # import: nodes added, their problems located
    if base_dir is not None and import_kinds:
        importable(base_dir)
    _resolve_classes(r)
    for name, (kind, data) in (set_aside or {}).items():  # a node left out: its params still
        _class_and_params(r, name, kind, data)  # checked (a bad trigger hid a bad param)
    _resolve_edges(r)
    _resolve_triggers(r)
    check_exports(r.spec, r.at, r.classes, r.params, r.names, r.invalid_nodes)
    _check_cycles(r.spec, r.edges, r.at)
    _check_frame_chains(r.triggers, r.at)
    _check_modes_and_qos(r)
    resolved = {
        name: ResolvedNode(name, ns, r.classes[name], r.params[name], r.triggers[name], i)
        for i, (name, ns) in enumerate(r.spec.nodes.items())
        if name in r.classes and name in r.params and name in r.triggers
    }
    graph = Graph(
        r.spec,
        resolved,
        r.edges,
        file=locs.file,
        base_dir=base_dir,
        not_imported=r.not_imported,
    )
    diags = r.diags
    _check_deadlines(graph, r.at)  # (with errors too: every warning at once, as the rest)
    diags.sort(key=lambda d: (d.line, d.column))
    if any(d.severity is Severity.error for d in diags):
        raise GraphError(diags)
    graph.warnings = diags
    return graph


def _resolve_classes(r: _Resolution) -> None:
    """Each node's class (imported unless told not to) and its validated params."""
    for name, ns in r.spec.nodes.items():
        found = _class_and_params(r, name, ns.kind, ns.params)
        if found is not None:
            r.classes[name], r.params[name] = found


def _class_and_params(
    r: _Resolution, name: str, kind: str, data: Mapping[str, Any]
) -> tuple[type[Node], BaseModel] | None:
    """A node's class and validated params, or None after saying what is wrong."""
    at, base_dir = r.at, r.base_dir
    try:
        cls = resolve_kind(kind, r.kinds, allow_import=r.import_kinds)
    except NotImported:
        r.not_imported[name] = kind
        return None
    except KindError as e:
        looked = ""
        if ":" in kind and "cannot import" in str(e):
            beside = f"beside the graph file ({base_dir}), " if base_dir is not None else ""
            looked = f"; looked {beside}on PYTHONPATH and in the installed packages"
        at(("nodes", name, "kind"), f"{e}{looked}")
        return None
    except Exception as e:  # the kind's own module raised while imported: say so, in place
        at(("nodes", name, "kind"), f"node kind {kind!r}: import failed: {e!r}")
        return None
    try:
        params = params_of(cls.Params, data, {PARAMS_BASE_DIR: base_dir})
    except ValidationError as e:
        r.diags.extend(pydantic_diagnostics(e, r.locs, ("nodes", name, "params"), cls.Params))
        return None
    try:
        advice = cls.advise(params)
    except Exception as e:  # a third-party hook must not turn validation into a traceback
        advice = [("", f"{kind}.advise failed: {e!r}")]
    for key, message in advice:
        at(("nodes", name, "params", *([key] if key else [])), message, Severity.warning)
    return cls, params


def _resolve_edges(r: _Resolution) -> None:
    """Every input's edge, its ports and types checked; required inputs connected. A port
    that may be one a node's invalid params would give it is not reported (see
    :func:`ports_unknown`); the rest of its edge is."""
    spec, at, classes, params = r.spec, r.at, r.classes, r.params
    names, invalid_nodes, edges = r.names, r.invalid_nodes, r.edges
    for name, ns in spec.nodes.items():
        cls = classes.get(name)
        misspelt: set[str | None] = set()  # inputs already named by a "did you mean"
        own_ins = node_ports(cls, params, name, True) if cls else {}
        for port, ins in ns.inputs.items():
            path = ("nodes", name, "inputs", port)
            if "." not in ins.source and ins.node not in spec.imports:
                at((*path, "from"), f"expected node.port, got {ins.source!r}")
                continue
            no_input = False
            if cls is not None and port not in own_ins and cls.any_inputs is None:
                no_input = True
                if not ports_unknown(cls, params, name, True):
                    have = ", ".join(own_ins) or "none"
                    at(
                        path,
                        f"{ns.kind} has no input {port!r} (its inputs: {have})"
                        + did_you_mean(port, own_ins),
                    )
                    misspelt.add(closest(port, cls.inputs))
                    continue
            if ins.node not in spec.nodes:
                if ins.node not in invalid_nodes:
                    hint = did_you_mean(ins.node, names)
                    at(path, f"input from unknown node {ins.node!r}" + hint)
                continue
            src_cls = classes.get(ins.node)
            if src_cls is None or cls is None:
                continue
            src_outs = _source_outputs(r, src_cls, ins, path)
            if src_outs is None:
                continue
            if no_input:  # an input its params may give it: no edge, and no type to check
                continue
            in_port = own_ins.get(port) or cls.any_inputs
            assert in_port is not None
            out_t, in_t = src_outs[ins.port].type, in_port.type
            if not is_compatible(out_t, in_t):
                at(
                    path,
                    f"incompatible port types: {ins.source} produces {type_name(out_t)}, "
                    f"{name}.{port} expects {type_name(in_t)}",
                )
                continue
            edges.append(_edge(name, port, ins, in_t, out_t, in_port.policy))
        if cls is not None:
            for port, p in cls.inputs.items():
                if p.required and port not in ns.inputs and port not in misspelt:
                    at(("nodes", name), f"required input {port!r} of {ns.kind} is not connected")


def _source_outputs(
    r: _Resolution, src_cls: type[Node], ins: InputSpec, path: tuple[str | int, ...]
) -> Mapping[str, Any] | None:
    """The outputs of an input's source node, or None when the port is not among them (an
    error, unless its params may give it one: see :func:`ports_unknown`)."""
    src_outs = node_ports(src_cls, r.params, ins.node, False)
    if ins.port in src_outs:
        return src_outs
    if not ports_unknown(src_cls, r.params, ins.node, False):
        r.at(
            path,
            f"node {ins.node!r} ({r.spec.nodes[ins.node].kind}) has no output {ins.port!r}"
            f" (its outputs: {', '.join(src_outs) or 'none'})" + did_you_mean(ins.port, src_outs),
        )
    return None


def _resolve_triggers(r: _Resolution) -> None:
    """Each node's trigger (its own, its class's default, or its inputs) and placement."""
    spec, at, classes, params = r.spec, r.at, r.classes, r.params
    names, triggers = r.names, r.triggers
    for name, ns in spec.nodes.items():
        cls = classes.get(name)
        trig = ns.trigger
        if trig is None and cls is not None and name in params:
            try:
                trig = cls.default_trigger(params[name])
            except ValueError as e:  # e.g. a rate that makes a timer out of range
                problem = e.errors()[0]["msg"] if isinstance(e, ValidationError) else str(e)
                at(("nodes", name, "params"), f"its default trigger: {problem}")
                continue
        if trig is None:
            if ns.inputs:
                trig = InputTrigger()
            elif cls is not None and name in params:  # bad params already reported
                at(
                    ("nodes", name),
                    "node has no trigger and no inputs: add trigger: {timer: ...} or loop",
                )
                continue
            else:
                continue
        triggers[name] = trig
        _check_trigger(name, ns, trig, spec, classes, at, names)
        _check_placement(name, ns, trig, cls, at)


def _check_placement(
    name: str, ns: NodeSpec, trig: Trigger, cls: type[Node] | None, at: Any
) -> None:
    """Where the node runs against what it asks of it: inline-only kinds, CPUs this machine
    has, ``timing: precise`` (a timer, ideally inline), worker-only keys on inline nodes."""
    if cls is not None and cls.inline_only and ns.placement.value != "inline":
        at(
            ("nodes", name, "placement"),
            f"{ns.kind} runs on the event loop (it serves or owns loop resources): "
            "placement must be inline",
        )
    if ns.cpus is not None and ns.placement.value != "inline":
        available = _available_cpus()
        missing = sorted(set(ns.cpus) - available)
        if missing:
            left = sorted(set(ns.cpus) & available)
            then = (
                f"its worker will run on CPU {', '.join(map(str, left))} only"
                if left
                else "its worker will not be pinned"
            )
            at(
                ("nodes", name, "cpus"),
                f"CPU {', '.join(map(str, missing))} not on this machine (it has "
                f"{', '.join(map(str, sorted(available)))}): {then}",
                Severity.warning,
            )
    if ns.timing == "precise" and not isinstance(trig, TimerTrigger):
        by = (
            "its inputs"
            if isinstance(trig, InputTrigger)
            else "frames"
            if isinstance(trig, FrameTrigger)
            else "loop"
        )
        at(
            ("nodes", name, "timing"),
            "timing: precise applies to a timer-triggered node (trigger: {timer: ...}); "
            f"this one is triggered by {by}",
        )
    elif ns.timing == "precise" and ns.placement.value != "inline":
        at(
            ("nodes", name, "timing"),
            f"timing: precise on a node at placement {ns.placement.value}: its release "
            "thread hands each release to the loop, which sends it to the worker "
            "(inline nodes are called in the thread itself)",
            Severity.warning,
        )
    sync = cls is not None and not inspect.iscoroutinefunction(cls.process)
    if ns.watchdog is not None and ns.placement.value == "inline" and sync:
        at(
            ("nodes", name, "watchdog"),
            "a watchdog cannot stop a synchronous inline node (its call holds the loop "
            "until it returns): give it placement: process, or make process async",
            Severity.warning,
        )
    if ns.placement.value == "inline":
        for key in ("cpus", "spin"):
            if key == "spin" and ns.timing == "precise":
                continue  # the release thread's spin (flowrt/kernel/precise.py)
            if getattr(ns, key) is not None:
                at(
                    ("nodes", name, key),
                    f"{key} applies to a node in a worker process (placement: process or "
                    "pool); an inline node runs in the loop process",
                )


def _check_modes_and_qos(r: _Resolution) -> None:
    """Modes override known nodes with fitting timing and valid params; QoS names nodes."""
    spec, at, classes, diags = r.spec, r.at, r.classes, r.diags
    locs, base_dir, names, triggers = r.locs, r.base_dir, r.names, r.triggers
    for mode_name, mode in spec.modes.items():
        for node, o in mode.nodes.items():
            path = ("modes", mode_name, "nodes", node)
            if node not in names:
                hint = did_you_mean(node, names)
                at(path, f"unknown node {node!r}" + hint)
                continue
            _check_override(path, o, triggers.get(node), at)
            if o.params and node in classes:
                merged = merge_params(spec.nodes[node].params, o.params)
                try:
                    params_of(classes[node].Params, merged, {PARAMS_BASE_DIR: base_dir})
                except ValidationError as e:
                    at_params = (*path, "params")
                    # A node whose own params are wrong is told so at the node: here only
                    # what the mode sets (not the node's 'object' at the line of a mode that
                    # sets 'min_area').
                    only = None if node in r.params else set(o.params)
                    diags.extend(
                        pydantic_diagnostics(e, locs, at_params, classes[node].Params, only=only)
                    )
    if spec.qos.overload is not None:
        for i, node in enumerate(spec.qos.overload.protect):
            if node not in names:
                hint = did_you_mean(node, names)
                at(("qos", "overload", "protect", i), f"unknown node {node!r}" + hint)
    if spec.initial_mode is not None and spec.initial_mode not in spec.modes:
        hint = did_you_mean(spec.initial_mode, spec.modes)
        at(("initial_mode",), f"unknown mode {spec.initial_mode!r}" + hint)


REMOTE_SOURCE = "flowrt.remote._bridge:RemoteSource"
REMOTE_FRAMES = "flowrt.remote._bridge:RemoteFrameSource"


def _with_imports(spec: GraphSpec, at: Any) -> GraphSpec:
    """``import:`` entries become nodes (outputs ``output`` and ``state``) of the resolved graph."""
    if not spec.imports:
        return spec
    extra: dict[str, NodeSpec] = {}
    for name, im in spec.imports.items():
        if name in spec.nodes and spec.nodes[name].kind in (REMOTE_SOURCE, REMOTE_FRAMES):
            continue  # a resolved graph's spec, resolved again (a recorder added to it)
        if name in spec.nodes:
            at(("import", name), f"import {name!r} has the name of a node; rename one of them")
            continue
        stale_after = None if im.stale_after == "never" else im.stale_after
        params = {"key": im.key, "stale_after": stale_after, "size": im.size, "stale": im.stale}
        if im.period is not None:
            params["period_ms"] = im.period
        kind = REMOTE_FRAMES if im.frames else REMOTE_SOURCE
        extra[name] = NodeSpec(kind=kind, params=params, priority=90)
    return spec.model_copy(update={"nodes": {**spec.nodes, **extra}})


def _edge(
    dst: str, dst_port: str, ins: InputSpec, in_type: Any, out_type: Any, default: str | None
) -> Edge:
    policy = ins.policy
    if policy is None and default is not None:
        policy = EdgePolicy(default)
    if policy is None:
        # Frames default to latest whichever side says so: a display reading ``object``
        # still wants the newest frame, not a backlog.
        is_frame = any(isinstance(t, type) and issubclass(t, Frame) for t in (in_type, out_type))
        policy = EdgePolicy.latest if is_frame else EdgePolicy.queue
    return Edge(ins.node, ins.port, dst, dst_port, policy, ins.size)


def _check_override(path: tuple[str | int, ...], o: Any, trig: Trigger | None, at: Any) -> None:
    """A mode's override must fit the node's trigger: frames take period/phase, timers ms."""
    if trig is None:
        return
    if isinstance(trig, FrameTrigger):
        if o.timer is not None:
            at((*path, "timer"), "timer applies to timer-triggered nodes; this one runs on frames")
        period = trig.period if o.period is None else o.period
        phase = trig.phase if o.phase is None else o.phase
        if period <= 0:
            at((*path, "period"), f"period must be a positive number of frames, got {period}")
        elif not 0 <= phase < period:
            at((*path, "phase"), f"phase {phase} must be in 0..{period - 1} (period {period})")
    elif o.period is not None or o.phase is not None:
        key = "period" if o.period is not None else "phase"
        at((*path, key), "period/phase in frames apply to frame-triggered nodes; use timer")
    elif isinstance(trig, TimerTrigger) and (o.timer is not None or o.timer_phase is not None):
        timer = trig.timer if o.timer is None else o.timer
        phase = trig.phase if o.timer_phase is None else o.timer_phase
        key = "timer" if o.timer is not None else "timer_phase"
        if timer <= 0:
            at((*path, "timer"), "timer period must be positive")
        elif not 0 <= phase < timer:  # the node's phase, kept by a mode that sets a timer
            at((*path, key), f"phase {phase:g} ms must be less than the timer {timer:g} ms")


def _check_trigger(
    name: str,
    ns: NodeSpec,
    trig: Trigger,
    spec: GraphSpec,
    classes: Mapping[str, type[Node]],
    at: Any,
    names: Collection[str],
) -> None:
    path = ("nodes", name, "trigger")
    if isinstance(trig, FrameTrigger):
        _check_frame_trigger(path, trig, spec, classes, at, names)
    elif isinstance(trig, TimerTrigger):
        _check_timer_trigger(path, trig, at)
    elif isinstance(trig, InputTrigger):
        wanted = [trig.input] if isinstance(trig.input, str) else trig.input
        for port in wanted:
            if port != "any" and port not in ns.inputs:
                hint = did_you_mean(port, ns.inputs)
                at((*path, "input"), f"trigger on input {port!r}, which is not connected" + hint)
    # a LoopTrigger has nothing to check


def _check_frame_trigger(
    path: tuple[str, ...],
    trig: FrameTrigger,
    spec: GraphSpec,
    classes: Mapping[str, type[Node]],
    at: Any,
    names: Collection[str],
) -> None:
    """A frame source that exists and makes frames, a period and a phase within it."""
    src, _, port = trig.frame.partition(".")
    if src not in names:
        at((*path, "frame"), f"unknown frame source {src!r}" + did_you_mean(src, names))
    elif src in classes:
        frame_ports = classes[src].frame_ports()
        kind = spec.nodes[src].kind
        if not frame_ports:
            at((*path, "frame"), f"frame trigger on {src!r} ({kind}), which produces no frames")
        elif port and port not in frame_ports:
            hint = did_you_mean(port, frame_ports)
            at((*path, "frame"), f"{src!r} has no frame output {port!r}" + hint)
    if trig.period <= 0:
        at((*path, "period"), f"period must be a positive number of frames, got {trig.period}")
    if trig.phase < 0:
        at((*path, "phase"), f"phase must be >= 0, got {trig.phase}")
    elif trig.period > 0 and trig.phase >= trig.period:
        at((*path, "phase"), f"phase {trig.phase} must be less than period {trig.period}")


def _check_timer_trigger(path: tuple[str, ...], trig: TimerTrigger, at: Any) -> None:
    """A positive period, and a phase within it."""
    if trig.timer <= 0:
        at((*path, "timer"), f"timer period must be positive, got {trig.timer:g} ms")
    if trig.phase < 0:
        at((*path, "phase"), f"phase must be >= 0, got {trig.phase:g} ms")
    elif trig.timer > 0 and trig.phase >= trig.timer:
        at(
            (*path, "phase"),
            f"phase {trig.phase:g} ms must be less than the period {trig.timer:g} ms",
        )


def _available_cpus() -> set[int]:
    """The CPUs this process may use (all of them where affinity is not supported)."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


def _check_cycles(spec: GraphSpec, edges: list[Edge], at: Any) -> None:
    """Report each cycle of edges once, at the input that closes it (back to its first node)."""
    succ: dict[str, list[Edge]] = {n: [] for n in spec.nodes}
    for e in edges:
        succ[e.src].append(e)
    # Only a node of a strongly connected component with a cycle can lead back to itself, and
    # only through that component: a search from every node across the whole graph was
    # quadratic (a chain of 1000 nodes took 0.1 s to validate, 2000 nodes 1.1 s).
    component = _components(succ)
    in_reported: set[str] = set()
    for start in spec.nodes:
        comp = component.get(start)
        if start in in_reported or comp is None:
            continue
        # Breadth first from `start`: the shortest way back to it, if there is one.
        came_by: dict[str, Edge] = {}
        todo = deque([start])
        closing: Edge | None = None
        while todo and closing is None:
            for e in succ[todo.popleft()]:
                if e.dst == start:
                    closing = e
                    break
                if e.dst not in came_by and component.get(e.dst) == comp:
                    came_by[e.dst] = e
                    todo.append(e.dst)
        if closing is None:
            continue
        path = [closing]
        while path[0].src != start:
            path.insert(0, came_by[path[0].src])
        cycle = [start, *(e.dst for e in path)]
        in_reported.update(cycle)
        where = ("nodes", closing.dst, "inputs", closing.dst_port)
        at(where, "cycle in the graph: " + " -> ".join(cycle))


def _components(succ: Mapping[str, list[Edge]]) -> dict[str, int]:
    """The nodes that lie on a cycle, each with the number of its strongly connected
    component (Tarjan's algorithm, iterative: a chain of thousands of nodes is no recursion)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: dict[str, int] = {}
    counter = 0
    for root in succ:
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            node, i = work.pop()
            if i == 0:
                index[node] = low[node] = counter
                counter += 1
                stack.append(node)
                on_stack.add(node)
            edges = succ[node]
            while i < len(edges):
                nxt = edges[i].dst
                i += 1
                if nxt not in index:
                    work.append((node, i))
                    work.append((nxt, 0))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                if low[node] == index[node]:  # the root of a component: pop it
                    members = []
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        members.append(m)
                        if m == node:
                            break
                    if len(members) > 1 or any(e.dst == node for e in edges):
                        for m in members:
                            out[m] = index[node]
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
    return out


def _check_frame_chains(triggers: Mapping[str, Trigger], at: Any) -> None:
    """Frame triggers that lead back to where they started: none of those nodes would ever run."""
    reported: set[str] = set()
    for start in triggers:
        chain = [start]
        while isinstance(trig := triggers.get(chain[-1]), FrameTrigger):
            src = trig.frame.partition(".")[0]
            if src in chain:
                loop = chain[chain.index(src) :]
                if not reported.intersection(loop):
                    reported.update(loop)
                    waits = ", ".join(
                        f"{a} waits for the frames of {b}"
                        for a, b in zip(loop, [*loop[1:], src], strict=True)
                    )
                    at(
                        ("nodes", chain[-1], "trigger", "frame"),
                        f"frame triggers in a cycle ({waits}): none of them would ever run",
                    )
                break
            chain.append(src)


def _check_deadlines(graph: Graph, at: Any) -> None:
    for name, node in graph.nodes.items():
        deadline = node.spec.deadline
        if deadline is None:
            continue
        period: float | None = None
        if isinstance(node.trigger, TimerTrigger):
            period = node.trigger.timer
        elif isinstance(node.trigger, FrameTrigger):
            try:
                interval = graph.frame_interval_ms(node.trigger.frame)
            except Exception:  # a frame chain that is itself an error (said already)
                continue
            period = None if interval is None else interval * node.trigger.period
        if period is not None and deadline > period:
            at(
                ("nodes", name, "deadline"),
                f"deadline {deadline:g} ms is longer than the period {period:g} ms",
                Severity.warning,
            )


def hyperperiod(periods: list[int]) -> int:
    h = 1
    for p in periods:
        h = h * p // gcd(h, p)
    return h
