"""What a caller of the control endpoint may change with a swap: an allow-list per kind.

The endpoint lets a local caller change an algorithm (``POST /swap`` with new params), never
where data goes: an address, a device, a token, a folder. A deny-list of such param names
missed one (a recorder's ``session`` pointed it at any folder, issue 37 item 1), so each
kind now says which of its params a swap may change, beside its ``Params``::

    class Tracker(Node):
        swappable = frozenset({"space", "bins", "colours", "object"})

and ``flowrt kinds KIND`` shows the list. A kind that declares nothing may be swapped in (when
the graph allows the kind) with its params as the graph file has them, none changed. A path
param a kind allows is confined to a folder param of the same node (``swap_folders =
{"session": "path"}``: a recorder's session inside its recordings folder): the value must be
a relative path without ``..``, and it is resolved under that folder (symbolic links
included). A name the kind has no param of is answered apart (422, with the YAML
validator's "did you mean"): that is a typo to fix, not a rule to take to the graph file.
``Runtime.swap`` from Python is the program's own code: it is not restricted.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from ..graph.diagnostics import did_you_mean

__all__ = ["SwapRefused", "UnknownParams", "allowed", "check_params", "confined"]


class SwapRefused(Exception):
    """A swap the endpoint does not allow (403): a kind not allowed, a param not swappable."""


class UnknownParams(SwapRefused):
    """Params the kind does not have at all (422): a typo, not a rule. Told apart from a
    param that may not be changed, whose answer sends the caller to the graph file: for a
    misspelt name that advice is wrong, the spelling is what to fix."""


def allowed(cls: type) -> frozenset[str]:
    """The params of kind ``cls`` a swap over the endpoint may change (its ``swappable``)."""
    return frozenset(getattr(cls, "swappable", frozenset()))


def param_names(cls: type) -> frozenset[str] | None:
    """The names a swap's params of kind ``cls`` may have (fields and their aliases), or
    None when its ``Params`` takes any name (``extra="allow"``) or is not a pydantic model."""
    model = getattr(cls, "Params", None)
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        return None
    if model.model_config.get("extra") == "allow":
        return None
    return frozenset(n for name, f in model.model_fields.items() for n in (name, f.alias) if n)


def confined(cls: type) -> Mapping[str, str]:
    """Path params of ``cls`` -> the folder param each is resolved under (``swap_folders``)."""
    return dict(getattr(cls, "swap_folders", {}))


def check_params(
    kind: str,
    cls: type,
    given: Mapping[str, Any],
    folder_of: Callable[[str], str],
) -> dict[str, Any]:
    """``given`` checked against the allow-list of ``cls``, path params resolved under their
    folders (``folder_of(param)``: the folder param's absolute value for this swap).

    Raises :class:`SwapRefused` naming every param refused and why, before anything changes;
    :class:`UnknownParams` first when some are not params of the kind at all.
    """
    known = param_names(cls)
    if known is not None and (unknown := [k for k in given if k not in known]):
        names = ", ".join(f"{k!r}{did_you_mean(k, sorted(known))}" for k in unknown)
        plural = "s" if len(unknown) > 1 else ""
        raise UnknownParams(f"{kind}: unknown param{plural} {names}; see flowrt kinds {kind}")
    allow = allowed(cls)
    refused = sorted(k for k in given if k not in allow)
    if refused:
        shown = ", ".join(sorted(allow)) or "none"
        raise SwapRefused(
            f"{kind}: params {', '.join(refused)} may not be changed over the control endpoint "
            f"(a swap may change: {shown}; see flowrt kinds {kind}); edit the graph file instead"
        )
    out = dict(given)
    for param, folder_param in confined(cls).items():
        if param in out and out[param] is not None:
            out[param] = _under(kind, param, out[param], folder_of(folder_param))
    return out


def _under(kind: str, param: str, value: Any, folder: str) -> str:
    """``folder/value`` when ``value`` is a plain relative path that stays inside ``folder``."""
    if not isinstance(value, str) or not value.strip():
        raise SwapRefused(f"{kind}: {param} must be a folder name inside {folder}")
    parts = Path(value).parts
    if os.path.isabs(value) or value.startswith("~") or ".." in parts:
        raise SwapRefused(
            f"{kind}: {param} {value!r} must be relative, without '..': it is resolved inside "
            f"{folder} (absolute paths and '..' are refused over the control endpoint)"
        )
    base = Path(folder).resolve()
    target = (base / value).resolve()  # a symbolic link inside may still point out
    if not target.is_relative_to(base):
        raise SwapRefused(f"{kind}: {param} {value!r} leads out of {folder}")
    return str(base / value)
