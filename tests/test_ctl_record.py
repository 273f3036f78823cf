"""``flowrt ctl record`` refuses what cannot be done, as the operator page's API does.

A start while the recorder was already recording exited 0 (``recording into .../rec_001``:
the session it was in all along), a stop while stopped exited 0 (``rec: stopped``); the
page's ``POST /api/record/start|stop`` answers 409 for both. The control endpoint's ``POST
/record`` only writes the recorders' command records and answers 200 (a recorder ignores a
command it cannot obey), so ``ctl`` decides from the state the recorders publish
(``flowrt.recording.NODE``), before it sends anything.
"""

from __future__ import annotations

import asyncio
import http.server
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import flowrt
from flowrt.cli import main

pytestmark = pytest.mark.timeout(60)


class _Endpoint:
    """A control endpoint's ``/rtdb`` and ``/record`` with a recorder that obeys at once."""

    def __init__(self, sessions: dict[str, str]) -> None:
        self.sessions = sessions
        self.posts: list[Any] = []
        endpoint = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def _reply(self, doc: Any) -> None:
                data = json.dumps(doc).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def do_GET(self) -> None:
                records = [
                    {"name": f"flowrt.recording.{n}", "seq": 1, "value": s}
                    for n, s in endpoint.sessions.items()
                ]
                path = self.path.split("?")[0]
                if path != "/rtdb":
                    records = [r for r in records if f"/rtdb/{r['name']}" == path]
                self._reply(records)

            def do_POST(self) -> None:
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                endpoint.posts.append(body)
                for n in endpoint.sessions:
                    endpoint.sessions[n] = f"/recs/{n}_001" if body["action"] == "start" else ""
                self._reply({"action": body["action"], "nodes": sorted(endpoint.sessions)})

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.HTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"


@pytest.fixture
def endpoint() -> Iterator[_Endpoint]:
    e = _Endpoint({"rec": ""})
    thread = threading.Thread(target=e.server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield e
    finally:
        e.server.shutdown()
        e.server.server_close()


def test_start_while_recording_and_stop_while_stopped_exit_1(
    endpoint: _Endpoint, capsys: pytest.CaptureFixture[str]
) -> None:
    url = ["ctl", "--url", endpoint.url]
    assert main([*url, "record", "stop"]) == 1
    assert capsys.readouterr().err.splitlines() == ["flowrt ctl: not recording (rec stopped)"]
    assert main([*url, "record", "start"]) == 0
    assert capsys.readouterr().out == "rec: recording into /recs/rec_001\n"
    assert main([*url, "record", "start"]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "flowrt ctl: already recording: rec into /recs/rec_001 (flowrt ctl record stop first)"
    ]
    assert main([*url, "record", "stop"]) == 0
    assert capsys.readouterr().out == "rec: stopped\n"
    assert [p["action"] for p in endpoint.posts] == ["start", "stop"]  # nothing else sent


def test_a_refused_record_in_json_is_an_error_document(
    endpoint: _Endpoint, capsys: pytest.CaptureFixture[str]
) -> None:
    endpoint.sessions["rec"] = "/recs/rec_001"
    assert main(["ctl", "--url", endpoint.url, "record", "start", "--json"]) == 1
    error = json.loads(capsys.readouterr().out)["error"]
    assert error["exit_code"] == 1
    assert error["command"] == "ctl record"
    assert error["message"].startswith("flowrt ctl: already recording: rec into /recs/rec_001")
    assert error["sessions"] == {"rec": "/recs/rec_001"}
    assert endpoint.posts == []


def test_node_limits_the_check_to_that_recorder(
    endpoint: _Endpoint, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--node other``: the state of ``rec`` does not decide; one never heard of goes to the
    endpoint, which names the recorders."""
    endpoint.sessions["rec"] = "/recs/rec_001"
    endpoint.sessions["other"] = ""
    url = ["ctl", "--url", endpoint.url]
    assert main([*url, "record", "stop", "--node", "other"]) == 1
    assert "not recording (other stopped)" in capsys.readouterr().err
    assert main([*url, "record", "stop", "--node", "rec"]) == 0
    assert endpoint.posts == [{"action": "stop", "node": "rec"}]


async def test_against_a_running_recorder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real thing: a recorder in a graph, the control endpoint, the session folders."""
    g = flowrt.GraphBuilder("ctl")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 20, "size": [80, 60]})
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp_path), "name": "drive", "start": False, "writer": "thread"},
        inputs={"cam.frame": {"from": "cam.frame", "policy": "lossless"}},
    )
    config = flowrt.ControlConfig("127.0.0.1", 0)
    async with flowrt.Runtime(g.build()) as rt, flowrt.ControlServer(rt, config) as server:
        url = ["ctl", "--url", server.url]

        async def ctl(*argv: str) -> int:
            return await asyncio.to_thread(main, [*url, *argv])

        await rt.run(0.3)
        assert await ctl("record", "stop") == 1
        assert "flowrt ctl: not recording" in capsys.readouterr().err
        assert await ctl("record", "start") == 0
        await rt.run(0.3)
        assert await ctl("record", "start") == 1
        assert "flowrt ctl: already recording: rec into " in capsys.readouterr().err
        assert await ctl("record", "stop") == 0
        assert await ctl("record", "stop") == 1
    assert sorted(os.listdir(tmp_path)) == ["drive_001"]  # the refused start made none


def test_a_start_names_its_session(endpoint: _Endpoint, capsys: pytest.CaptureFixture[str]) -> None:
    """``POST /record`` took ``name``; ``flowrt ctl record`` had no way to give it."""
    url = ["ctl", "--url", endpoint.url, "record"]
    assert main([*url, "start", "--name", "drive"]) == 0
    assert endpoint.posts[-1] == {"action": "start", "name": "drive"}
    assert main([*url, "stop", "--name", "drive"]) == 2  # a stop names nothing
    with pytest.raises(SystemExit) as bad:
        main([*url, "start", "--name", "../x"])
    assert bad.value.code == 2
    err = capsys.readouterr().err
    assert "--name names a new session" in err
    assert "a session name is letters, digits, _ and - (at most 64)" in err
    assert len(endpoint.posts) == 1
