"""A plain Zenoh subscriber (eclipse-zenoh only, no flowrt) reading what a flowrt graph
exports: the payload is the value (JSON here), the attachment flowrt's binary header (its
layout in docs/zenoh.md).

    python docs/examples/zenoh_plain_sub.py tcp/127.0.0.1:7460 demo/count 5
"""

import json
import struct
import sys
import threading

import zenoh

endpoint, key, wanted = sys.argv[1], sys.argv[2], int(sys.argv[3])
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("scouting/multicast/enabled", "false")
HEADER = struct.Struct("<4sBBBB16s32sQddQIII4x8s8s")  # flowrt's header, version 2
got: list[dict] = []
done = threading.Event()


def on_sample(sample: zenoh.Sample) -> None:
    fields = HEADER.unpack(sample.attachment.to_bytes())  # flowrt's header (docs/zenoh.md)
    magic, version, kind, seq = fields[0], fields[1], fields[2], fields[7]
    assert (magic, version, kind) == (b"FLRT", 2, 0)  # a JSON message
    value = json.loads(sample.payload.to_bytes())  # the value itself
    got.append({"encoding": str(sample.encoding), "seq": seq, "value": value})
    if len(got) >= wanted:
        done.set()


with zenoh.open(conf) as session:
    sub = session.declare_subscriber(key, on_sample)
    done.wait(20)
print(json.dumps(got[:wanted]))
