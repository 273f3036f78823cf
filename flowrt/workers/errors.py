"""How a worker call fails: the exception the kernel sees, and its kind."""

from __future__ import annotations

import re
from typing import Literal

WorkerKind = Literal["exception", "crashed", "killed", "hung"]


class WorkerError(RuntimeError):
    """A node in a worker failed; ``kind`` tells the supervisor how.

    - ``exception``: ``process``/``setup`` raised; ``detail`` is the worker's traceback, and the
      worker (and the node object) are still alive.
    - ``crashed``: the worker died on its own (segfault, abort, exit) — or under another node of
      the same pool worker; ``detail`` names the signal or exit code.
    - ``killed``: the worker was killed from outside (SIGKILL, SIGTERM, the OOM killer).
    - ``hung``: a call exceeded its watchdog; the worker was SIGKILLed at that instant.

    After any kind, ``await executor.start()`` gives the node a fresh instance. ``fatal``
    says that it cannot help (the worker cannot load the node at all): the supervisor gives
    the node up at once instead of restarting it.
    """

    def __init__(
        self,
        node: str,
        kind: WorkerKind,
        detail: str,
        exitcode: int | None = None,
        *,
        fatal: bool = False,
    ) -> None:
        super().__init__(f"{node}: worker {kind}: {detail}")
        self.node = node
        self.kind: WorkerKind = kind
        self.detail = detail
        self.exitcode = exitcode
        self.fatal = fatal

    @property
    def summary(self) -> str:
        """One line for logs and reasons: the node's own exception, or what became of the
        worker (the supervisor shows this instead of the main side's stack)."""
        if self.kind == "exception":
            lines = [ln for ln in self.detail.strip().splitlines() if ln.strip()]
            # "pkg.mod.Error: text" -> "Error: text", as an inline node's failure reads
            return re.sub(r"^[\w.]+\.(\w+:)", r"\1", lines[-1].strip()) if lines else "exception"
        if self.fatal:
            return self.detail
        return f"worker {self.kind}: {self.detail}"

    @property
    def traceback(self) -> str:
        """The worker's traceback for an exception; nothing for a death (no stack to show)."""
        return self.detail if self.kind == "exception" else ""


# --------------------------------------------------------------------------------------------
