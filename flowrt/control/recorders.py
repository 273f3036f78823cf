"""Starting and stopping the recorder nodes of a running graph: one owner, one at a time.

A recorder obeys the newest value of its RTDB record ``flowrt.record.NODE`` and says where
it records in ``flowrt.recording.NODE`` (``""``: stopped). Two clients writing commands at
once (the operator page and ``flowrt ctl record``, two operators, a double click in two
tabs) each overwrote the other's and were both told 200; the control endpoint answered
before the recorder had obeyed, and a start while recording was "done". Every client of the
runtime goes through :func:`obey` under the runtime's one :func:`turn`: a command is
written only when the recorders' state allows it, and answered once they said they obeyed.
"""

from __future__ import annotations

import asyncio
import weakref
from pathlib import Path
from typing import Any

from ..rtdb import RECORD_COMMAND, RECORDING_SESSION

__all__ = ["obey", "recorders", "turn"]

_TURNS: weakref.WeakKeyDictionary[Any, asyncio.Lock] = weakref.WeakKeyDictionary()


def turn(rtdb: Any) -> asyncio.Lock:
    """The lock every start or stop of the recorders of ``rtdb``'s runtime is made under."""
    lock = _TURNS.get(rtdb)
    if lock is None:
        lock = _TURNS[rtdb] = asyncio.Lock()
    return lock


def recorders(rtdb: Any) -> list[str]:
    """The recorder nodes of the running graph: those that publish their state."""
    return sorted(
        n[len(RECORDING_SESSION) :] for n in rtdb.names() if n.startswith(RECORDING_SESSION)
    )


async def obey(
    rtdb: Any,
    action: str,
    name: Any,
    wait: float,
    nodes: list[str] | None = None,
) -> dict[str, Any]:
    """Start (``name``: the session's prefix; None: each recorder's own) or stop ``nodes``
    (default: every recorder), and wait until each says it did. ``{"status": 200,
    "sessions": {node: folder}}`` or ``{"status", "error"}``; call it under :func:`turn`.

    A command written meanwhile by a client outside the turn ends the wait with 409 and
    the state as it is, never a wait for a state that will not come; recorders slower than
    ``wait`` are a 202 for a start (the command stands: they obey when they can)."""
    known = recorders(rtdb)
    if not known:
        return {
            "status": 404,
            "error": "the graph has no recorder (run it with --recordings DIR, or add one)",
        }
    nodes = known if nodes is None else [n for n in nodes if n in known]
    current = {n: str(rtdb.value(RECORDING_SESSION + n, "") or "") for n in nodes}
    command: Any
    if action == "start":
        from ..recording.session import SESSION_NAME  # (the recording package: when asked)

        if name is not None and (not isinstance(name, str) or not SESSION_NAME.match(name)):
            return {"status": 400, "error": "name: letters, digits, _ and - (at most 64)"}
        busy = {n: s for n, s in current.items() if s}
        if busy:
            where = ", ".join(f"{n} into {Path(s).name}" for n, s in busy.items())
            return {"status": 409, "error": f"already recording: {where}", "sessions": current}
        targets, command = nodes, "start" if name is None else {"action": "start", "name": name}
    elif action == "stop":
        targets = [n for n, s in current.items() if s]
        if not targets:
            return {"status": 409, "error": "not recording", "sessions": current}
        command = "stop"
    else:
        return {"status": 400, "error": "action: start or stop"}
    ours: dict[str, int] = {}
    for node in targets:
        rtdb.write(RECORD_COMMAND + node, command)
        ours[node] = _seq(rtdb, RECORD_COMMAND + node)
    loop = asyncio.get_running_loop()
    end = loop.time() + wait
    while True:
        now = {n: str(rtdb.value(RECORDING_SESSION + n, "") or "") for n in targets}
        if all(bool(s) == (action == "start") for s in now.values()):
            break
        others = [n for n in targets if _seq(rtdb, RECORD_COMMAND + n) != ours[n]]
        if others:
            return {
                "status": 409,
                "error": f"another client changed the recording of {', '.join(others)} meanwhile",
                "sessions": now,
            }
        if loop.time() > end:
            late = [n for n, s in now.items() if bool(s) != (action == "start")]
            # Not a failure: the command stands and the recorder obeys when it can (its
            # state is in the statistics); the caller is told, in time.
            return {
                "status": 409 if action == "stop" else 202,
                "error": f"{', '.join(late)} did not {action} within {wait:g} s; it will",
                "sessions": now,
            }
        await asyncio.sleep(0.05)
    return {"status": 200, "sessions": now if action == "start" else current}


def _seq(rtdb: Any, name: str) -> int:
    rec = rtdb.read(name)
    return rec.seq if rec is not None else -1
