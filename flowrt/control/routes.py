"""The control endpoint's routes: one table, method + path -> handler (starlette's ``Router``).

Both sides of the endpoint read this table. Its server process (:mod:`flowrt.control.server`)
serves each route's method and path, refuses a POST body that its request model does not
accept (400, before the runtime hears of it) and forwards the request by the route's
``op``; the runtime answers it with the route's handler, one request at a time, between
ticks. The paths and the JSON keys are users' (their scripts rely on them): README
"Control endpoint".
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

from pydantic import BaseModel, ValidationError

from ..graph.spec import merge_params
from ..runtime._hotswap import SwapError
from . import recorders as commands
from ._swap_policy import SwapRefused, UnknownParams, check_params, confined
from .wire import (
    ModeRequest,
    RecordRequest,
    ReloadRequest,
    SwapRequest,
    TimingRequest,
    event_json,
    jsonable,
)

if TYPE_CHECKING:
    from ..runtime._runtime import Runtime

log = logging.getLogger("flowrt.control.server")

RECORD_WAIT = 8.0  # seconds POST /record waits for the recorders (the gateway's answer: 10)

Answer = tuple[int, bytes]  # HTTP status, JSON body


class Answering(Protocol):
    """What a handler needs of the control server (:class:`flowrt.control.server.ControlServer`)."""

    @property
    def rt(self) -> Runtime: ...

    def allowed_kinds(self) -> set[str]: ...


Handler = Callable[[Answering, Any], Awaitable[Answer]]


@dataclass(frozen=True)
class Route:
    """One endpoint: where it is, what it accepts, who answers it."""

    method: Literal["GET", "POST"]
    path: str  # aiohttp's pattern; a ``{name}`` part is passed to the handler by that name
    op: str  # the request's name between the server process and the runtime
    handler: Handler  # in the runtime's process, on its loop, between ticks
    body: type[BaseModel] | None = None  # POST: the request model the body must satisfy
    query: tuple[tuple[str, int], ...] = ()  # integer query parameters, with their defaults
    example: str = ""  # shown after the path in the index (``?n=50``)
    listed: bool = True  # in the index's list of endpoints

    @property
    def shown(self) -> str:
        return f"{self.method} {self.path}{self.example}"


def dumps(data: Any) -> bytes:
    return json.dumps(data, allow_nan=False).encode()


def one_line(e: Exception) -> str:
    """An error as one line for the client (a pydantic error without its URL)."""
    if isinstance(e, ValidationError):
        return "; ".join(
            f"{'.'.join(str(x) for x in err['loc']) or 'body'}: {err['msg']}" for err in e.errors()
        )
    return str(e).splitlines()[0] if str(e) else type(e).__name__


async def answer(server: Answering, op: str, body: bytes) -> Answer:
    """The runtime's answer to one forwarded request; never raises (a bug is a 500 and the
    traceback in the log).

    The body was accepted by the route's request model in the server process (the edge);
    it is rebuilt here without a second pass (``model_construct``): a timing change is
    checked once, against its node, where it is applied (``Runtime.apply_timing``).
    """
    route = BY_OP.get(op)
    if route is None:
        return 404, dumps({"error": f"unknown operation {op!r}"})
    if not server.rt.started:
        return 503, dumps({"error": "the runtime is stopping"})
    try:
        args = json.loads(body) if body else {}
        request = route.body.model_construct(**args) if route.body is not None else args
        return await route.handler(server, request)
    except KeyError as e:
        return 404, dumps({"error": str(e.args[0] if e.args else e)})
    except UnknownParams as e:  # a misspelt name: the request is at fault, not a rule
        return 422, dumps({"error": str(e)})
    except SwapRefused as e:
        return 403, dumps({"error": str(e)})
    except SwapError as e:
        return 409, dumps({"error": str(e)})
    except (ValueError, ValidationError) as e:
        return 400, dumps({"error": one_line(e)})
    except Exception as e:
        log.exception("control endpoint: %s failed", op)
        return 500, dumps({"error": f"{type(e).__name__}: {e}"})


# --- the handlers, in the order of the table ----------------------------------------------


async def _index(server: Answering, args: dict[str, Any]) -> Answer:
    endpoints = [r.shown for r in ROUTES if r.listed]
    return 200, dumps({"graph": server.rt.graph.spec.name, "endpoints": endpoints})


async def _stats(server: Answering, args: dict[str, Any]) -> Answer:
    return 200, server.rt.stats().model_dump_json().encode()


async def _events(server: Answering, args: dict[str, Any]) -> Answer:
    n = int(args.get("n", 50))
    events = list(server.rt.events)[-n:] if n > 0 else []
    return 200, dumps([event_json(e) for e in events])


async def _modes(server: Answering, args: dict[str, Any]) -> Answer:
    rt = server.rt
    return 200, dumps({"modes": list(rt.graph.spec.modes), "current": rt.mode})


async def _mode(server: Answering, req: ModeRequest) -> Answer:
    server.rt.set_mode(req.mode, origin="control", force=req.force)
    return 200, dumps({"mode": server.rt.mode})


async def _timing(server: Answering, req: TimingRequest) -> Answer:
    runner = server.rt.scheduler.runners.get(req.node)  # unknown: apply_timing says so
    rnode = None if runner is None else runner.rnode
    if rnode is not None and rnode.cls.timing_fixed:
        kind = rnode.spec.kind
        article = "an" if kind[:1].lower() in "aeiou" else "a"  # ("a arbiter")
        raise SwapRefused(
            f"{req.node}: {article} {kind} keeps the robot safe: its timing is the graph "
            "file's (its modes included), not changed over the control endpoint"
        )
    change = server.rt.apply_timing(req.node, req.change(), origin="control", force=req.force)
    return 200, dumps({"node": req.node, "change": change})


async def _qos(server: Answering, args: dict[str, Any]) -> Answer:
    status = server.rt.qos_status()
    return 200, dumps({**jsonable(status), "summary": status.describe()})


async def _rtdb(server: Answering, args: dict[str, Any]) -> Answer:
    return 200, dumps([jsonable(r) for r in server.rt.rtdb.records()])


async def _rtdb_record(server: Answering, args: dict[str, Any]) -> Answer:
    name = str(args.get("name", ""))
    records = server.rt.rtdb.history(name, int(args.get("n", 1)))
    if not records:
        return 404, dumps({"error": f"no record {name!r}"})
    return 200, dumps([jsonable(r) for r in records])


async def _record(server: Answering, req: RecordRequest) -> Answer:
    """Answered once the recorders obeyed (under the runtime's one turn with the operator
    page: :mod:`flowrt.recording.commands`), so that every answer says what was done."""
    nodes = server.rt.graph.spec.nodes
    recorders = [n for n, spec in nodes.items() if spec.kind == "recorder"]
    if req.node is not None and req.node not in recorders:
        raise KeyError(f"{req.node!r} is not a recorder node (recorders: {recorders})")
    targets = [req.node] if req.node is not None else recorders
    if not targets:
        raise KeyError("the graph has no recorder node (add one, or use flowrt record)")
    rtdb = server.rt.rtdb
    async with commands.turn(rtdb):
        result = await commands.obey(rtdb, req.action, req.name, RECORD_WAIT, targets)
    status = int(result.pop("status"))
    if status == 404:  # recorders that have not said anything yet: they cannot obey
        result["error"] = f"{', '.join(targets)} not running yet: try again"
        status = 409
    return status, dumps({"action": req.action, "nodes": targets, **result})


async def _swap(server: Answering, req: SwapRequest) -> Answer:
    """The new instance is set up while the graph runs (awaited, between ticks)."""
    await checked_swap(server, req)
    return 200, dumps({"node": req.node, "kind": req.kind, "op": "swap"})


async def _reload(server: Answering, req: ReloadRequest) -> Answer:
    await server.rt.reload(req.node, origin="control")
    kind = server.rt.graph.spec.nodes[req.node].kind
    return 200, dumps({"node": req.node, "kind": kind, "op": "reload"})


async def checked_swap(server: Answering, req: SwapRequest) -> None:
    """The endpoint's rules, then ``Runtime.swap`` with the class imported off the loop.

    An import may run anything at module level (``unittest.__main__`` calls
    ``sys.exit``): it happens in a thread, and a ``BaseException`` from it is an error for
    the caller, never the end of the runtime.
    """
    from ..graph._registry import resolve_kind

    rt = server.rt
    allowed = server.allowed_kinds()
    if req.kind not in allowed:
        raise SwapRefused(
            f"kind {req.kind!r} is not allowed over the control endpoint (allowed: "
            f"{', '.join(sorted(allowed))}; more with --control-allow-kinds or the graph's "
            "control_allow_kinds)"
        )
    if req.node not in rt.graph.nodes:
        raise KeyError(f"unknown node {req.node!r}")
    try:
        cls = await asyncio.to_thread(resolve_kind, req.kind, None)
    except asyncio.CancelledError:
        raise
    except BaseException as e:  # SystemExit from an import is contained
        raise SwapError(f"{req.node}: kind {req.kind!r}: import failed: {e!r}") from None
    params = req.params
    if params is not None:
        from ..runtime._hotswap import as_written

        same = req.kind == rt.scheduler.node_view(req.node).node.spec.kind  # as swapped
        base = as_written(rt, rt.runner(req.node)) if same else {}
        paths = confined(cls)
        plain = {k: v for k, v in params.items() if k not in paths}

        def folder_of(param: str) -> str:
            model = rt.graph.validate_params(cls, merge_params(base, plain))
            return str(getattr(model, param))

        params = check_params(req.kind, cls, params, folder_of)
    await rt.swap(req.node, req.kind, params, origin="control", resolved=cls)


ROUTES: tuple[Route, ...] = (
    Route("GET", "/", "index", _index, listed=False),
    Route("GET", "/stats", "stats", _stats),
    Route("GET", "/events", "events", _events, query=(("n", 50),), example="?n=50"),
    Route("GET", "/modes", "modes", _modes),
    Route("POST", "/mode", "mode", _mode, body=ModeRequest),
    Route("POST", "/timing", "timing", _timing, body=TimingRequest),
    Route("GET", "/qos", "qos", _qos),
    Route("GET", "/rtdb", "rtdb", _rtdb),
    Route("GET", "/rtdb/{name}", "rtdb_record", _rtdb_record, query=(("n", 1),), example="?n=8"),
    Route("POST", "/record", "record", _record, body=RecordRequest),
    Route("POST", "/swap", "swap", _swap, body=SwapRequest),
    Route("POST", "/reload", "reload", _reload, body=ReloadRequest),
)
BY_OP = {r.op: r for r in ROUTES}
ENDPOINTS = [r.shown for r in ROUTES if r.listed]
"""What ``GET /`` lists (users' scripts read it)."""
