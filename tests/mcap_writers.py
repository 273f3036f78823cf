"""MCAP files as other programs write them, each by its own official writer.

Every writer gets a few channels of the encodings it is for; flowrt must read them all
(``info``, ``replay``). Times are 20 Hz from ``T0`` (ns), 20 messages per channel.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

T0 = 1_700_000_000_000_000_000
COUNT = 20
PERIOD = 50_000_000


def _times() -> list[int]:
    return [T0 + i * PERIOD for i in range(COUNT)]


def python_mcap(path: Path) -> Path:
    """``mcap``'s own Writer: a JSON channel and a schemaless binary one."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        schema = json.dumps({"type": "object", "properties": {"x": {"type": "number"}}})
        sid = w.register_schema("Point", "jsonschema", schema.encode())
        cj = w.register_channel("/point", "json", sid)
        cb = w.register_channel("/blob", "application/octet-stream", 0)
        for i, t in enumerate(_times()):
            w.add_message(cj, t, json.dumps({"x": i * 0.5}).encode(), t, i)
            w.add_message(cb, t, bytes([i, 255 - i, 7]), t, i)
        w.finish()
    return path


def protobuf(path: Path) -> Path:
    """``mcap-protobuf-support``: well-known protobuf types (their descriptors in the file)."""
    from google.protobuf.timestamp_pb2 import Timestamp
    from google.protobuf.wrappers_pb2 import DoubleValue
    from mcap_protobuf.writer import Writer

    with open(path, "wb") as f, Writer(f) as w:
        for i, t in enumerate(_times()):
            w.write_message("/stamp", Timestamp(seconds=t // 10**9, nanos=i), t, t, i)
            w.write_message("/speed", DoubleValue(value=1.5 * i), t, t, i)
    return path


ROS1_IMAGE = """std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
uint32 seq
time stamp
string frame_id
"""


def ros1(path: Path) -> Path:
    """``mcap-ros1-support``: a ROS 1 image (mono8) and a std_msgs/Float64."""
    from mcap_ros1._vendor.genpy import dynamic
    from mcap_ros1.writer import Writer

    image = dynamic.generate_dynamic("sensor_msgs/Image", ROS1_IMAGE)["sensor_msgs/Image"]
    number = dynamic.generate_dynamic("std_msgs/Float64", "float64 data")["std_msgs/Float64"]
    with open(path, "wb") as f:
        w = Writer(f)
        for i, t in enumerate(_times()):
            px = np.full((12, 16), i * 10, np.uint8)
            msg = image(height=12, width=16, encoding="mono8", step=16, data=px.tobytes())
            msg.header.stamp.secs, msg.header.stamp.nsecs = divmod(t, 10**9)
            w.write_message("/ros1/image", msg, t, t, i)
            w.write_message("/ros1/value", number(data=i * 0.25), t, t, i)
        w.finish()
    return path


def ros2(path: Path) -> Path:
    """``mcap-ros2-support``: CDR with ros2msg schemas (an Image, a Twist)."""
    from mcap_ros2.writer import Writer

    image_def = (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n" + "=" * 80 + "\n"
        "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
        + "=" * 80
        + "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    )
    twist_def = (
        "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n" + "=" * 80 + "\n"
        "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    )
    with open(path, "wb") as f:
        w = Writer(f)
        img = w.register_msgdef("sensor_msgs/msg/Image", image_def)
        tw = w.register_msgdef("geometry_msgs/msg/Twist", twist_def)
        for i, t in enumerate(_times()):
            sec, nsec = divmod(t, 10**9)
            msg = {
                "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "cam"},
                "height": 8,
                "width": 8,
                "encoding": "rgb8",
                "is_bigendian": 0,
                "step": 24,
                "data": bytes([i % 256]) * 192,
            }
            w.write_message("/ros2/image", img, msg, t, t, i)
            vel = {
                "linear": {"x": 0.1 * i, "y": 0.0, "z": 0.0},
                "angular": {"x": 0, "y": 0, "z": 1},
            }
            w.write_message("/ros2/cmd_vel", tw, vel, t, t, i)
        w.finish()
    return path


def foxglove_sdk(path: Path) -> Path:
    """foxglove-sdk: its protobuf schemas (RawImage, a Vector3) and a JSON dict channel."""
    import foxglove
    from foxglove.channels import RawImageChannel, Vector3Channel
    from foxglove.messages import RawImage, Timestamp, Vector3

    with foxglove.open_mcap(str(path), allow_overwrite=True):
        images = RawImageChannel("/sdk/image")
        vectors = Vector3Channel("/sdk/vector")
        plain = foxglove.Channel("/sdk/json")
        for i, t in enumerate(_times()):
            sec, nsec = divmod(t, 10**9)
            px = bytes([i * 5 % 256]) * (6 * 4 * 3)
            images.log(
                RawImage(
                    timestamp=Timestamp(sec=sec, nsec=nsec),
                    width=6,
                    height=4,
                    encoding="bgr8",
                    step=18,
                    data=px,
                ),
                log_time=t,
            )
            vectors.log(Vector3(x=i, y=0.0, z=-1.0), log_time=t)
            plain.log({"i": i, "ok": True}, log_time=t)
    return path


NODE_SCRIPT = r"""
import { McapWriter } from "@mcap/core";
import { open } from "node:fs/promises";
const out = process.argv[2];
const fh = await open(out, "w");
const writable = {
  pos: 0n,
  position() { return this.pos; },
  async write(buf) { await fh.write(buf); this.pos += BigInt(buf.byteLength); },
};
const w = new McapWriter({ writable });
await w.start({ profile: "ros2", library: "@mcap/core test" });
const sid = await w.registerSchema({
  name: "std_msgs/msg/Int32", encoding: "ros2msg",
  data: new TextEncoder().encode("int32 data\n"),
});
const cdr = await w.registerChannel({
  topic: "/node/count", messageEncoding: "cdr", schemaId: sid, metadata: new Map(),
});
const bin = await w.registerChannel({
  topic: "/node/raw", messageEncoding: "", schemaId: 0, metadata: new Map(),
});
for (let i = 0; i < 20; i++) {
  const t = 1700000000000000000n + BigInt(i) * 50000000n;
  const data = new Uint8Array(8);
  data.set([0, 1, 0, 0]);
  new DataView(data.buffer).setInt32(4, i * 3, true);
  await w.addMessage({ channelId: cdr, sequence: i, logTime: t, publishTime: t, data });
  await w.addMessage({
    channelId: bin, sequence: i, logTime: t, publishTime: t, data: new Uint8Array([i, 1, 2]),
  });
}
await w.end();
await fh.close();
"""


def mcap_core(path: Path) -> Path | None:
    """@mcap/core (Node.js): a CDR channel (std_msgs/msg/Int32) and a binary one; None when
    Node.js or FLOWRT_NODE_MODULES is missing."""
    modules = os.environ.get("FLOWRT_NODE_MODULES")
    node = shutil.which("node")
    if not modules or node is None or not (Path(modules) / "@mcap" / "core").is_dir():
        return None
    # ES modules resolve packages from the script's folder: the script goes beside them
    script = Path(modules).parent / f"flowrt_write_{os.getpid()}.mjs"
    script.write_text(NODE_SCRIPT)
    try:
        r = subprocess.run(
            [node, str(script), str(path)],
            cwd=Path(modules).parent,
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        script.unlink(missing_ok=True)
    assert r.returncode == 0, r.stderr
    return path


WRITERS = {
    "mcap": python_mcap,
    "protobuf": protobuf,
    "ros1": ros1,
    "ros2": ros2,
    "foxglove-sdk": foxglove_sdk,
    "mcap-core": mcap_core,
}
