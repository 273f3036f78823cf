"""End of the 10-node pipeline: end-to-end latency from the stamp in the frame."""

import os
import sys
import time

from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import stamp_of, write

count = int(os.environ.get("COUNT", "90"))
warmup = int(os.environ.get("WARMUP", "15"))  # the first frames queue behind start-up
out = os.environ["OUT"]
node = Node()
lat, first, seen = [], None, 0
for event in node:
    if event["type"] == "INPUT":
        now = time.monotonic()
        if first is None:
            first = now
            write(out + ".first", {"first": now})
        seen += 1
        if seen > warmup and len(lat) < count:
            lat.append(now - stamp_of(event["value"]))
            if len(lat) == count:
                write(out, {"lat": lat, "first": first})
    elif event["type"] == "STOP":
        break
