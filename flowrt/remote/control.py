"""``flowrt ctl`` through Zenoh: a queryable forwarding to the local control endpoint.

A robot's runtime is often reachable only through the Zenoh session its graph already has
(a router, a TLS link). Rather than open a second network door, a graph that says
``zenoh: {control: KEY}`` declares a queryable on KEY; each query is one control request
(``{"method", "path", "body", "token"}`` as JSON) that is forwarded, over loopback HTTP, to the
runtime's own control endpoint (:mod:`flowrt.control.server`), and the answer comes back as the
reply (``{"status", "body"}``). So every rule is the HTTP endpoint's, unchanged: the same
routes, limits, cache, and token check (the query's token is sent as the bearer token, and a
missing or wrong one gets the same 401). The one thing Zenoh changes is who can ask: when the
session is reachable beyond loopback (:meth:`flowrt.graph.spec.ZenohSpec.beyond_loopback`), the
HTTP endpoint requires the token on loopback too, as HTTP itself does when bound beyond
loopback, so that a remote peer cannot pass as a local process.

Off the scheduler's path: Zenoh's thread only queues the query; one thread of this module
makes the HTTP request (the server is its own process, see :mod:`flowrt.control.server`)
and replies.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import urllib.error
import urllib.request
from typing import Any

from ..control.server import ControlError

log = logging.getLogger("flowrt.remote.control")

MAX_TIMEOUT = 120.0  # seconds a forwarded request may take (swap sets up a worker)
QUEUE = 64  # queries waiting for the forwarder; more are refused (503) at once


class ZenohControl:
    """The runtime side: a queryable on ``key`` of ``session`` forwarding to ``url``."""

    def __init__(self, session: Any, key: str, url: str) -> None:
        self.session = session
        self.key = key
        self.url = url.rstrip("/")
        self.forwarded = 0
        self.refused = 0
        self._queue: queue.Queue[Any] = queue.Queue(QUEUE)
        self._queryable: Any = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(
            target=self._forward_all, name="flowrt-zenoh-control", daemon=True
        )
        self._thread.start()
        self._queryable = self.session.declare_queryable(self.key, self._on_query)

    def stop(self) -> None:
        if self._queryable is not None:
            try:
                self._queryable.undeclare()
            except Exception as e:  # the session may be closing
                log.debug("zenoh control: undeclare: %s", e)
            self._queryable = None
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(2.0)
            self._thread = None

    def _on_query(self, query: Any) -> None:
        """Zenoh's thread: queue only."""
        try:
            self._queue.put_nowait(query)
        except queue.Full:
            self.refused += 1
            _reply(query, self.key, 503, {"error": "too many control queries at once"})

    def _forward_all(self) -> None:
        while True:
            query = self._queue.get()
            if query is None:
                return
            with query:  # the query is answered (finalised) when it leaves this block
                status, body = self.forward(query.payload)
                _reply(query, self.key, status, body)
                self.forwarded += 1

    def forward(self, payload: Any) -> tuple[int, Any]:
        """(status, JSON answer) of one query's request, sent to the local endpoint."""
        try:
            req = json.loads(payload.to_bytes() if payload is not None else b"")
            method = str(req["method"]).upper()
            path = str(req["path"])
            timeout = min(float(req.get("timeout", 5.0)), MAX_TIMEOUT)
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            return 400, {"error": f"not a flowrt control query ({e})"}
        if method not in ("GET", "POST") or not path.startswith("/") or path.startswith("//"):
            return 400, {"error": f"not a control request: {method} {path}"}
        data = None if req.get("body") is None else json.dumps(req["body"]).encode()
        http = urllib.request.Request(self.url + path, data=data, method=method)
        if data is not None:
            http.add_header("Content-Type", "application/json")
        token = req.get("token")
        if token:
            http.add_header("Authorization", f"Bearer {token}")
        try:
            with urllib.request.urlopen(http, timeout=timeout) as resp:
                return resp.status, json.loads(resp.read() or b"null")
        except urllib.error.HTTPError as e:
            try:
                return e.code, json.loads(e.read())
            except ValueError:
                return e.code, {"error": str(e.reason)}
        except (urllib.error.URLError, OSError, ValueError) as e:
            return 503, {"error": f"the runtime's control endpoint did not answer ({e})"}


