"""The receiver's work: the mean of the frame (zero-copy view); counts what it processed."""

import os
import sys
import time

from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import STAMP, write

out = os.environ["OUT"]
node = Node()
n, first, last, prev, ordered, first_seq = 0, 0.0, 0.0, -1.0, True, -1.0
for event in node:
    if event["type"] == "INPUT":
        data = event["value"].to_numpy(zero_copy_only=True)
        seq = float(data[8:16].view(STAMP)[0])
        data.mean()
        now = time.monotonic()
        if n == 0:
            first = now
            first_seq = seq
        n += 1
        last = now
        ordered = ordered and seq > prev
        prev = seq
    elif event["type"] == "STOP":
        break
write(
    out,
    {
        "n": n,
        "first": first,
        "last": last,
        "ordered": ordered,
        "first_seq": first_seq,
        "last_seq": prev,
    },
)
