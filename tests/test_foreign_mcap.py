"""MCAP files of other writers: every encoding decodes, replays without a failure, and what
cannot be decoded is left out with one line and an exit code that says so.

The files are written in the test by the official writers (:mod:`mcap_writers`): Python
``mcap`` (json, binary), ``mcap-protobuf-support``, ``mcap-ros1-support``,
``mcap-ros2-support`` (cdr), foxglove-sdk and ``@mcap/core`` (Node.js; skipped without it).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer
from mcap_writers import COUNT, PERIOD, T0, WRITERS

import flowrt
from flowrt.recording.decoding import MessageDecoder, undecodable
from flowrt.recording.reader import iter_session, scan_session

pytestmark = pytest.mark.timeout(120)

FAST = [w for w in WRITERS if w != "mcap-core"]


def _written(name: str, folder: Path) -> Path:
    path = WRITERS[name](folder / f"{name}.mcap")
    if path is None:
        pytest.skip("needs Node.js and FLOWRT_NODE_MODULES with @mcap/core")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("foreign")


@pytest.mark.parametrize("writer", [*FAST, pytest.param("mcap-core", marks=pytest.mark.subprocess)])
def test_every_message_of_every_writer_decodes(writer: str, files: Path) -> None:
    path = _written(writer, files)
    info = scan_session(path)
    assert info.closed_cleanly
    assert {s.count for s in info.streams} == {COUNT}
    assert undecodable([path], [s.topic for s in info.streams]) == {}
    dec = MessageDecoder()
    kinds: dict[str, set[str]] = {}
    for m in iter_session([path]):
        d = dec.decode(m.encoding, m.schema, m.data)
        kinds.setdefault(m.topic, set()).add(d.kind)
        if d.kind == "image":
            px, fmt = d.value
            assert isinstance(px, np.ndarray)
            assert fmt in ("BGR", "RGB", "GRAY")
            assert d.stamp == m.log_time  # the writers stamp each image with its log time
        else:
            assert isinstance(d.value, dict | bytes)
    assert all(len(k) == 1 for k in kinds.values())


def test_values_are_plain_and_right() -> None:
    """One value per family, checked against what was written."""
    import json

    dec = MessageDecoder()
    from mcap.records import Schema

    twist = Schema(id=1, name="geometry_msgs/msg/Twist", encoding="ros2msg", data=_TWIST.encode())
    from mcap_ros2._dynamic import serialize_dynamic

    enc = serialize_dynamic("geometry_msgs/msg/Twist", _TWIST)["geometry_msgs/msg/Twist"]
    raw = enc({"linear": {"x": 1.0, "y": 2.0, "z": 3.0}, "angular": {"x": 0, "y": 0, "z": 4}})
    assert dec.decode("cdr", twist, raw).value == {
        "linear": {"x": 1.0, "y": 2.0, "z": 3.0},
        "angular": {"x": 0.0, "y": 0.0, "z": 4.0},
    }
    assert dec.decode("application/x-custom", None, b"\x01\x02").value == b"\x01\x02"
    assert dec.decode("json", None, json.dumps({"a": [1, 2]}).encode()).value == {"a": [1, 2]}


_TWIST = (
    "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n" + "=" * 80 + "\n"
    "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
)


def test_a_channel_without_a_decoder_is_refused_with_the_reason() -> None:
    from mcap.records import Schema

    dec = MessageDecoder()
    flat = Schema(id=1, name="robot.Pose", encoding="flatbuffer", data=b"\x10\x00")
    assert "no decoder for 'flatbuffer'" in (dec.why_not("flatbuffer", flat) or "")
    assert "without a schema" in (dec.why_not("cdr", None) or "")
    broken = Schema(
        id=2, name="pkg/msg/Bad", encoding="ros2msg", data=b"this is not a message definition %%%"
    )
    assert dec.why_not("cdr", broken) is not None


def _mixed(path: Path, flatbuffer: bool = True, bad_cdr_at: int | None = None) -> Path:
    """A json channel, optionally a flatbuffer one (no decoder) and a cdr one with one
    message that does not decode."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cj = w.register_channel("/ok", "json", 0)
        sf = w.register_schema("robot.Pose", "flatbuffer", b"\x10\x00\x00\x00")
        cf = w.register_channel("/flat", "flatbuffer", sf) if flatbuffer else None
        st = w.register_schema("geometry_msgs/msg/Twist", "ros2msg", _TWIST.encode())
        ct = w.register_channel("/cmd_vel", "cdr", st)
        good = b"\x00\x01\x00\x00" + bytes(48)
        for i in range(COUNT):
            t = T0 + i * PERIOD
            w.add_message(cj, t, b'{"i": %d}' % i, t, i)
            if cf is not None:
                w.add_message(cf, t, b"\x00" * 8, t, i)
            w.add_message(ct, t, b"\x00\x01" if i == bad_cdr_at else good, t, i)
        w.finish()
    return path


@pytest.mark.subprocess
@pytest.mark.parametrize("writer", WRITERS)
def test_replay_of_every_writer_exits_0(writer: str, files: Path, flowrt_cli: Any) -> None:
    path = _written(writer, files)
    r = flowrt_cli("replay", str(path), "--duration", "3", "--no-ui", timeout=90)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "NodeFailed" not in r.stdout + r.stderr
    assert "left out" not in r.stderr


@pytest.mark.subprocess
def test_replay_leaves_out_what_it_cannot_decode_and_says_so(
    tmp_path: Path, flowrt_cli: Any
) -> None:
    path = _mixed(tmp_path / "mixed.mcap")
    r = flowrt_cli("replay", str(path), "--duration", "3", "--no-ui", timeout=90)
    assert r.returncode == 1, r.stderr  # not everything asked for was replayed
    said = [line for line in r.stderr.splitlines() if "left out" in line]
    assert said == [
        "flowrt replay: /flat: left out, cannot decode (no decoder for 'flatbuffer' "
        "messages (schema encoding 'flatbuffer'))"
    ]
    assert "Traceback" not in r.stderr
    only = flowrt_cli("replay", str(path), "--topics", "/flat", "--no-ui", timeout=90)
    assert only.returncode == 2
    assert "nothing to replay (no stream decodes)" in only.stderr


@pytest.mark.realtime
def test_a_message_that_fails_to_decode_is_skipped_alone_and_counted(tmp_path: Path) -> None:
    """No crash loop: the node goes on, in error, said once; the bad message alone is not
    replayed (it took the rest of its channel with it, uncounted) and the report counts it."""
    path = _mixed(tmp_path / "bad.mcap", flatbuffer=False, bad_cdr_at=5)

    async def main() -> tuple[list[Any], Any]:
        g = flowrt.GraphBuilder("bad")
        g.add("rep", "replay", params={"path": str(path)})
        async with flowrt.Runtime(g.build()) as rt:
            sub = rt.subscribe("rep.message", size=256)
            await asyncio.wait_for(rt.run(), timeout=30)
            return list(sub.drain()), rt.stats()

    got, stats = asyncio.run(main())
    node = next(n for n in stats.nodes if n.name == "rep")
    assert node.errors == 0
    assert node.restarts == 0
    assert node.state == "error"
    assert "/cmd_vel: a message skipped, cannot decode" in node.reason
    assert sum(isinstance(v, dict) and "i" in v for v in got) == COUNT  # /ok whole
    assert sum(isinstance(v, dict) and "linear" in v for v in got) == COUNT - 1  # but one
    (row,) = stats.reports["rep"]["not_replayed"].items()
    assert row[0] == "/cmd_vel"
    assert row[1]["messages"] == 1
    assert row[1]["why"].startswith("cannot decode: ")
