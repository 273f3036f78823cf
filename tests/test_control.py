"""The control endpoint (loopback only in tests) and ``flowrt ctl`` against it."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from conftest import trickled_post

import flowrt
from flowrt import GraphBuilder, Runtime, VirtualClock
from flowrt.control.server import ControlConfig, ControlServer
from flowrt.control.serving import is_loopback

TOKEN = "s3cret-token"


def graph() -> flowrt.Graph:
    g = GraphBuilder("ctl")
    g.add("src", "counter", trigger={"timer": "50ms"})
    g.add("slow", "burn", params={"ms": 0.1}, trigger={"timer": "100ms"}, priority=20)
    g.mode("defend", slow={"enabled": False})
    g.mode("attack", slow={"timer": "50ms", "priority": 40})
    return g.build()


SERVERS: dict[int, ControlServer] = {}


async def served(config: ControlConfig) -> AsyncIterator[Runtime]:
    """A runtime on a virtual clock and its control endpoint, a user of it."""
    async with Runtime(graph(), clock=VirtualClock()) as r, ControlServer(r, config) as server:
        SERVERS[id(r)] = server
        yield r
        del SERVERS[id(r)]


@pytest.fixture
async def rt() -> AsyncIterator[Runtime]:
    async for r in served(ControlConfig("127.0.0.1", 0)):
        yield r


@pytest.fixture
async def rt_token() -> AsyncIterator[Runtime]:
    # a token given on loopback is required; relay and a module that exits at import may be
    # named by POST /swap besides the graph's own kinds
    config = ControlConfig(
        "127.0.0.1", 0, token=TOKEN, allow_kinds=("relay", "unittest.__main__:X")
    )
    async for r in served(config):
        yield r


def url(rt: Runtime, path: str) -> str:
    return SERVERS[id(rt)].url + path


async def call(
    method: str, target: str, body: Any = None, headers: dict[str, str] | None = None
) -> tuple[int, Any]:
    async with (
        aiohttp.ClientSession() as s,
        s.request(method, target, json=body, headers=headers) as r,
    ):
        return r.status, await r.json(content_type=None)


async def test_read_stats_change_timing_switch_modes(rt: Runtime) -> None:
    status, stats = await call("GET", url(rt, "/stats"))
    assert status == 200
    assert stats["graph"] == "ctl"
    assert {n["name"] for n in stats["nodes"]} == {"src", "slow"}
    flowrt.RuntimeStats.model_validate(stats)  # the typed model, as --stats-json

    status, reply = await call(
        "POST", url(rt, "/timing"), {"node": "slow", "timer": 200, "priority": 30}
    )
    assert status == 200
    assert reply == {
        "node": "slow",
        "change": "timer_ms 100.0 -> 200.0, priority 20 -> 30",
    }
    s = rt.stats().node("slow")
    assert (s.period, s.priority) == ("200ms", 30)
    changed = [e for e in rt.events if isinstance(e, flowrt.TimingChanged)]
    assert changed[-1].origin == "control"

    status, reply = await call("POST", url(rt, "/mode"), {"mode": "defend"})
    assert status == 200
    assert reply == {"mode": "defend"}
    assert rt.mode == "defend"
    assert not rt.stats().node("slow").enabled
    status, reply = await call("GET", url(rt, "/modes"))
    assert reply == {"modes": ["defend", "attack"], "current": "defend"}

    status, events = await call("GET", url(rt, "/events?n=2"))
    assert [e["kind"] for e in events] == ["TimingChanged", "ModeChanged"]
    assert events[1]["mode"] == "defend"
    assert events[1]["origin"] == "control"
    status, qos = await call("GET", url(rt, "/qos"))
    assert qos["mode"] == "defend"
    assert qos["summary"] == "qos: mode defend"
    status, records = await call("GET", url(rt, "/rtdb"))
    assert [(r["name"], r["value"]) for r in records] == [("flowrt.mode", "defend")]
    status, history = await call("GET", url(rt, "/rtdb/flowrt.mode?n=4"))
    assert status == 200
    assert history[0]["value"] == "defend"


async def test_bad_requests_are_refused_with_reasons(rt: Runtime) -> None:
    status, reply = await call("POST", url(rt, "/timing"), {"node": "slwo", "priority": 30})
    assert status == 404
    assert "did you mean 'slow'" in reply["error"]
    status, reply = await call("POST", url(rt, "/timing"), {"node": "slow", "period": 2})
    assert status == 400
    assert "frame-triggered" in reply["error"]
    assert "code" not in reply  # a refused change, not a malformed body
    status, reply = await call("POST", url(rt, "/timing"), {"node": "slow", "speed": 2})
    assert status == 400
    assert "bad request body" in reply["error"]
    assert reply["code"] == "malformed"
    status, reply = await call("POST", url(rt, "/mode"), {"mode": "atack"})
    assert status == 404
    assert "unknown mode" in reply["error"]
    async with aiohttp.ClientSession() as s:
        async with s.post(url(rt, "/mode"), data="mode=defend") as r:  # a browser form
            assert r.status == 415
        async with s.get(url(rt, "/stats"), headers={"Host": "evil.example:80"}) as r:  # rebinding
            assert r.status == 403
    assert rt.mode is None


async def test_requests_without_the_token_are_refused(rt_token: Runtime) -> None:
    status, reply = await call("GET", url(rt_token, "/stats"))
    assert status == 401
    assert "token" in reply["error"]
    status, _ = await call("POST", url(rt_token, "/mode"), {"mode": "defend"})
    assert status == 401
    assert rt_token.mode is None
    status, _ = await call(
        "GET", url(rt_token, "/stats"), headers={"Authorization": "Bearer wrong"}
    )
    assert status == 401
    status, _ = await call(
        "GET", url(rt_token, "/stats"), headers={"Authorization": f"Basic {TOKEN}"}
    )
    assert status == 401
    status, reply = await call(
        "POST",
        url(rt_token, "/mode"),
        {"mode": "defend"},
        headers={"Authorization": f"Bearer {TOKEN}"},
    )
    assert status == 200
    assert rt_token.mode == "defend"


async def test_refuses_to_serve_beyond_loopback_without_a_token() -> None:
    assert is_loopback("127.0.0.1")
    assert is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    assert not is_loopback("192.168.1.5")
    assert not is_loopback("::")
    assert ControlConfig.parse("9000") == ControlConfig("127.0.0.1", 9000)
    assert ControlConfig.parse("[::1]:9000").host == "::1"
    assert ControlConfig.parse("0.0.0.0:9000").needs_token
    with pytest.raises(ValueError, match="PORT"):
        ControlConfig.parse("host:port")
    async with Runtime(graph(), clock=VirtualClock()) as rt:
        for host in ("0.0.0.0", "::", "192.168.1.5"):
            with pytest.raises(ValueError, match="without a token"):
                ControlServer(rt, ControlConfig(host, 0))  # refused before binding anything
        ControlServer(rt, ControlConfig("0.0.0.0", 0, token=TOKEN))  # allowed (not started here)
    with pytest.raises(ValueError, match="without a token"):
        ControlConfig.checked("0.0.0.0:8765")  # before anything runs
    with pytest.raises(ValueError, match="token_required without a token"):
        ControlConfig.checked(ControlConfig("127.0.0.1", 0, token_required=True))


async def ctl(*args: str, token: str | None = None) -> tuple[int, str, str]:
    env_args = ["--token", token] if token else []
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "flowrt.cli",
        "ctl",
        *env_args,
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def test_flowrt_ctl_client(rt_token: Runtime) -> None:
    base = ["--url", url(rt_token, "")]
    code, out, err = await ctl(*base, "mode", "attack", token=TOKEN)
    assert (code, out.strip()) == (0, "mode attack"), err
    assert rt_token.mode == "attack"
    assert rt_token.stats().node("slow").priority == 40
    code, out, err = await ctl(
        *base, "timing", "slow", "--disable", "--priority", "25", token=TOKEN
    )
    assert code == 0, err
    assert out.strip() == "slow: priority 40 -> 25, enabled True -> False"
    code, out, _ = await ctl(*base, "modes", token=TOKEN)
    assert out.splitlines() == ["  defend", "* attack"]
    code, out, _ = await ctl(*base, "stats", "--json", token=TOKEN)
    assert code == 0
    assert json.loads(out)["nodes"][1]["enabled"] is False
    code, out, _ = await ctl(*base, "stats", token=TOKEN)
    assert code == 0
    assert "slow" in out
    assert "mode attack" in out
    # refused without the token: exit 1, a message, no traceback
    code, out, err = await ctl(*base, "mode", "defend")
    assert code == 1
    assert "401" in err
    assert "token" in err
    assert "Traceback" not in err
    assert rt_token.mode == "attack"
    code, out, err = await ctl(*base, "timing", "nope", "--priority", "3", token=TOKEN)
    assert code == 1
    assert "unknown node 'nope'" in err


async def test_a_taken_port_fails_before_anything_starts(rt: Runtime) -> None:
    port = SERVERS[id(rt)].port
    other = Runtime(graph(), clock=VirtualClock())
    server = ControlServer(other, ControlConfig("127.0.0.1", port))
    with pytest.raises(OSError, match=f"cannot listen on 127.0.0.1:{port}: .*in use"):
        server.bind()  # checked before the runtime is started
    assert not other.started
    with pytest.raises(RuntimeError, match="start the runtime"):
        await server.start()


async def test_flowrt_ctl_without_a_runtime() -> None:
    code, _, err = await ctl("--url", "http://127.0.0.1:9", "stats")
    assert code == 1
    assert "cannot reach the runtime" in err
    assert "Traceback" not in err


# --- the endpoint cannot break the robot (issue 19, item 6) ---------------------------------


async def post_raw(target: str, text: str) -> tuple[int, str]:
    async with (
        aiohttp.ClientSession() as s,
        s.post(target, data=text, headers={"Content-Type": "application/json"}) as r,
    ):
        return r.status, await r.text()


BAD_CHANGES = [
    ('{"node": "slow", "timer": 1e-9}', "timer period must be at least 0.1 ms"),
    ('{"node": "slow", "timer": 1e300}', "timer period must be at most 3600000 ms"),
    ('{"node": "slow", "timer": NaN}', "NaN is not a number"),
    ('{"node": "slow", "deadline": NaN}', "NaN is not a number"),
    ('{"node": "slow", "deadline": Infinity}', "Infinity is not a number"),
    ('{"node": "slow", "deadline": -Infinity, "priority": 30}', "Infinity is not a number"),
    ('{"node": "slow", "priority": 30, "deadline": 1e300}', "deadline: Value error, must be"),
    ('{"node": "slow", "priority": 30, "timer": 0}', "timer period must be positive"),
    ('{"node": "slow", "priority": 30, "period": 1000000000000000000}', "period must be"),
    ('{"node": "slow", "priority": 300}', "priority"),
    ('{"node": "slow", "enabled": "yes please"}', "enabled"),
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"node": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested too deeply"),
    ("{not json", "bad request body"),
]


async def test_a_bad_change_is_refused_whole_and_nothing_is_applied(rt: Runtime) -> None:
    for body, reason in BAD_CHANGES:
        before = rt.stats().node("slow")
        status, text = await post_raw(url(rt, "/timing"), body)
        assert status == 400, (body[:60], text)
        assert reason in json.loads(text)["error"], body[:60]
        assert "Traceback" not in text
        after = rt.stats().node("slow")
        assert (after.period, after.priority, after.enabled) == (
            before.period,
            before.priority,
            before.enabled,
        ), body[:60]
        assert not [e for e in rt.events if isinstance(e, flowrt.TimingChanged)], body[:60]
    # the endpoint still works after them
    status, reply = await call("POST", url(rt, "/timing"), {"node": "slow", "priority": 30})
    assert (status, reply["change"]) == (200, "priority 20 -> 30")


@pytest.mark.parametrize(
    "change",
    [
        {"timer": float("nan")},
        {"timer": float("inf")},
        {"timer": 1e-9},
        {"deadline": float("nan"), "priority": 30},
        {"priority": 30, "deadline": 1e300},
        {"priority": 30, "period": 10**18},
        {"priority": 30, "phase": -1},
    ],
)
async def test_the_api_checks_a_change_whole_before_applying_it(change: dict[str, Any]) -> None:
    async with Runtime(graph(), clock=VirtualClock()) as rt:
        with pytest.raises(ValueError, match="slow: "):
            rt.set_timing("slow", **change)
        s = rt.stats().node("slow")
        assert (s.period, s.priority) == ("100ms", 20)
        assert rt.scheduler.runners["slow"].timing.deadline is None


async def test_slow_clients_are_timed_out_and_connections_capped() -> None:
    async with (
        Runtime(graph(), clock=VirtualClock()) as rt,
        ControlServer(
            rt, ControlConfig("127.0.0.1", 0), max_connections=3, request_timeout=0.5
        ) as server,
    ):
        # a client sending its headers a byte at a time is closed once its time is up
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"GET /stats HTTP/1.1\r\nHo")
        await writer.drain()
        assert await asyncio.wait_for(reader.read(), 5) == b""  # closed by the server
        writer.close()
        # three idle connections fill the cap: a fourth takes the slot of the oldest one
        # that has sent no request yet (slow clients never lock others out)
        idle = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(3)]
        await asyncio.sleep(0.1)
        status, stats = await call("GET", server.url + "/stats")  # served at once
        assert status == 200
        assert stats["graph"] == "ctl"
        assert await asyncio.wait_for(idle[0][0].read(), 0.4) == b""  # the oldest, evicted
        for _, w in idle:
            w.close()


async def test_many_slow_clients_do_not_lock_out_a_new_one_nor_the_token_holder() -> None:
    """Issue 32 item 8: 40 clients that send half a request hold no slot for long (cap 20):
    a new client is served at once, and the token holder has a slot kept even when every
    slot is in a request."""
    config = ControlConfig("127.0.0.1", 0, token=TOKEN)
    async with (
        Runtime(graph(), clock=VirtualClock()) as rt,
        ControlServer(rt, config, max_connections=20, request_timeout=10.0) as server,
    ):
        slow = []
        for _ in range(40):
            r, w = await asyncio.open_connection("127.0.0.1", server.port)
            w.write(b"GET /stats HTTP/1.1\r\nHo")  # never finished
            slow.append((r, w))
        await asyncio.sleep(0.2)
        auth = {"Authorization": f"Bearer {TOKEN}"}
        t0 = asyncio.get_running_loop().time()
        status, _ = await call("GET", server.url + "/stats", headers=auth)
        assert status == 200
        assert asyncio.get_running_loop().time() - t0 < 2.0
        for _, w in slow:
            w.close()


async def test_token_required_on_loopback() -> None:
    config = ControlConfig("127.0.0.1", 0, token=TOKEN, token_required=True)
    async with Runtime(graph(), clock=VirtualClock()) as rt, ControlServer(rt, config) as server:
        status, _ = await call("POST", server.url + "/mode", {"mode": "defend"})
        assert status == 401
        assert rt.mode is None
        status, _ = await call(
            "GET", server.url + "/stats", headers={"Authorization": f"Bearer {TOKEN}"}
        )
        assert status == 200


async def test_many_readers_cost_the_runtime_one_answer_per_cache_period(rt: Runtime) -> None:
    server = SERVERS[id(rt)]
    before = server.answered
    async with aiohttp.ClientSession() as s:

        async def poll() -> int:
            async with s.get(url(rt, "/stats")) as r:
                await r.read()
                return r.status

        statuses = await asyncio.gather(*(poll() for _ in range(50)))
    assert statuses == [200] * 50
    assert server.answered - before < 10  # shared answers, not one per client


def test_flowrt_run_with_a_taken_control_port_says_so_and_exits_1(tmp_path: Path) -> None:
    import socket
    import subprocess

    graph_file = tmp_path / "g.yaml"
    graph_file.write_text("name: g\nnodes:\n  src: {kind: counter, trigger: {timer: 50ms}}\n")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        command = [sys.executable, "-m", "flowrt.cli", "run", str(graph_file), "--no-ui"]
        proc = subprocess.run(
            [*command, "--duration", "5", "--control", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert f"127.0.0.1:{port}" in lines[0]
    assert "--control PORT" in lines[0]


async def test_clients_hold_the_servers_descriptors_not_the_runtimes() -> None:
    """Slow or idle clients cannot exhaust the descriptors the runtime's workers need."""
    import os
    import socket

    import psutil

    async with (
        Runtime(graph(), clock=VirtualClock()) as rt,
        ControlServer(rt, ControlConfig("127.0.0.1", 0)) as server,
    ):
        before = len(os.listdir("/proc/self/fd"))
        server_before = psutil.Process(server._proc.pid).num_fds()
        clients = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(40)]
        try:
            await asyncio.sleep(0.5)
            # this process holds only the clients' own ends; the server's ends are elsewhere
            assert len(os.listdir("/proc/self/fd")) - before == 40
            assert psutil.Process(server._proc.pid).num_fds() - server_before >= 40
        finally:
            for c in clients:
                c.close()


