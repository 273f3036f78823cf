"""What the conformance matrix (test_conformance.py) checks a stream with: outside tools only.

- :func:`read_recording`: every channel and message of an MCAP file through the ``mcap``
  package's reader, JSON messages validated with ``jsonschema`` against their own channel's
  schema, protobuf messages decoded with the descriptors stored in the file, every JSON schema
  walked with the port of the apps' ``parseJsonSchema`` rules.
- :class:`LiveClient`: a plain ``foxglove.websocket.v1`` client (the subprotocol of Lichtblick
  and ``@foxglove/ws-protocol``) that subscribes to every channel it is advertised and keeps
  what arrives, validated the same way.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any

import jsonschema

from flowrt.recording.jsonschema import schema_problems


@dataclass
class Channel:
    """One stream as a tool sees it: topic, schema, encodings, messages and what was wrong."""

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    schema: bytes
    messages: int = 0
    invalid: list[str] = field(default_factory=list)  # first few problems, one line each
    problems: list[str] = field(default_factory=list)  # the apps' rules on the schema
    decoded: list[Any] = field(default_factory=list)  # protobuf: the first few, decoded

    def note(self, why: str) -> None:
        if len(self.invalid) < 3:
            self.invalid.append(why)


class _Validators:
    def __init__(self) -> None:
        self._by_schema: dict[bytes, Any] = {}

    def check(self, ch: Channel, data: bytes) -> None:
        v = self._by_schema.get(ch.schema)
        if v is None:
            schema = json.loads(ch.schema)
            jsonschema.Draft202012Validator.check_schema(schema)
            v = self._by_schema[ch.schema] = jsonschema.Draft202012Validator(schema)
            ch.problems = schema_problems(schema)
        try:
            value = json.loads(data)
        except ValueError as e:
            ch.note(f"not JSON: {e}")
            return
        for err in v.iter_errors(value):
            ch.note(f"{'/'.join(map(str, err.absolute_path)) or '<root>'}: {err.message[:120]}")
            break


def read_recording(path: Any) -> dict[str, Channel]:
    """Every channel of ``path`` with its messages checked (see the module docstring)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    factory = DecoderFactory()
    decoders: dict[int, Any] = {}
    validators = _Validators()
    out: dict[str, Channel] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schema is not None, channel.topic
            ch = out.get(channel.topic)
            if ch is None:
                ch = out[channel.topic] = Channel(
                    channel.topic,
                    schema.name,
                    schema.encoding,
                    channel.message_encoding,
                    bytes(schema.data),
                )
            ch.messages += 1
            if schema.encoding == "jsonschema":
                validators.check(ch, message.data)
            elif schema.encoding == "protobuf":
                dec = decoders.get(schema.id) or decoders.setdefault(
                    schema.id, factory.decoder_for("protobuf", schema)
                )
                try:
                    msg = dec(message.data)
                except Exception as e:
                    ch.note(f"protobuf: {e}")
                    continue
                if len(ch.decoded) < 400:
                    ch.decoded.append(msg)
            else:
                ch.note(f"schema encoding {schema.encoding!r}")
    return out


class LiveClient:
    """A ``foxglove.websocket.v1`` client of ``url`` that subscribes to every channel."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.subprotocol = ""
        self.channels: dict[str, Channel] = {}
        self.by_id: dict[int, Channel] = {}  # subscription id -> channel
        self.arrivals: dict[str, list[bytes]] = defaultdict(list)  # protobuf payloads
        self.ops: Counter[str] = Counter()
        self._validators = _Validators()

    async def run(self, seconds: float) -> None:
        import aiohttp

        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(self.url, protocols=["foxglove.websocket.v1"], max_msg_size=0) as ws,
        ):
            self.subprotocol = ws.protocol or ""
            loop = asyncio.get_running_loop()
            end = loop.time() + seconds
            next_sub = 1
            while (left := end - loop.time()) > 0:
                try:
                    msg = await ws.receive(timeout=left)
                except TimeoutError:
                    break
                if msg.type == aiohttp.WSMsgType.TEXT:
                    body = json.loads(msg.data)
                    self.ops[body.get("op", "?")] += 1
                    if body.get("op") != "advertise":
                        continue
                    subs = []
                    for c in body["channels"]:
                        ch = self._channel(c)
                        subs.append({"id": next_sub, "channelId": c["id"]})
                        self.by_id[next_sub] = ch
                        next_sub += 1
                    await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    self._message(msg.data)
                else:
                    break

    def _channel(self, c: dict[str, Any]) -> Channel:
        enc = c.get("schemaEncoding") or ("jsonschema" if c["encoding"] == "json" else "")
        raw = c.get("schema", "")
        data = base64.b64decode(raw) if enc == "protobuf" else raw.encode()
        ch = Channel(c["topic"], c["schemaName"], enc, c["encoding"], data)
        self.channels[ch.topic] = ch
        return ch

    def _message(self, data: bytes) -> None:
        if not data or data[0] != 0x01:  # 0x01: message data
            return
        (sub,) = struct.unpack_from("<I", data, 1)
        payload = data[1 + 4 + 8 :]
        ch = self.by_id.get(sub)
        if ch is None:
            return
        ch.messages += 1
        if ch.message_encoding == "json":
            self._validators.check(ch, payload)
        else:
            self.arrivals[ch.topic].append(bytes(payload))


def audio_times(schema: bytes, payloads: list[bytes]) -> list[float]:
    """The first-sample times (s) of RawAudio messages, decoded with their own schema."""
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    dec = DecoderFactory().decoder_for(
        "protobuf", Schema(id=1, name="foxglove.RawAudio", encoding="protobuf", data=schema)
    )
    assert dec is not None
    times = []
    for p in payloads:
        m = dec(p)
        times.append(m.timestamp.seconds + m.timestamp.nanos / 1e9)
    return times


def blocks_delivered(times: list[float], block_seconds: float) -> float:
    """Share of the blocks between the first and last received that arrived (1.0: none lost)."""
    if len(times) < 2:
        return 0.0
    ts = sorted(times)
    expected = round((ts[-1] - ts[0]) / block_seconds) + 1
    return len(set(round(t / block_seconds) for t in ts)) / expected
