"""The live Foxglove connection: a running graph's outputs served as Foxglove channels.

``flowrt run g.yaml --foxglove [PORT]`` starts foxglove-sdk's WebSocket server (loopback by
default) and serves every output (a node class's and those its params make: a ``can``
node's messages) with the channels a recording has (one description per stream:
:mod:`.streams`): frames as ``foxglove.CompressedImage`` (JPEG by default: a live view over a
socket, not an archive; ``raw`` gives the recording's ``foxglove.RawImage``), audio as
``foxglove.RawAudio``, every block in order, a ``sync`` set as its members and index, every
other output as JSON (a detection also as ``foxglove.ImageAnnotations`` on its camera's
``CAMERA/annotations/DETECTIONS``, stamped with its frame's time), the statistics table
once a second on ``/flowrt/stats`` and events on ``/flowrt/events``. The Foxglove app shows
a running graph as it shows a recording.

A viewer never slows the graph: the monitor reads each output through its own ``latest``
buffer (the graph never waits on it), takes values off the loop only when some client is
subscribed to that channel, encodes and sends on its own thread with at most one value per
channel in flight (a newer one replaces it, counted), except audio and events, which wait in
order in a bounded queue (``AUDIO_QUEUE``; beyond it counted in ``lost_audio``); and
foxglove-sdk's server keeps a bounded queue per client (``BACKLOG`` messages) that drops the
oldest when a client does not read. At stop, a client that does not read cannot hold the
runtime: the server is given ``STOP_WAIT`` to close.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from ..audio import AudioBlock
from ..frames import Frame
from .encoding import (
    StreamSchema,
    annotations_schema,
    annotations_topic,
    audio_schema,
    encode_annotations,
    encode_json,
    epoch_ns,
    is_detection,
    to_jsonable,
)
from .streams import StreamBook, is_set, split_set

if TYPE_CHECKING:
    from ..events import Event
    from ..runtime._runtime import Runtime
    from ..runtime._subscription import Subscription

__all__ = ["FoxgloveLive"]

PUMP_INTERVAL = 0.01  # s: how often the loop looks for new values (a few microseconds each)
AUDIO_QUEUE = (
    256  # audio blocks (and events) that may wait to be sent (5 s of 1024-sample blocks at 48 kHz)
)
BACKLOG = 32  # messages queued per client before the oldest is dropped (foxglove-sdk's queue)
STOP_WAIT = 1.0  # s: at stop, how long to wait for the server to say goodbye to its clients


log = logging.getLogger("flowrt.foxglove")


class FoxgloveLive:
    """A runtime monitor serving the graph live to Foxglove. Call :meth:`open` first.

    Args:
        port: TCP port (0: any free one; see :attr:`port` after :meth:`open`).
        host: loopback by default; the server has no authentication.
        image_format: ``jpeg`` (default), ``png`` or ``raw`` for frame outputs.
    """

    def __init__(self, port: int = 8765, host: str = "127.0.0.1", image_format: str = "jpeg"):
        self.host = host
        self.port = port
        self.image_format = image_format
        self.sent = 0
        self.replaced = 0  # values superseded before the sender thread took them (by design)
        self.failed = 0  # values that could not be encoded
        self._server: Any = None
        self._bridge: Any = None  # wsbridge.SubprotocolBridge: the port users connect to
        self._ctx: Any = None
        self._subs: dict[str, Subscription] = {}
        self._channels: dict[str, Any] = {}
        # An Output(object) whose values change type: its first value's schema (the channel
        # above) and a channel per other schema on the same topic, as the recorder has, so
        # every message matches its own channel's schema (the sender thread adds them)
        self._first_schema: dict[str, StreamSchema] = {}
        self._typed: dict[tuple[str, StreamSchema], Any] = {}
        self._frame_topics: set[str] = set()
        self._cameras: dict[str, str] = {}  # node -> its first frame output's topic
        self._annotations: dict[str, Any] = {}  # detection topic -> its annotations channel
        self._pending: dict[str, tuple[Any, float]] = {}
        # audio: every block, in order (a latest slot would lose a third of them)
        self._queued: deque[tuple[str, Any, float]] = deque()
        self._audio_topics: set[str] = set()
        self._book = StreamBook(default_image_format=image_format)
        self.lost_audio = 0  # blocks (or events) not sent: their queue was full (counted)
        self._cond = threading.Condition()
        self._done: deque[Frame] = deque()
        self._thread: threading.Thread | None = None
        self._stopping = False
        self._handle: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._rt: Runtime | None = None
        self._next_stats = 0.0
        self._epoch = 0.0  # added to the runtime clock: Unix time
        self._event_epoch = 0.0  # added to an event's t (seconds since the start): Unix time

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def open(self) -> None:
        """Start the server; raises OSError with the reason (e.g. the port is taken)."""
        import foxglove

        from .wsbridge import SubprotocolBridge

        # The user's port is the bridge's, which speaks both subprotocols (foxglove.sdk.v1
        # and foxglove.websocket.v1: Lichtblick, Studio 1.x, @foxglove/ws-protocol); the
        # SDK's server listens on a private loopback port behind it.
        try:
            bridge = SubprotocolBridge(self.host, self.port, 0)
        except OSError as e:
            raise OSError(
                f"foxglove server on {self.host}:{self.port}: {e.strerror or e}"
            ) from None
        self._ctx = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name="flowrt",
                host="127.0.0.1",
                port=0,
                context=self._ctx,
                message_backlog_size=BACKLOG,
            )
        except RuntimeError as e:
            bridge.close()
            raise OSError(f"foxglove server on {self.host}:{self.port}: {e}") from None
        bridge.upstream = int(self._server.port)
        bridge.start()
        self._bridge = bridge
        self.port = bridge.port

    # --- Monitor -------------------------------------------------------------------------

    def started(self, rt: Runtime) -> None:
        if self._server is None:
            self.open()
        self._rt = rt
        self._loop = asyncio.get_running_loop()
        self._epoch = time.time() - rt.clock.now()
        self._event_epoch = self._epoch + rt.clock.origin
        self._book.epoch_offset = self._epoch
        for name, node in rt.graph.nodes.items():
            # every output: the class's and those its params make (a can node's messages)
            outputs = {**node.cls.outputs, **node.cls.params_outputs(node.params)}
            for port, out in outputs.items():
                topic = f"{name}.{port}"
                kind = out.type if isinstance(out.type, type) else object
                if issubclass(kind, AudioBlock):
                    # every block: a queue read each pump; counted if it overflows
                    self._subs[topic] = rt.subscribe(topic, policy="queue", size=AUDIO_QUEUE)
                    self._audio_topics.add(topic)
                    self._channels[topic] = self._channel(topic, audio_schema())
                    continue
                # sampled: values nobody asked for are unread, not red drops in the table
                self._subs[topic] = rt.subscribe(topic, policy="latest", size=1, sampled=True)
                if issubclass(kind, Frame):  # advertised at its first frame, as a message's
                    self._frame_topics.add(topic)  # channel (a replay node's `frame` output
                    self._cameras.setdefault(name, topic)  # of a text topic never has one)
        self._stats_schema = _json_schema("flowrt.RuntimeStats")
        self._events_schema = _json_schema("flowrt.Event")
        self._stats_channel = self._channel("/flowrt/stats", self._stats_schema)
        self._events_channel = self._channel("/flowrt/events", self._events_schema)
        self._thread = threading.Thread(target=self._send_loop, name="foxglove", daemon=True)
        self._thread.start()
        self._handle = self._loop.call_later(PUMP_INTERVAL, self._pump)

    def event(self, event: Event) -> None:
        ch = getattr(self, "_events_channel", None)
        if ch is not None and ch.has_sinks():  # every event, in order (not the newest only)
            with self._cond:
                if len(self._queued) >= AUDIO_QUEUE:
                    self.lost_audio += 1
                    return
                self._queued.append(("/flowrt/events", event, time.time()))
                self._cond.notify()

    def stopped(self, rt: Runtime) -> None:
        if self._handle is not None:
            self._handle.cancel()
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for value, _ in self._pending.values():
            _release(value)
        self._pending.clear()
        self._release_done()
        if self._bridge is not None:
            bridge, self._bridge = self._bridge, None
            bridge.close()
        if self._server is not None:
            # The server's stop waits for its clients to go; a viewer that never reads would
            # hold the runtime's stop forever. Stop on a thread, wait a bounded time.
            server, self._server = self._server, None
            stopper = threading.Thread(target=_stop_server, args=(server,), daemon=True)
            stopper.start()
            stopper.join(timeout=STOP_WAIT)

    # --- on the loop ---------------------------------------------------------------------

    def _pump(self) -> None:
        """Take the newest value of each output that some client wants; never waits.

        Rescheduled whatever happens: one value that fails must not end the live view for
        the rest of the run (counted in ``failed``, logged once).
        """
        try:
            self._pump_once()
        except Exception:
            self.failed += 1
            if self.failed == 1:
                log.exception("foxglove: a live value could not be offered")
        finally:
            if self._loop is not None and not self._stopping:
                self._handle = self._loop.call_later(PUMP_INTERVAL, self._pump)

    def _pump_once(self) -> None:
        from ..edges import EMPTY

        self._release_done()
        for topic, sub in self._subs.items():
            ch = self._channels.get(topic)
            if topic in self._audio_topics:
                self._pump_audio(topic, sub, ch)
                continue
            drawn = self._annotations.get(topic)
            watched = drawn is not None and drawn.has_sinks()
            if ch is not None and not watched and not ch.has_sinks():  # a set's members
                prefix = topic + "/"
                watched = any(  # a copy: the sender thread adds a channel at a first value
                    c.has_sinks() for t, c in tuple(self._channels.items()) if t.startswith(prefix)
                )
            if ch is not None and not ch.has_sinks() and not watched and self._typed:
                watched = any(
                    c.has_sinks() for (t, _), c in tuple(self._typed.items()) if t == topic
                )
            if ch is not None and not ch.has_sinks() and not watched:
                continue  # nobody watches: the latest buffer just keeps the newest value
            value = sub.take_held()
            if value is EMPTY:
                continue
            t = value.timestamp if isinstance(value, Frame) else time.monotonic()
            self._offer(topic, value, t + self._epoch if isinstance(value, Frame) else time.time())
        rt = self._rt
        now = time.monotonic()
        if rt is not None and now >= self._next_stats:
            self._next_stats = now + 1.0
            if self._stats_channel.has_sinks():
                self._offer("/flowrt/stats", rt.stats(), time.time())

    def _pump_audio(self, topic: str, sub: Subscription, ch: Any) -> None:
        """Every block waiting, in order, when someone listens (else they are let go)."""
        from ..edges import EMPTY

        watched = ch.has_sinks()
        while (value := sub.take_held()) is not EMPTY:
            if not watched:
                continue
            with self._cond:
                if len(self._queued) >= AUDIO_QUEUE:
                    self.lost_audio += 1
                    continue
                self._queued.append((topic, value, value.timestamp + self._epoch))
                self._cond.notify()

    def _offer(self, topic: str, value: Any, epoch_time: float) -> None:
        with self._cond:
            old = self._pending.pop(topic, None)
            self._pending[topic] = (value, epoch_time)
            self._cond.notify()
        if old is not None:
            self.replaced += 1
            _release(old[0])

    def _release_done(self) -> None:
        while self._done:
            self._done.popleft().release()

    # --- on the sender thread --------------------------------------------------------------

    def _send_loop(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._queued and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                if self._queued:
                    topic, value, epoch_time = self._queued.popleft()
                else:
                    topic = next(iter(self._pending))
                    value, epoch_time = self._pending.pop(topic)
            try:
                self._send(topic, value, epoch_time)
            except Exception:  # a value that cannot be shown must not stop the others
                self.failed += 1
            finally:
                if isinstance(value, Frame):
                    self._done.append(value)

    def _send(self, topic: str, value: Any, epoch_time: float) -> None:
        ns = epoch_ns(epoch_time)
        if topic == "/flowrt/stats":
            data = encode_json(value, self._stats_schema).data
            self._stats_channel.log(data, log_time=ns)
        elif topic == "/flowrt/events":
            body = {"kind": getattr(value, "kind", type(value).__name__), **to_jsonable(value)}
            if isinstance(body.get("t"), float):
                body["t"] = body["t"] + self._event_epoch  # Unix time, as every recorded time
            self._events_channel.log(encode_json(body, self._events_schema).data, log_time=ns)
        elif is_set(value):  # a sync set: its members on channels of their own (streams.py)
            index, members = split_set(topic, value)
            for sub, member in members:
                self._send(sub, member, member.timestamp + self._epoch)
            self._send(topic, index, epoch_time)
            return
        else:
            # the stream's one description (streams.py): the recorder's channel and bytes
            d = self._book.description(topic, value)
            ch = self._channels.get(topic)
            if ch is None:  # a message channel is advertised with its first value's schema
                ch = self._channels[topic] = self._channel(topic, d.schema)
                self._first_schema[topic] = d.schema
            elif d.schema != self._first_schema.get(topic, d.schema):  # another type
                ch = self._typed.get((topic, d.schema))
                if ch is None:
                    ch = self._typed[(topic, d.schema)] = self._channel(topic, d.schema)
            ch.log(self._book.encode(topic, value).data, log_time=ns)
            if is_detection(value):
                self._draw(topic, value)
        self.sent += 1

    def _draw(self, topic: str, det: Any) -> None:
        """A detection as annotations on its camera's image, at its frame's time."""
        ch = self._annotations.get(topic)
        if ch is None:
            camera = self._cameras.get(det.source)
            if camera is None:
                return
            ch = self._annotations[topic] = self._channel(
                annotations_topic(camera, topic), annotations_schema()
            )
        epoch = det.timestamp + self._epoch
        ch.log(encode_annotations(det, epoch).data, log_time=epoch_ns(epoch))

    def _channel(self, topic: str, schema: StreamSchema) -> Any:
        import foxglove

        # advertised to the viewers only once the server takes subscriptions to it: a viewer
        # that subscribes at once would else be told "Unknown channel ID" (wsbridge.py)
        bridge = self._bridge
        with bridge.holding() if bridge is not None else contextlib.nullcontext():
            return foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data
                ),
                message_encoding=schema.message_encoding,
                context=self._ctx,
            )


def _stop_server(server: Any) -> None:
    with contextlib.suppress(Exception):
        server.stop()


def _json_schema(name: str) -> StreamSchema:
    """The statistics' schema from their model, events as one object of every event's fields;
    both in the subset the apps read (flowrt.recording.jsonschema)."""

    from ..stats import RuntimeStats
    from .jsonschema import app_schema

    schema = (
        app_schema(RuntimeStats.model_json_schema()) if name == "flowrt.RuntimeStats" else _events()
    )
    schema["title"] = name
    return StreamSchema(name, "jsonschema", json.dumps(schema).encode(), "json")


def _events() -> dict[str, Any]:
    """Every event kind's fields (flowrt.events) in one object: an alert's ``alert``,
    ``detail`` and ``severity`` were untyped (the schema had only the common ``t``, ``node``
    and ``kind``), so the apps could not plot or filter them."""
    import dataclasses

    from pydantic import TypeAdapter

    from .. import events
    from .jsonschema import app_schema

    properties: dict[str, Any] = {"kind": {"type": "string"}}
    for cls in vars(events).values():
        if (
            isinstance(cls, type)
            and issubclass(cls, events.Event)
            and dataclasses.is_dataclass(cls)
        ):
            one = app_schema(TypeAdapter(cls).json_schema())
            for key, field in one.get("properties", {}).items():
                properties.setdefault(key, field)
    return {"type": "object", "properties": properties}


def _release(value: Any) -> None:
    if isinstance(value, Frame):
        value.release()
