"""Frames made in a worker: written into shared-memory slots the main process lends it.

A node at ``placement: process`` (or ``pool``) that makes a new frame — ``self.ctx.new_frame``
and fills it (zero copy), or returns ``Frame(array)`` of its own (copied once) — hands it back
as a slot descriptor, exactly as the frames it receives travel: its pixels never cross the
worker's socket nor the main process. Frames then cross any number of worker hops without a
copy through the event loop.

The protocol keeps the rule of :mod:`flowrt.frames` that only the main process creates,
recycles and unlinks segments; a worker only maps them:

1. *Grant.* With each call, the main process reserves slots in the node's pool (owner: the
   node's name) and sends their descriptors along with the inputs, enough that the worker holds
   ``frames per call x calls in flight`` free slots. A granted slot holds the grant's link: it
   cannot be recycled or given to anyone else while the worker may write into it.
2. *Write.* In the worker, ``ctx.new_frame`` is a writable view of a granted slot (mapped once
   per worker); a heap frame returned is copied into one when the reply is pickled.
3. *Return.* The result carries the slot's descriptor (with the frame's shape, dtype and
   metadata). Unpickled in the main process it is the granted frame itself, now holding the new
   frame and carrying the grant's link, which the activation takes (``Frame.take_link``): the
   slot returns to the pool when its last reader lets go. The worker marks what it handed
   back read-only and never uses that slot again unless granted anew (a new generation).

What cannot take a slot takes the socket, as before, and is counted with its reason
(:class:`OutputStats`): ``not-granted`` (the node's first frame: nothing told the main process
it makes frames, or their size), ``no-free-slot`` (every granted slot is in use),
``too-large`` (larger than the granted slots: the worker gives them back and later grants are
sized to the frame), ``nested`` (a frame inside another value of the result: only the values
of the node's outputs are link counted). A grant the pool cannot serve (all ``max_slots``
held by slow readers) is counted as ``refused``; the worker's frame then takes the socket.

A worker that dies (or a node restarted) holds grants nobody will return: the main process
takes their links back (``reclaimed``), the slots return to the pool.

*Lent ahead.* Reserving a slot costs the event loop tens of microseconds on a loaded machine
(the pool's lock, the generation stamp, a view), and a grant made with the call sits on the
hop's path: the reply before it has arrived and the worker waits for the request. So once a
call is written, the slots of the node's *next* call are reserved at once (``lend_ahead``),
while the worker computes; the next call only sends their descriptors. A node holds one
call's worth of slots more than it is lent (counted in ``outstanding``), and a reserved slot
that no longer fits the frames (a larger input) goes back to the pool when the call comes.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .frame import HEADER, Frame, MappingCache, set_worker_outputs
from .pool import FramePool

__all__ = ["OutputGrants", "OutputStats", "WorkerSlots", "lazy_report"]

# A grant on the wire: (segment name, segment size, generation, bytes available for pixels).
Grant = tuple[str, int, int, int]
# What a worker reports with a call's reply (None when the call made no frame):
# ((reason, frames) sent by the socket, largest frame that found no slot (bytes), frames made,
#  names of grants given back unused: too small for what the node makes).
Report = tuple[tuple[tuple[str, int], ...], int, int, tuple[str, ...]]


@dataclass(frozen=True, slots=True)
class OutputStats:
    """Frames a worker node made, and how they came back to the main process."""

    node: str
    in_slots: int  # written into a granted slot: only the descriptor crossed the socket
    by_socket: dict[str, int]  # pixels through the socket, by reason
    granted: int  # slots lent to the worker so far
    outstanding: int  # held for the worker: lent now, or reserved for its next call
    refused: int  # grants the pool could not serve (every slot held)
    reclaimed: int  # grants taken back from a worker that died or a node restarted


# --------------------------------------------------------------------------------------------
# Main side


class OutputGrants:
    """The slots lent to one worker node, from its frame pool (main process, event loop).

    ``per_call`` is how many frames a call makes (the node's declared frame outputs, then the
    most seen in one reply); a node that makes none is lent nothing, so a tracker returning
    detections costs no shared memory. The slot size is the largest frame among the call's
    inputs (a filter's output is usually its input's size) or the largest the node made.
    """

    def __init__(self, node: str, pool: FramePool, per_call: int = 0) -> None:
        self.node = node
        self.pool = pool
        self.per_call = per_call
        self.capacity = 0
        self.outstanding: dict[str, Frame] = {}
        self.ahead: list[Frame] = []  # reserved for the next call, not sent yet (lend_ahead)
        self._cap = 0  # the slot size of the last grant (what lend_ahead reserves)
        self.in_slots = 0
        self.by_socket: Counter[str] = Counter()
        self.granted = 0
        self.refused = 0
        self.reclaimed = 0

    def grant(self, inputs: Mapping[str, Any], window: int, size: int = 0) -> tuple[Grant, ...]:
        """Slots to send with a call, so that the worker holds enough for ``window`` calls
        (``size``: of a frame input still to come, flowrt.kernel.hops)."""
        if self.per_call <= 0:
            return ()
        cap = max(self.capacity, size)
        for v in inputs.values():
            if isinstance(v, Frame) and v.nbytes > cap:
                cap = v.nbytes
        if cap <= 0:
            return ()
        self._cap = cap
        out: list[Grant] = []
        need = self.per_call * max(1, window) - len(self.outstanding)
        ahead = self.ahead
        while ahead and need > 0:
            early = ahead.pop()
            slot = early._slot
            assert slot is not None
            if slot.capacity < cap:  # reserved before the frames grew: back to the pool
                early.release()
                continue
            out.append(self._lend(early))
            need -= 1
        for _ in range(need):
            f = self.pool.reserve((cap,), np.uint8, source=self.node, count_drop=False)
            if f is None:
                self.refused += 1
                break
            out.append(self._lend(f))
        self.granted += len(out)
        return tuple(out)

    def lend_ahead(self) -> None:
        """Reserve the slots of the next call now, while the worker computes this one.

        Called once a call is written: what would be on the next hop's path is done while the
        loop waits anyway. A pool that cannot serve it now is not a refusal yet: the next call
        tries again (and counts it).
        """
        cap = self._cap
        if cap <= 0:
            return
        for _ in range(self.per_call - len(self.ahead)):
            f = self.pool.reserve((cap,), np.uint8, source=self.node, count_drop=False)
            if f is None:
                return
            self.ahead.append(f)

    def _lend(self, f: Frame) -> Grant:
        slot = f._slot
        assert slot is not None
        f._grant = self
        self.outstanding[slot.name] = f
        return (slot.name, slot.size, f._gen, slot.capacity)

    def returned(
        self,
        frame: Frame,
        shape: tuple[int, ...],
        dtype: str,
        source: str,
        seq: int,
        timestamp: float,
        pixel_format: str,
    ) -> Frame:
        """A granted slot is back with a frame in it (called while unpickling the reply)."""
        slot = frame._slot
        assert slot is not None
        self.outstanding.pop(slot.name, None)
        frame._grant = None
        dt = np.dtype(dtype)
        n = math.prod(shape) * dt.itemsize if shape else dt.itemsize
        if n > slot.capacity:
            frame.release()
            raise ValueError(f"{self.node}: a {n}-byte frame in a {slot.capacity}-byte slot")
        frame.data = slot.view(tuple(shape), dt)
        frame.source, frame.seq, frame.timestamp = source, seq, timestamp
        frame.pixel_format = pixel_format
        frame._handoff = True
        self.in_slots += 1
        return frame

    def replied(self, report: Report | None) -> None:
        """What the worker said about the frames of a call (after its result was unpickled)."""
        if report is None:
            return
        socket, wanted, made, unused = report
        for reason, n in socket:
            self.by_socket[reason] += n
        self.capacity = max(self.capacity, wanted)
        self.per_call = max(self.per_call, made)
        for name in unused:
            self._take_back(name)

    def unsent(self, grants: tuple[Grant, ...]) -> None:
        """A call that never reached the worker: its grants come back at once."""
        for g in grants:
            self._take_back(g[0])

    def reclaim(self, *, count: bool = True) -> int:
        """Take back every slot lent (the worker died, or the node starts anew); how many.

        ``count=False`` at a clean stop: the slots come back, but nothing was lost.
        """
        names = list(self.outstanding)
        for name in names:
            self._take_back(name)
        ahead, self.ahead = self.ahead, []
        for f in ahead:  # never lent: nothing lost
            f.release()
        if count:
            self.reclaimed += len(names)
        return len(names)

    def _take_back(self, name: str) -> None:
        f = self.outstanding.pop(name, None)
        if f is not None:
            f._grant = None
            f.release()

    def stats(self) -> OutputStats:
        return OutputStats(
            self.node,
            self.in_slots,
            dict(self.by_socket),
            self.granted,
            len(self.outstanding) + len(self.ahead),
            self.refused,
            self.reclaimed,
        )


# --------------------------------------------------------------------------------------------
# Worker side


_writable = MappingCache(writable=True)


class WorkerSlots:
    """The slots one node holds in a worker, and what its current call did with them.

    Installed with :func:`flowrt.frames.set_worker_outputs` for the node's call and the pickling
    of its reply (``begin``/``reply``/``end``); implements :class:`flowrt.frames.WorkerOutputs`.
    """

    def __init__(self) -> None:
        self.free: list[Grant] = []
        self.ever = False  # any slot granted yet
        self.taken: dict[str, tuple[Grant, np.ndarray]] = {}  # by new_frame in this call
        self.top: set[int] = set()  # ids of the frames that are output values of the result
        self.replying = False
        self.handed: list[tuple[Grant, np.ndarray]] = []
        # What each frame of this call's result pickled to: sent twice (straight to another
        # worker, flowrt.workers.hops, then in the reply) it is the same slot both times.
        self.placed: dict[int, tuple[Any, ...] | None] = {}
        self.socket: Counter[str] = Counter()
        self.wanted = 0
        self.made = 0

    def begin(self, grants: tuple[Grant, ...]) -> None:
        if grants:
            self.free.extend(grants)
            self.ever = True
        set_worker_outputs(self)

    def reply(self, result: Any) -> None:
        """The result is about to be pickled: its output values may take slots."""
        values = result.values() if isinstance(result, Mapping) else (result,)
        self.top = {id(v) for v in values if isinstance(v, Frame)}
        self.replying = True

    def report(self) -> Report | None:
        """What the main process needs to know about this call (after the result pickled)."""
        unused: tuple[str, ...] = ()
        if self.wanted:
            small = [g for g in self.free if g[3] < self.wanted]
            if small:
                self.free = [g for g in self.free if g[3] >= self.wanted]
                unused = tuple(g[0] for g in small)
                for g in small:
                    _writable.forget(g[0])
        if not self.made and not unused:
            return None
        return (tuple(self.socket.items()), self.wanted, self.made, unused)

    def end(self) -> None:
        """The call is over: handed-back frames read-only, slots taken but not returned free."""
        set_worker_outputs(None)
        for _, data in self.handed:
            data.flags.writeable = False
        self.handed.clear()
        self.placed.clear()
        for grant, _ in self.taken.values():
            self.free.append(grant)
        self.taken.clear()
        self.top = set()
        self.replying = False
        self.socket.clear()
        self.wanted = 0
        self.made = 0

    def abort(self) -> None:
        """The reply could not be pickled: what it had handed back is free again."""
        for grant, _ in self.handed:
            self.free.append(grant)
        self.handed.clear()
        self.placed.clear()
        self.made = 0

    # -- flowrt.frames.WorkerOutputs --------------------------------------------------------

    def take(
        self, shape: tuple[int, ...], dtype: np.dtype[Any], source: str, pixel_format: str
    ) -> Frame | None:
        if self.replying:
            return None
        n = math.prod(shape) * dtype.itemsize if shape else dtype.itemsize
        grant = self._pop(n)
        if grant is None:
            return None
        name, size, gen, _ = grant
        data = _view(grant, shape, dtype)
        frame = Frame(data, source=source, pixel_format=pixel_format)
        frame._origin = ((name, size, gen, shape, dtype.str), data)
        self.taken[name] = (grant, data)
        return frame

    def place(self, frame: Frame) -> tuple[Any, ...] | None:
        if not self.replying:
            return None
        key = id(frame)
        if key in self.placed:
            return self.placed[key]
        self.placed[key] = desc = self._place(frame)
        return desc

    def _place(self, frame: Frame) -> tuple[Any, ...] | None:
        origin = frame._origin
        mine = origin is not None and origin[0][0] in self.taken
        if not mine and origin is not None and frame.data is origin[1]:
            return None  # a frame received, passed on: its own descriptor (frame.py)
        if id(frame) not in self.top:
            self.socket["nested"] += 1
            self.made += 1
            return None
        self.made += 1
        meta = (frame.source, frame.seq, frame.timestamp, frame.pixel_format)
        if mine and origin is not None and frame.data is origin[1]:
            self.handed.append(self.taken.pop(origin[0][0]))
            return (*origin[0], *meta)
        data = frame.data  # a frame of its own: copied once into a slot
        if data.dtype.hasobject:
            self.socket["not-granted"] += 1
            return None
        grant = self._pop(data.nbytes)
        if grant is None:
            reason = (
                "not-granted"
                if not self.ever
                else "too-large"
                if any(g[3] < data.nbytes for g in self.free)
                else "no-free-slot"
            )
            self.socket[reason] += 1
            self.wanted = max(self.wanted, data.nbytes)
            return None
        view = _view(grant, data.shape, data.dtype)
        np.copyto(view, data)
        self.handed.append((grant, view))
        name, size, gen, _ = grant
        return (name, size, gen, tuple(data.shape), data.dtype.str, *meta)

    def _pop(self, nbytes: int) -> Grant | None:
        """The smallest free slot that fits (keeps the large ones for large frames)."""
        best = -1
        for i, g in enumerate(self.free):
            if g[3] >= nbytes and (best < 0 or g[3] < self.free[best][3]):
                best = i
        return None if best < 0 else self.free.pop(best)


def _view(grant: Grant, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
    name, size, _, _ = grant
    m = _writable.get(name, size)
    n = math.prod(shape) if shape else 1
    return np.frombuffer(m, dtype=dtype, count=n, offset=HEADER).reshape(shape)


class _LazyReport:
    """Pickles to the report of the call at the instant it is pickled: placed after the
    payload in the reply, it knows which frames the payload's pickling put in slots."""

    __slots__ = ("slots",)

    def __init__(self, slots: WorkerSlots) -> None:
        self.slots = slots

    def __reduce__(self) -> tuple[Any, ...]:
        return (_identity, (self.slots.report(),))


def lazy_report(slots: WorkerSlots) -> Any:
    """The report of a call, to put after its result in the reply tuple."""
    return _LazyReport(slots)


def _identity(x: Any) -> Any:
    return x
