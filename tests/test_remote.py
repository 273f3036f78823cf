"""Remote edges over Zenoh: the wire format, graph-file checks, and two real processes over
loopback (explicit tcp/127.0.0.1 endpoints, no scouting): frames and detections flow, are
counted, a killed exporter turns the imports stale and a restarted one resumes them."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import signal
import socket
import subprocess
import sys
import textwrap
import types
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel

from flowrt import Frame, Graph, GraphBuilder, GraphError, Node, Output, Runtime
from flowrt.edges import EMPTY
from flowrt.remote._importer import FRAME_BACKLOG, ImportLink
from flowrt.remote.wire import HEADER, Header, decode_frame, encode_frame, from_wire, to_wire

pytestmark = pytest.mark.timeout(90)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclasses.dataclass
class Det:
    found: bool
    centroid: tuple[float, float]
    area: float


def test_wire_values_round_trip_without_pickle() -> None:
    value = {"a": Det(True, (1.5, 2.0), float("nan")), "n": np.int64(3), "arr": np.eye(2)}
    back = from_wire(to_wire(value))
    assert back["a"].found is True
    assert back["a"].centroid == [1.5, 2.0]
    assert back["a"].area is None  # NaN is not JSON
    assert back["n"] == 3
    assert back["arr"] == [[1.0, 0.0], [0.0, 1.0]]


def test_header_round_trip_and_version() -> None:
    meta = {"shape": [2, 3], "dtype": "uint16", "pf": "GRAY", "seq": 4, "enc": "raw"}
    h = Header("s1", "z1", 7, 1.5, 1.25, "frame", meta)
    assert Header.decode(h.encode()) == h
    msg = Header("0123456789abcdef", "f" * 32, 2**63, 1.5, 1.25, "json")
    assert Header.decode(msg.encode()) == msg
    with pytest.raises(ValueError, match="wire version"):
        Header.decode(b'{"v": 99}')
    with pytest.raises(ValueError, match="wire version 9"):
        Header.decode(b"FLRT\x09" + bytes(115))
    with pytest.raises(ValueError, match="magic"):
        Header.decode(bytes(120))
    with pytest.raises(ValueError, match="header of 119 bytes"):
        Header.decode(h.encode()[:119])


def test_header_is_the_fixed_binary_layout_of_the_docs() -> None:
    """Issue 31: what docs/zenoh.md tells a plain program, read with ``struct`` alone."""
    import struct

    meta = {"shape": [480, 640, 3], "dtype": "uint8", "pf": "BGR", "seq": 11, "enc": "jpeg"}
    raw = Header("0123456789abcdef", "a1b2", 9, 1.5, 1.25, "frame", meta, 1700000000).encode()
    assert len(raw) == 120
    fields = struct.unpack("<4sBBBB16s32sQddQIIII8s8s", raw)
    magic, version, kind, enc, _, stream, zid, n, t, c, fseq, h, w, ch, t0, dtype, pf = fields
    assert (magic, version, kind, enc) == (b"FLRT", 2, 1, 1)
    assert (stream.rstrip(b"\0"), zid.rstrip(b"\0")) == (b"0123456789abcdef", b"a1b2")
    assert (n, t, c, fseq, h, w, ch, t0) == (9, 1.5, 1.25, 11, 480, 640, 3, 1700000000)
    assert (dtype.rstrip(b"\0"), pf.rstrip(b"\0")) == (b"uint8", b"BGR")
    with pytest.raises(ValueError, match="longer than"):
        Header("s", "z", 0, 0.0, 0.0, "frame", {**meta, "pf": "TOO-LONG-FORMAT"}).encode()
    docs = (Path(__file__).resolve().parents[1] / "docs" / "zenoh.md").read_text()
    assert f'"{HEADER.format}"' in docs  # the documented layout is the one on the wire


def test_a_version_1_json_header_is_still_read() -> None:
    """An exporter of an older flowrt (the JSON header) is still understood."""
    raw = b'{"v":1,"s":"ab","z":"z1","n":3,"t":1.0,"c":0.5,"k":"json"}'
    assert Header.decode(raw) == Header("ab", "z1", 3, 1.0, 0.5, "json")


@pytest.mark.parametrize("encoding", ["raw", "png", "jpeg"])
def test_frame_encodings(encoding: str) -> None:
    rng = np.random.default_rng(1)
    data = np.zeros((48, 64, 3), np.uint8)
    data[10:30, 20:40] = rng.integers(0, 255, (20, 20, 3), dtype=np.uint8)
    meta, payload = encode_frame(Frame(data, seq=5), encoding, 95)
    back = decode_frame(meta, payload)
    assert back.shape == data.shape
    if encoding == "jpeg":
        assert np.abs(back.astype(int) - data).mean() < 8
        assert len(payload) < data.nbytes
    else:
        assert np.array_equal(back, data)
    assert meta["seq"] == 5


BASE = """
name: base
zenoh: {listen: [], connect: ["tcp/127.0.0.1:7447"]}
import: {rball: r1/ball}
nodes:
  sink: {kind: sink, inputs: {input: rball}}
