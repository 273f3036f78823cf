"""Located problems in a graph: every error names file:line:column and the key, all at once.

A user fixing a graph file wants the whole list in one go, pointing at the exact place, not
one Python traceback per attempt.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from dataclasses import dataclass
from enum import StrEnum


class Severity(StrEnum):
    error = "error"
    warning = "warning"


@dataclass(frozen=True)
class Diagnostic:
    """One problem: where (file, 1-based line and column, dotted key path) and what."""

    severity: Severity
    message: str
    key: str = ""
    file: str = "<graph>"
    line: int = 0
    column: int = 0

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}:{self.column}" if self.line else self.file
        key = f" {self.key}:" if self.key else ""
        return f"{where}: {self.severity.value}:{key} {self.message}"


class GraphError(Exception):
    """A graph that cannot run; carries every error found, not just the first."""

    def __init__(self, diagnostics: Iterable[Diagnostic]) -> None:
        self.diagnostics = list(diagnostics)
        super().__init__("\n".join(str(d) for d in self.diagnostics))

    @property
    def errors(self) -> list[Diagnostic]:
        return [d for d in self.diagnostics if d.severity is Severity.error]


def closest(word: str, choices: Iterable[str]) -> str | None:
    """The choice most like ``word`` when one is close enough to be a typo, else None.

    A word that begins exactly one choice is that choice's abbreviation (``prio``:
    ``priority``, where plain similarity says ``period``).
    """
    options = list(choices)
    if len(word) >= 3:
        starting = [c for c in options if c.startswith(word) and c != word]
        if len(starting) == 1:
            return starting[0]
    matches = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    return matches[0] if matches else None


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """A ' (did you mean X?)' suffix when a close match exists, else ''."""
    match = closest(word, choices)
    return f" (did you mean {match!r}?)" if match is not None else ""


def validation_text(e: Exception) -> str:
    """A pydantic ValidationError as one line a user reads (``object: Input should be a
    valid string, got 5``), without pydantic's header and documentation links; any other
    exception as its first line."""
    errors = getattr(e, "errors", None)
    if not callable(errors):
        return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    parts = []
    for err in errors(include_url=False):
        where = ".".join(str(x) for x in err.get("loc", ())) or "params"
        got = f", got {err['input']!r}" if err.get("type") != "missing" and "input" in err else ""
        parts.append(f"{where}: {err.get('msg')}{got}"[:300])
    return "; ".join(parts)
