"""Changing a running node's algorithm or params: ``Runtime.swap``, ``reload``, ``set_params``.

A swap to the node's own kind merges the given params into the running ones (issue 37 item
2: the display swapped with ``{"allowed_hosts": [...]}`` alone moved to the default port).

The kernel swaps one runner's instance (:mod:`flowrt.kernel.swapping`); this resolves what
the caller names (a kind, a class, params to validate, a module to re-import) and says
what happened (a ``NodeSwapped`` event), or why not (:class:`SwapError`: the old instance
runs on).
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Mapping
from typing import Any, Protocol

from pydantic import ValidationError

from ..events import Event, NodeSwapped
from ..graph._resolve import Graph
from ..graph.diagnostics import validation_text
from ..graph.spec import ModeSpec, Placement, merge_params
from ..kernel import NodeRunner, Scheduler
from ..node import Node, NodeFactory, reimport


class SwapHost(Protocol):
    """What a swap needs of the runtime (owned here: this module does not import it)."""

    @property
    def graph(self) -> Graph: ...

    @property
    def scheduler(self) -> Scheduler: ...

    def runner(self, node: str) -> NodeRunner: ...

    def emit(self, event: Event) -> None: ...

    def now(self) -> float: ...


class SwapError(Exception):
    """A swap that did not happen; the old instance runs on. The message says why."""


async def swap(
    rt: SwapHost,
    node: str,
    kind: str | type[Node],
    params: Mapping[str, Any] | None,
    origin: str,
    resolved: type[Node] | None,
) -> None:
    """See :meth:`flowrt.Runtime.swap`."""
    from ..graph._registry import KindError, resolve_kind

    runner = rt.runner(node)
    old_kind = runner.rnode.spec.kind
    label = kind if isinstance(kind, str) else f"{kind.__module__}:{kind.__qualname__}"
    try:
        cls = resolved if resolved is not None else resolve_kind(kind, None)
    except KindError as e:
        raise SwapError(f"{node}: {e}") from None
    except Exception as e:
        raise SwapError(f"{node}: kind {label!r}: import failed: {e!r}") from None
    raw = dict(params or {})
    if cls is runner.rnode.cls or label == old_kind:
        # Merged into the running params, as written (a duration stays "200ms", a path
        # relative to the graph file): a swap of one param keeps the port, the folder...
        raw = merge_params(as_written(rt, runner), raw)
    if params is None and cls is runner.rnode.cls:
        model = runner.rnode.params
    else:
        try:
            model = rt.graph.validate_params(cls, raw)
        except ValidationError as e:
            raise SwapError(f"{node}: params for {label}: {validation_text(e)}") from None
    await _swap_to(rt, runner, cls, model, label, origin)
    spec = runner.rnode.spec.model_copy(update={"params": raw})
    runner.install(runner.executor, dataclasses.replace(runner.rnode, spec=spec))


def as_written(rt: SwapHost, runner: NodeRunner) -> dict[str, Any]:
    """The running params as a graph file writes them: the file's text where the running
    value is still the file's (a duration stays "200ms", not seconds read again as ms), the
    running value where something set it since (``flowrt run --display-port``)."""
    raw = dict(runner.rnode.spec.params)
    running = runner.rnode.params
    try:
        written = rt.graph.validate_params(runner.rnode.cls, raw)
    except ValidationError:
        return dict(running.model_dump())
    for key, value in running.model_dump().items():
        if getattr(written, key, None) != getattr(running, key, None):
            raw[key] = value
    return raw


async def _swap_to(
    rt: SwapHost,
    runner: NodeRunner,
    cls: type[Node],
    model: Any,
    label: str,
    origin: str,
    reload: bool = False,
) -> None:
    old_kind = runner.rnode.spec.kind
    try:
        await runner.swapper.swap(cls, model, label, reload=reload)
    except Exception as e:
        from ..workers.errors import WorkerError  # (not at import: workers load lazily)

        # One line: a worker's failure is its traceback, whose last line says what happened.
        why = e.summary if isinstance(e, WorkerError) else str(e)
        raise SwapError(
            f"{runner.name}: swap to {label} failed, the old instance runs on: {_one_line(why)}"
        ) from e
    rt.emit(NodeSwapped(rt.now(), runner.name, label, old_kind, origin))


async def reload(rt: SwapHost, node: str, origin: str) -> None:
    """See :meth:`flowrt.Runtime.reload`.

    A node in a worker is reloaded there only: the new instance's worker imports the module
    anew (``NodeFactory.reload``) and the main process keeps its classes, which are those of
    the other nodes of the module and of the values their workers send back (unpickled by
    name). Re-imported here, every other node of the module had classes that were no longer
    the module's: their results failed their output check ("expects FrameDetection, got
    FrameDetection") and their factories no longer pickled for a restart.

    An inline node's module is re-imported here, and its params carried over to the new
    class; the other nodes of the module go on with their classes, which factories pickle
    and the type checks compare by name.
    """
    runner = rt.runner(node)
    cls = runner.rnode.cls
    kind = runner.rnode.spec.kind
    placement = runner.rnode.spec.placement
    if placement is not Placement.inline:
        if placement is Placement.pool:
            _refuse_shared_pool(rt, node, cls.__module__)
        await _swap_to(rt, runner, cls, runner.rnode.params, kind, origin, reload=True)
        return
    try:  # off the loop
        new_cls = await asyncio.to_thread(reimport, cls)
    except ImportError as e:
        raise SwapError(f"{node}: {e}; the old instance runs on") from None
    params = NodeFactory.carry_params(new_cls, runner.rnode.params)
    await _swap_to(rt, runner, new_cls, params, kind, origin, reload=True)


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _refuse_shared_pool(rt: SwapHost, node: str, module: str) -> None:
    """A pool worker holds several nodes: re-importing ``module`` there for ``node`` would
    leave any other node of that module in the same worker with classes that are no longer
    the module's (its results and its restart would no longer pickle). Which worker a node
    lands in is the pool's choice, so any other pool node of the module refuses the reload."""
    others = [
        name
        for name, r in rt.scheduler.runners.items()
        if name != node and r.rnode.spec.placement is Placement.pool and _uses(r, module)
    ]
    if others:
        who = f"{', '.join(sorted(others))} {'uses' if len(others) == 1 else 'use'}"
        raise SwapError(
            f"{node}: not reloaded: {who} {module} in the worker pool too, where re-importing "
            f"it would replace the classes of a running node under it; give {node} "
            "placement: process to reload it in a worker of its own"
        )