def _reply(query: Any, key: str, status: int, body: Any) -> None:
    try:
        query.reply(key, json.dumps({"status": status, "body": body}).encode())
    except Exception as e:  # the querier is gone
        log.debug("zenoh control: reply: %s", e)


class ZenohControlClient:
    """``flowrt ctl --zenoh ENDPOINT --key KEY``: the same requests as
    :class:`flowrt.control.server.ControlClient`, sent as Zenoh queries (client mode, no
    scouting: it reaches the endpoints it is given and nothing else)."""

    def __init__(
        self,
        connect: list[str],
        key: str,
        token: str | None = None,
        timeout: float = 5.0,
        config: dict[str, Any] | None = None,
    ) -> None:
        self.connect = connect
        self.key = key
        self.token = token
        self.timeout = timeout
        self.config = config or {}
        self._session: Any = None

    def _open(self) -> Any:
        if self._session is None:
            import zenoh

            cfg = zenoh.Config()
            cfg.insert_json5("mode", '"client"')  # fails at once if no endpoint answers
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
            cfg.insert_json5("scouting/multicast/enabled", "false")
            cfg.insert_json5("scouting/gossip/enabled", "false")
            for path, value in self.config.items():
                cfg.insert_json5(path, json.dumps(value))
            try:
                self._session = zenoh.open(cfg)
            except Exception as e:
                text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                cut = text.find(" at /")
                text = (text[:cut] if cut > 0 else text).rstrip("! ")
                where = ", ".join(self.connect)
                raise ControlError(f"cannot reach {where} through Zenoh ({text})") from None
        return self._session

    def close(self) -> None:
        if self._session is not None:
            session, self._session = self._session, None
            session.close()

    def request(self, method: str, path: str, body: Any = None) -> Any:
        session = self._open()
        query = {"method": method, "path": path, "body": body, "token": self.token}
        query["timeout"] = self.timeout
        where = f"{self.key} via {', '.join(self.connect)}"
        asked = time.monotonic()
        try:
            replies = list(
                session.get(
                    self.key, payload=json.dumps(query).encode(), timeout=self.timeout + 1.0
                )
            )
        except Exception as e:
            raise ControlError(f"zenoh query on {where} failed: {e}") from None
        for r in replies:
            ok = getattr(r, "ok", None)
            if ok is None:
                continue
            try:
                answer = json.loads(ok.payload.to_bytes())
                status, data = int(answer["status"]), answer["body"]
            except (ValueError, KeyError, TypeError):
                raise ControlError(f"{where}: not a flowrt control reply") from None
            if status >= 400:
                message = data.get("error") if isinstance(data, dict) else data
                code = data.get("code") if isinstance(data, dict) else None  # "malformed"
                if status == 401:
                    message = f"{message} (give --token or set FLOWRT_TOKEN)"
                raise ControlError(
                    f"{status}: {message}", status, code if isinstance(code, str) else None
                )
            return data
        waited = time.monotonic() - asked
        # Zenoh ends a query at once when nothing there answers this key: "within 16 s" after
        # 0.65 s said a wait that never was
        said = f"within {self.timeout + 1.0:g} s" if waited >= self.timeout else "(none there)"
        raise ControlError(
            f"no runtime answered on {where} {said}; is a graph with "
            f"`zenoh: {{control: {self.key}}}` running there?"
        )

    def get(self, path: str) -> Any:
        return self.request("GET", path)

    def post(self, path: str, body: Any) -> Any:
        return self.request("POST", path, body)
