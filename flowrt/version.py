"""flowrt's version, from the installed distribution's metadata (pyproject.toml says it once).

In a module of its own: what records a recording's provenance (the MCAP writer, a session's
metadata) reads it without importing the whole package. A source checkout that is not
installed has no metadata: the version is then read from its pyproject.toml, and failing
that is ``0+unknown`` (never an import error: provenance is not worth a crash).
"""

from __future__ import annotations

import tomllib
from importlib import metadata
from pathlib import Path


def _version() -> str:
    try:
        return metadata.version("flowrt")
    except metadata.PackageNotFoundError:
        pass
    try:
        with (Path(__file__).resolve().parent.parent / "pyproject.toml").open("rb") as f:
            return str(tomllib.load(f)["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "0+unknown"


__version__ = _version()
