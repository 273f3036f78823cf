"""Records the arrival instant of each dora timer tick."""

import os
import sys
import time

from dora import Node

sys.path.insert(0, os.path.dirname(__file__))
from common import write

count = int(os.environ.get("COUNT", "120"))
out = os.environ["OUT"]
node = Node()
t = []
for event in node:
    if event["type"] == "INPUT":
        t.append(time.monotonic())
        if len(t) == count + 1:
            write(out, {"t": t})
    elif event["type"] == "STOP":
        break
