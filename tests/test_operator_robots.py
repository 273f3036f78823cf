"""Several machines: the base station's view (graphs/zenoh_base.yaml) shows the robot of
graphs/zenoh_robot.yaml (its streams, health and recording state) and starts and stops the
robot's recorder through the robot's Zenoh control channel, both run as a user runs them."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import socket
import sys
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.test_display import chromium_path
from tests.test_operator_api import get, post

pytestmark = [pytest.mark.timeout(180), pytest.mark.subprocess, pytest.mark.realtime]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def flowrt_run(
    graph: Path, *options: str
) -> tuple[asyncio.subprocess.Process, list[str], asyncio.Future[None]]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "flowrt.cli",
        "run",
        str(graph),
        "--no-ui",
        *options,
        cwd=graph.parent,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        env={**os.environ, "COLUMNS": "200"},
    )
    out: list[str] = []

    async def collect() -> None:
        assert proc.stdout is not None
        async for line in proc.stdout:
            out.append(line.decode())

    return proc, out, asyncio.ensure_future(collect())


async def until(cond: Any, within: float, what: str, out: list[str]) -> Any:
    end = asyncio.get_running_loop().time() + within
    while asyncio.get_running_loop().time() < end:
        value = await cond()
        if value:
            return value
        await asyncio.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}:\n" + "".join(out[-30:]))


async def test_the_base_station_records_on_the_robot(tmp_path: Path, repo: Path) -> None:
    port = free_port()
    for name in ("zenoh_robot.yaml", "zenoh_base.yaml"):
        text = (repo / "graphs" / name).read_text().replace("127.0.0.1:7447", f"127.0.0.1:{port}")
        (tmp_path / name).write_text(text)
    robot, robot_out, robot_done = await flowrt_run(tmp_path / "zenoh_robot.yaml")
    base, base_out, base_done = await flowrt_run(
        tmp_path / "zenoh_base.yaml", "--display-port", "0"
    )
    try:

        async def view() -> str:
            m = re.search(r"display: (http://127\.0\.0\.1:\d+)", "".join(base_out))
            return m.group(1) if m else ""

        url = await until(view, 60, "the base's view", base_out)
        # its page can release the e-stop: the view needs the token it printed
        m = re.search(r"\?token=([\w-]+)", "".join(base_out))
        assert m, "".join(base_out[-30:])
        token = m.group(1)
        auth = {"Authorization": f"Bearer {token}"}
        async with aiohttp.ClientSession(headers=auth) as http:

            async def robot1() -> Any:
                (r,) = (await get(http, f"{url}/api/robots"))["robots"]
                fps = {s["name"]: s["fps"] for s in r.get("streams", [])}
                ready = r["reachable"] and r["health"] and (fps.get("front_cam") or 0) > 15
                return r if ready else None

            r = await until(robot1, 60, "robot1 reachable with its streams", robot_out + base_out)
            assert r["name"] == "robot1"
            assert r["graph"] == "zenoh-robot"
            assert r["failed"] == []
            assert r["recording"] == {"recorder": ""}
            assert 0 <= r["health"]["cpu_percent"] <= 100

            status, started = await post(
                http, f"{url}/api/robots/robot1/record/start", {"name": "field"}
            )
            assert status == 200, started
            assert started["session"] == "field_001"
            status, busy = await post(http, f"{url}/api/robots/robot1/record/start", {"name": "x"})
            assert status == 409, busy
            await asyncio.sleep(2.0)
            status, table = await post(http, f"{url}/api/robots/robot1/record/stop", {})
            assert status == 200, table
            assert table["session"] == "field_001"
            assert table["lost"] == 0
            cam = next(s for s in table["streams"] if s["topic"] == "front_cam.frame")
            assert cam["written"] == cam["received"] >= 25
            # on the robot's disk, beside its graph
            assert (tmp_path / "recordings" / "field_001" / "streams.json").is_file()
            status, _ = await post(
                http,
                f"{url}/api/robots/robot1/record/start",
                {"name": "x"},
                Origin="http://evil.example",
            )
            assert status == 403
            async with http.post(f"{url}/api/robots/nobody/record/start", json={}) as resp:
                assert resp.status == 404
        if chromium_path() is not None:
            await the_page_records_on_the_robot(url, tmp_path, token)
    finally:
        for proc in (base, robot):
            if proc.returncode is None:
                proc.send_signal(signal.SIGINT)
        for proc in (base, robot):
            try:
                await asyncio.wait_for(proc.wait(), 30)
            except TimeoutError:
                proc.kill()
                await proc.wait()
        await asyncio.gather(robot_done, base_done, return_exceptions=True)


async def the_page_records_on_the_robot(url: str, tmp_path: Path, token: str) -> None:
    """The same from the base's page: the robot's row, its Start and Stop clicked."""
    from tests.test_display import browser
    from tests.test_operator_page import click, shot
    from tests.test_operator_page import until as page_until

    async with browser(f"{url}/?token={token}") as page:
        row = '#robots tr[data-robot="robot1"]'
        await page_until(
            page,
            f"document.querySelector('{row}')?.dataset.reachable === 'true'"
            " && !document.querySelector('#robotspanel').hidden",
            20,
            "robot1",
        )
        await page.eval("document.querySelector('#recname').value = 'page'; true")
        await click(page, f"{row} button[data-action=start]")
        await page_until(
            page, "window.flowrt.operator.lastRobot?.session === 'page_001'", 20, "start"
        )
        await page_until(
            page, f"document.querySelector('{row}').textContent.includes('REC page_001')", 20, "REC"
        )
        await asyncio.sleep(2.0)
        await shot(page, "#robotspanel", "operator-robots.png")
        await click(page, f"{row} button[data-action=stop]")
        await page_until(page, "window.flowrt.operator.lastRobot?.streams", 30, "the stop table")
        text = await page.eval("document.querySelector('#robotmsg').textContent")
        assert "page_001" in text, text
        assert "0 lost" in text, text
