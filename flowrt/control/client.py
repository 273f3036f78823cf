"""A small synchronous client of the control endpoint (stdlib only): ``flowrt ctl``'s, and a
script's. The server side is :mod:`flowrt.control.server`."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import Any

DEFAULT_PORT = 8766  # not 8765: that is the Foxglove apps' default (flowrt run --foxglove)
DEFAULT_URL = f"http://127.0.0.1:{DEFAULT_PORT}"

__all__ = ["DEFAULT_PORT", "DEFAULT_URL", "ControlClient", "ControlError"]


class ControlError(Exception):
    """The runtime could not be reached or refused the request; the message says which,
    ``status`` the HTTP status of a refusal (None: not reached)."""

    def __init__(self, message: str, status: int | None = None, code: str | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code  # the refusal's ``code`` (``malformed``), when the endpoint gave one

    @property
    def malformed(self) -> bool:
        """The endpoint refused the request's body as malformed (a value out of range), not
        the change it asks for (admission control, a safety rule: also 400, exit 1)."""
        return self.status == 400 and self.code == "malformed"


class ControlClient:
    """A small synchronous client of the control endpoint (stdlib only)."""

    def __init__(
        self, url: str = DEFAULT_URL, token: str | None = None, timeout: float = 15.0
    ) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    def request(self, method: str, path: str, body: Any = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        try:
            req = urllib.request.Request(self.url + path, data=data, method=method)
        except ValueError:  # "nonsense", "http://[::1": urllib's traceback otherwise
            raise ControlError(f"{self.url}: not a URL (http://HOST:PORT)") from None
        if data is not None:
            req.add_header("Content-Type", "application/json")
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                reply = resp.read()
        except urllib.error.HTTPError as e:
            raise ControlError(*self._refused(e)) from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            if isinstance(reason, TimeoutError) and data is not None:
                raise ControlError(
                    f"{self.url}: no answer within {self.timeout:g} s; the change may still "
                    "be applied (see `flowrt ctl events`)"
                ) from None
            raise ControlError(
                f"cannot reach the runtime at {self.url} ({reason}); "
                "is `flowrt run --control` running?"
            ) from None
        try:
            return json.loads(reply or b"null")
        except ValueError:  # the live view's port given for the control endpoint's, say
            raise ControlError(
                f"{self.url}: not a flowrt control endpoint (its reply is not JSON)"
            ) from None

    @staticmethod
    def _refused(e: urllib.error.HTTPError) -> tuple[str, int, str | None]:
        """The refusal's line, status and code."""
        code = None
        try:
            reply = json.loads(e.read())
            message = reply.get("error", e.reason)
            code = reply.get("code")
        except (ValueError, AttributeError):
            message = e.reason
        if e.code == 401:
            message = f"{message} (give --token or set FLOWRT_TOKEN)"
        return f"{e.code}: {message}", e.code, code if isinstance(code, str) else None

    def get(self, path: str) -> Any:
        return self.request("GET", path)

    def post(self, path: str, body: Any) -> Any:
        return self.request("POST", path, body)
