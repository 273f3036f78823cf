"""640x480x3 frames (seq and send time in the first 16 bytes): flat out, or on a timer tick.

Stops sending after SECONDS and records how many it sent.
"""

import os
import sys
import time

import numpy as np
import pyarrow as pa
from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import STAMP, write

w, h = int(os.environ.get("WIDTH", "640")), int(os.environ.get("HEIGHT", "480"))
seconds = float(os.environ.get("SECONDS", "3"))
flat_out = os.environ.get("FLAT_OUT", "0") == "1"
out = os.environ.get("OUT", "")
buf = np.zeros(w * h * 3, np.uint8)
head = buf[:16].view(STAMP)
node = Node()
sent, first = 0, None


def send():
    global sent, first
    now = time.monotonic()
    if first is None:
        first = now
    if now - first >= seconds:
        return False
    head[0] = now
    head[1] = sent
    node.send_output("frame", pa.array(buf))
    sent += 1
    return True


if flat_out:
    while send():
        pass
else:
    for event in node:
        if event["type"] == "INPUT":
            if not send():
                break
        elif event["type"] == "STOP":
            break
if out:
    write(out, {"sent": sent, "seconds": time.monotonic() - first})
