"""A node's ports: its class's, the ones its params give it, and what types fit together.

Here, not in :mod:`flowrt.graph._resolve` (which checks a graph's edges with them), to keep
that module to one concern a reader can hold; the kernel's run-time checks use
:func:`checked_type` too.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from ..node import Node

__all__ = ["checked_type", "is_compatible", "node_ports", "ports_unknown", "type_name"]


def is_compatible(out_type: Any, in_type: Any) -> bool:
    """Where both ports declare a type, what the output produces must be what the input
    takes (an ``int`` output may feed a ``float`` input, as at run time)."""
    if in_type in (object, Any) or out_type in (object, Any):
        return True
    if isinstance(out_type, type) and isinstance(in_type, type):
        return issubclass(out_type, checked_type(in_type) or object)
    return bool(out_type == in_type)


_NUMERIC = {float: numbers.Real, int: numbers.Integral, complex: numbers.Complex}


def checked_type(t: Any) -> type | None:
    """The class a value on a port declared ``t`` must be an instance of; None: anything.

    Generic aliases (``list[int]``) and ``object``/``Any`` are not checked at run time.
    ``float`` takes any real number (an int, a numpy float), as static typing does.
    """
    if not isinstance(t, type) or t is object:
        return None
    return _NUMERIC.get(t, t)


def type_name(t: Any) -> str:
    """A port type as an error message names it."""
    return getattr(t, "__name__", str(t))


def node_ports(
    cls: type[Node], params: Mapping[str, BaseModel], name: str, inputs: bool
) -> dict[str, Any]:
    """A node's inputs (or outputs): its class's and those its params give it (none of these
    while its params are invalid)."""
    own = cls.inputs if inputs else cls.outputs
    if name not in params:
        return {**own}
    given = cls.params_inputs(params[name]) if inputs else cls.params_outputs(params[name])
    return {**own, **given}


def ports_unknown(
    cls: type[Node], params: Mapping[str, BaseModel], name: str, inputs: bool
) -> bool:
    """Whether a node's inputs (or outputs) cannot be known: some come from its params (a
    CAN node's from its DBC file) and those are invalid, which is reported at them. A port
    it seems to lack would be one more error that only follows from that one (a wrong
    ``dbc:`` path buried under an error for each message, and for each edge from it)."""
    if name in params:
        return False
    hook = "params_inputs" if inputs else "params_outputs"
    return getattr(cls, hook).__func__ is not getattr(Node, hook).__func__
