"""What a caller of the control endpoint may not change with a swap: where data goes.

The endpoint lets a local caller change an algorithm (``POST /swap`` with new params), never
an address, a path, a device or a token: those would move the live view to another address
with a token the caller chose, or point a recorder at any folder. The rule is by param
name, nested mappings and lists included (``where_keys``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["SwapRefused", "lookup", "where_keys"]

# Param names that say where data goes or comes from: an address, a path, a token. A caller
# of the endpoint may change an algorithm's params, never these (README: who can do what).
_WHERE_KEYS = frozenset(
    {"host", "port", "address", "addr", "url", "endpoint", "endpoints", "connect", "listen",
     "path", "paths", "dir", "directory", "folder", "output", "file", "files", "token",
     "dbc", "script", "source", "interface", "channel", "device", "key", "keys"}
)  # fmt: skip
_WHERE_SUFFIXES = ("_host", "_port", "_url", "_path", "_dir", "_file", "_token", "_address")


def where_keys(params: Any, prefix: str = "") -> list[str]:
    """The keys of ``params`` (nested) that name an address, a path or a token."""
    found: list[str] = []
    if isinstance(params, dict):
        for k, v in params.items():
            name = str(k).lower()
            dotted = f"{prefix}{k}"
            if name in _WHERE_KEYS or name.endswith(_WHERE_SUFFIXES):
                found.append(dotted)
            else:
                found += where_keys(v, dotted + ".")
    elif isinstance(params, list):
        for i, v in enumerate(params):
            found += where_keys(v, f"{prefix}{i}.")
    return found


class SwapRefused(Exception):
    """A swap the endpoint does not allow (403): a kind not allowed, a param that moves data."""


def lookup(tree: Any, dotted: str) -> Any:
    """``tree["a"]["b"]`` for ``"a.b"`` (list indexes as numbers); None when absent."""
    for part in dotted.split("."):
        if isinstance(tree, dict):
            tree = tree.get(part)
        elif isinstance(tree, list) and part.isdigit() and int(part) < len(tree):
            tree = tree[int(part)]
        else:
            return None
    return tree
