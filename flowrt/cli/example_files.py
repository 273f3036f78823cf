"""The example graphs in the installed package (``flowrt.examples``, from ``graphs/``).

Apart from :mod:`flowrt.cli.examples` (the command) because :mod:`flowrt.cli.common`'s
error for a missing ``graphs/NAME.yaml`` reads them too, and the command imports common.
"""

from __future__ import annotations

from importlib import resources
from importlib.abc import Traversable
from pathlib import Path

PACKAGE = "flowrt.examples"
SUFFIXES = (".yaml", ".avi", ".py")  # graphs, the sample clip, the script that renders it


def shipped() -> list[Traversable]:
    """The example files in the installed package, by name (none: an incomplete install)."""
    try:
        root = resources.files(PACKAGE)
    except ModuleNotFoundError:
        return []
    files = [f for f in root.iterdir() if f.is_file() and f.name.endswith(SUFFIXES)]
    return sorted((f for f in files if f.name != "__init__.py"), key=lambda f: f.name)


def is_example(path: str) -> bool:
    """``graphs/cambada.yaml`` (or ``cambada.yaml``) names a graph flowrt ships."""
    name = Path(path).name
    return name.endswith(".yaml") and any(f.name == name for f in shipped())