async def test_ctl_swap_and_reload(rt_token: Runtime) -> None:
    """``flowrt ctl swap``/``reload``: the node's kind changes while running; a bad kind is
    refused with the reason (409) and the old node runs on."""
    base = ["--url", url(rt_token, "")]
    code, out, err = await ctl(*base, "swap", "slow", "relay", token=TOKEN)
    assert code == 1  # relay needs an input that `slow` has no edge for: refused, old one kept
    assert "swap" in err
    assert rt_token.stats().node("slow").kind == "burn"
    code, out, err = await ctl(
        *base, "swap", "slow", "burn", "--params", '{"ms": 0.2}', token=TOKEN
    )
    assert (code, out.strip()) == (0, "slow: now burn (swap)"), err
    assert rt_token.scheduler.runners["slow"].rnode.params.ms == 0.2  # type: ignore[attr-defined]
    code, out, err = await ctl(*base, "swap", "slow", "no_such_kind", token=TOKEN)
    assert code == 1
    assert "not allowed over the control endpoint" in err
    assert "Traceback" not in err
    code, out, err = await ctl(*base, "swap", "slow", "burn", "--params", "[1]", token=TOKEN)
    assert code == 2
    code, out, err = await ctl(*base, "reload", "slow", token=TOKEN)
    assert (code, out.strip()) == (0, "slow: now burn (reload)"), err
    kinds = [e.node_kind for e in rt_token.events if isinstance(e, flowrt.NodeSwapped)]
    assert kinds == ["burn", "burn"]


