"""``--json``: exactly one JSON document on stdout, whatever happens.

A script runs ``flowrt ... --json`` and does ``json.loads(stdout)``. So, while a command runs
with ``--json``, everything it (or a node, a worker process, a library) prints on stdout goes
to stderr instead, where a person still sees it; the command hands its result to :func:`emit`,
and that document alone is written on stdout at the end. A command that fails before it has
a result (a bad file, a refused option, no runtime to talk to) gets ``{"error": {...}}`` built
from the one-line message it printed on stderr, with the exit code it would have without
``--json``; one that fails after (a run whose node failed) gets ``"error"`` added to its
result. Exit codes do not change.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import sys
from collections.abc import Iterator
from typing import Any, TextIO

from .. import _startup

_active: JsonOutput | None = None

#: A log line of :func:`flowrt.cli.common.plain_handler`: not an error message.
_LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d[ T]\d\d:\d\d")
_MESSAGE = re.compile(r"^flowrt[\w -]*: ")


def active() -> bool:
    """True while a command runs with ``--json``."""
    return _active is not None


def emit(doc: Any) -> None:
    """The command's result: kept for the end of a ``--json`` run, printed at once otherwise
    (a command called from Python without :func:`json_mode`)."""
    if _active is None:
        print(json.dumps(doc, indent=2))
    elif _active.doc is None:  # the first result is the result
        _active.doc = doc


def name_command(command: str) -> None:
    """The subcommand, once the arguments are parsed (before: the first word given)."""
    if _active is not None:
        _active.command = command


def note(**detail: Any) -> None:
    """Structured detail for the error document (a graph file's diagnostics)."""
    if _active is not None:
        _active.detail.update(detail)


class _Stderr(io.TextIOBase):
    """stderr, remembering what was written to it (the failure's message is in there)."""

    def __init__(self, target: TextIO) -> None:
        self.target = target
        self.parts: list[str] = []

    def write(self, s: str) -> int:
        self.parts.append(s)
        return self.target.write(s)

    def flush(self) -> None:
        self.target.flush()

    def isatty(self) -> bool:
        return self.target.isatty()

    def fileno(self) -> int:
        return self.target.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return getattr(self.target, "encoding", "utf-8")

    def text(self) -> str:
        return "".join(self.parts)

    def heard(self, line: str) -> None:
        """A line a signal handler wrote on fd 2 itself (:func:`flowrt._startup.say`)."""
        self.parts.append(line + "\n")


class JsonOutput:
    """One ``--json`` command's stdout: its document, or an error one (see the module)."""

    def __init__(self, command: str) -> None:
        self.command = command
        self.doc: Any = None
        self.detail: dict[str, Any] = {}
        self.stderr = _Stderr(sys.stderr)

    def _lines(self) -> list[str]:
        """What stderr said, without log lines."""
        return [
            line.rstrip()
            for line in self.stderr.text().splitlines()
            if line.strip() and not _LOG_LINE.match(line)
        ]

    def _said(self) -> list[str]:
        """The one-line messages (``flowrt info: ...``), warnings left out."""
        return [ln for ln in self._lines() if _MESSAGE.match(ln) and ": warning:" not in ln]

    def error_doc(self, code: int) -> dict[str, Any]:
        lines, said = self._lines(), self._said()
        quiet = "interrupted" if code == 130 else f"exit code {code}"  # Ctrl-C says nothing
        message = said[-1] if said else (lines[-1] if lines else quiet)
        return {
            "message": message,
            "exit_code": code,
            "command": self.command,
            "lines": lines[-20:],
            **self.detail,
        }

    def document(self, code: int) -> Any:
        if self.doc is None:
            return {"error": self.error_doc(code)} if code else {}
        if isinstance(self.doc, dict) and "exit_code" in self.doc:  # the process's, at the end
            self.doc = {**self.doc, "exit_code": code}
        failed = code and (self._said() or self.detail)  # not only a verdict (check: 1)
        if failed and isinstance(self.doc, dict) and "error" not in self.doc:
            return {**self.doc, "error": self.error_doc(code)}
        return self.doc


@contextlib.contextmanager
def json_mode(command: str) -> Iterator[JsonOutput]:
    """Run a command with ``--json`` (see the module); the caller writes :func:`finish`."""
    global _active
    out = JsonOutput(command)
    real_stdout: TextIO = sys.stdout
    real_stderr: TextIO = sys.stderr
    saved_fd: int | None = None
    # The process's own stdout (not a test's capture): its file descriptor is pointed at
    # stderr too, so a worker process or a C library printing cannot add to the document.
    if real_stdout is sys.__stdout__ and _fileno(real_stdout) == 1:
        real_stdout.flush()
        saved_fd = os.dup(1)
        os.dup2(2, 1)
    sys.stderr = out.stderr
    sys.stdout = real_stderr  # what a command says besides its result: for a person
    _active = out
    _startup.listeners.append(out.stderr.heard)
    try:
        yield out
    finally:
        _startup.listeners.remove(out.stderr.heard)
        _active = None
        sys.stdout, sys.stderr = real_stdout, real_stderr
        if saved_fd is not None:
            real_stdout.flush()
            os.dup2(saved_fd, 1)
            os.close(saved_fd)


def finish(out: JsonOutput, code: int) -> None:
    """Write the one document on the (restored) stdout."""
    print(json.dumps(out.document(code), indent=2, default=str), flush=True)


def _fileno(stream: Any) -> int:
    try:
        return int(stream.fileno())
    except (AttributeError, OSError, ValueError):
        return -1
