"""The event-loop policy: uvloop when installed, for every entry point alike.

Kept apart so that the runtime (a lower layer) and the CLI (one of its users) both take the
policy from here instead of from each other.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


def new_event_loop() -> asyncio.AbstractEventLoop:
    """uvloop when installed: lower per-callback overhead than the default loop."""
    try:
        import uvloop

        return uvloop.new_event_loop()
    except ImportError:
        return asyncio.new_event_loop()


def run(main: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run`` on uvloop when it is installed: the embedding program's entry point."""
    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        return runner.run(main)
