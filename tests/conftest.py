"""What the tests share: the repository's paths, a ``flowrt`` command runner, and the tiers.

Tiers (markers registered in pyproject.toml): a test that drives headless Chromium
(``browser``), starts flowrt or another program as a process (``subprocess``), measures real
time (``realtime``) or runs Node.js (``node``) is also ``slow``, so that::

    python -m pytest -q -n 2 -m "not slow"   # the inner loop: no process, no browser, < 2 min
    python -m pytest -q -n 2                 # everything (CI; -n 2: pytest-xdist, one worker
                                             # per core, each test file in one worker)

The markers are derived from what a test uses (its code, its fixtures and the helpers they
call) and a guard fails a fast-tier test that starts a process or takes too long anyway:
see tests/tiers.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator, Callable, Generator
from pathlib import Path
from typing import Any

import pytest
import tiers

REPO = Path(__file__).resolve().parents[1]
TIERS = tiers.TIERS

# pytest-xdist's workers get COLUMNS=80 where a plain run has none (piped output is then 200
# wide, see flowrt.cli.common.stdout_console): the same output with -n 2 as without.
if os.environ.get("PYTEST_XDIST_WORKER") is not None:
    os.environ.pop("COLUMNS", None)


def pytest_configure(config: pytest.Config) -> None:
    tiers.install_guard()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    tiers.derive(items)


@pytest.fixture(autouse=True)
def _logging_as_before() -> Generator[None]:
    """A CLI run in the test process (``main([...])``) sets the root logger's handlers to a
    stream of that moment (``logging.basicConfig(force=True)``); once pytest has closed that
    stream, a later test's log line prints a "Logging error" traceback. Each test leaves the
    root logger's handlers and level as it found them."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None]:
    tiers.start(item)
    try:
        yield
    finally:
        tiers.stop()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Generator[None]:
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if call.when == "call" and report.passed and (why := tiers.verdict(item)) is not None:
        report.outcome = "failed"
        report.longrepr = why


@pytest.fixture
def repo() -> Path:
    """The repository's root (graphs/, nodes/, ...)."""
    return REPO


FlowrtCli = Callable[..., "subprocess.CompletedProcess[str]"]


@pytest.fixture
def flowrt_cli() -> FlowrtCli:
    """``flowrt_cli("validate", path, cwd=..., timeout=...)``: the command as a user runs it
    (``python -m flowrt.cli`` of this interpreter), from the repository root by default, with
    a wide terminal so lines are not wrapped."""

    def run(
        *args: str, cwd: Path | None = None, timeout: float = 120, env: dict[str, str] | None = None
    ) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "flowrt.cli", *args],
            cwd=cwd or REPO,
            env={**os.environ, "COLUMNS": "200", **(env or {})},
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    return run


class FlowrtRun:
    """A ``flowrt`` command running in the background, its output kept (see flowrt_running)."""

    def __init__(self, proc: asyncio.subprocess.Process) -> None:
        self.proc = proc
        self.out: list[str] = []
        self._drain: asyncio.Future[None] | None = None

    async def addresses(self, **patterns: str) -> dict[str, str]:
        """Read the output until each regular expression has matched (group 1 kept), then keep
        reading it in the background (a full pipe would stall the run)."""
        stdout = self.proc.stdout
        assert stdout is not None
        found: dict[str, str] = {}
        while len(found) < len(patterns):
            line = (await asyncio.wait_for(stdout.readline(), 60)).decode()
            assert line, "flowrt ended: " + "".join(self.out)
            self.out.append(line)
            for key, pattern in patterns.items():
                if m := re.search(pattern, line):
                    found[key] = m.group(1)
        self._drain = asyncio.ensure_future(self._collect(stdout))
        return found

    async def _collect(self, stream: asyncio.StreamReader) -> None:
        async for line in stream:
            self.out.append(line.decode())

    async def stop(self, tolerated: str | None = None) -> None:
        """Ctrl-C, as a user stops it: the run must end cleanly (exit 0), or, when the run's
        only failure is ``tolerated`` (a load-dependent one, counted, e.g. a recorder behind
        a loaded machine), with exit 1 and that reason in its last line."""
        self.proc.send_signal(signal.SIGINT)
        code = await asyncio.wait_for(self.proc.wait(), 60)
        if self._drain is not None:
            await self._drain
        said = [ln for ln in self.out if ln.startswith("flowrt run: node ")]
        if code == 1 and tolerated is not None and said and all(tolerated in ln for ln in said):
            return
        assert code == 0, "".join(self.out)


@contextlib.asynccontextmanager
@tiers.uses("subprocess")
async def flowrt_running(*args: str, cwd: Path | None = None) -> AsyncIterator[FlowrtRun]:
    """``python -m flowrt.cli ARGS`` in the background; killed on the way out if still running
    (the body calls ``stop()`` for a clean end it checks)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "flowrt.cli",
        *args,
        cwd=cwd or REPO,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        yield FlowrtRun(proc)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


# -- counts reached over real time ------------------------------------------------------------


async def wait_until(done: Callable[[], object], within: float = 10.0, step: float = 0.05) -> bool:
    """Poll ``done()`` every ``step`` s of the real clock until it holds or ``within`` s have
    passed; whether it holds. For what a run makes over real time (frames, activations): a
    machine loaded by the whole suite (CI: 2 busy cores) starts workers and releases timers
    later than an idle one, so a test waits (bounded) for the count it asserts instead of
    assuming an idle machine in a fixed window, then asserts the same bar. Waiting on the
    event loop costs no CPU (the fast tier's budget)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + within
    while not done():
        if loop.time() >= end:
            return False
        await asyncio.sleep(step)
    return True


def drained(sub: Any, into: list[Any]) -> list[Any]:
    """``into``, with what the subscription ``sub`` holds now moved onto its end (a long wait
    drains as it goes: a subscription's buffer is bounded)."""
    into += sub.drain()
    return into


def recorded_counter(folder: Path, timer: str = "20ms", **params: Any) -> Any:
    """A graph builder: a counter every ``timer`` recorded by a recorder ``rec`` into
    ``folder`` (``params`` over ``log_report: false``): the graph of the recorder's tests."""
    from flowrt import GraphBuilder

    g = GraphBuilder("rec")
    g.add("src", "counter", trigger={"timer": timer})
    g.add(
        "rec",
        "recorder",
        params={"path": str(folder), "log_report": False, **params},
        inputs={"src.value": "src.value"},
    )
    return g


async def trickled_post(port: int, path: str, body_start: bytes) -> bytes:
    """The status line a server at ``port`` answers to a POST whose headers are whole and
    whose body stops after ``body_start`` (of 40 bytes announced): a slow client's body."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(
        f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        "Content-Length: 40\r\n\r\n".encode()
        + body_start
    )
    await writer.drain()
    try:
        return await asyncio.wait_for(reader.readline(), 5)
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
