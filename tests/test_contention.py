"""Two operators and careless scripts at once (issue 37 item 3 and its "Done when").

20 clients drive the control endpoint and the operator station's API together, at random:
record start and stop (the station's panel and ``POST /record``), swaps, timing changes and
mode switches. Nothing answers 5xx, nothing logs a traceback, every session that started is
closed with its per-stream table (``streams.json``), a stop answers within 10 s, and the
runtime runs on. ``FLOWRT_CONTENTION_S`` sets how long (60 in the issue; 12 by default here,
to keep the suite in its CI budget). The critical node's interval p99 with and without clients
is printed; ``FLOWRT_CONTENTION_TIMING=1`` also asserts the issue's bound (within 1 ms), which
a machine shared with other work cannot promise.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from flowrt import GraphBuilder, Runtime
from flowrt.control.server import ControlConfig, ControlServer

REPO = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.subprocess, pytest.mark.realtime, pytest.mark.timeout(300)]

SECONDS = float(os.environ.get("FLOWRT_CONTENTION_S", "12"))
BASELINE = 3.0  # seconds of the run without clients, to compare the critical node's timing
CLIENTS = 20


def graph(folder: Path) -> Any:
    g = GraphBuilder("contention")
    g.add("crit", "counter", trigger={"timer": "50ms"}, priority=40)
    g.add("slow", "burn", params={"ms": 0.5}, trigger={"timer": "100ms"}, priority=10)
    g.add(
        "rec",
        "recorder",
        params={"path": str(folder), "start": False, "writer": "thread", "log_report": False},
        inputs={"crit.value": {"from": "crit.value", "policy": "lossless"}},
    )
    g.add("view", "display", params={"port": 0, "health_hz": 1})
    g.mode("calm", slow={"timer": "200ms"})
    g.mode("busy", slow={"timer": "100ms"})
    return g.build()


async def client(
    http: aiohttp.ClientSession, view: str, ctl: str, seed: int, end: float, seen: list[Any]
) -> None:
    rng = random.Random(seed)
    while time.monotonic() < end:
        choice = rng.random()
        body: dict[str, Any]
        if choice < 0.5:  # the record panel, as a double click in two tabs does
            action = rng.choice(["start", "stop"])
            url, body = f"{view}/api/record/{action}", {"name": f"c{seed}"}
        elif choice < 0.6:
            url, body = f"{ctl}/record", {"action": rng.choice(["start", "stop"])}
        elif choice < 0.75:
            url, body = f"{ctl}/swap", {"node": "slow", "kind": "burn", "params": {"ms": 0.2}}
        elif choice < 0.9:
            url, body = f"{ctl}/timing", {"node": "slow", "priority": rng.randint(5, 30)}
        else:
            url, body = f"{ctl}/mode", {"mode": rng.choice(["calm", "busy"])}
        t0 = time.monotonic()
        try:
            async with http.post(url, json=body) as r:
                text = await r.text()
                seen.append((url, r.status, time.monotonic() - t0, text[:200]))
        except (aiohttp.ClientError, TimeoutError) as e:
            seen.append((url, 599, time.monotonic() - t0, repr(e)))
        await asyncio.sleep(rng.uniform(0.0, 0.3))


def p99(samples: list[float]) -> float:
    """The 99th percentile of interval samples (seconds), in ms."""
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1000


def closed(folder: Path) -> tuple[list[str], list[str]]:
    """The sessions in ``folder``, and those without their table (never closed)."""
    sessions = [p for p in folder.iterdir() if p.is_dir()]
    unclosed = [p.name for p in sessions if not (p / "streams.json").exists()]
    for p in sessions:
        if p.name not in unclosed:
            json.loads((p / "streams.json").read_text())
    return [p.name for p in sessions], unclosed


async def test_twenty_clients_on_the_endpoint_and_the_station(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    async with Runtime(graph(tmp_path)) as rt:
        view = rt.runner("view").executor.node.url  # type: ignore[attr-defined]
        async with (
            ControlServer(rt, ControlConfig("127.0.0.1", 0)) as server,
            aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=30)) as http,
        ):
            ring = rt.runner("crit").counts.interval.ring  # seconds, in order: < RING samples
            await asyncio.sleep(BASELINE)  # the run without clients
            quiet = len(ring)
            # the clients in a process of their own, as real ones are: not on this loop
            proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "tests.test_contention",
                view,
                server.url,
                str(SECONDS),
                cwd=REPO,
                stdout=asyncio.subprocess.PIPE,
            )
            answers, _ = await asyncio.wait_for(proc.communicate(), SECONDS + 120)
            seen = [tuple(s) for s in json.loads(answers)]
            busy = len(ring)
            async with http.post(f"{view}/api/record/stop", json={}) as r:
                assert r.status in (200, 202, 409), await r.text()
            async with http.get(f"{view}/stats.json") as r:
                assert r.status == 200
        assert rt.started
        crit = rt.stats().node("crit")
    # a change queued too long behind the others is refused, never sent: an honest answer
    failed = [s for s in seen if s[1] >= 500 and not (s[1] == 503 and "not applied" in s[3])]
    assert not failed, failed[:5]
    sessions, unclosed = closed(tmp_path)
    assert not unclosed, unclosed
    stops = [s for s in seen if s[0].endswith("/api/record/stop")]
    assert stops
    assert max(s[2] for s in stops) < 10, max(stops, key=lambda s: s[2])
    started = [
        json.loads(s[3])["session"]
        for s in seen
        if s[0].endswith("/api/record/start") and s[1] == 200
    ]
    assert started, seen[:20]
    assert len(set(started)) == len(started), "one session reported to two starts"
    assert set(started) <= set(sessions)
    assert crit.errors == 0
    p99_quiet, p99_busy = p99(list(ring)[2:quiet]), p99(list(ring)[quiet:busy])
    if os.environ.get("FLOWRT_CONTENTION_TIMING"):  # on a quiet machine: the bound
        assert p99_busy - p99_quiet < 1.0, (p99_quiet, p99_busy)
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
    print(
        f"{len(seen)} requests, {len(sessions)} sessions, statuses "
        f"{sorted({s[1] for s in seen})}, slowest stop {max(s[2] for s in stops):.2f} s; "
        f"crit interval p99 {p99_quiet:.2f} ms without clients, {p99_busy:.2f} ms with"
    )


async def drive(view: str, ctl: str, seconds: float) -> list[Any]:
    """CLIENTS clients for ``seconds``: every request as (url, status, seconds, text)."""
    seen: list[Any] = []
    timeout = aiohttp.ClientTimeout(total=30)
    async with aiohttp.ClientSession(timeout=timeout) as http:
        end = time.monotonic() + seconds
        await asyncio.gather(*(client(http, view, ctl, i, end, seen) for i in range(CLIENTS)))
    return seen


if __name__ == "__main__":  # the clients' process
    print(json.dumps(asyncio.run(drive(sys.argv[1], sys.argv[2], float(sys.argv[3])))))
