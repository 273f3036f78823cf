"""Plain Zenoh programs and a flowrt graph, following only docs/zenoh.md (issue 26): a plain
subscriber reads an export, a plain publisher feeds an import (format: json), in processes of
their own, over loopback with explicit endpoints."""

from __future__ import annotations

import asyncio
import json
import socket
import sys
from pathlib import Path

import pytest
from conftest import drained, wait_until

import flowrt

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.timeout(90)]

DOCS = Path(__file__).resolve().parents[1] / "docs" / "examples"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_plain_programs_read_an_export_and_feed_an_import() -> None:
    port = free_port()
    text = (DOCS / "zenoh_plain.yaml").read_text().replace("7460", str(port))
    graph = flowrt.Graph.from_text(text, "zenoh_plain.yaml")
    endpoint = f"tcp/127.0.0.1:{port}"
    async with flowrt.Runtime(graph) as rt:
        cmds = rt.subscribe("cmd.output", size=100)
        await asyncio.sleep(1.5)  # no command yet: the docs' graph must not call that an error
        assert rt.stats().node("cmd").state != "error"
        sub = await asyncio.create_subprocess_exec(
            sys.executable, str(DOCS / "zenoh_plain_sub.py"), endpoint, "demo/count", "5",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        pub = await asyncio.create_subprocess_exec(
            sys.executable, str(DOCS / "zenoh_plain_pub.py"), endpoint, "demo/cmd", "20",
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        out, err = await asyncio.wait_for(sub.communicate(), 40)
        _, perr = await asyncio.wait_for(pub.communicate(), 40)
        await asyncio.sleep(0.5)
        got = cmds.drain()
        last = {"vx": pytest.approx(1.9), "w": 0.0}
        # the last commands may reach the graph later on a loaded machine: waited for (bounded)
        await wait_until(lambda: len(drained(cmds, got)) >= 18 and got[-1] == last)
        link = rt.stats().edge("zenoh:demo/cmd->cmd")
        state = rt.stats().node("cmd").state  # the commands come now and then: never stale
    assert state != "error"
    assert sub.returncode == 0, err.decode()
    assert pub.returncode == 0, perr.decode()
    read = json.loads(out)
    assert len(read) == 5
    # set right on the wire, with the recording's schema name: a plain value as {"value": N}
    assert all(r["encoding"] == "application/json;builtins.int" for r in read)
    seqs = [r["seq"] for r in read]
    assert seqs == list(range(seqs[0], seqs[0] + 5))
    assert [r["value"] for r in read] == [{"value": n} for n in seqs]  # counted, in order
    assert len(got) >= 18  # header-less JSON from a plain program, into the graph
    assert got[-1] == last
    assert link.dropped == 0
