"""Remote edges: graph outputs exported, and remote streams imported, over Zenoh.

flowrt does not invent a network protocol: a graph's ``export:`` entries become Zenoh
publishers and its ``import:`` entries Zenoh subscribers, on a session configured by the
graph's ``zenoh:`` section (Zenoh's own discovery, routing, reliability, TLS and access
control). As the agent-based control source keeps its network links as sender/receiver agents
outside the real-time router, no network I/O runs on the event loop.

Every message carries its stream id, sequence number, send time and capture time: the
importing side counts sequence gaps as drops of the remote link (an edge named
``zenoh:KEY->NAME`` in the statistics, beside the local ones) and reports the age at arrival,
on the exporter's clock corrected by the measured offset, so it holds without synchronised
clocks. An import that hears nothing for ``stale_after`` periods is stale: its node is in an
error state (red, with the reason), a health alert is raised, its RTDB record (written with
that validity) turns stale; it resumes by itself when the exporter comes back (a restarted
exporter is a new stream: its sequence starts again, not a gap).

This module is the session and its wiring (:class:`ZenohBridge`). The parts, each a module:

- :mod:`flowrt.remote.wire`: the wire format (header, payload encodings, what is refused);
- :mod:`flowrt.remote._export`: the sender thread behind the exported outputs;
- :mod:`flowrt.remote._shm`: raw frames put from Zenoh's shared memory;
- :mod:`flowrt.remote._importer`: one imported stream, from Zenoh's thread to the loop;
- :mod:`flowrt.remote._node`: the node an ``import:`` entry becomes;
- :mod:`flowrt.remote._clock`: the exporters' clock offsets;
- :mod:`flowrt.remote._host`: the runtime as the bridge sees it;
- :mod:`flowrt.remote._threads`: Zenoh's threads at the loop's priority.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import uuid
from typing import Any

from ..edges import make_buffer
from ..graph.spec import EdgePolicy, GraphSpec, ZenohSpec
from ._clock import CLOCK_PREFIX, ClockOffsets, answer_clock
from ._export import STOPPED, Export, ExportSender
from ._host import BridgeHost
from ._importer import FRAME_BACKLOG, ImportLink, RemoteLinkStats, worker_downstream
from ._node import RemoteFrameSource, RemoteSource, RemoteSourceParams
from ._threads import ThreadShare
from .wire import PlainFormat

__all__ = [
    "FRAME_BACKLOG",
    "BridgeHost",
    "RemoteError",
    "RemoteFrameSource",
    "RemoteLinkStats",
    "RemoteSource",
    "RemoteSourceParams",
    "ZenohBridge",
    "worker_downstream",
]


log = logging.getLogger("flowrt.remote._bridge")
UNREACHED_AFTER = 3.0
"""Seconds after the start at which a peer whose ``connect`` endpoints never answered is
said so (a warning: the other side may start later)."""


class RemoteError(Exception):
    """A remote-edge problem found at start (bad endpoint, a port in use, no zenoh)."""


class ZenohBridge:
    """The graph's Zenoh session, its exports and imports (see the module docstring)."""

    def __init__(self, host: BridgeHost, spec: GraphSpec) -> None:
        self.host = host
        self.spec = spec
        self.zspec = spec.zenoh or ZenohSpec()
        self.session: Any = None
        self.shm = False  # the session enables Zenoh's shared memory (raw frames use it)
        self.stream = uuid.uuid4().hex[:16]
        self.zid = ""
        self.exports: list[Export] = []
        self.imports: dict[str, ImportLink] = {}
        self._subs: list[Any] = []
        self._queryable: Any = None
        self._sender: ExportSender | None = None
        self._clocks = ClockOffsets(lambda: self.session)
        self.threads = ThreadShare()  # Zenoh's threads at the loop's nice (see _threads)
        self._unreached: asyncio.TimerHandle | None = None  # the check of `connect`, pending

    # --- lifecycle ----------------------------------------------------------------------

    def config(self) -> Any:
        import zenoh

        z = self.zspec
        cfg = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(z.mode))
        cfg.insert_json5("listen/endpoints", json.dumps(z.listen if z.mode == "peer" else []))
        cfg.insert_json5("connect/endpoints", json.dumps(z.connect))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(z.scouting))
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(z.scouting))
        for path, value in z.config.items():
            cfg.insert_json5(path, json.dumps(value))
        return cfg

    async def open(self) -> None:
        """Open the session (before any node runs): a port in use fails here, in one line."""
        try:
            import zenoh
        except ImportError as e:  # pragma: no cover - a dependency
            raise RemoteError(f"zenoh: the eclipse-zenoh package is missing ({e})") from None
        try:
            cfg = self.config()
            self.shm = json.loads(cfg.get_json("transport/shared_memory/enabled")) is True
            self.session = await asyncio.to_thread(zenoh.open, cfg)
        except Exception as e:
            text = _first_line(e)
            if "Address already in use" in text:
                where = self.zspec.listen
                raise RemoteError(
                    f"zenoh: cannot listen on {', '.join(where)}: address already in use "
                    "(change zenoh.listen in the graph file or --zenoh-listen, or stop the "
                    "other process)"
                ) from None
            if "Unable to connect" in text:
                raise RemoteError(
                    f"zenoh: cannot connect to {', '.join(self.zspec.connect) or 'any endpoint'}"
                    " (in client mode a router or peer must answer at start; peer mode keeps"
                    " trying)"
                ) from None
            raise RemoteError(f"zenoh: {text}") from None
        self.zid = str(self.session.info.zid())
        self._queryable = self.session.declare_queryable(f"{CLOCK_PREFIX}/{self.zid}", answer_clock)
        if self.zspec.connect and self.zspec.mode == "peer":  # a typo in a port went unnoticed
            loop = asyncio.get_running_loop()
            self._unreached = loop.call_later(UNREACHED_AFTER, self._say_unreached)

    def _say_unreached(self) -> None:
        """Once, a while after the start: nothing answers at the ``connect`` endpoints (peer
        mode keeps trying, silently: an export to a wrong port counted every value as
        delivered, exit 0)."""
        session = self.session
        if session is None:
            return
        try:
            linked = list(session.info.peers_zid()) + list(session.info.routers_zid())
        except Exception:  # a session closing meanwhile: nothing to say
            return
        if not linked:
            log.warning(
                "zenoh: nothing answers at %s after %g s (peer mode keeps trying): is the "
                "other side running, and the address right?",
                ", ".join(self.zspec.connect),
                UNREACHED_AFTER,
            )

    def attach_exports(self) -> None:
        """Buffers on the exported outputs, before the nodes start publishing."""
        sender = ExportSender(self.host, self.stream, self.zid, self.shm)
        for key, ex in self.spec.exports.items():
            node, port = ex.source.split(".")
            outs = self.host.runner_output(node, port)
            policy = ex.policy
            if policy is None:
                frames = self.host.is_frame_port(node, port)
                policy = EdgePolicy.latest if frames else EdgePolicy.queue
            buf = make_buffer(
                policy.value, f"{ex.source}->zenoh:{key}", ex.size, self.host.now_mono
            )
            exp = Export(key, node, port, ex.encoding, ex.quality, buf)
            exp.publisher = self.session.declare_publisher(key)
            buf.on_put = functools.partial(sender.take, exp)  # (C: one Python frame less)
            outs.append(buf)
            self.host.add_buffer(buf)
            self.exports.append(exp)
        if self.exports:
            sender.start()
            self._sender = sender
        self.threads.share()  # the loop's nice is set by now

    def attach_imports(self) -> None:
        """Subscribers for the imports, bound to their nodes (once the nodes are set up)."""
        for name, im in self.spec.imports.items():
            stale_after = None if im.stale_after == "never" else im.stale_after
            imp = ImportLink(self, name, im.key, im.period, stale_after, im.size, im.stale)
            imp.max_bytes, imp.max_pixels = im.byte_limit, im.max_pixels
            imp.zero_copy = not worker_downstream(self.spec, name)
            imp.plain = (
                PlainFormat(im.format, im.shape, im.dtype) if im.format != "flowrt" else None
            )
            node = self.host.import_node(name)
            if node is not None:
                node.link = imp
            self.imports[name] = imp
            self.host.add_buffer(imp.link)
            self._subs.append(self.session.declare_subscriber(im.key, imp.on_sample))
        self.threads.share()

    async def close(self) -> None:
        if self._unreached is not None:
            self._unreached.cancel()
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        self._subs.clear()
        for imp in self.imports.values():
            imp.close()
        if self._sender is not None:
            await self._sender.stop()
            for exp in self.exports:  # what waited for the sender is never sent: counted
                exp.buf.discard(STOPPED)
            self._sender = None
        if self.session is not None:
            session, self.session = self.session, None
            with contextlib.suppress(Exception):
                await asyncio.to_thread(session.close)
        self.threads.restore()

    # --- clocks -------------------------------------------------------------------------

    def offset(self, zid: str) -> float:
        """Exporter clock minus ours, seconds (0 until measured; same host: ~0)."""
        return self._clocks.offset(zid)

    def clock_known(self, zid: str) -> bool:
        return self._clocks.measured(zid)

    def clock_probe(self, zid: str) -> None:
        """From Zenoh's thread: measure an exporter's clock once, off the loop."""
        self._clocks.probe(zid)

    def clocks(self) -> dict[str, tuple[float, float]]:
        return self._clocks.clocks()


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    # Zenoh's errors end with " at /path/to/source.rs:line." twice; keep the message.
    cut = text.find(" at /")
    return text[:cut] if cut > 0 else text
