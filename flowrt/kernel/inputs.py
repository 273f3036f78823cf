"""A node's inputs: which buffer feeds each port, which trigger it, and taking their values.

An input is taken once per activation: a triggering input takes what is new (and waits when
nothing is), a sampled one takes the latest it holds. A required input without a value, or a
value of a type the port refuses, skips the activation (counted) instead of calling the node.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from ..edges import EMPTY, Buffer, LatestBuffer, LosslessBuffer
from ..graph._resolve import ResolvedNode, checked_type
from ..graph.spec import InputTrigger
from .activation import release_all
from .counters import Counters
from .outputs import same_name

log = logging.getLogger("flowrt.scheduler")


class Inputs:
    """The buffers feeding one node, by port.

    Invariants: ``ports`` lists every declared input, then the any-named ones connected;
    ``triggers`` and ``lossless`` are subsets of the connected ports' buffers;
    ``times[port]`` is the publication time of the value the port held at the last take,
    and the port is absent when it held none (``NodeContext.input_time``).
    """

    def __init__(self, name: str, rnode: ResolvedNode, counts: Counters) -> None:
        self._name = name
        self._rnode = rnode  # the node as built (ports and types do not change by a swap)
        self._counts = counts
        self.buffers: dict[str, Buffer] = {}
        self.ports = list(rnode.cls.inputs)
        self.required = [p for p, port in rnode.cls.inputs.items() if port.required]
        self.types: dict[str, type] = {}  # inputs whose values are type-checked
        self.type_errors: set[tuple[str, str]] = set()  # (port, type) already logged
        self.triggers: list[str] = []
        self.lossless: list[LosslessBuffer] = []  # inputs that must deliver every value
        self.times: dict[str, float] = {}

    def connect(
        self, port: str, buf: Buffer, on_trigger: Callable[[], None], on_full: Callable[[], None]
    ) -> None:
        self.buffers[port] = buf
        if port not in self.ports:
            self.ports.append(port)
        if isinstance(buf, LosslessBuffer):
            self.lossless.append(buf)
            buf.on_full = on_full
        cls = self._rnode.cls
        declared = cls.inputs.get(port) or cls.any_inputs
        checked = checked_type(declared.type) if declared is not None else None
        if checked is not None:
            self.types[port] = checked
        trig = self._rnode.trigger
        if isinstance(trig, InputTrigger):
            wanted = [trig.input] if isinstance(trig.input, str) else trig.input
            if "any" in wanted or port in wanted:
                self.triggers.append(port)
                buf.on_put = on_trigger
                return
        # Periodic readers sample: values they never read are expected, not lost.
        buf.sampled = isinstance(buf, LatestBuffer)

    def backlog(self) -> bool:
        """A lossless input holds values not yet delivered."""
        return any(b.pending() for b in self.lossless)

    def take(self) -> dict[str, Any] | None:
        """One value per port (None where it has none); None: the activation is skipped."""
        values: dict[str, Any] = {}
        for port in self.ports:
            buf = self.buffers.get(port)
            if buf is None:
                values[port] = None
                continue
            value = buf.take_new() if port in self.triggers else buf.take()  # type: ignore[attr-defined]
            if value is EMPTY or buf.taken_t is None:
                self.times.pop(port, None)
            else:
                self.times[port] = buf.taken_t
            if value is EMPTY:
                if port in self.required:
                    release_all(values.values())
                    return None
                value = None
            elif (
                port in self.types
                and not isinstance(value, self.types[port])
                and not same_name(value, self.types[port])  # (a reloaded module's: cold)
            ):
                self._wrong_type(port, value)
                release_all([*values.values(), value])
                return None
            values[port] = value
        return values

    def _wrong_type(self, port: str, value: Any) -> None:
        """A value the input's type refuses: one counted error, one log line per type.

        Validation refuses edges whose declared types differ; this catches what an
        ``object``-typed output (a relay, ``Runtime.publish``) lets through. The node is
        not called (it would raise on every value) and the activation is skipped.
        """
        self._counts.errors += 1
        got = type(value).__name__
        if (port, got) not in self.type_errors:
            self.type_errors.add((port, got))
            cls = self._rnode.cls
            want = cls.inputs.get(port) or cls.any_inputs
            log.error(
                "node %s: input %r expects %s, got %s: values of this type are dropped "
                "and counted as errors",
                self._name,
                port,
                getattr(want.type if want else None, "__name__", "?"),
                got,
            )