"""


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("tcp/127.0.0.1:7447", "tcp/127.0.0.1:70000"), "port in 0..65535"),
        (("tcp/127.0.0.1:7447", "carrier-pigeon"), "not a Zenoh endpoint"),
        (("r1/ball}", "r1//ball}"), "empty chunk"),
        (("r1/ball}", "r1/*}"), "no * or **"),
        (("{rball: r1/ball}", "{sink: r1/ball}"), "has the name of a node"),
        (("input: rball", "input: nothing"), "expected node.port"),
        (("nodes:", "export: {r1/x: sink.out}\nnodes:"), "has no output 'out'"),
        (("nodes:", "export: {r1/x: ghost.out}\nnodes:"), "unknown node 'ghost'"),
        (
            (
                "nodes:",
                "export: {r1/x: {from: c.value, encoding: jpeg}}\nnodes:\n  c: {kind: counter}",
            ),
            "encoding jpeg is for frames: c.value is not a Frame output",
        ),  # (accepted: the counter's int went out as JSON)
        (("nodes:", "export: {r1/**: sink.out}\nnodes:"), "name one key, no * or **"),
        (("nodes:", "export: {r1/$x: sink.out}\nnodes:"), "are reserved"),
        (("connect:", "control: a//b, connect:"), "empty chunk"),
        (("listen: []", "listen: [tcp/127.0.0.1]"), "expected host:port"),
    ],
)
def test_bad_remote_configuration_is_located(
    tmp_path: Path, change: tuple[str, str], message: str
) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(BASE.replace(*change))
    with pytest.raises(GraphError) as e:
        Graph.from_file(path)
    text = "\n".join(str(d) for d in e.value.diagnostics)
    assert message in text
    assert f"{path}:" in text


ROBOT = """
name: robot
zenoh: {{listen: ["tcp/127.0.0.1:{port}"]}}
nodes:
  cam: {{kind: capture, params: {{source: "synthetic:soccer", fps: 20, size: [160, 120]}}}}
  ball:
    kind: tracker
    params: {{object: ball}}
    inputs: {{frame: cam.frame}}
export: {{"t/ball": ball.detection, "t/frame": cam.frame}}
"""

BASE_E2E = """
name: base
zenoh: {{listen: [], connect: ["tcp/127.0.0.1:{port}"]}}
import:
  rball: {{key: t/ball, period: 50ms, stale_after: 6}}
  rframe: {{key: t/frame, frames: true, period: 50ms, stale_after: 6}}
nodes:
  track:
    kind: tracker
    params: {{object: ball}}
    trigger: {{frame: rframe}}
    inputs: {{frame: rframe}}