def _uses(runner: NodeRunner, module: str) -> bool:
    """The runner's node has a class of ``module``: its own, its params', a port's type."""
    cls = runner.rnode.cls
    types: list[Any] = [cls, type(runner.rnode.params)]
    types += [p.type for p in cls.inputs.values()]
    types += [p.type for p in cls.outputs.values()]
    return any(getattr(t, "__module__", None) == module for t in types)


def set_params(rt: SwapHost, node: str, params: Mapping[str, Any], merge: bool) -> None:
    """See :meth:`flowrt.Runtime.set_params`."""
    runner = rt.runner(node)
    current = runner.rnode.params.model_dump()
    target = merge_params(current, dict(params)) if merge else dict(params)
    try:
        model = rt.graph.validate_params(runner.rnode.cls, target)
    except ValidationError as e:
        raise ValueError(f"{node}: params: {validation_text(e)}") from None
    runner.swapper.set_params(model)


def apply_mode_params(rt: SwapHost, previous: ModeSpec | None, new: ModeSpec) -> None:
    """Params a mode sets, merged over the graph file's; the previous mode's undone."""
    before = previous.nodes if previous is not None else {}
    for name in dict.fromkeys([*before, *new.nodes]):
        o, old = new.nodes.get(name), before.get(name)
        if not (o is not None and o.params) and not (old is not None and old.params):
            continue
        base = rt.graph.spec.nodes[name].params
        target = merge_params(base, o.params if o is not None else None)
        runner = rt.scheduler.runners[name]
        runner.swapper.set_params(rt.graph.validate_params(runner.rnode.cls, target))
