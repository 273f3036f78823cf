"""Timer source + round-trip sink: sends NBYTES with the send time in the first 8 bytes."""

import os
import sys
import time

import numpy as np
import pyarrow as pa
from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import STAMP, write

nbytes = int(os.environ["NBYTES"])
count = int(os.environ.get("COUNT", "200"))
warmup = int(os.environ.get("WARMUP", "20"))
out = os.environ["OUT"]
buf = np.zeros(max(nbytes, 8), np.uint8)
node = Node()
one, rtt, seen, done = [], [], 0, False
for event in node:
    if event["type"] != "INPUT":
        if event["type"] == "STOP":
            break
        continue
    if event["id"] == "tick":
        buf[:8].view(STAMP)[0] = time.monotonic()
        node.send_output("out", pa.array(buf))
    elif event["id"] == "back":
        now = time.monotonic()
        seen += 1
        if seen <= warmup or done:
            continue
        sent, one_way = event["value"].to_pylist()
        one.append(one_way)
        rtt.append(now - sent)
        if len(rtt) >= count:
            done = True
            write(out, {"one_way": one, "rtt": rtt})