# --- what a local caller may not do (issue 32 item 2) ------------------------------------


async def test_swap_to_a_kind_the_graph_does_not_allow_is_refused_and_nothing_imported(
    rt_token: Runtime,
) -> None:
    import sys

    before = set(sys.modules)
    status, body = await call(
        "POST",
        url(rt_token, "/swap"),
        {"node": "slow", "kind": "xml.dom.minidom:Node"},
        headers={"Authorization": f"Bearer {TOKEN}"},
    )
    assert status == 403
    assert "not allowed" in body["error"]
    assert "xml.dom.minidom" not in set(sys.modules) - before
    assert rt_token.started


async def test_a_module_that_exits_at_import_does_not_end_the_runtime(rt_token: Runtime) -> None:
    status, body = await call(
        "POST",
        url(rt_token, "/swap"),
        {"node": "slow", "kind": "unittest.__main__:X"},  # allowed, and calls sys.exit
        headers={"Authorization": f"Bearer {TOKEN}"},
    )
    assert status == 409
    assert "SystemExit" in body["error"]
    assert rt_token.started
    status, _ = await call(
        "GET", url(rt_token, "/stats"), headers={"Authorization": f"Bearer {TOKEN}"}
    )
    assert status == 200
    assert rt_token.stats().node("slow").kind == "burn"


