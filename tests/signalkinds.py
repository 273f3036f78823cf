"""Node kinds for the signal tests (``signalkinds:Marked``): each step leaves a marker file.

The tests run ``flowrt run`` in a subprocess and need to know, without timing guesses, when
the nodes are running and when their teardown has begun or ended.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from flowrt import Input, Node, Output


class Marked(Node):
    """A counter that writes ``<name>.started`` (set up), ``<name>.running`` (first
    activation), ``<name>.teardown`` and ``<name>.done``."""

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
        if self.n == 0:  # every node is set up: the run runs (a signal now is a stop)
            self._mark("running")
        self.n += 1
        return self.n

    def teardown(self) -> None:
        self._mark("teardown")
        time.sleep(self.params.teardown_s)
        self._mark("done")


class SlowSink(Node):
    """Takes ``delay_s`` per value and writes ``<name>.started`` at set-up: behind a fast
    source on a lossless edge it holds a backlog that the drain at stop has to deliver."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str
        delay_s: float = 0.02

    value = Input(int)

    def setup(self) -> None:
        Path(self.params.dir, f"{self.ctx.name}.started").write_text(str(time.monotonic()))

    async def process(self, value: int) -> None:
        await asyncio.sleep(self.params.delay_s)


class SlowSetup(Node):
    """A worker node whose ``setup()`` takes ``setup_s`` (a camera that takes long to open)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str
        setup_s: float = 30.0

    value = Output(int)

    def setup(self) -> None:
        Path(self.params.dir, f"{self.ctx.name}.setup").write_text(str(time.monotonic()))
        time.sleep(self.params.setup_s)

    def process(self) -> int:
        return 1


def interrupt_self() -> None:
    """A spawned child's body: Ctrl-C to itself; a child of the ``flowrt`` command ignores it
    (the main process stops its children in order) and goes on."""
    import os
    import signal

    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.2)
    print("child went on", flush=True)


class Holding(Node):
    """A synchronous node whose call holds the loop ``hold_s``; each call's start (wall
    clock) is appended to ``<dir>/<name>.calls``."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str
        hold_s: float = 0.5

    value = Input(int)

    def process(self, value: int) -> None:
        with Path(self.params.dir, f"{self.ctx.name}.calls").open("a") as f:
            f.write(f"{time.time()}\n")
        time.sleep(self.params.hold_s)


class SlowDouble(Node):
    """Doubles each value in ``delay_s``; writes ``<dir>/<name>.running`` at its first call
    (a deterministic replay re-executes it in its worker: the signal test's cue)."""

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        dir: str
        delay_s: float = 0.03

    value = Input(int)
    doubled = Output(int)

    def process(self, value: int) -> int:
        marker = Path(self.params.dir, f"{self.ctx.name}.running")
        if not marker.exists():
            marker.write_text(str(time.monotonic()))
        time.sleep(self.params.delay_s)
        return 2 * value
