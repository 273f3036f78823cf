"""What the loop and a worker say to each other: one reply per request.

The messages travel on the process wire (:mod:`flowrt.ipc`: length-prefixed pickles, shared
with the recording writer process). Requests and replies are tuples whose first item says
what they are (below); frames travel as descriptors of their shared-memory slot
(:mod:`flowrt.frames`).
"""

from __future__ import annotations

import signal

# Requests (main -> worker); every request gets exactly one reply.
OP_ADD = 0  # (op, node_id, node_name, factory, WorkerScheduling) -> granted: str
OP_CALL = 1  # (op, node_id, inputs, grants, alone) -> result (grants: slots lent,
# frames.lending; alone: no other call of the node in flight behind it, so the worker may
# poll for the next one, workers/child.py Linger)
OP_REMOVE = 2  # (op, node_id) -> None (teardown)
OP_EXIT = 3  # (op,) -> None (teardown all, then exit)
OP_PRIORITY = 4  # (op, node_id, WorkerScheduling) -> granted: str
OP_DISABLE = 5  # (op, node_id) -> what the node's ``on_disable`` returned (None: or it has none)
# OP_CALL may carry a sixth item, a hop (workers/hops.py): its input from another worker
# (an input value ``FromPeer(tag)``) and/or where its output goes straight to (``Forward``).
# Not a request (no reply, not counted): the input a call waits for from another worker will
# not come (its writer's call ended without publishing it); stale ones are ignored.
OP_SKIP = 6  # (op, tag)

# Replies (worker -> main), in the order of the requests; ``index`` counts the requests the
# worker has read (0, 1, 2, ...), so that the main side matches each reply to its call;
# ``report`` says what a call did with its output slots (flowrt.frames.lending), else None.
R_OK = 0  # (status, payload, run_seconds, index, report)
R_ERR = 1  # (status, formatted traceback, run_seconds, index)
R_FATAL = 2  # as R_ERR, from an exception whose ``fatal`` is true: do not restart
R_SKIP = 3  # (status, None, run_seconds, index, None): a call whose input from another worker
# did not come: the node did not run

SIGNALS_KILLED = {signal.SIGKILL, signal.SIGTERM, signal.SIGINT, signal.SIGHUP}