"""


def start_robot(path: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "flowrt.cli", "run", str(path), "--no-ui", "--duration", "60"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


async def wait_for(cond: Any, within: float) -> bool:
    loop = asyncio.get_running_loop()
    end = loop.time() + within
    while loop.time() < end:
        if cond():
            return True
        await asyncio.sleep(0.1)
    return bool(cond())


async def test_two_processes_kill_and_restart(tmp_path: Path) -> None:
    port = free_port()
    robot = tmp_path / "robot.yaml"
    robot.write_text(textwrap.dedent(ROBOT.format(port=port)))
    base = tmp_path / "base.yaml"
    base.write_text(textwrap.dedent(BASE_E2E.format(port=port)))
    proc = start_robot(robot)
    try:
        async with Runtime.from_file(base) as rt:
            dets = rt.subscribe("rball.output", size=1024)
            frames = rt.subscribe("rframe.output", size=1024)
            tracked = rt.subscribe("track.detection", size=1024)

            def node(name: str) -> Any:
                return rt.stats().node(name)

            assert await wait_for(lambda: node("track").completions >= 10, 30)
            got = dets.drain()
            assert got
            assert hasattr(got[-1], "found")  # attribute access, as on the robot
            frame = frames.drain()[-1]
            assert isinstance(frame, Frame)
            assert frame.shape == (120, 160, 3)
            assert tracked.drain()
            links = {e.name: e for e in rt.stats().edges if e.policy == "remote"}
            assert set(links) == {"zenoh:t/ball->rball", "zenoh:t/frame->rframe"}
            assert all(e.delivered > 0 for e in links.values())
            assert node("rball").state != "error", node("rball").reason

            os.killpg(proc.pid, signal.SIGKILL)  # the robot's process dies
            proc.wait(10)
            assert await wait_for(lambda: node("rball").state == "error", 10)
            assert "stale" in node("rball").reason
            assert await wait_for(lambda: node("rframe").state == "error", 5)
            rec = rt.rtdb.read("rball")
            assert rec is not None
            assert await wait_for(lambda: rt.rtdb.read("rball").stale, 5)

            before = node("track").completions
            first_life = rt.stats().edge("zenoh:t/ball->rball").published
            proc = start_robot(robot)  # it comes back: a new stream, not a gap
            assert await wait_for(lambda: node("rball").state != "error", 30)
            assert await wait_for(lambda: node("track").completions > before + 5, 15)
            assert not rt.rtdb.read("rball").stale
            link = rt._bridge.imports["rball"]
            with link.lock:  # the new life is published from its number 0 on: the values
                # before the first one heard (the link not yet back) are counted, not hidden
                assert link.link.published - first_life == link.last_seq + 1
                reasons = dict(link.link.drop_reasons)
            # the restart is not a gap (from the old life's last number to the new one's)
            assert reasons.get("sequence gap", 0) <= 2
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def test_port_in_use_is_one_line_and_exit_1(tmp_path: Path) -> None:
    port = free_port()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        path = tmp_path / "robot.yaml"
        path.write_text(textwrap.dedent(ROBOT.format(port=port)))
        r = subprocess.run(
            [sys.executable, "-m", "flowrt.cli", "run", str(path), "--no-ui", "--duration", "5"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert f"tcp/127.0.0.1:{port}" in lines[0]
    assert "already in use" in lines[0]


def test_client_mode_without_a_router_is_one_line_and_exit_1(tmp_path: Path) -> None:
    port = free_port()  # nothing listens there
    path = tmp_path / "base.yaml"
    text = BASE.replace("listen: []", "mode: client, listen: []").replace("7447", str(port))
    path.write_text(text)
    r = subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "run", str(path), "--no-ui", "--duration", "5"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1
    assert r.stderr.strip() == (
        f"flowrt run: zenoh: cannot connect to tcp/127.0.0.1:{port} (in client mode a router "
        "or peer must answer at start; peer mode keeps trying)"
    )


class Pattern(Node):
    """Frames whose every pixel is the frame's number (mod 256): a copy error shows."""

    class Params(BaseModel):
        shape: tuple[int, ...] = (48, 64, 3)

    frame = Output(Frame)

    def setup(self) -> None:
        self.n = 0

    def process(self) -> Any:
        self.n += 1
        f = self.ctx.new_frame(self.params.shape)
        f.data[...] = self.n % 256
        return f


