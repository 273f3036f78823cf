"""Passes its input through unchanged: a hop in the chain."""

from dora import Node

node = Node()
for event in node:
    if event["type"] == "INPUT":
        node.send_output("out", event["value"])
    elif event["type"] == "STOP":
        break
