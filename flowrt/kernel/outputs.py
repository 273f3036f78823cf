"""What a node returns, checked where it is made: output names and declared types.

A value on a port its node does not have, or that does not match its output's declared type
(``score = Output(float)`` returning ``"high"``), is the producer's error: raised here, it
reaches the node's supervisor like an exception from ``process`` (counted, the restart
policy applied, the run's exit code 1 when the node ends failed). Left to the readers, it
showed only at a typed reader far from the node at fault, or as an exception in a loop
callback that no one counted while the node stayed ``running`` with 0 errors.

The check is one dictionary lookup and one ``isinstance`` per published value: the class
each output's declared type asks for is worked out once per runner
(:func:`flowrt.graph._resolve.checked_type`: generic aliases and ``object`` are not checked,
``float`` takes any real number, as on the reader's side). A value ``isinstance`` refuses
is taken when its class (or a base) has the expected one's module and qualified name: an
edited module re-imported by ``flowrt ctl reload`` has new classes of the same names, which
the nodes of that module that were not reloaded, and the values their workers send back
(unpickled by name), meet beside the old ones (:func:`same_name`; off the fast path).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from ..graph._resolve import ResolvedNode, checked_type


def same_name(value: Any, want: type) -> bool:
    """``value``'s class, or a base, has ``want``'s module and qualified name: the same class
    in an other import of its module (see the module's documentation). Called only once
    ``isinstance`` has refused the value, so the per-message path pays nothing for it."""
    key = (want.__module__, want.__qualname__)
    return any((c.__module__, c.__qualname__) == key for c in type(value).__mro__)


class OutputError(TypeError):
    """A node returned or published a value its outputs cannot carry.

    Its ``traceback`` is empty: the kernel's stack that found it would only point away from
    the node at fault, which the message names."""

    traceback = ""


class OutputCheck:
    """One runner's outputs: their names, and the class each declared type asks for."""

    def __init__(self, rnode: ResolvedNode, ports: Iterable[str]) -> None:
        self.ports = list(ports)
        self.types: dict[str, type] = {}
        self.names: dict[str, str] = {}  # the declared type's name, as the reader says it
        for port, out in rnode.cls.outputs.items():
            checked = checked_type(out.type)
            if checked is not None:
                self.types[port] = checked
                self.names[port] = getattr(out.type, "__name__", str(out.type))

    def value(self, port: str, value: Any) -> None:
        """Raise :class:`OutputError` unless ``value`` may go out on ``port``."""
        want = self.types.get(port)
        if want is None:
            if port not in self.ports:
                has = ", ".join(self.ports) or "none"
                raise OutputError(f"no output port {port!r} (its outputs: {has})")
        elif not isinstance(value, want) and not same_name(value, want):
            raise OutputError(
                f"output {port!r} expects {self.names[port]}, got {type(value).__name__}"
            )

    def problem(self, result: Any) -> OutputError | None:
        """What is wrong with ``process``'s return value (see :meth:`result`), or None."""
        try:
            self.result(result)
        except OutputError as e:
            return e
        return None

    def result(self, result: Any) -> None:
        """Raise :class:`OutputError` unless ``process``'s return value can be published.

        One output: the value itself. Several: a mapping of some of them (None: nothing on
        that port).
        """
        if len(self.ports) == 1:
            self.value(self.ports[0], result)
            return
        if type(result) is not dict and not isinstance(result, Mapping):  # (ABC check: cold)
            raise OutputError(
                f"a node with outputs {self.ports} must return a mapping of them, "
                f"not {type(result).__name__}"
            )
        for port, value in result.items():
            if value is not None or port not in self.ports:
                self.value(port, value)