async def intact_frames(sub: Any, want: int, shape: tuple[int, ...]) -> AsyncIterator[Frame]:
    """:class:`Pattern`'s frames from ``sub`` until ``want`` came (20 s at most), each checked
    whole: its shape, one frame's pixels (not a mix of two), a new frame's (not a slot's old
    ones). Each is held while the caller has it (its slot is not reused meanwhile)."""
    seen, last = 0, -1
    loop = asyncio.get_running_loop()
    end = loop.time() + 20
    while seen < want and loop.time() < end:
        await asyncio.sleep(0.05)
        while (f := sub.take_held()) is not EMPTY:
            assert f.shape == shape
            values = np.unique(f.data)
            assert len(values) == 1, values
            assert values[0] != last
            last = int(values[0])
            seen += 1
            try:
                yield f
            finally:
                f.release()


@pytest.mark.subprocess  # a worker (or writer) process, from its graph
@pytest.mark.parametrize("placement", ["process", "inline"])
async def test_frames_arrive_intact_in_the_pool_and_go_back_to_it(placement: str) -> None:
    """Frames a worker reads are copied into the importer's pool on Zenoh's thread (a spare
    frame the loop keeps ready): every pixel arrives, every pool slot is returned at the end.
    Frames only inline nodes read are not copied at all (issue 31): heap frames over the
    received bytes, read-only."""
    port = free_port()
    ex = GraphBuilder("ex").add("src", Pattern, trigger={"timer": "20ms"})
    ex.zenoh(listen=[f"tcp/127.0.0.1:{port}"]).export("p/frame", "src.frame")
    im = GraphBuilder("im").zenoh(listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    im.import_("rx", {"key": "p/frame", "frames": True, "period": "20ms"})
    im.add("relay", "relay", inputs={"input": "rx.output"})  # a worker reads it after a hop
    im.add("sink", "sink", inputs={"input": "relay.output"}, placement=placement)
    async with Runtime(ex.build()) as rx_side, Runtime(im.build()) as rt:
        sub = rt.subscribe("rx.output", size=1024)
        seen = pooled = 0
        async for f in intact_frames(sub, 40, (48, 64, 3)):
            pooled += f._slot is not None  # in the local pool, readable zero-copy
            assert f._slot is not None or not f.data.flags.writeable
            seen += 1
        assert seen >= 40
        imp = rt._bridge.imports["rx"]
        if placement == "process":
            assert pooled == seen
            # the next frame's slot is ready off the loop (unless a frame is arriving now)
            assert await wait_for(lambda: imp.spare is not None, 2.0)
        else:
            assert pooled == 0
            assert imp.spare is None
        del rx_side
    pools = {p.owner: p for p in rt.stats().frames}
    assert "rx" not in pools or pools["rx"].slots_in_use == 0


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data

    def __len__(self) -> int:
        return len(self.data)


class _Sample:
    def __init__(self, header: Header, payload: bytes) -> None:
        self.attachment = _Bytes(header.encode())
        self.payload = _Bytes(payload)


def test_link_counts_each_loss_with_its_reason() -> None:
    """Sequence gaps, hand-over overruns (the loop not taking frames in time) and
    undecodable messages are each counted on the remote link, with their reason."""
    woken: list[Any] = []
    host = types.SimpleNamespace(
        loop=types.SimpleNamespace(call_soon_threadsafe=woken.append), now_mono=lambda: 0.0
    )
    bridge = types.SimpleNamespace(host=host, clock_probe=lambda zid: None)
    imp = ImportLink(bridge, "rx", "k", None, 5.0, 16)  # type: ignore[arg-type]
    meta, pixels = encode_frame(Frame(np.zeros((4, 4, 3), np.uint8)), "raw", 90)
    for seq in (0, 1, 3, 4, 5, 6):  # 2 never arrives; the loop takes none of them
        imp.on_sample(_Sample(Header("s", "z", seq, 0.0, 0.0, "frame", meta), pixels))
    imp.on_sample(_Sample(Header("s", "z", 7, 0.0, 0.0, "json"), b"{not json"))
    assert len(woken) == 1  # one wake-up for the whole burst
    assert len(imp.pending) == FRAME_BACKLOG
    overruns = 6 - FRAME_BACKLOG
    assert imp.link.drop_reasons == {
        "sequence gap": 1,
        "hand-over overrun": overruns,
        "undecodable": 1,
    }
    assert imp.link.dropped == 1 + overruns + 1
    # 0..6 by sequence number, and the undecodable one: it arrived (published) and was dropped
    assert imp.link.published == 8


class _Encoded(_Sample):
    def __init__(self, header: Header, payload: bytes, encoding: Any) -> None:
        super().__init__(header, payload)
        self.encoding = encoding


def test_each_message_is_read_by_the_schema_its_own_encoding_names() -> None:
    """The import keeps the last encoding's schema (its text is costly to read on Zenoh's
    thread): messages of several types on one key, in any order, each come back as its own."""
    from flowrt.recording.streams import StreamBook
    from flowrt.remote._streams import encoding_of

    book = StreamBook(epoch_offset=0.0)
    values = [{"a": 1}, 7, {"a": 2}, {"a": 3}, Det(True, (1.0, 2.0), 3.0), 8, {"a": 4}]
    imp = _imp()
    for seq, value in enumerate(values):
        msg = book.encode("n.out", value)
        enc = encoding_of("json", msg.schema.name)
        imp.on_sample(_Encoded(Header("s", "z", seq, 0.0, 0.0, "json", {}), msg.data, enc))
    got = [v for _, v in imp.pending]
    assert got[:4] == [{"a": 1}, 7, {"a": 2}, {"a": 3}]
    assert got[4].found is True
    assert tuple(got[4].centroid) == (1.0, 2.0)
    assert got[5:] == [8, {"a": 4}]
    assert imp.link.dropped == 0


def test_a_frame_copied_while_the_import_closes_goes_back_to_the_pool() -> None:
    """Zenoh's thread may still be copying into a pool frame when the import closes (its
    subscriber undeclared): that frame is released on the loop, not kept, nor published."""
    woken: list[Any] = []
    host = types.SimpleNamespace(
        loop=types.SimpleNamespace(call_soon_threadsafe=woken.append), now_mono=lambda: 0.0
    )
    bridge = types.SimpleNamespace(host=host, clock_probe=lambda zid: None)
    imp = ImportLink(bridge, "rx", "k", None, 5.0, 16)  # type: ignore[arg-type]
    released: list[int] = []

    class Counted(Frame):
        def release(self) -> None:
            released.append(1)

    held = Counted(np.zeros((4, 4, 3), np.uint8))
    imp._frame = lambda meta, arr: held  # type: ignore[method-assign]  # the spare, taken
    meta, pixels = encode_frame(Frame(np.zeros((4, 4, 3), np.uint8)), "raw", 90)
    imp.close()  # on the loop, while the copy runs
    imp.on_sample(_Sample(Header("s", "z", 0, 0.0, 0.0, "frame", meta), pixels))
    assert not imp.pending
    assert woken == [imp.deliver]
    imp.deliver()  # the loop runs it
    assert released == [1]


def _imp() -> Any:
    host = types.SimpleNamespace(
        loop=types.SimpleNamespace(call_soon_threadsafe=lambda f: None), now_mono=lambda: 0.0
    )
    bridge = types.SimpleNamespace(host=host, clock_probe=lambda zid: None)
    imp = ImportLink(bridge, "rx", "k", None, 5.0, 16)  # type: ignore[arg-type]
    imp.max_bytes, imp.max_pixels = 1 << 20, 4096 * 4096
    return imp


def _png_header(w: int, h: int) -> bytes:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", len(ihdr))
        + chunk
        + struct.pack(">I", zlib.crc32(chunk))
        + b"\x00" * 64
    )


