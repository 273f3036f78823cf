"""Two machines on one host: a "robot" and a "base" network namespace joined by a veth pair.

Used by tests/test_two_machines.py and benchmarks/bench_two_machines.py (issue 40). Each side
runs its own ``flowrt`` process inside its namespace (``ip netns exec``); the addresses exist
in those namespaces only (10.203.0.1 robot, 10.203.0.2 base), so nothing crosses the host's
loopback. Faults: :meth:`Bed.cut` / :meth:`Bed.restore` set the robot's end of the link down
and up (a pulled cable: no carrier on either end), :meth:`Bed.flap`.

Cleanup whatever happens: :class:`Bed` is a context manager that kills the processes it
started (by their pid) and deletes both namespaces (which deletes the veth pair); namespaces
left by an earlier run whose process is gone (a SIGKILLed pytest) are deleted at the next
start. Needs root (``ip netns add``); :func:`unavailable` says why not, for a skip.

Run as a program, it is the operator's hand on the base's page (from inside the base's
namespace, where the page is)::

    ip netns exec BASE python tests/netns_bed.py estop release http://127.0.0.1:8751
    ip netns exec BASE python tests/netns_bed.py wait-link http://127.0.0.1:8751 remote_drive 60
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

PREFIX = "flrt"  # namespaces flrt-robot-PID, flrt-base-PID; veth flrtrPID / flrtbPID
ROBOT_IP = "10.203.0.1"
BASE_IP = "10.203.0.2"
ZENOH_PORT = 7447
ROBOT_EP = f"tcp/{ROBOT_IP}:{ZENOH_PORT}"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=10)


def unavailable() -> str | None:
    """Why network namespaces cannot be made here (None: they can)."""
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is missing"
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add); CI runs as root"
    probe = f"{PREFIX}-probe-{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except (subprocess.SubprocessError, OSError) as e:
        return f"ip netns add failed: {getattr(e, 'stderr', '') or e}".strip()
    _ip("netns", "del", probe, check=False)
    return None


def leftovers() -> list[str]:
    """This bed's namespaces still present (of any run)."""
    out = _ip("netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.startswith(f"{PREFIX}-")]


def _sweep() -> None:
    """Delete namespaces of earlier runs whose process is gone, with what still runs in them
    (their children die with them, :func:`_die_with_parent`; this is for the rest)."""
    for ns in leftovers():
        m = re.search(r"-(\d+)$", ns)
        if m and not Path(f"/proc/{m.group(1)}").exists():
            for pid in _ip("netns", "pids", ns, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
            _ip("netns", "del", ns, check=False)


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL when the process that started it dies (a killed
    pytest leaves no flowrt running in a namespace; kept across ``ip netns exec``'s exec)."""
    import ctypes

    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


class Bed:
    """The two namespaces, the link between them, and the processes started in them."""

    def __init__(self) -> None:
        pid = os.getpid()
        self.robot = f"{PREFIX}-robot-{pid}"
        self.base = f"{PREFIX}-base-{pid}"
        self.veth_robot = f"{PREFIX}r{pid}"[:15]
        self.veth_base = f"{PREFIX}b{pid}"[:15]
        self.procs: list[subprocess.Popen[bytes]] = []
        self.events: list[tuple[str, float]] = []  # (what, time.time()) of every fault

    # --- lifecycle ------------------------------------------------------------------------

    def __enter__(self) -> Bed:
        _sweep()
        try:
            self._up()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _up(self) -> None:
        for ns in (self.robot, self.base):
            _ip("netns", "add", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        _ip("link", "add", self.veth_robot, "type", "veth", "peer", "name", self.veth_base)
        _ip("link", "set", self.veth_robot, "netns", self.robot)
        _ip("link", "set", self.veth_base, "netns", self.base)
        _ip("-n", self.robot, "addr", "add", f"{ROBOT_IP}/24", "dev", self.veth_robot)
        _ip("-n", self.base, "addr", "add", f"{BASE_IP}/24", "dev", self.veth_base)
        _ip("-n", self.robot, "link", "set", self.veth_robot, "up")
        _ip("-n", self.base, "link", "set", self.veth_base, "up")

    def close(self) -> None:
        """Stop every process started here (by pid), delete both namespaces and the link."""
        for p in self.procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=10)
        for ns in (self.robot, self.base):
            _ip("netns", "del", ns, check=False)  # takes the veth end inside it along
        _ip("link", "del", self.veth_robot, check=False)  # if never moved into its namespace

    # --- processes ------------------------------------------------------------------------

    def start(
        self, ns: str, argv: list[str], env: dict[str, str] | None = None, **kw: Any
    ) -> subprocess.Popen[bytes]:
        """Start ``argv`` inside namespace ``ns`` (``ip netns exec`` execs it: same pid)."""
        full_env = {**os.environ, **(env or {})}
        p = subprocess.Popen(
            ["ip", "netns", "exec", ns, *argv], env=full_env, preexec_fn=_die_with_parent, **kw
        )
        self.procs.append(p)
        return p

    def flowrt(self, ns: str, args: list[str], log: Path, **kw: Any) -> subprocess.Popen[bytes]:
        """``flowrt ARGS`` in ``ns``, its output in ``log``."""
        out = log.open("wb")
        return self.start(
            ns,
            [sys.executable, "-m", "flowrt.cli", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            **kw,
        )

    def stop(self, p: subprocess.Popen[bytes], timeout: float = 30.0) -> int:
        """SIGINT (an orderly stop: files finished, the final table), then wait for the exit."""
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
        try:
            return p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)
            return -9

    def page(self, *args: str, timeout: float = 60.0) -> str:
        """Run this file's page client in the base's namespace; its stdout (one line)."""
        argv = ["ip", "netns", "exec", self.base, sys.executable, __file__, *args]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
        if done.returncode != 0:
            raise RuntimeError(f"page {' '.join(args)}: {done.stderr.strip() or done.stdout}")
        return done.stdout.strip()

    # --- faults ---------------------------------------------------------------------------

    def cut(self) -> float:
        """The robot's end of the link down (no carrier on either end); the time of the cut."""
        _ip("-n", self.robot, "link", "set", self.veth_robot, "down")
        t = time.time()
        self.events.append(("cut", t))
        return t

    def restore(self) -> float:
        _ip("-n", self.robot, "link", "set", self.veth_robot, "up")
        t = time.time()
        self.events.append(("restore", t))
        return t

    def flap(self, every: float = 0.5, total: float = 5.0) -> None:
        """Down and up every ``every`` seconds for ``total`` seconds; the link ends up."""
        end = time.monotonic() + total
        while time.monotonic() < end:
            self.cut()
            time.sleep(every)
            self.restore()
            time.sleep(every)


# --- the operator's hand on the base's page (run inside the base's namespace) ---------------


async def _estop(action: str, url: str, deadline: float) -> tuple[str, float]:
    """Open the page (waiting for it), then send one e-stop action over its WebSocket."""
    import secrets

    import aiohttp

    async with aiohttp.ClientSession(headers=VIEW_AUTH) as http:
        while True:
            try:
                async with http.get(url + "/") as r:
                    page = await r.text()
                break
            except aiohttp.ClientError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.25)
        m = re.search(r'const SESSION = "([^"]+)"', page)
        if m is None:
            raise RuntimeError("no session in the page")
        aid = f"{action}-{secrets.token_hex(6)}"
        async with http.ws_connect(f"{url}/ws?session={m.group(1)}") as ws:
            sent = time.time()
            await ws.send_json({"estop": {"action": action, "id": aid}})
            await asyncio.sleep(0.3)  # the display takes it before the socket closes
        return aid, sent


async def _wait_link(url: str, node: str, deadline: float) -> float:
    """Poll the page's statistics until import ``node`` hears its exporter; the time then."""
    import aiohttp

    async with aiohttp.ClientSession(headers=VIEW_AUTH) as http:
        while time.monotonic() < deadline:
            try:
                async with http.get(url + "/stats.json") as r:
                    stats = await r.json()
                reports = (stats.get("runtime") or {}).get("reports") or {}
                report = reports.get(node) or {}
                if report.get("last_contact") and not report.get("stale"):
                    return time.time()
            except (aiohttp.ClientError, ValueError):
                pass
            await asyncio.sleep(0.1)
    raise TimeoutError(f"import {node} heard nothing")


async def _edge(url: str, name: str) -> dict[str, Any]:
    """One edge's counters from the page's statistics (``{}`` when it has none)."""
    import aiohttp

    async with aiohttp.ClientSession(headers=VIEW_AUTH) as http, http.get(url + "/stats.json") as r:
        stats = await r.json()
    edges = (stats.get("runtime") or {}).get("edges") or []
    return next((e for e in edges if e.get("name") == name), {})


async def _post(url: str, body: str) -> tuple[int, str]:
    """POST a JSON body to the page (its API): the status and the body's text."""
    import aiohttp

    timeout = aiohttp.ClientTimeout(total=60)
    async with (
        aiohttp.ClientSession(timeout=timeout, headers=VIEW_AUTH) as http,
        http.post(url, data=body, headers={"Content-Type": "application/json"}) as r,
    ):
        return r.status, (await r.text()).strip()


#: The base's live view has an e-stop, so it needs a token: the bed gives the base this one
#: (``FLOWRT_DISPLAY_TOKEN``) and its page client sends it.
VIEW_TOKEN = "netns-bed-view-token"
VIEW_AUTH = {"Authorization": f"Bearer {VIEW_TOKEN}"}


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "estop" and argv[1] in ("stop", "release"):
        aid, sent = asyncio.run(_estop(argv[1], argv[2].rstrip("/"), time.monotonic() + 45))
        print(aid, sent)  # the action's id, and when it was sent
        return 0
    if len(argv) == 4 and argv[0] == "wait-link":
        limit = time.monotonic() + float(argv[3])
        print(asyncio.run(_wait_link(argv[1].rstrip("/"), argv[2], limit)))
        return 0
    if len(argv) == 3 and argv[0] == "post":
        status, text = asyncio.run(_post(argv[1], argv[2]))
        print(status, text.replace("\n", " "))
        return 0
    if len(argv) == 3 and argv[0] == "edge":
        print(json.dumps(asyncio.run(_edge(argv[1].rstrip("/"), argv[2]))))
        return 0
    print(
        "usage: netns_bed.py estop stop|release URL | wait-link URL NODE TIMEOUT | edge URL NAME"
        " | post URL JSON",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
