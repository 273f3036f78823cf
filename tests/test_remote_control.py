"""``flowrt ctl`` through Zenoh: two real processes over loopback (explicit tcp/127.0.0.1
endpoints, no scouting), the same answers and the same token refusal as HTTP; and the checks
that decide when a token is required, and bad configurations that must be one line."""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from flowrt.cli.run import _control_config
from flowrt.control.server import ControlClient, ControlError
from flowrt.graph.spec import ZenohSpec
from flowrt.remote.control import ZenohControl, ZenohControlClient

pytestmark = pytest.mark.timeout(90)

TOKEN = "s3cret-token"
KEY = "t1/flowrt/control"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ctl(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FLOWRT_TOKEN", "FLOWRT_URL")}
    return subprocess.run(
        [sys.executable, "-m", "flowrt.cli", "ctl", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )


ROBOT = """
name: robot
zenoh: {{listen: ["tcp/127.0.0.1:{port}"], control: "{key}"}}
nodes:
  cam: {{kind: capture, params: {{source: "synthetic:soccer", fps: 20, size: [160, 120]}}}}
  ball:
    kind: tracker
    params: {{object: ball}}
    inputs: {{frame: cam.frame}}
"""


def test_ctl_through_zenoh_same_answers_and_token_rules_as_http(tmp_path: Path) -> None:
    zport, hport = free_port(), free_port()
    graph = tmp_path / "robot.yaml"
    graph.write_text(textwrap.dedent(ROBOT.format(port=zport, key=KEY)))
    cmd = [sys.executable, "-m", "flowrt.cli", "run", str(graph), "--no-ui", "--duration", "60"]
    cmd += ["--control", f"127.0.0.1:{hport}", "--token", TOKEN]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    endpoint = f"tcp/127.0.0.1:{zport}"
    zc = ZenohControlClient([endpoint], KEY, TOKEN)
    try:
        http = ControlClient(f"http://127.0.0.1:{hport}", TOKEN)
        end = time.monotonic() + 40
        while True:  # until the runtime answers through Zenoh
            try:
                stats = zc.get("/stats")
                break
            except ControlError:
                if time.monotonic() > end or proc.poll() is not None:
                    raise
                zc.close()
                time.sleep(0.3)
        assert {n["name"] for n in stats["nodes"]} == {"cam", "ball"}
        # the same request, the same answer as HTTP (modes do not change while running)
        assert zc.get("/modes") == http.get("/modes")
        # a change through Zenoh is applied and seen through HTTP
        reply = zc.post("/timing", {"node": "ball", "deadline": 40.0})
        assert reply["node"] == "ball"
        ball = next(n for n in http.get("/stats")["nodes"] if n["name"] == "ball")
        assert ball["deadline_ms"] == pytest.approx(40.0)
        # a bad request is refused the same way
        with pytest.raises(ControlError) as z_err:
            zc.post("/timing", {"node": "ghost", "deadline": 40.0})
        with pytest.raises(ControlError) as h_err:
            http.post("/timing", {"node": "ghost", "deadline": 40.0})
        assert str(z_err.value) == str(h_err.value)
        assert str(z_err.value).startswith("404")
        # a malformed body: exit 2 both ways (through Zenoh it was 1: no code carried)
        with pytest.raises(ControlError) as z_err:
            zc.post("/timing", {"node": "ball", "deadline": 0})
        assert (z_err.value.status, z_err.value.malformed) == (400, True)
        for via in (("--zenoh", endpoint, "--key", KEY), ("--url", f"http://127.0.0.1:{hport}")):
            bad = ctl(*via, "--token", TOKEN, "timing", "ball", "--deadline", "0")
            assert bad.returncode == 2, (via, bad.stderr)
        # a key nothing answers: Zenoh ends the query at once ("within 16 s" was said)
        none = ctl("--zenoh", endpoint, "--key", "elsewhere/control", "--token", TOKEN, "qos")
        assert none.returncode == 1
        assert "no runtime answered on elsewhere/control" in none.stderr
        assert "(none there)" in none.stderr, none.stderr

        # from the CLI: without the token, the same one-line refusal as HTTP
        no_z = ctl("--zenoh", endpoint, "--key", KEY, "qos")
        no_h = ctl("--url", f"http://127.0.0.1:{hport}", "qos")
        assert no_z.returncode == no_h.returncode == 1
        assert no_z.stderr == no_h.stderr
        assert no_z.stderr.startswith("flowrt ctl: 401: missing or wrong bearer token")
        assert len(no_z.stderr.strip().splitlines()) == 1
        wrong = ctl("--zenoh", endpoint, "--key", KEY, "--token", "nope", "qos")
        assert wrong.returncode == 1
        assert "401" in wrong.stderr
        ok = ctl("--zenoh", endpoint, "--key", KEY, "--token", TOKEN, "stats", "--json")
        assert ok.returncode == 0, ok.stderr
        assert {n["name"] for n in json.loads(ok.stdout)["nodes"]} == {"cam", "ball"}
    finally:
        zc.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def test_ctl_zenoh_unreachable_and_bad_arguments_are_one_line() -> None:
    port = free_port()  # nothing listens there
    r = ctl("--zenoh", f"tcp/127.0.0.1:{port}", "--key", KEY, "qos")
    assert r.returncode == 1
    assert r.stderr.strip() == (
        f"flowrt ctl: cannot reach tcp/127.0.0.1:{port} through Zenoh "
        f"(Unable to connect to any of [Single(tcp/127.0.0.1:{port})])"
    )
    for args, message in (
        (["--zenoh", f"tcp/127.0.0.1:{port}", "qos"], "--zenoh needs --key"),
        (["--zenoh", "pigeon", "--key", KEY, "qos"], "not a Zenoh endpoint"),
        (["--zenoh", f"tcp/127.0.0.1:{port}", "--key", "a/**", "qos"], "no * or **"),
    ):
        r = ctl(*args)
        assert r.returncode == 2, args
        assert message in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("zenoh", "beyond"),
    [
        ({}, False),  # the defaults: loopback listen, no scouting
        ({"listen": ["tcp/[::1]:7447"], "connect": ["tcp/localhost:7448"]}, False),
        ({"listen": ["unixsock-stream//tmp/z.sock"]}, False),
        ({"listen": ["tcp/0.0.0.0:7447"]}, True),
        ({"listen": [], "connect": ["tls/robot.example:7447"]}, True),
        ({"scouting": True}, True),
        ({"config": {"transport/link/tx/lease": 5000}}, False),  # times the link only
        ({"config": {"connect/retry": {"period_max_ms": 1000}}}, False),
        (
            {
                "config": {
                    "transport/link/tx/lease": 5000,
                    "routing/router/peers_failover_brokering": True,
                }
            },
            True,
        ),
        ({"config": {"transport/shared_memory/enabled": False}}, True),  # flowrt cannot tell
    ],
)
def test_zenoh_session_beyond_loopback(zenoh: dict[str, Any], beyond: bool) -> None:
    assert ZenohSpec.model_validate(zenoh).beyond_loopback() is beyond


def run_args(**kw: Any) -> argparse.Namespace:
    base = {"control": None, "token": None, "control_token_required": False}
    return argparse.Namespace(**{**base, **kw})


def test_control_token_rules_for_zenoh(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FLOWRT_TOKEN", raising=False)
    quiet = Console(file=open(os.devnull, "w"))  # noqa: SIM115
    # no zenoh.control: no endpoint unless asked
    assert _control_config(run_args(), quiet, zenoh=ZenohSpec()) is None
    # loopback session: an endpoint on a free loopback port, no token (as HTTP on loopback)
    local = _control_config(run_args(), quiet, zenoh=ZenohSpec(control=KEY))
    assert (local.host, local.port, local.token, local.needs_token) == ("127.0.0.1", 0, None, False)
    # reachable beyond loopback: the token is required on loopback too, one is generated
    wide = ZenohSpec(listen=["tcp/0.0.0.0:7447"], control=KEY)
    cfg = _control_config(run_args(), quiet, zenoh=wide)
    assert cfg.token_required
    assert cfg.token
    given = _control_config(run_args(token="mine", control="8770"), quiet, zenoh=wide)
    assert (given.port, given.token, given.token_required) == (8770, "mine", True)


class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (None, "not a flowrt control query"),
        (b"not json", "not a flowrt control query"),
        (b'{"path": "/stats"}', "not a flowrt control query"),
        (b'{"method": "DELETE", "path": "/stats"}', "not a control request"),
        (b'{"method": "GET", "path": "//evil.example/x"}', "not a control request"),
        (b'{"method": "GET", "path": "@evil.example/x"}', "not a control request"),
    ],
)
def test_forwarder_refuses_what_is_not_a_control_request(
    payload: bytes | None, message: str
) -> None:
    fwd = ZenohControl(None, KEY, "http://127.0.0.1:1")
    status, body = fwd.forward(None if payload is None else _Payload(payload))
    assert status == 400
    assert message in body["error"]