@pytest.mark.parametrize(
    ("meta", "payload", "reason"),
    [
        ({"shape": [0, 2, 3], "dtype": "uint8", "enc": "raw"}, b"", "bad frame"),
        ({"shape": [2, 2, 5], "dtype": "uint8", "enc": "raw"}, bytes(20), "bad frame"),
        ({"shape": [2, 2, 3], "dtype": "object", "enc": "raw"}, bytes(12), "bad frame"),
        (
            {"shape": [12000, 12000, 3], "dtype": "uint8", "enc": "png"},
            _png_header(12000, 12000),
            "bad frame",
        ),
        (
            {"shape": [4, 4, 3], "dtype": "uint8", "enc": "png"},
            _png_header(12000, 12000),
            "bad frame",
        ),
        ({"shape": [4, 4, 3], "dtype": "uint8", "enc": "raw"}, bytes(2 << 20), "too large"),
        ({"shape": [2, 2, 3], "dtype": "uint8", "enc": "raw"}, bytes(11), "bad frame"),  # (docs)
    ],
    ids=[
        "empty",
        "5-channels",
        "dtype",
        "huge-declared",
        "png-header-huge",
        "over-byte-limit",
        "raw-size-mismatch",
    ],
)
def test_an_import_refuses_what_is_not_an_image_before_decoding(
    meta: dict[str, Any], payload: bytes, reason: str
) -> None:
    """Issue 32 item 3: shapes, dtypes and encoded sizes are checked before decoding."""
    imp = _imp()
    imp.on_sample(_Sample(Header("s", "z", 0, 0.0, 0.0, "frame", meta), payload))
    assert imp.link.drop_reasons == {reason: 1}
    assert imp.link.published == 1
    assert not imp.pending


