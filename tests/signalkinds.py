"""Node kinds for the signal tests (``signalkinds:Marked``): each step leaves a marker file.

The tests run ``flowrt run`` in a subprocess and need to know, without timing guesses, when
the nodes are running and when their teardown has begun or ended.
"""

from __future__ import annotations

import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from flowrt import Node, Output


class Marked(Node):
    """A counter that writes ``<name>.started``, ``<name>.teardown`` and ``<name>.done``."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str
        teardown_s: float = 0.0

    value = Output(int)

    def _mark(self, what: str) -> None:
        Path(self.params.dir, f"{self.ctx.name}.{what}").write_text(str(time.monotonic()))

    def setup(self) -> None:
        self.n = 0
        self._mark("started")

    def process(self) -> int:
        self.n += 1
        return self.n

    def teardown(self) -> None:
        self._mark("teardown")
        time.sleep(self.params.teardown_s)
        self._mark("done")
