"""Node kinds that fail on purpose, for the supervision and exit-code tests.

Referenced from graph files as ``failkinds:Class`` (tests/ is on the path of the CLI tests).
"""

from __future__ import annotations

import time

from flowrt import FatalError, Input, Node, Output


class AlwaysFails(Node):
    """Every activation raises the same error: a persistently failing node."""

    tick = Output(int)

    def process(self) -> int:
        raise ValueError("boom")


class SetupFails(Node):
    """``setup`` raises: a crash loop at start-up, whatever the placement."""

    tick = Output(int)

    def setup(self) -> None:
        raise RuntimeError("cannot open the device")

    def process(self) -> int:
        return 1


class FailsEveryOther(Node):
    """Fails one activation in two (counted across restarts): never two failures in a row."""

    tick = Output(int)
    calls = 0

    def process(self) -> int:
        FailsEveryOther.calls += 1
        if FailsEveryOther.calls % 2:
            raise ValueError(f"odd call {FailsEveryOther.calls}")
        return FailsEveryOther.calls


class GivesUp(Node):
    """Knows that restarting cannot help: raises FatalError."""

    tick = Output(int)

    def process(self) -> int:
        raise FatalError("calibration file unusable")


class TeardownFails(Node):
    """Runs well, but ``teardown`` raises: the device it holds is not released."""

    tick = Output(int)

    def process(self) -> int:
        return 1

    def teardown(self) -> None:
        raise OSError("cannot release the device")


class TeardownHangs(Node):
    """Runs well, but ``teardown`` never returns (a device that does not let go)."""

    tick = Output(int)

    def process(self) -> int:
        return 1

    def teardown(self) -> None:
        while True:
            time.sleep(1)


class WrongOutputName(Node):
    """Returns a port it does not have (a typo: ``scor``)."""

    score = Output(float)
    level = Output(int)

    def process(self) -> dict[str, float]:
        return {"scor": 1.0}


class WrongOutputType(Node):
    """``score = Output(float)`` returning ``"high"``: the producer's error."""

    score = Output(float)

    def process(self) -> str:
        return "high"


class NotAMapping(Node):
    """Two outputs, one bare value returned."""

    score = Output(float)
    level = Output(int)

    def process(self) -> float:
        return 0.5


class PublishesWrongPort(Node):
    """``ctx.publish`` on a port the node does not have."""

    score = Output(float)

    def process(self) -> None:
        self.ctx.publish("nope", 1.0)


class FailingSink(Node):
    """A reader that fails at once: what its lossless edge holds will never be taken."""

    value = Input(int)

    def process(self, value: int) -> None:
        raise ValueError("cannot write")
