"""An exporter that restarts under a listening import, over loopback (explicit endpoints, no
scouting): every value of each life counts, from its number 0, also those published before
Zenoh's link to the import was back up (``before the link was up``); an import that joins a
running exporter counts none of what it published before (docs/zenoh.md)."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import wait_until

import flowrt
from flowrt.remote._importer import BEFORE_LINK

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.timeout(90)]

EXPORTER = """
name: zex
zenoh: {{listen: ["tcp/127.0.0.1:{port}"]}}
nodes:
  cnt: {{kind: counter, trigger: {{timer: 20ms}}}}
export: {{demo/count: cnt.value}}
"""

IMPORTER = """
name: {name}
zenoh:
  listen: []
  connect: ["tcp/127.0.0.1:{port}"]
  config: {{connect/retry: {{period_init_ms: 500, period_max_ms: 500}}}}
import:
  rcount: {{key: demo/count, period: 20ms, stale: state, size: 256}}
nodes:
  sink: {{kind: sink, inputs: {{input: rcount}}}}
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start(path: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "flowrt.cli", "run", str(path), "--no-ui", "--duration", "60"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


async def test_each_exporter_life_counts_from_its_first_value_a_late_joiner_does_not(
    tmp_path: Path,
) -> None:
    port = free_port()
    exporter = tmp_path / "zex.yaml"
    exporter.write_text(EXPORTER.format(port=port))

    def importer(name: str) -> flowrt.Runtime:
        text = IMPORTER.format(name=name, port=port)
        return flowrt.Runtime(flowrt.Graph.from_text(text, f"{name}.yaml"))

    async with importer("zim") as rt:
        imp = rt._bridge.imports["rcount"]
        link = imp.link
        before, streams = 0, set()
        for life in (1, 2):  # the first begins after the import listens, the second restarts
            if life == 1:  # a stream's start is in whole seconds (the header's room): one that
                await asyncio.sleep(1.2)  # began within a second of the listening may look
            proc = start(exporter)  # older than it, not counted (docs/zenoh.md); not this one
            try:
                assert await wait_until(lambda n=link.delivered + 10: link.delivered >= n, 30)
                if life == 2:  # a second import joins the running exporter late
                    async with importer("late") as late:
                        other = late._bridge.imports["rcount"]
                        assert await wait_until(lambda o=other: o.link.delivered >= 5, 30)
                        with other.lock:
                            assert BEFORE_LINK not in other.link.drop_reasons
                            assert other.link.published < other.last_seq + 1  # joined late
            finally:
                stop(proc)
            # the last values reach the loop: each one published is delivered or dropped
            assert await wait_until(lambda: link.delivered + link.dropped == link.published, 10)
            with imp.lock:
                published, last, reasons = link.published, imp.last_seq, dict(link.drop_reasons)
                streams.add(imp.stream)
            assert published - before == last + 1, (life, reasons)  # values 0..last, all
            assert set(reasons) <= {BEFORE_LINK, "sequence gap"}
            before = published
        assert len(streams) == 2  # a restart is a new stream
