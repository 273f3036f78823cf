"""One activation of a node and the frame links it holds.

The ownership rule of shared-memory frames, in one place: an activation holds one link per
input value it took and per frame it made (``ctx.new_frame``) or adopted (a frame a worker
returned); :meth:`Activation.close` gives each back exactly once, whatever way the
activation ends (completed, discarded after a deadline miss, failed, cancelled, aborted with
its worker). Publishing takes links of its own (each reader's buffer), so closing after
publishing is always right.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from ..clock import Handle
from ..frames import Frame, release_handoffs


def release_all(values: Iterable[Any]) -> None:
    """Give back the link of every frame among ``values`` (other values hold none)."""
    for v in values:
        if isinstance(v, Frame):
            v.release()


def _values(result: Any) -> Iterable[Any]:
    return result.values() if isinstance(result, Mapping) else (result,)


class Activation:
    """A release of a node that took its inputs: what it holds until it ends.

    Invariants: ``inputs`` and ``made`` are released by :meth:`close` and only there;
    after ``close`` both are empty and ``closed`` is true; ``missed`` turns true at most once
    (one ``DeadlineMissed`` per activation, see :mod:`flowrt.kernel.deadlines`).
    """

    __slots__ = ("closed", "gen", "id", "inputs", "made", "missed", "start", "t_release", "timer")

    def __init__(
        self,
        id: int,
        t_release: float,
        start: float,
        gen: int = 0,
        inputs: dict[str, Any] | None = None,
    ) -> None:
        self.id = id
        self.t_release = t_release
        self.start = start
        self.inputs: dict[str, Any] = {} if inputs is None else inputs
        self.made: list[Frame] = []  # frames made or adopted: released at close
        self.missed = False  # its deadline passed (counted once)
        self.closed = False
        self.timer: Handle | None = None  # the deadline timer while it runs
        self.gen = gen  # the node instance it runs on (pipelined calls: see pipeline)

    def adopt(self, result: Any) -> None:
        """Hold the pooled frames of a worker's result until they are published.

        A worker that passes on a frame it received returns its descriptor, which resolves
        to the very frame the activation sent (:func:`flowrt.frames.frame.attach_frame`):
        without a link of its own it would be recycled when the inputs are released. A frame
        the worker made in a slot lent to it (:mod:`flowrt.frames.lending`) carries its link:
        taken over.
        """
        for v in _values(result):
            if isinstance(v, Frame) and v.shared:
                v.take_link()
                self.made.append(v)

    def discard(self, result: Any) -> None:
        """The result is not published (deadline missed, policy discard): its frames that
        this activation does not hold already are given back now; the rest at close."""
        release_all(v for v in _values(result) if not any(v is m for m in self.made))

    def abandon(self, result: Any) -> None:
        """A result nobody will take (its node instance failed meanwhile): drop the links
        its frames carry, then close."""
        self.close()
        release_handoffs(result)

    def close(self) -> None:
        """Give back every link this activation holds, exactly once."""
        if self.closed:
            return
        self.closed = True
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        for v in self.inputs.values():
            if isinstance(v, Frame):
                v.release()
        self.inputs = {}
        if self.made:
            made, self.made = self.made, []
            release_all(made)