def test_a_forged_sequence_jump_is_a_restart_not_a_gap_of_2_to_the_63() -> None:
    imp = _imp()
    meta, pixels = encode_frame(Frame(np.zeros((4, 4, 3), np.uint8)), "raw", 90)
    for seq in (0, 1, 2**63, 2**63 + 1, 5):
        imp.on_sample(_Sample(Header("s", "z", seq, 0.0, 0.0, "frame", meta), pixels))
    assert imp.restarts == 2  # forward by 2**63, then back to 5
    assert imp.link.published == 5
    assert imp.link.drop_reasons.get("sequence gap", 0) == 0


def test_a_large_json_message_is_refused_without_parsing(caplog: pytest.LogCaptureFixture) -> None:
    imp = _imp()
    big = b"[" + b"1," * (1 << 20) + b"1]"
    for seq in range(50):
        imp.on_sample(_Sample(Header("s", "z", seq, 0.0, 0.0, "json"), big))
    assert imp.link.drop_reasons == {"too large": 50}
    warnings = [r for r in caplog.records if "too large" in r.getMessage()]
    assert len(warnings) == 1  # rate-limited: a flood is counted, logged once


@pytest.mark.realtime
async def test_a_connect_endpoint_nobody_answers_is_said(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A typo in the other side's port: peer mode retries silently, the export counted every
    value as delivered and the run exited 0 without a word."""
    from flowrt.remote import _bridge

    monkeypatch.setattr(_bridge, "UNREACHED_AFTER", 0.3)
    port = free_port()
    g = GraphBuilder("lonely")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.zenoh(listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    g.export("t/x", "src.value")
    async with Runtime(g.build()) as rt:
        await rt.run(0.8)
    assert f"zenoh: nothing answers at tcp/127.0.0.1:{port} after 0.3 s" in caplog.text
