"""Takes the payload (zero-copy view), answers (sent, one-way) seconds."""

import os
import sys
import time

import pyarrow as pa
from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import stamp_of

node = Node()
for event in node:
    if event["type"] == "INPUT":
        now = time.monotonic()
        sent = stamp_of(event["value"])
        node.send_output("back", pa.array([sent, now - sent]))
    elif event["type"] == "STOP":
        break