@pytest.mark.parametrize(
    "params",
    [
        {"ms": 0.2, "path": "../../elsewhere"},
        {"ms": 0.2, "host": "0.0.0.0"},
        {"ms": 0.2, "token": "chosen"},
        {"ms": 0.2, "nested": {"output_dir": "/tmp/x"}},
    ],
)
async def test_params_that_move_data_are_refused_over_the_endpoint(
    rt_token: Runtime, params: dict[str, Any]
) -> None:
    status, body = await call(
        "POST",
        url(rt_token, "/swap"),
        {"node": "slow", "kind": "burn", "params": params},
        headers={"Authorization": f"Bearer {TOKEN}"},
    )
    # burn has no such params: unknown (422); a kind's real ones that move data are 403
    # (tests/test_swap_rules.py, a recorder's path)
    assert status == 422, body
    assert body["error"].startswith("burn: unknown param")
    assert rt_token.stats().node("slow").kind == "burn"


async def test_a_body_sent_a_byte_at_a_time_is_408_and_its_slot_freed() -> None:
    """Headers in, the body trickling: answered 408 once the body's time is up (it held the
    connection's slot for as long as the client liked)."""
    async with (
        Runtime(graph(), clock=VirtualClock()) as rt,
        ControlServer(rt, ControlConfig("127.0.0.1", 0), request_timeout=0.5) as server,
    ):
        status = await trickled_post(server.port, "/mode", b'{"mo')
        assert status.startswith(b"HTTP/1.1 408"), status
        assert rt.mode is None


CHANGES = {  # (the runtime's answer after s, None: never; the lock held s) -> status
    "answered": ((0.05, None), 200),
    "sent, never answered: may be applied, not 408": ((None, None), 504),
    "queued behind others past the wait: never sent": ((0.05, 5.0), 503),
}


@pytest.mark.parametrize("name", list(CHANGES))
async def test_a_change_answer_says_whether_it_was_applied(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A change answered 408 was applied after all (ten queued behind a 1 s quiet gap): now
    503 when it was never sent (not applied), 504 when sent and not answered (unknown)."""
    from flowrt.control import server as control_server

    (answer_after, held), status = CHANGES[name]
    monkeypatch.setattr(control_server, "QUEUE_WAIT", 0.2)
    gateway = control_server._Gateway(
        {"host": "127.0.0.1", "token": None, "max_connections": 4, "request_timeout": 0.3}
    )
    sent: list[str] = []

    async def ask(op: str, args: Any) -> tuple[int, bytes]:
        sent.append(op)
        await asyncio.sleep(3600 if answer_after is None else answer_after)
        return 200, b"{}"

    monkeypatch.setattr(gateway, "_ask", ask)
    if held is not None:
        await gateway._changes.acquire()
        asyncio.get_running_loop().call_later(held, gateway._changes.release)
    got, body = await gateway.change("mode", {"mode": "x"})
    assert got == status, body
    assert sent == ([] if status == 503 else ["mode"])
    assert not gateway._changes.locked() or held is not None


@pytest.mark.parametrize(
    ("chunks", "late"),
    [
        ([b"GET /stats HTTP/1.1\r\nHo"], True),  # still sending its headers: closed
        ([b"GET /stats HTTP/1.1\r\nHost: x\r\n\r\n"], False),  # in: answered, however late
        ([b"POST /mode HTTP/1.1\r\nHost: x\r\n\r", b"\n{"], False),  # the blank line split
        ([b"GET / HTTP/1.1\r\n", b"\r", b"\n"], False),
    ],
)
def test_a_request_whose_headers_are_in_is_never_swept(chunks: list[bytes], late: bool) -> None:
    """The endpoint's process runs at nice 19: on a busy machine it read a request only
    after the sweeper's 2 s were up, closed it unanswered, then applied the change anyway.
    A connection is closed for lateness only while its headers are still coming."""
    import time

    from flowrt.control.serving import Conn

    conn = Conn(transport=None, deadline=time.monotonic() - 1.0)  # type: ignore[arg-type]
    for chunk in chunks:
        conn.received(chunk)
    assert conn.late(time.monotonic()) is late
    conn.answered(10.0)  # its answer sent: the next request has its own time
    assert not conn.headers_in
    assert not conn.late(time.monotonic())
